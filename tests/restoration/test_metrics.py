"""Scoring functions, checked against hand values and synthetic images with known answers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from restoration.metrics import (
    checkerboard_corners_lab,
    corner_offsets,
    corner_spread,
    image_metrics,
    object_plane_center,
    predict_corners,
    psnr_db,
    refine_corners,
    score_corners,
    surface_errors,
)
from restoration.reverse_trace import restore_view, trace_to_object
from wai_core.config import load_config
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.heightfield import Heightfield

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "paper.toml"


@pytest.fixture(scope="module")
def cfg():
    return load_config(SCENE)


def _sea(x, y):
    xx, yy = np.meshgrid(x, y)
    return 150.0 + 3.0 * np.sin(xx / 40.0) * np.cos(yy / 50.0)


# --- surface ----------------------------------------------------------------------------------


def test_constant_offset_is_all_bias():
    x, y = np.linspace(0, 660, 133), np.linspace(-330, 330, 133)
    truth = Heightfield(x, y, _sea(x, y))
    xe, ye = np.linspace(100, 400, 61), np.linspace(-150, 150, 61)
    xx, yy = np.meshgrid(xe, ye)
    est = Heightfield(xe, ye, truth.height(xx, yy) + 2.0)
    e = surface_errors(est, truth)
    assert e["rmse_mm"] == pytest.approx(2.0, abs=1e-9)
    assert e["rmse_demeaned_mm"] == pytest.approx(0.0, abs=1e-9)
    assert e["mean_offset_mm"] == pytest.approx(2.0, abs=1e-9)
    assert e["max_abs_mm"] == pytest.approx(2.0, abs=1e-9)
    assert e["n_points"] == 61 * 61
    assert e["error_map_mm"].shape == (61, 61)


def test_unknown_points_are_left_out():
    x, y = np.linspace(0, 660, 67), np.linspace(-330, 330, 67)
    truth = Heightfield(x, y, _sea(x, y))
    z = truth.z.copy()
    z[:, :10] = np.nan
    z[5, 20] += 4.0  # one bad sample: rmse = 4 / sqrt(n)
    e = surface_errors(Heightfield(x, y, z), truth)
    n = 67 * 57
    assert e["n_points"] == n
    assert e["rmse_mm"] == pytest.approx(4.0 / np.sqrt(n), rel=1e-9)
    assert e["max_abs_mm"] == pytest.approx(4.0, rel=1e-9)
    assert np.isnan(e["error_map_mm"][:, :10]).all()


def test_disjoint_surfaces_raise():
    x, y = np.linspace(0, 100, 11), np.linspace(0, 100, 11)
    far = Heightfield(x + 500, y, _sea(x, y))
    with pytest.raises(WaiInputError):
        surface_errors(far, Heightfield(x, y, _sea(x, y)))


# --- images -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def photo():
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:80, 0:100]
    base = 0.5 + 0.3 * np.sin(xx / 5.0) * np.cos(yy / 7.0)
    return np.clip(base[..., None] + 0.05 * rng.standard_normal((80, 100, 3)), 0, 1)


@pytest.mark.parametrize("gray", [False, True])
def test_identical_images_score_perfectly(photo, gray):
    img = photo[..., 0] if gray else photo
    m = image_metrics(img, img.copy())
    assert m["mse"] == 0.0
    assert m["psnr_db"] == float("inf")
    assert m["ssim"] == pytest.approx(1.0, abs=1e-12)
    assert m["n_pixels"] == 80 * 100


def test_psnr_is_eq46_on_unit_images(photo):
    assert psnr_db(0.01) == pytest.approx(20.0, abs=1e-12)
    # Table 2 of the paper: MSE 0.1367 <-> PSNR 8.6414 dB (data 1, distorted) only if max = 1.
    assert psnr_db(0.1367) == pytest.approx(8.6414, abs=2e-3)
    truth = np.full((40, 50), 0.3)
    m = image_metrics(truth + 0.1, truth)
    assert m["mse"] == pytest.approx(0.01, rel=1e-12)
    assert m["psnr_db"] == pytest.approx(20.0, abs=1e-9)


def test_values_are_clipped_to_unit_range():
    truth = np.ones((30, 30))
    m = image_metrics(np.full((30, 30), 1.5), truth)
    assert m["mse"] == 0.0


def test_only_the_mask_counts(photo):
    damaged = photo.copy()
    damaged[:, 60:] = 0.0  # e.g. masked (TIR) pixels of a restoration
    mask = np.zeros(photo.shape[:2], bool)
    mask[:, :60] = True
    m = image_metrics(damaged, photo, mask)
    assert m["mse"] == 0.0
    assert m["ssim"] == pytest.approx(1.0, abs=1e-12)  # windows touching column 60 are dropped
    assert m["n_pixels"] == 80 * 60
    assert m["n_ssim_pixels"] == (80 - 6) * (60 - 6)
    unmasked = image_metrics(damaged, photo)
    assert unmasked["ssim"] < 0.9 and unmasked["mse"] > 0.05


def test_image_metrics_rejects_bad_input(photo):
    with pytest.raises(WaiInputError):
        image_metrics(photo, photo[:-1])
    with pytest.raises(WaiInputError):
        image_metrics(photo, photo, np.zeros(photo.shape[:2], bool))
    with pytest.raises(WaiInputError):
        image_metrics(np.full_like(photo, np.nan), photo)
    with pytest.raises(WaiInputError):
        image_metrics(photo, photo, win_size=4)


# --- checkerboard -----------------------------------------------------------------------------


def test_object_plane_center_by_hand(cfg):
    # Camera v: centre (107, 0, ~0) mm, axis tilted 26 deg towards +x (Table 1's R).
    cam = cfg.rig.camera_v
    o = cam.pose.center_lab_mm
    tilt = np.arctan2(cam.pose.axis_lab[0], cam.pose.axis_lab[2])
    assert np.degrees(tilt) == pytest.approx(26.0, abs=0.05)
    x_water = o[0] + (150.0 - o[2]) * np.tan(tilt)
    air = np.arcsin(4.0 / 3.0 * np.sin(tilt))  # Snell at flat water
    x_obj = x_water + 1000.0 * np.tan(air)
    np.testing.assert_allclose(object_plane_center(cfg), [x_obj, 0.0, 1150.0], atol=0.01)
    assert x_obj == pytest.approx(900.4, abs=0.5)


def test_checkerboard_inner_corners(cfg):
    corners = checkerboard_corners_lab(cfg)
    assert corners.shape == (11, 15, 3)  # 12 x 16 squares
    np.testing.assert_allclose(np.diff(corners[..., 0], axis=1), 200.0)  # 3200 mm / 16
    np.testing.assert_allclose(np.diff(corners[..., 1], axis=0), 200.0)  # 2400 mm / 12
    np.testing.assert_allclose(corners.reshape(-1, 3).mean(0), object_plane_center(cfg))
    np.testing.assert_allclose(corners[..., 2], cfg.object_z_mm)


def _rotated_board(shape=(160, 200), square=20.0, angle_deg=10.0, origin=(100.3, 80.6), ss=4):
    """Checkerboard image with corners at known sub-pixel positions (area-sampled)."""
    h, w = shape
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    off = (np.arange(ss) + 0.5) / ss - 0.5
    img = np.zeros(shape)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    for a in off:
        for b in off:
            u = (c * (xx + a - origin[0]) + s * (yy + b - origin[1])) / square
            v = (-s * (xx + a - origin[0]) + c * (yy + b - origin[1])) / square
            img += np.where((np.floor(u) + np.floor(v)) % 2 == 0, 0.9, 0.1)
    img /= ss * ss
    k = np.arange(-3, 4)
    ku, kv = np.meshgrid(k, k)
    ku, kv = ku.ravel() * square, kv.ravel() * square
    corners = np.stack([origin[0] + c * ku - s * kv, origin[1] + s * ku + c * kv], axis=1)
    return img, corners


def test_refine_corners_finds_known_corners():
    img, corners = _rotated_board()
    rng = np.random.default_rng(0)
    init = corners + rng.uniform(-2.0, 2.0, corners.shape)
    px, ok = refine_corners(np.repeat(img[..., None], 3, axis=2), init, win=5)
    inside = (corners.min(1) > 7) & (corners[:, 0] < 192) & (corners[:, 1] < 152)
    assert ok[inside].all()
    assert np.abs(px[ok] - corners[ok]).max() < 0.1


def test_refine_corners_rejects_non_corners():
    img, corners = _rotated_board()
    c = corners[24]  # the origin corner, well inside
    d = np.array([np.cos(np.radians(10)), np.sin(np.radians(10))])
    e = np.array([-d[1], d[0]])
    flat = c + 10.0 * d + 10.0 * e  # middle of a square
    edge = c + 10.0 * d  # middle of an edge
    px, ok = refine_corners(img, np.array([c, flat, edge, [np.nan, 5.0], [2.0, 2.0]]), win=5)
    assert list(ok) == [True, False, False, False, False]
    assert np.isnan(px[1:]).all()


def test_corner_spread_by_hand():
    d = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0], [50.0, 50.0]])
    used = np.array([True, True, True, True, False])
    s = corner_spread(d, used)
    assert s["std_px"] == pytest.approx(1.0) and s["rms_px"] == pytest.approx(1.0)
    assert s["n_used"] == 4 and s["n_lost"] == 1
    shifted = corner_spread(d + [3.0, 4.0], used)  # a common shift: no spread, rms 5
    assert shifted["std_px"] == pytest.approx(1.0)
    assert corner_spread(np.tile([3.0, 4.0], (4, 1)), np.ones(4, bool))["std_px"] == 0.0
    assert corner_spread(np.tile([3.0, 4.0], (4, 1)), np.ones(4, bool))["rms_px"] == 5.0
    assert np.isnan(corner_spread(d, np.zeros(5, bool))["std_px"])
    one = corner_spread(d, np.eye(5, dtype=bool)[0])  # a single corner has no spread
    assert np.isnan(one["std_px"]) and one["n_used"] == 1 and one["n_lost"] == 4


def test_corner_offsets_need_both():
    px = np.array([[1.0, 1.0], [2.0, 2.0], [np.nan, np.nan]])
    ref = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    d, used = corner_offsets(px, [True, True, False], ref, [True, False, True])
    assert list(used) == [True, False, False]
    np.testing.assert_allclose(d[0], [1.0, 1.0])
    assert np.isnan(d[1:]).all()


def test_corners_through_flat_water_are_inside_snells_window(cfg):
    px, ok = predict_corners(cfg, None)
    assert 0 < ok.sum() < 165  # the board is wider than the window: some corners are lost
    cam = cfg.rig.camera_v
    tr = trace_to_object(
        cam, None, cfg.water.h0_mm, cfg.water.n_water, cfg.object_z_mm, px[ok, 0], px[ok, 1]
    )
    np.testing.assert_allclose(
        tr.object_mm, checkerboard_corners_lab(cfg).reshape(-1, 3)[ok], atol=1e-2
    )


def test_fig15_statistic_on_geometric_renders(cfg):
    """Render a checkerboard geometrically (2x2 samples per pixel) through flat water and
    through a wavy surface, restore with the true surface, and score the corners: the wave
    scatters them by pixels, the restoration brings them back to within the detector's noise."""
    v = cfg.rig.camera_v
    cam = PinholeCamera(200, 150, v.focal_mm, v.pixel_pitch_mm * 4, v.pose)
    h0, n, za = cfg.water.h0_mm, cfg.water.n_water, cfg.object_z_mm
    x, y = np.linspace(0, 660, 67), np.linspace(-330, 330, 67)
    sea = Heightfield(x, y, _sea(x, y))
    c = object_plane_center(cfg)
    (sx, sy), (nx, ny) = cfg.object.size_mm, cfg.object.squares

    def board(p):
        i = np.floor((p[..., 0] - c[0] + sx / 2) / (sx / nx))
        j = np.floor((p[..., 1] - c[1] + sy / 2) / (sy / ny))
        on = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        return np.where(on, np.where((i + j) % 2 == 0, 0.05, 0.95), 0.5)

    def render(surface):
        cols, rows = cam.pixel_grid()
        out = 0.0
        for a in (-0.25, 0.25):
            for b in (-0.25, 0.25):
                tr = trace_to_object(cam, surface, h0, n, za, cols + a, rows + b)
                out = out + np.where(tr.ok, board(np.nan_to_num(tr.object_mm)), 0.0)
        return out / 4

    truth, distorted = render(None), render(sea)
    res = restore_view(distorted, cam, sea, h0, n, za, warp_step_px=4)
    sc = score_corners(cfg, truth, distorted, res.image, sea, res.valid, win=2, camera=cam)
    assert sc["truth"]["n_found"] > 80
    assert sc["truth"]["detector"]["rms_px"] < 0.3
    assert sc["restored"]["n_used"] > 80
    assert sc["restored"]["std_px"] < 0.5
    assert sc["distorted"]["std_px"] > 3 * sc["restored"]["std_px"]
    for view in ("distorted", "restored"):
        assert sc[view]["n_used"] + sc[view]["n_lost"] == 165
    assert sc["points_px"]["distorted"].shape == (165, 2)


