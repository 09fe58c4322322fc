"""The truth-free frame status: which evidence makes a frame ``sparse``, ``inconsistent`` or
``ok`` (restoration.result). The rules read counts only, so stand-ins carry them here."""

from types import SimpleNamespace

import numpy as np
import pytest

from restoration import RestoreOptions
from restoration.result import REFERENCE_RMS_FRACTION, SPARSE_FRACTION, STATUSES
from restoration.structured_light import frame_status


class _Features(SimpleNamespace):
    def __len__(self) -> int:
        return self.n


def _status(n_matched, ambiguous, observed=1000, in_view=1000, median_px=0.2, rms_px=0.3):
    features = _Features(n=n_matched, counts={"labels_ambiguous": int(ambiguous)})
    reference = SimpleNamespace(counts={"predicted_in_view": in_view, "observed": observed},
                                rms_px=rms_px, spacing_px=np.full(in_view, 13.0))
    surface = SimpleNamespace(anchor={"method": "integrability"})
    check = SimpleNamespace(consistent=median_px <= 1.0, median_px=median_px, threshold_px=1.0)
    return frame_status(features, reference, surface, check, True, RestoreOptions())


def test_a_large_consistent_patch_is_ok():
    assert _status(800, ambiguous=True)[0] == "ok"


def test_a_small_patch_labelled_by_ordering_alone_is_sparse():
    # A few dozen dots matched by ordering, away from the pattern's edge: shifted by whole dots
    # they integrate nearly as well, so nothing tells right labels from wrong.
    status, message = _status(int(0.1 * 1000), ambiguous=True)
    assert status == "sparse"
    assert "pins" in message


@pytest.mark.parametrize("n_matched", [40, 200])
def test_a_small_patch_with_pinned_labels_is_judged_by_its_consistency(n_matched):
    # Decoded (or uniquely anchored) labels: the patch is judged like any other.
    assert _status(n_matched, ambiguous=False)[0] == "ok"
    assert _status(n_matched, ambiguous=False, median_px=3.0)[0] == "inconsistent"


def test_a_reference_that_shows_few_dots_is_sparse_whatever_the_labels():
    status, message = _status(800, ambiguous=False, observed=int(0.5 * SPARSE_FRACTION * 1000))
    assert status == "sparse"
    assert "reference" in message


def test_a_reference_off_the_flat_water_prediction_is_bad_whatever_else_holds():
    # Spots a third of a spacing from where flat water puts them: not a flat-water image.
    far = 1.01 * REFERENCE_RMS_FRACTION * 13.0
    assert _status(800, ambiguous=False, rms_px=far)[0] == "bad_reference"
    assert _status(800, ambiguous=False, rms_px=0.99 * REFERENCE_RMS_FRACTION * 13.0)[0] == "ok"


def test_statuses_are_listed():
    assert {"ok", "sparse", "inconsistent"} <= set(STATUSES)
