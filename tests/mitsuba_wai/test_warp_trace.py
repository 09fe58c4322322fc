"""Camera v's exact warp traced by Dr.Jit (:class:`mitsuba_wai.ViewWarpTracer`) against the
vectorised light path it compresses: each pixel traced through the surface to the object plane
(:func:`wai_core.optics.trace_to_object`) and the object point taken back through flat water
(:func:`wai_core.light_paths.flat_pixel_of`)."""

from __future__ import annotations

import numpy as np
import pytest

from wai_core import load_system
from wai_core.heightfield import Heightfield
from wai_core.light_paths import flat_pixel_of
from wai_core.optics import trace_to_object


@pytest.mark.parametrize(("wind_m_s", "height_scale"), [(0.6, 1.0), (2.0, 1.0), (1.0, 3.0)])
def test_the_traced_warp_is_trace_to_object_then_flat_pixel_of(wind_m_s: float,
                                                               height_scale: float) -> None:
    from mitsuba_wai import ViewWarpTracer, wave_surface

    cfg = load_system("paper").replace("camera_v", width_px=160, height_px=120).replace(
        "waves", wind_speed_m_s=wind_m_s, time_s=3.0, seed=11, height_scale=height_scale)
    surf = wave_surface(cfg)
    cam = cfg.rig.camera_v
    points = trace_to_object(cam, surf, cfg.water.h0_mm, cfg.water.n_water,
                             cfg.object_z_mm, *cam.pixel_grid()).object_mm
    want = np.stack(flat_pixel_of(cfg.rig, points), axis=-1)
    ok = np.isfinite(want[..., 0])
    assert ok.mean() > 0.5  # the rest is totally reflected or misses the object
    got = ViewWarpTracer(cfg.rig)(cfg.rig, surf)
    assert got.shape == (120, 160, 2) and got.dtype == np.float32
    # Every ray starts from the mean plane here, from its neighbour's hit there: a ray that
    # crosses the surface twice may settle elsewhere, and none may be lost or gained besides.
    differ = np.isfinite(got[..., 0]) != ok
    assert differ.mean() < 1e-3
    both = ok & ~differ
    err = np.abs(got[both] - want[both]).max(axis=-1)
    assert np.mean(err < 1e-3) > 0.999
    # How far the waves move the pixels: the agreement above is not a flat sea's.
    cols, rows = cam.pixel_grid()
    assert np.percentile(np.hypot(want[..., 0] - cols, want[..., 1] - rows)[ok], 90) > 0.5


def test_a_tilted_plane_moves_the_view_as_snell_says() -> None:
    # A plane tilted by a known slope: each pixel's object point by Snell's law written out
    # here, taken back through flat water, against the tracer.
    from mitsuba_wai import ViewWarpTracer

    cfg = load_system("paper").replace("camera_v", width_px=64, height_px=48)
    h0, n = cfg.water.h0_mm, cfg.water.n_water
    x = y = np.linspace(-800.0, 800.0, 41)
    slope = 0.05
    surf = Heightfield(x, y, h0 + slope * x[None, :] + 0.0 * y[:, None])
    cam = cfg.rig.camera_v
    origin, dirs = cam.pixel_rays(*cam.pixel_grid())
    t = (h0 - origin[2] + slope * origin[0]) / (dirs[..., 2] - slope * dirs[..., 0])
    hit = origin + t[..., None] * dirs
    normal = np.array([-slope, 0.0, 1.0]) / np.sqrt(1.0 + slope**2)
    cos_i = dirs @ normal
    k = 1.0 - n**2 * (1.0 - cos_i**2)
    lit = k >= 0
    # Snell's law in vector form with the normal facing the ray (-N: both point up here).
    out = n * dirs - (n * cos_i - np.sqrt(np.where(lit, k, 0.0)))[..., None] * normal
    s = (cfg.object_z_mm - hit[..., 2]) / out[..., 2]
    obj = hit + s[..., None] * out
    want = np.stack(flat_pixel_of(cfg.rig, obj), axis=-1)
    got = ViewWarpTracer(cfg.rig)(cfg.rig, surf)
    keep = lit & np.isfinite(got[..., 0])
    assert keep.mean() > 0.5
    np.testing.assert_allclose(got[keep], want[keep], rtol=0, atol=1e-3)
