"""Forward geometric model of both systems, with no Mitsuba render.

- Spots: each lit dot's projector ray meets the exact surface (Newton ray hit on the bicubic
  heightfield), reflects about the exact normal, meets the diffuser plane and is projected into
  camera s (:func:`wai_core.light_paths.spots_through`). That is the chief ray of the dot; the
  rendered spot is the image of the whole dot.
- View: camera v's rays refract at the exact surface (Snell's law) and meet the object plane;
  the texture is sampled there (bilinear). Pixels are supersampled on a regular sub-grid, as a
  box reconstruction filter averages a pixel's area.

It shares the restoration's ray geometry (:func:`wai_core.optics.trace_to_object`), not
its outputs: what it is compared with are Mitsuba's renders.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates

from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield
from wai_core.light_paths import real_spot_px, spots_through
from wai_core.optics import trace_to_object

__all__ = ["predict_spots", "predict_view", "texture_coords"]


def texture_coords(points_lab_mm: NDArray, cfg: SystemConfig, shape: tuple[int, ...]) -> NDArray:
    """Continuous texture pixel ``(col, row)`` (..., 2) of points on the object plane, for a
    texture of ``shape`` (h, w, ...); outside [-0.5, w - 0.5) x [-0.5, h - 0.5) is off the board.
    Column grows with lab +x, row with lab +y; the texture spans ``cfg.object.size_mm``."""
    c = cfg.rig.object_center_mm
    sx, sy = cfg.object.size_mm
    h, w = shape[:2]
    u = ((points_lab_mm[..., 0] - c[0]) / sx + 0.5) * w - 0.5
    v = ((points_lab_mm[..., 1] - c[1]) / sy + 0.5) * h - 0.5
    return np.stack([u, v], axis=-1)


def predict_spots(
    cfg: SystemConfig, surface: Heightfield | None
) -> tuple[NDArray, NDArray]:
    """Grid indices (K, 2) and predicted camera-s pixels (K, 2) of every lit dot in view."""
    ij, panel = cfg.rig.dot_grid
    lit = cfg.rig.dot_weights > 0
    px = spots_through(cfg.rig, surface, panel[lit])
    real = real_spot_px(cfg.rig, px)  # the real image's pixels (a lens, a port)
    seen = np.isfinite(real[:, 0]) & cfg.rig.camera_s.in_image(real[:, 0], real[:, 1])
    return ij[lit][seen], px[seen]


def predict_view(
    cfg: SystemConfig, surface: Heightfield | None, texture: NDArray, supersample: int = 2
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Camera v's image (H, W, 3) of the textured plane through ``surface`` (None: flat water),
    in the texture's units, and a mask of pixels whose rays all reached the object."""
    cam = cfg.rig.camera_v
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    acc = np.zeros((cam.height_px, cam.width_px, texture.shape[2]))
    all_ok = np.ones((cam.height_px, cam.width_px), dtype=bool)
    cols, rows = cam.pixel_grid()
    for dy in offsets:
        for dx in offsets:
            tr = trace_to_object(
                cam,
                surface,
                cfg.water.h0_mm,
                cfg.water.n_water,
                cfg.object_z_mm,
                cols + dx,
                rows + dy,
            )
            uv = texture_coords(tr.object_mm, cfg, texture.shape)
            uv = np.where(tr.ok[..., None], uv, -1e6)
            for k in range(texture.shape[2]):
                acc[..., k] += map_coordinates(
                    texture[..., k], [uv[..., 1], uv[..., 0]], order=1, mode="constant"
                )
            all_ok &= tr.ok
    return (acc / supersample**2).astype(np.float32), all_ok
