"""The exact warp between camera v's views through the true surface and through flat water."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield
from wai_core.light_paths import view_warp_px

__all__ = ["NEWTON_STEPS", "true_view_warp"]


def true_view_warp(cfg: SystemConfig, surface: Heightfield,
                   rays: tuple[NDArray, NDArray] | None = None) -> NDArray[np.float32]:
    """Where each pixel of camera v's view through ``surface`` appears in the flat-water view.

    Each pixel's ray is traced through the true surface to the object plane (as
    :func:`wai_core.optics.trace_to_object`), and the object point is taken back to the pixel
    that sees it through flat water (:func:`wai_core.light_paths.flat_pixel_of`).

    Parameters
    ----------
    cfg : SystemConfig
    surface : Heightfield
        The true surface, absolute heights, mm.
    rays : (origin (3,), directions (H, W, 3)), optional
        Camera v's pixel rays (``camera_v.pixel_rays(*camera_v.pixel_grid())``), when the
        caller keeps them for many surfaces.

    Returns
    -------
    (H, W, 2) ndarray of float32
        The flat-water view's (col, row) of each pixel, NaN where the ray is totally reflected
        or misses the surface or the object plane.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system
    >>> from wai_core.heightfield import Heightfield
    >>> cfg = load_system("paper").replace("camera_v", width_px=40, height_px=30)
    >>> x = y = np.linspace(-600.0, 600.0, 9)
    >>> flat = Heightfield(x, y, np.full((9, 9), cfg.water.h0_mm))
    >>> warp = true_view_warp(cfg, flat)
    >>> cols, rows = np.meshgrid(np.arange(40.0), np.arange(30.0))
    >>> ok = np.isfinite(warp[..., 0])
    >>> bool(np.allclose(warp[ok], np.stack([cols, rows], axis=-1)[ok], atol=1e-3))
    True
    """
    cam = cfg.rig.camera_v
    origin, dirs = cam.pixel_rays(*cam.pixel_grid()) if rays is None else rays
    hit, hit_ok, normals = surface.intersect_normals(origin, dirs, n_iter=NEWTON_STEPS)
    return view_warp_px(cfg.rig, hit, normals, dirs, hit_ok)


# Newton steps of the rays' surface hits: from the mean level, four reach the steps' rounding
# on sea waves (the default eight cost twice the time for nothing).
NEWTON_STEPS = 4
