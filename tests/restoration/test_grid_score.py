"""The truth-free grid score: a board seen from under flat water fits the flat-water model
and not a homography; what the water adds on top of it shows in the residual."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from restoration.metrics import object_plane_center, predict_corners
from restoration.video import grid_residual_px, grid_score
from wai_core.errors import WaiInputError
from wai_core.optics import trace_to_object


def _board(cfg) -> tuple[int, int]:
    nx, ny = cfg.object.squares
    return nx - 1, ny - 1


def _flat_view(cfg, supersample: int = 2) -> np.ndarray:
    """Camera v's view of the board through flat water, traced pixel by pixel with Snell's
    law (:func:`wai_core.optics.trace_to_object`, not the renderer), 2 x 2 samples a pixel."""
    cam = cfg.rig.camera_v
    h, w = cfg.camera_v.height_px, cfg.camera_v.width_px
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    centre = object_plane_center(cfg)
    (sx, sy), (nx, ny) = cfg.object.size_mm, cfg.object.squares
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    acc = np.zeros((h, w))
    for dy in offsets:
        for dx in offsets:
            tr = trace_to_object(cam, None, cfg.water.h0_mm, cfg.water.n_water,
                                 cfg.object_z_mm, cols + dx, rows + dy)
            u = (tr.object_mm[..., 0] - centre[0] + sx / 2) / (sx / nx)
            v = (tr.object_mm[..., 1] - centre[1] + sy / 2) / (sy / ny)
            on_board = tr.ok & (u >= 0) & (u < nx) & (v >= 0) & (v < ny)
            cell = np.where((np.floor(u) + np.floor(v)) % 2 == 0, 0.2, 0.9)
            acc += np.where(on_board, cell, 0.0)  # beyond Snell's window: black
    return (acc / supersample**2).astype(np.float32)


@pytest.fixture(scope="module")
def flat_view(paper_cfg) -> np.ndarray:
    return _flat_view(paper_cfg)


@pytest.fixture(scope="module")
def flat_corners(paper_cfg):
    """The board's inner corners through flat water, from the restoration's own ray solver
    (Newton on the pixel), NaN where beyond Snell's window or out of view."""
    px, ok = predict_corners(paper_cfg, None)
    assert ok.sum() >= 40
    return px, ok


def test_flat_water_corners_fit_the_flat_water_model_and_not_a_homography(paper_cfg,
                                                                         flat_corners):
    px, ok = flat_corners
    board = _board(paper_cfg)
    flat = grid_residual_px(px, board, ok, model="flat-water", trim=0.0,
                            n_water=paper_cfg.water.n_water)
    hom = grid_residual_px(px, board, ok)
    assert flat < 0.01
    assert hom > 2.0


def test_a_tilted_camera_under_flat_water_fits_the_flat_water_model():
    """Snell's law by hand: a camera just under the surface sees a board point at tangent q
    from the zenith along the water-side tangent q / sqrt(n^2 + (n^2 - 1)|q|^2); tilting the
    camera by 25 degrees maps those tangents by a homography."""
    n = 1.34
    j, i = np.mgrid[0:7, 0:9]
    grid = np.c_[i.ravel(), j.ravel()].astype(float)
    q = 0.35 * (grid - [3.0, 2.0])
    p = q / np.sqrt(n**2 + (n**2 - 1) * np.sum(q**2, axis=1, keepdims=True))
    t = np.radians(25.0)
    rot = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    k = np.array([[500.0, 0, 400], [0, 500.0, 300], [0, 0, 1]])
    x = np.c_[p, np.ones(len(p))] @ (k @ rot).T
    pts = x[:, :2] / x[:, 2:]
    assert grid_residual_px(pts, (9, 7), model="flat-water", trim=0.0, n_water=n) < 1e-3
    assert grid_residual_px(pts, (9, 7)) > 1.0


@pytest.mark.parametrize("sigma_px", [0.2, 0.5])
def test_a_random_displacement_shows_as_its_rms(paper_cfg, flat_corners, sigma_px):
    """Least squares absorbs a little of a random displacement (12 of about 2 x 100 degrees of
    freedom) and no more: the residual lies just under the displacement's RMS."""
    px, ok = flat_corners
    shift = np.random.default_rng(7).normal(0.0, sigma_px, px.shape)
    rms = np.sqrt(np.mean(np.sum(shift[ok] ** 2, axis=1)))
    res = grid_residual_px(px + shift, _board(paper_cfg), ok, model="flat-water", trim=0.0,
                           n_water=paper_cfg.water.n_water)
    assert 0.8 * rms < res <= rms
    trimmed = grid_residual_px(px + shift, _board(paper_cfg), ok, model="flat-water",
                               n_water=paper_cfg.water.n_water)
    assert 0.6 * rms < trimmed < res


