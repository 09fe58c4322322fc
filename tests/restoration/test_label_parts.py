"""Parts of the labelled lattice beyond a neck, their labels carried across it by whole dots:
a rendered frame where the structured light said ``ok`` 1.18 mm off, against its truth."""

from __future__ import annotations

import numpy as np

from restoration import Status, get_method, restore_folder
from restoration.label_parts import MIN_PART, misplaced_parts, necked_parts
from tests.conftest import render_paper_frame


def test_a_part_is_tested_only_beyond_a_neck():
    # Two blocks of 6 x 6 dots joined by a neck one dot wide: the smaller side is a part;
    # joined by a band three dots wide, there is no neck; a part under MIN_PART dots is
    # not tested.
    block = np.array([(i, j) for i in range(6) for j in range(6)])
    necked = np.vstack([block, [(6, 2), (7, 2)], block[:30] + (8, 0)])
    (part, neck), = necked_parts(necked)
    assert part.sum() == 30 and neck.sum() == 2 and not part[:36].any()
    band = np.vstack([block, [(6, j) for j in range(1, 4)], block + (7, 0)])
    assert necked_parts(band) == []
    small = np.vstack([block, [(6, 2), (7, 2)], block[: MIN_PART - 1] + (8, 0)])
    assert necked_parts(small) == []
    # A residual lowest at the part's own labels keeps it; one far lower at a shift drops it.
    keep, gains = misplaced_parts(necked, lambda m, s: 1.0 + abs(s[0]) + abs(s[1]))
    assert not keep.any() and gains == [1.0]


def test_a_part_whose_labels_a_neck_shifted_is_not_called_right(tmp_path):
    # U = 1.5 m/s, sea 3, gravity-capillary waves to 6 omega_p, 10.2 s (the compare case's
    # frame 6): beyond a neck one or two dots wide the labels were carried three dots along
    # i, the part's surface ramped to 4.7 mm off, and the frame said ok at 1.18 mm RMSE.
    # Dropped, the frame must be right where it says ok.
    frame = render_paper_frame(tmp_path / "f", seed=3, wind=1.5, texture="speckle",
                               waves={"dispersion": "capillary", "omega_max_rel": 6.0,
                                      "time_s": 10.2})
    done = restore_folder(frame, get_method("structured-light"), write=False)
    assert done.result.counts["rejected_shifted_part"] > 0
    assert done.result.status is not Status.OK or done.metrics["wai_rmse_mm"] <= 0.1
