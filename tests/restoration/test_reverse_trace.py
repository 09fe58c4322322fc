"""Reverse tracing and restoration, checked against facts that do not depend on the code.

The views are rendered geometrically: each pixel's ray is traced to the object plane and an
analytic, smooth texture is read there, so bilinear resampling is accurate and any mismatch is the
restoration's.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_erosion
from skimage.metrics import structural_similarity

from restoration.reverse_trace import (
    RayStatus,
    SplinePatches,
    ViewPlan,
    ViewState,
    find_pixels,
    restore_view,
    solve_pixels,
    trace_to_object,
)
from wai_core.config import load_config, with_keys
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera, Pose
from wai_core.heightfield import Heightfield
from wai_core.port import PortCamera

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "paper.toml"
PERIOD_MM = 150.0  # texture period on the object plane: ~10 pixels of the small camera


@pytest.fixture(scope="module")
def cfg():
    return load_config(SCENE)


@pytest.fixture(scope="module")
def optics(cfg):
    return cfg.water.h0_mm, cfg.water.n_water, cfg.object_z_mm


@pytest.fixture(scope="module")
def small_cam(cfg):
    """Camera v with 4x fewer pixels per side: same pose and field of view, fast renders."""
    v = cfg.rig.camera_v
    return PinholeCamera(200, 150, v.focal_mm, v.pixel_pitch_mm * 4, v.pose)


def _grid():
    x = np.linspace(0.0, 660.0, 67)
    y = np.linspace(-330.0, 330.0, 67)
    xx, yy = np.meshgrid(x, y)
    return x, y, xx, yy


def _wavy(h0):
    x, y, xx, yy = _grid()
    return Heightfield(x, y, h0 + 3.0 * np.sin(xx / 40.0) * np.cos(yy / 50.0))


def _tilted(h0, slope=0.05):
    x, y, xx, yy = _grid()
    return Heightfield(x, y, h0 + slope * (xx - 180.0) + 0.5 * slope * yy)


def _texture(p):
    return 0.5 + 0.35 * np.sin(2 * np.pi * p[..., 0] / PERIOD_MM) * np.cos(
        2 * np.pi * p[..., 1] / PERIOD_MM
    )


def _render(cam, surface, optics):
    cols, rows = cam.pixel_grid()
    tr = trace_to_object(cam, surface, *optics, cols, rows)
    return np.where(tr.ok, _texture(np.nan_to_num(tr.object_mm)), 0.0), tr


def _ssim_inside(img, ref, mask):
    smap = structural_similarity(img, ref, data_range=1.0, full=True)[1]
    return smap[binary_erosion(mask, np.ones((7, 7)), border_value=0)].mean()


# --- Snell's window ---------------------------------------------------------------------------


def test_snells_window_edge_is_the_critical_angle(cfg, optics):
    cam = cfg.rig.camera_v
    cols, rows = cam.pixel_grid(step=2)
    tr = trace_to_object(cam, None, *optics, cols, rows)
    _, dirs = cam.pixel_rays(cols, rows)
    zenith = np.degrees(np.arccos(dirs[..., 2]))
    critical = np.degrees(np.arcsin(3.0 / 4.0))
    assert critical == pytest.approx(48.59, abs=0.01)
    assert 2 * critical == pytest.approx(97.2, abs=0.05)  # the paper's Snell cone
    tir = tr.status == RayStatus.TIR
    assert tir.any() and tr.ok.any()
    # Every ray below the critical angle gets out, every ray above is reflected, and the view
    # samples both sides closely, so the edge found is the critical angle itself.
    assert np.all(tr.ok == (zenith < critical))
    assert zenith[tr.ok].max() == pytest.approx(critical, abs=0.1)
    assert zenith[tir].min() == pytest.approx(critical, abs=0.1)


def test_flat_refraction_obeys_snell(cfg, optics):
    cam = cfg.rig.camera_v
    cols, rows = cam.pixel_grid(step=37)
    tr = trace_to_object(cam, None, *optics, cols, rows)
    _, dirs = cam.pixel_rays(cols, rows)
    air = tr.object_mm - tr.surface_mm
    sin_air = np.linalg.norm(air[..., :2], axis=-1) / np.linalg.norm(air, axis=-1)
    sin_water = np.linalg.norm(dirs[..., :2], axis=-1)
    np.testing.assert_allclose(sin_air[tr.ok], optics[1] * sin_water[tr.ok], rtol=1e-9)
    np.testing.assert_allclose(tr.surface_mm[tr.ok][:, 2], optics[0])
    np.testing.assert_allclose(tr.object_mm[tr.ok][:, 2], optics[2])


# --- surface model ----------------------------------------------------------------------------


def test_spline_patches_match_the_heightfield():
    """The solver's per-cell polynomials give FITPACK's values and derivatives, and NaN exactly
    where the heightfield does not know the surface (outside, and next to unknown samples)."""
    x = np.r_[0.0, 7.0, np.linspace(15.0, 300.0, 40)]  # non-uniform cells too
    y = np.linspace(-100.0, 120.0, 31)
    xx, yy = np.meshgrid(x, y)
    z = 150.0 + 2.0 * np.sin(xx / 23.0) * np.cos(yy / 17.0) + 1e-3 * xx * yy
    z[5:9, 10:13] = np.nan
    hf = Heightfield(x, y, z)
    rng = np.random.default_rng(4)
    px = np.r_[rng.uniform(-5.0, 305.0, 5000), x[[0, -1, 5]], 100.0]
    py = np.r_[rng.uniform(-105.0, 125.0, 5000), y[[0, -1, 3]], y[-1]]
    h, hx, hy, hxx, hxy, hyy = SplinePatches(hf).jet(px, py)
    known = hf.contains(px, py)
    np.testing.assert_array_equal(np.isfinite(h), known)
    gx, gy = hf.gradient(px, py)
    np.testing.assert_allclose(h[known], hf.height(px, py)[known], atol=1e-10)
    np.testing.assert_allclose(hx[known], gx[known], atol=1e-10)
    np.testing.assert_allclose(hy[known], gy[known], atol=1e-10)
    spline = hf._spline  # FITPACK: first axis y
    for value, dx, dy in ((hxx, 2, 0), (hxy, 1, 1), (hyy, 0, 2)):
        ref = spline.ev(py[known], px[known], dx=dy, dy=dx)
        np.testing.assert_allclose(value[known], ref, atol=1e-9)


# --- inverse map ------------------------------------------------------------------------------


@pytest.mark.parametrize("wavy, port_mm", [(False, 0.0), (True, 0.0), (False, 10.0),
                                            (True, 10.0)])
def test_find_pixels_inverts_trace_to_object(cfg, optics, wavy, port_mm):
    """The Newton solve inverts the forward trace, also for camera v behind a 10 mm port
    10 mm from its pinhole (a non-central camera: wai_core.port.PortCamera)."""
    if port_mm:
        ported = with_keys(cfg, {"camera_v.port_thickness_mm": port_mm,
                                 "camera_v.port_gap_mm": 10.0})
        cam = ported.rig.camera_model("camera_v")
        assert isinstance(cam, PortCamera)
    else:
        cam = cfg.rig.camera_v
    surface = _wavy(optics[0]) if wavy else None
    cols, rows = cam.pixel_grid(step=10)
    tr = trace_to_object(cam, surface, *optics, cols, rows)
    truth = np.stack([cols, rows], axis=-1)
    px, ok = find_pixels(cam, surface, *optics, tr.object_mm, truth + [3.0, -2.0])
    assert ok[tr.ok].mean() > 0.999  # at most a ray or two at the very edge of the window
    assert not ok[~tr.ok].any()  # no pixel found for targets that no ray reaches
    err = np.linalg.norm(px - truth, axis=-1)[ok]
    assert err.max() < 1e-3


def test_solve_pixels_reports_why(cfg, optics):
    cam = cfg.rig.camera_v
    h0, n, za = optics
    x, y, xx, _ = _grid()
    patch = Heightfield(x, y, np.where(xx < 160.0, h0, np.nan))  # known only for x < 160 mm
    # Seen through x ~ 111 mm (inside the patch), x ~ 240 mm (outside it), and no target.
    targets = np.array([[150.0, 0.0, za], [2000.0, 0.0, za], [np.nan, 0.0, za]])
    start = [[400.0, 300.0]] * 3  # its ray crosses the water at x ~ 180 mm, off the patch
    sol = solve_pixels(cam, patch, h0, n, za, targets, start)
    flat = solve_pixels(cam, None, h0, n, za, targets, start)
    assert list(sol.status) == [RayStatus.OK, RayStatus.MISSED_SURFACE, RayStatus.MISSED_OBJECT]
    assert list(flat.status) == [RayStatus.OK, RayStatus.OK, RayStatus.MISSED_OBJECT]
    np.testing.assert_allclose(sol.px[0], flat.px[0], atol=1e-3)
    assert sol.surface_mm[0, 0] == pytest.approx(111.0, abs=2.0)
    assert flat.surface_mm[1, 0] == pytest.approx(240.0, abs=10.0)
    assert np.all(np.isnan(sol.px[1:]))


def test_find_pixels_rejects_bad_input(cfg, optics):
    cam = cfg.rig.camera_v
    with pytest.raises(WaiInputError):
        find_pixels(cam, None, *optics, np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(WaiInputError):  # not on the object plane
        find_pixels(cam, None, *optics, [[0.0, 0.0, 500.0]], [[400.0, 300.0]])
    with pytest.raises(WaiInputError):
        find_pixels(cam, None, optics[0], 0.9, optics[2], [[0.0, 0.0, optics[2]]], [[0, 0]])


# --- restoration ------------------------------------------------------------------------------


def test_flat_estimate_restores_the_flat_view_exactly(cfg, optics):
    cam = cfg.rig.camera_v
    truth, tr = _render(cam, None, optics)
    h0 = optics[0]
    x, y, xx, _ = _grid()
    flat = Heightfield(x, y, np.full(xx.shape, h0))
    rgb = np.stack([truth, 1.0 - truth, 0.5 * truth], axis=-1).astype(np.float32)
    res = restore_view(rgb, cam, flat, *optics, warp_step_px=8)
    assert res.image.shape == rgb.shape and res.image.dtype == np.float32
    assert res.valid.mean() > 0.6
    assert not (res.valid & ~tr.ok).any()  # never restores a pixel that sees no object
    assert np.all(res.image[~res.valid] == 0)
    # The warp is the identity to within the solver's tolerance.
    dev = res.warp_px[res.valid] - np.stack(cam.pixel_grid(), axis=-1)[res.valid]
    assert np.abs(dev).max() < 2e-3
    mse = np.mean((res.image[res.valid] - rgb[res.valid]) ** 2)
    assert mse < 1e-8
    assert _ssim_inside(res.image[..., 0], truth.astype(np.float32), res.valid) > 0.9999
    assert sum(res.counts.values()) == cam.width_px * cam.height_px
    assert res.counts["ok"] == res.valid.sum()
    assert res.counts["tir"] >= (~tr.ok).sum()  # coarse cells lose a little more at the edge


def test_tilted_plane_is_undone_by_the_same_plane(small_cam, optics):
    """A tilted plane shifts and shears the view by several pixels (SSIM ~0.35 against the
    truth). Restoring with the same plane brings it back to SSIM > 0.98. What remains is
    resampling: the distorted image holds the texture (period ~10 px) only at pixel centres,
    and bilinear reading between them damps it by up to 1 - cos(pi / 10) ~ 5 %. Scoring keeps
    to air angles below 60 deg; beyond, towards the edge of Snell's window, the object plane is
    squeezed into few pixels and the texture aliases in both renders."""
    tilt = _tilted(optics[0])
    truth, tr = _render(small_cam, None, optics)
    distorted, _ = _render(small_cam, tilt, optics)
    air = tr.object_mm - tr.surface_mm
    core = tr.ok & (air[..., 2] / np.linalg.norm(air, axis=-1) > np.cos(np.radians(60)))
    res = restore_view(distorted, small_cam, tilt, *optics, warp_step_px=4)
    mask = res.valid & core
    assert mask.sum() > 0.5 * core.sum()
    assert _ssim_inside(res.image, truth, mask) > 0.98
    assert np.mean((res.image - truth)[mask] ** 2) < 2e-3
    naive = restore_view(distorted, small_cam, None, *optics, warp_step_px=4)
    assert _ssim_inside(naive.image, truth, naive.valid & core) < 0.6
    assert np.mean((naive.image - truth)[naive.valid & core] ** 2) > 10 * np.mean(
        (res.image - truth)[mask] ** 2
    )


def test_unknown_surface_is_masked_and_counted(small_cam, optics):
    h0 = optics[0]
    x, y, xx, _ = _grid()
    patch = Heightfield(x, y, np.where(xx < 160.0, h0, np.nan))
    truth, tr = _render(small_cam, None, optics)
    res = restore_view(truth, small_cam, patch, *optics, warp_step_px=8)
    full = restore_view(truth, small_cam, None, *optics, warp_step_px=8)
    assert res.counts["missed_surface"] > 0
    assert res.valid.sum() + res.counts["missed_surface"] <= full.valid.sum() + 64 * 4
    assert np.all(res.image[~res.valid] == 0)
    assert np.all(np.isnan(res.warp_px[~res.valid]))
    assert sum(res.counts.values()) == truth.size
    # Where it is known the patch is flat water: those pixels are restored exactly.
    np.testing.assert_allclose(res.image[res.valid], truth[res.valid], atol=1e-6)


@pytest.mark.parametrize("step", [5, 8])
def test_coarse_warp_matches_the_per_pixel_warp(small_cam, optics, step):
    """The warp solved every ``step`` px and interpolated bilinearly stays within 0.05 px of the
    warp solved at every pixel, up to air angles of 60 deg (this camera's pixels are 4x
    coarser than camera v's, so its 8 px cells span what 32 px do there)."""
    tilt = _tilted(optics[0])
    distorted, _ = _render(small_cam, tilt, optics)
    _, tr = _render(small_cam, None, optics)
    air = tr.object_mm - tr.surface_mm
    core = tr.ok & (air[..., 2] / np.linalg.norm(air, axis=-1) > np.cos(np.radians(60)))
    ref = restore_view(distorted, small_cam, tilt, *optics, warp_step_px=1)
    res = restore_view(distorted, small_cam, tilt, *optics, warp_step_px=step)
    both = ref.valid & res.valid & core
    assert both.sum() > 0.9 * (ref.valid & core).sum()
    assert np.abs(res.warp_px[both] - ref.warp_px[both]).max() < 0.05


def test_restore_view_keeps_dtype_and_channels(small_cam, optics):
    truth, _ = _render(small_cam, None, optics)
    gray = restore_view(truth, small_cam, None, *optics)
    assert gray.image.dtype == np.float64 and gray.image.shape == truth.shape
    rgba = np.repeat(truth[..., None], 4, axis=2).astype(np.float32)
    res = restore_view(rgba, small_cam, None, *optics)
    assert res.image.dtype == np.float32 and res.image.shape == rgba.shape
    np.testing.assert_allclose(res.image[..., 3], gray.image, atol=1e-6)


def test_restore_view_rejects_bad_input(small_cam, optics):
    img = np.zeros((150, 200))
    with pytest.raises(WaiInputError):
        restore_view(np.zeros((100, 200)), small_cam, None, *optics)
    with pytest.raises(WaiInputError):
        restore_view(img.astype(np.uint8), small_cam, None, *optics)
    with pytest.raises(WaiInputError):
        restore_view(np.full((150, 200), np.nan), small_cam, None, *optics)
    with pytest.raises(WaiInputError):
        restore_view(img, small_cam, None, *optics, warp_step_px=0)
    with pytest.raises(WaiInputError):
        restore_view(img, small_cam, None, optics[0], optics[1], optics[0] - 1.0)


def test_a_passed_plan_and_table_give_the_same_view(small_cam, optics):
    """A rig's :class:`ViewPlan` and a frame's :class:`SplinePatches`, built once and passed,
    restore exactly what restore_view builds for itself."""
    wavy = _wavy(optics[0])
    distorted, _ = _render(small_cam, wavy, optics)
    own = restore_view(distorted, small_cam, wavy, *optics, warp_step_px=5, gain=1.5)
    plan = ViewPlan.build(small_cam, *optics, 5)
    patches = SplinePatches(wavy)
    for _ in range(2):  # reused
        got = restore_view(distorted, small_cam, wavy, *optics, warp_step_px=5, gain=1.5,
                           plan=plan, patches=patches)
        np.testing.assert_array_equal(got.image, own.image)
        np.testing.assert_array_equal(got.map_px, own.map_px)
        assert got.counts == own.counts


def test_a_plan_or_table_of_something_else_is_refused(small_cam, optics):
    img = np.zeros((150, 200))
    wavy = _wavy(optics[0])
    h0, n, z = optics
    with pytest.raises(WaiInputError, match="plan"):  # another step
        restore_view(img, small_cam, wavy, *optics, plan=ViewPlan.build(small_cam, *optics, 4))
    with pytest.raises(WaiInputError, match="plan"):  # another water level
        restore_view(img, small_cam, wavy, *optics, plan=ViewPlan.build(small_cam, h0 + 1, n, z))
    pose = Pose(small_cam.pose.R, small_cam.pose.t_mm + np.array([1.0, 0.0, 0.0]))
    moved = PinholeCamera(200, 150, small_cam.focal_mm, small_cam.pixel_pitch_mm, pose)
    with pytest.raises(WaiInputError, match="plan"):  # another pose
        restore_view(img, small_cam, wavy, *optics, plan=ViewPlan.build(moved, *optics))
    with pytest.raises(WaiInputError, match="another surface"):  # an equal copy is not it
        restore_view(img, small_cam, wavy, *optics,
                     patches=SplinePatches(Heightfield(wavy.x, wavy.y, wavy.z)))
    with pytest.raises(WaiInputError, match="warp_step_px"):
        ViewPlan.build(small_cam, *optics, 0)



def test_a_reused_plan_leaves_earlier_frames_views_alone(small_cam, optics):
    """The plan's scratch arrays serve frame after frame: a view handed out stays as it was
    when the next frame restores, and each equals what a fresh plan gives. While another
    frame holds the scratch (a thread), and after pickling, the views are the same."""
    h0 = optics[0]
    waves = [_wavy(h0), _tilted(h0)]
    images = [_render(small_cam, w, optics)[0].astype(np.float32) for w in waves]
    fresh = [restore_view(img, small_cam, w, *optics, gain=1.5)
             for img, w in zip(images, waves, strict=True)]
    plan = ViewPlan.build(small_cam, *optics)
    first = restore_view(images[0], small_cam, waves[0], *optics, gain=1.5, plan=plan)
    kept = first.image.copy(), first.valid.copy()
    second = restore_view(images[1], small_cam, waves[1], *optics, gain=1.5, plan=plan)
    assert not np.array_equal(first.image, second.image)  # two different frames
    np.testing.assert_array_equal(first.image, kept[0])
    np.testing.assert_array_equal(first.valid, kept[1])
    for got, want in ((first, fresh[0]), (second, fresh[1])):
        np.testing.assert_array_equal(got.image, want.image)
        np.testing.assert_array_equal(got.map_px, want.map_px)  # upsampled when read
    with plan.workspace.borrow(*plan.image_shape):  # held elsewhere: fresh arrays
        held = restore_view(images[0], small_cam, waves[0], *optics, gain=1.5, plan=plan)
    np.testing.assert_array_equal(held.image, fresh[0].image)
    copied = pickle.loads(pickle.dumps(plan))
    again = restore_view(images[1], small_cam, waves[1], *optics, gain=1.5, plan=copied)
    np.testing.assert_array_equal(again.image, fresh[1].image)


def test_a_warm_start_agrees_with_a_cold_one_to_the_tolerance(small_cam, optics):
    """A sequence's state starts each frame's solve at the previous frame's solution: the
    warp agrees with a cold start's to the solver's tolerance (second order in its last step,
    well below 0.05 px) wherever both restore, and no node a cold start solves is lost. A
    state of another plan starts cold (the same view to the bit)."""
    h0 = optics[0]
    x, y, xx, yy = _grid()
    frames = [Heightfield(x, y, h0 + 3.0 * np.sin((xx - 4.0 * k) / 40.0) * np.cos(yy / 50.0))
              for k in range(3)]
    images = [_render(small_cam, f, optics)[0] for f in frames]
    plan = ViewPlan.build(small_cam, *optics, 5)
    state = ViewState()
    for img, surface in zip(images, frames, strict=True):
        cold = restore_view(img, small_cam, surface, *optics, warp_step_px=5, plan=plan)
        warm = restore_view(img, small_cam, surface, *optics, warp_step_px=5, plan=plan,
                            state=state)
        both = cold.valid & warm.valid
        assert both.sum() > 0.9 * cold.valid.sum() and warm.counts["ok"] >= cold.counts["ok"]
        assert np.abs(warm.map_px[both] - cold.map_px[both]).max() < 0.01
    other = ViewPlan.build(small_cam, *optics, 4)
    got = restore_view(images[0], small_cam, frames[0], *optics, warp_step_px=4, plan=other,
                       state=state)
    want = restore_view(images[0], small_cam, frames[0], *optics, warp_step_px=4)
    np.testing.assert_array_equal(got.map_px, want.map_px)
    with pytest.raises(WaiInputError, match="state"):
        restore_view(images[0], small_cam, frames[0], *optics, state="warm")
