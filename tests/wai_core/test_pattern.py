"""Tests of the projector pattern: the plain dot grid and the coded pattern's symbols."""

from __future__ import annotations

import numpy as np
import pytest

from wai_core.config import PatternConfig, load_config
from wai_core.errors import WaiInputError
from wai_core.pattern import (
    CODE_LEVELS,
    CODE_MIN_DISTANCE,
    CODE_REACH,
    code_array,
    dot_codes,
    dot_colours,
    pattern_image,
    window_distances,
)

SCENE = "scenes/paper.toml"


def test_code_array_is_deterministic_and_verified():
    a = code_array(35, 35, 0)
    assert np.array_equal(a, code_array.__wrapped__(35, 35, 0))
    assert not np.array_equal(a, code_array(35, 35, 1))
    assert window_distances(a, CODE_REACH).min() >= CODE_MIN_DISTANCE
    # All four symbols are used about equally (each colour lights a quarter of the dots).
    share = np.bincount(a.ravel(), minlength=4) / a.size
    assert np.all(np.abs(share - 0.25) < 0.05)


def test_window_distances_finds_a_repeat():
    a = np.array(code_array(20, 20, 3), dtype=np.int64)
    a[10:13, 10:13] = a[4:7, 4:7]  # the window at (11, 11) now repeats the one at (5, 5)
    d = window_distances(a, reach=8)
    assert d[11, 11] == 0 and d[5, 5] == 0


def test_windows_are_locally_unique_on_the_paper_grid():
    cfg = load_config(SCENE).replace("pattern", code="colour")
    codes = dot_codes(cfg.pattern, cfg.rig.projector)
    ij, _ = cfg.rig.dot_grid
    side = int(ij[:, 0].max() - ij[:, 0].min() + 1)
    words = {}
    grid = codes.reshape(side, side)
    for j in range(1, side - 1):
        for i in range(1, side - 1):
            words.setdefault(grid[j - 1 : j + 2, i - 1 : i + 2].tobytes(), []).append((i, j))
    # Every repeated 3x3 word lies farther apart than the code's reach (the guarantee).
    for places in words.values():
        for a in places[1:]:
            assert max(abs(a[0] - places[0][0]), abs(a[1] - places[0][1])) > CODE_REACH


def test_plain_pattern_unchanged():
    cfg = load_config(SCENE)
    cam = cfg.rig.projector
    img = pattern_image(cfg.pattern, cam)
    ratio = img[..., 2] / np.maximum(img[..., 1], 1e-12)
    lit = img[..., 2] > 1e-3
    np.testing.assert_allclose(ratio[lit], 1.0 / 0.75, rtol=1e-5)
    assert np.all(dot_codes(cfg.pattern, cam) == 0)


def test_coded_panel_keeps_luminance_and_colours():
    cfg = load_config(SCENE)
    cam = cfg.rig.projector
    coded = cfg.pattern.__class__(**{**cfg.pattern.__dict__, "code": "colour"})
    plain, col = pattern_image(cfg.pattern, cam), pattern_image(coded, cam)
    np.testing.assert_allclose(plain[..., 1:].sum(-1), col[..., 1:].sum(-1), atol=1e-5)
    assert np.all(col[..., 0] == 0)
    colours = dot_colours(coded, cam)
    g = colours[:, 1] / colours[:, 1:].sum(1)
    assert set(np.round(g, 6)) <= set(np.round(CODE_LEVELS, 6))


def test_config_rejects_unknown_code():
    cfg = load_config(SCENE)
    from wai_core.config import validate

    with pytest.raises(WaiInputError, match="code"):
        validate(cfg.replace("pattern", code="stripes"))
    assert PatternConfig().code == "none"
