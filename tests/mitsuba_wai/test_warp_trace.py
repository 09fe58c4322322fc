"""Camera v's exact warp traced by Dr.Jit (:class:`mitsuba_wai.ViewWarpTracer`) against Snell's
law written out on a tilted plane (on wavy seas against the vectorised light path:
``tests/wai/test_dataset.py``)."""

from __future__ import annotations

import numpy as np

from wai_core import load_system
from wai_core.heightfield import Heightfield
from wai_core.light_paths import flat_pixel_of


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