def test_a_flat_water_view_scores_near_zero_and_a_displaced_one_does_not(paper_cfg,
                                                                        flat_view):
    """The traced flat-water view: its corners (the part of the board in view and inside
    Snell's window) lie on the flat-water model within the detector's accuracy; the same view
    warped by a known ripple (RMS 1.5 px, 60 px wavelength) scores a good part of it, and no
    more (the model absorbs the ripple's smooth share across the board)."""
    board, n = _board(paper_cfg), paper_cfg.water.n_water
    flat = grid_score(flat_view, board=board, n_water=n)
    assert flat.found and 0.3 < flat.fraction < 1.0
    assert flat.rms_px < 0.3
    assert grid_score(flat_view, board=board, model="homography").rms_px > 3.0

    h, w = flat_view.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    amp = 1.5
    dx = amp * np.sin(2 * np.pi * yy / 60.0)
    dy = amp * np.cos(2 * np.pi * xx / 60.0)
    rippled = cv2.remap(flat_view, xx + dx, yy + dy, cv2.INTER_CUBIC)
    ripple = grid_score(rippled, board=board, n_water=n)
    assert ripple.found
    assert ripple.rms_px > 3.0 * flat.rms_px
    assert 0.5 * amp < ripple.rms_px < amp


def test_a_valid_mask_drops_the_corners_it_does_not_cover(paper_cfg, flat_view):
    board, n = _board(paper_cfg), paper_cfg.water.n_water
    whole = grid_score(flat_view, board=board, n_water=n)
    valid = np.ones(flat_view.shape, bool)
    valid[:, : flat_view.shape[1] // 2] = False
    half = grid_score(flat_view, board=board, valid=valid, n_water=n)
    assert half.found and 0 < half.used.sum() < whole.used.sum()
    assert np.all(half.corners[half.used, 0] > flat_view.shape[1] // 2)


def test_nothing_to_find_and_bad_input():
    s = grid_score(np.full((60, 80), 0.5, np.float32), board=(8, 6))
    assert not s.found and s.fraction == 0.0 and np.isnan(s.rms_px)
    grid = np.c_[np.arange(16) % 4, np.arange(16) // 4].astype(float)
    with pytest.raises(WaiInputError, match="model"):
        grid_residual_px(grid, (4, 4), model="poly9")
    with pytest.raises(WaiInputError, match="trim"):
        grid_residual_px(grid, (4, 4), trim=0.9)
    with pytest.raises(WaiInputError, match="valid"):
        grid_score(np.zeros((60, 80)), valid=np.ones((6, 8), bool))
    assert np.isnan(grid_residual_px(grid, (4, 4), np.arange(16) < 12, model="flat-water"))


def test_a_grid_that_skips_corners_is_refused():
    """The detector may join every other row of a board cut into pieces, or jump a corner:
    halfway between such neighbours lies a corner, not an edge, and one step doubles."""
    from restoration.video.checkerboard import _skips_corners

    y, x = np.mgrid[0:240, 0:320]
    image = ((((x + 7) // 20 + (y + 3) // 20) % 2) * 255).astype(np.uint8)
    s = grid_score(image, model="homography")
    assert s.found and s.rms_px < 0.1 and min(s.pattern) >= 8
    cols, rows = s.pattern
    grid = s.corners.reshape(rows, cols, 2)
    assert not _skips_corners(image, s.corners, s.pattern)
    for part in (grid[::2], grid[np.r_[0:3, 4:rows]]):  # every other row; row 3 jumped
        assert _skips_corners(image, part.reshape(-1, 2), (cols, part.shape[0]))
    # Two corners found in one place: no step to compare, refused without a warning.
    folded = grid.copy()
    folded[2, 3] = folded[2, 2]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _skips_corners(image, folded.reshape(-1, 2), (cols, rows))


def test_a_distorted_views_score_does_not_depend_on_opencvs_random_state():
    """``findChessboardCornersSB`` draws from OpenCV's random generator, and on a distorted
    view the board it grows can depend on the draw (on this image 1.28, 4.83 or 7.27 px). The data:
    the registration baseline's fused view of `wai experiment compare`'s case U = 1.5 m/s,
    seed 0, no degradation (30 frames, float16)."""
    from tests.conftest import ROOT

    data = np.load(ROOT / "tests" / "data" / "fused_registration_U1.5_seed0.npz")
    image, valid = data["image"].astype(np.float32), data["valid"]
    scores = []
    for seed in (0, 7, 8):  # states that gave three boards before the seed was fixed
        cv2.setRNGSeed(seed)
        scores.append(grid_score(image, valid=valid))
    assert all(s.found for s in scores)
    assert len({s.rms_px for s in scores}) == 1
    assert all(np.array_equal(s.corners, scores[0].corners) for s in scores)
