"""Geometry derived from the configuration: where things are, not what they are made of.

- The diffuser is a finite horizontal screen spanning camera s's view of the plane ``z = z_h``.
  The projector's upward beam crosses that plane too; the renderer's screen is one-way (see
  :mod:`mitsuba_wai.bsdfs`), as the paper's geometry implicitly assumes.
- The object plane is a rectangle centred where camera v's optical axis, refracted by flat water,
  meets ``z = z_a``.
- The observed patch is the part of the flat water that either system looks at; a surface given
  as a file must cover it.

These are the formulas; the values a configuration needs again and again (the diffuser's
extent, the dots lit and their weights, the object's centre) are kept by its rig
(``cfg.rig``, :class:`wai_core.rig.Rig`), which every stage asks. The rig is built on these
formulas, so their configuration parameter (a :class:`~wai_core.config.SystemConfig`) is
annotated ``Any`` rather than imported back.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from wai_core.geometry import (
    PinholeCamera,
    fresnel_reflectance,
    intersect_plane_z,
    refract,
)

UP = np.array([0.0, 0.0, 1.0])


def frame_border_px(camera: PinholeCamera, n: int = 64) -> tuple[NDArray, NDArray]:
    """Pixel coordinates along the outer border of a device's image, shape (4 n,) each."""
    w, h = camera.width_px - 0.5, camera.height_px - 0.5
    s = np.linspace(0.0, 1.0, n, endpoint=False)
    cols = np.concatenate([-0.5 + s * w, np.full(n, w), w - s * w, np.full(n, -0.5)])
    rows = np.concatenate([np.full(n, -0.5), -0.5 + s * h, np.full(n, h), h - s * h])
    return cols, rows


def footprint_on_plane(camera: PinholeCamera, z_mm: float) -> NDArray:
    """Bounding box ``[[x0, x1], [y0, y1]]`` (mm) of a device's view of the plane ``z = z_mm``
    (rays that never reach the plane are ignored)."""
    o, d = camera.pixel_rays(*frame_border_px(camera))
    p, _ = intersect_plane_z(o, d, z_mm)
    p = p[np.isfinite(p[:, 0])]
    return np.array([[p[:, 0].min(), p[:, 0].max()], [p[:, 1].min(), p[:, 1].max()]])


def diffuser_rect(cfg: Any) -> NDArray:
    """Extent ``[[x0, x1], [y0, y1]]`` of the diffuser, mm: camera s's view of ``z = z_h``
    (the rig's :attr:`~wai_core.rig.Rig.diffuser_rect`)."""
    return cfg.rig.diffuser_rect


def flat_pattern_hits(cfg: Any) -> tuple[NDArray, NDArray, NDArray]:
    """Flat-water path of every dot: water hit ``q`` (K, 3), diffuser hit ``s`` (K, 3), and a
    mask of the dots whose spot lands on the diffuser inside camera s's view (the rig's
    :func:`wai_core.light_paths.flat_spots`)."""
    flat = cfg.rig.flat_spots
    cam_s = cfg.rig.camera_s
    seen = (flat.in_front & cam_s.in_image(flat.px[:, 0], flat.px[:, 1])
            & flat.on_diffuser(cfg.rig.diffuser_rect))
    return flat.water_mm, flat.diffuser_mm, seen


def lit_dots(cfg: Any, margin_spacings: float = 2.0) -> NDArray[np.bool_]:
    """Dots (K,) worth projecting: those whose flat-water spot lands on the diffuser grown by
    ``margin_spacings`` dot spacings (waves move spots by less). Lighting only these spends every
    projected photon on a spot that camera s can see."""
    rig = cfg.rig
    s = rig.flat_spots.diffuser_mm
    # Spacing of neighbouring spots on the diffuser, from the flat-water model.
    rows = s.reshape(-1, _dots_per_row(rig.dot_ij), 3)
    spacing = np.nanmedian(np.linalg.norm(np.diff(rows, axis=1), axis=2))
    return rig.flat_spots.on_diffuser(rig.diffuser_rect, margin_spacings * spacing)


def _dots_per_row(ij: NDArray) -> int:
    """Dots per grid row (:func:`~wai_core.pattern.dot_grid` lays the grid out row by row; a
    panel that is not square has rows and columns of different lengths)."""
    return int(ij[:, 0].max() - ij[:, 0].min() + 1)


def dot_weights(cfg: Any, max_gain: float = 60.0) -> NDArray:
    """Brightness (K,) in [0, 1] of each dot on the panel: the paper's "adaptive" pattern.

    Dots that cannot reach the diffuser (:func:`lit_dots`) stay dark. On a dielectric surface
    the others are weighted by ``1 / R`` (R: Fresnel reflectance at their flat-water incidence,
    1 under total internal reflection), at most ``max_gain``, so that every spot reaches the
    diffuser about equally bright and gets about as many photons in the particle tracer.
    """
    lit = cfg.rig.lit.astype(float)
    if cfg.water.surface == "mirror":
        return lit
    d = cfg.rig.flat_spots.dirs
    gain = np.minimum(1.0 / fresnel_reflectance(d[:, 2], cfg.water.n_water), max_gain)
    w = lit * gain
    return w / w.max()


def snell_window_hits(cfg: Any, step_px: float = 8.0) -> NDArray:
    """Points (N, 3) where camera v's rays that leave the water (flat, not TIR) cross it."""
    cam = cfg.rig.camera_v
    o, d = cam.pixel_rays(*cam.pixel_grid(step_px))
    q, _ = intersect_plane_z(o, d.reshape(-1, 3), cfg.water.h0_mm)
    _, tir = refract(d.reshape(-1, 3), np.broadcast_to(UP, (q.shape[0], 3)), cfg.water.n_water)
    return q[~tir & np.isfinite(q[:, 0])]


def observed_patch(cfg: Any, margin_mm: float = 10.0) -> NDArray:
    """Extent ``[[x0, x1], [y0, y1]]`` (mm) of flat water seen by system S (the dots that reach
    camera s) or system V (camera v inside Snell's window), plus a margin."""
    q, _, seen = flat_pattern_hits(cfg)
    pts = np.concatenate([q[seen], snell_window_hits(cfg)])
    lo, hi = pts[:, :2].min(0) - margin_mm, pts[:, :2].max(0) + margin_mm
    return np.stack([lo, hi], axis=1)


def object_plane_center(cfg: Any) -> NDArray:
    """Centre (3,) mm of the object rectangle: camera v's axis refracted by flat water, on z_a."""
    cam = cfg.rig.camera_v
    o, axis = cam.pose.center_lab_mm, cam.pose.axis_lab
    q, _ = intersect_plane_z(o, axis, cfg.water.h0_mm)
    d_air, tir = refract(axis, UP, cfg.water.n_water)
    if tir:
        raise ValueError("camera v's axis is beyond the critical angle: it sees no sky")
    p, _ = intersect_plane_z(q, d_air, cfg.object_z_mm)
    return p


def surface_extent(cfg: Any, margin_mm: float = 15.0) -> NDArray:
    """Extent ``[[x0, x1], [y0, y1]]`` (mm) of the water that must be modelled: the observed
    patch and all of camera v's footprint (its TIR rays must meet water too), plus a margin for
    the waves' deflections. Nothing beyond it is modelled."""
    patch = observed_patch(cfg, margin_mm=0.0)
    view = footprint_on_plane(cfg.rig.camera_v, cfg.water.h0_mm)
    lo = np.minimum(patch[:, 0], view[:, 0]) - margin_mm
    hi = np.maximum(patch[:, 1], view[:, 1]) + margin_mm
    return np.stack([lo, hi], axis=1)