def test_corner_window_and_angular_pixels_follow_the_focal_length():
    from restoration.metrics import CORNER_REF_FOCAL_PX, angular_px, corner_window_px

    cfg = load_config(SCENE)
    cam = cfg.rig.camera_v
    assert cam.focal_px == pytest.approx(CORNER_REF_FOCAL_PX)  # the tuning: 800 x 600
    assert corner_window_px(cam) == 5
    fine = cfg.replace("camera_v", width_px=1600, height_px=1200).rig.camera_v
    assert corner_window_px(fine) == 10
    assert angular_px(0.3, fine) == pytest.approx(0.15)  # x 800 / 1600
    assert angular_px(0.3, cam) == pytest.approx(0.3)
    assert angular_px(None, cam) is None
    small = cfg.replace("camera_v", width_px=200, height_px=150).rig.camera_v
    assert corner_window_px(small) == 2  # at least 2 px


def test_a_view_restored_nowhere_on_the_object_has_no_image_scores(paper_cfg):
    # A frame whose restored view holds no valid pixel (every ray failed) is scored on its
    # surface alone, not refused: its image scores are absent and its restored share 0.
    import numpy as np

    from restoration import RestoredView, RestoreResult, Truth, score
    from restoration.calibration import Calibration

    cal = Calibration(paper_cfg)
    h, w = cal.image_size("view")
    truth_view = np.full((h, w, 3), 0.5, np.float32)
    result = RestoreResult("x", view=RestoredView(np.zeros((h, w, 3)), np.zeros((h, w), bool)))
    s = score(result, truth_view, cal, Truth(None, truth_view))
    assert s.restored is None and s.distorted is None and s.view_restored_fraction == 0.0
    assert "restored" not in s.to_dict()
