"""Checks of the rig's geometry and of a water surface against it, before anything is rendered
or restored.

The rig (``lab`` frame, z up, mm) stacks, in the paper's configuration: camera s (z = -190),
the projector and camera v (z = 0), the diffuser (z_h = 60), the water (h0 = 150) and the object
plane (z_a = h0 + 1000). Every device and the diffuser look at the water from below, the object
is seen through it from below, so over the patch both systems observe the surface must stay
above each of them and below the object plane. A surface that does not (a file at the wrong
height, waves taller than the rig) would render black or meaningless images without any error;
:func:`check_surface_in_rig` refuses it in one line that says what is wrong and where.

The rig itself must be able to see something through flat water (:func:`check_rig`): the
devices below the water, camera s below the diffuser and looking up at it, some of the
projector's dots landing in its view, and camera v seeing the object plane through the water.
A rig that fails one of these (a camera moved by metres, turned away, a device above the
water) is impossible geometry: restoring or rendering it would only end in a ``failed`` frame
or black images, so it is refused up front.
"""

from __future__ import annotations

import numpy as np

from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.geometry import intersect_plane_z
from wai_core.heightfield import Heightfield
from wai_core.layout import (
    flat_pattern_hits,
    footprint_on_plane,
    frame_border_px,
    observed_patch,
    snell_window_hits,
)

__all__ = ["check_rig", "check_surface_in_rig", "rig_levels"]


def rig_levels(cfg: SystemConfig) -> list[tuple[str, float]]:
    """The rig's parts the surface must not reach: ``(name, z_mm)`` for the projector, the
    cameras (their centres), the diffuser and the object plane."""
    levels = [
        (label, float(cfg.rig.device(name).pose.center_lab_mm[2]))
        for name, label in (("projector", "the projector"), ("camera_s", "camera s"),
                            ("camera_v", "camera v"))
    ]
    return levels + [("the diffuser", cfg.diffuser.z_mm), ("the object plane", cfg.object_z_mm)]


def _mm(z: float) -> str:
    return f"{round(z, 1) + 0.0:.1f}" if abs(z) < 1e6 else f"{z:.3g}"  # + 0.0: no "-0.0"


def check_surface_in_rig(
    cfg: SystemConfig, surface: Heightfield, what: str = "the surface"
) -> None:
    """Refuse a surface that leaves the space between the rig's parts over the observed patch.

    Parts below the mean level ``h0`` (the devices, the diffuser) must stay below the surface
    everywhere over :func:`~wai_core.layout.observed_patch`; parts above it (the object plane)
    must stay above it.

    Parameters
    ----------
    cfg : SystemConfig
    surface : Heightfield
        Absolute heights, mm, lab frame (a file's surface or the sea state's).
    what : str
        How the message names the surface's origin, e.g. ``heightfield F.npz`` or
        ``--wind 1e+06``.

    Raises
    ------
    WaiInputError
        E.g. ``heightfield F.npz: the surface reaches z = 5000.0 mm (at x = 12, y = -40 mm),
        above the object plane at 1150.0 mm``.
    """
    patch = observed_patch(cfg)
    ix = (surface.x >= patch[0, 0]) & (surface.x <= patch[0, 1])
    iy = (surface.y >= patch[1, 0]) & (surface.y <= patch[1, 1])
    z = surface.z[np.ix_(iy, ix)]
    if z.size == 0 or not np.isfinite(z).any():
        raise WaiInputError(f"{what}: no height over the observed patch")
    if not np.isfinite(z).all():
        z = np.where(np.isfinite(z), z, np.nan)
    xs, ys = surface.x[ix], surface.y[iy]
    h0 = cfg.water.h0_mm
    levels = rig_levels(cfg)
    under = sorted((p for p in levels if p[1] < h0), key=lambda p: -p[1])  # highest first
    over = sorted((p for p in levels if p[1] >= h0), key=lambda p: p[1])  # lowest first
    bounds = []
    if under:
        bounds.append(f"above {under[0][0]} ({_mm(under[0][1])} mm)")
    if over:
        bounds.append(f"below {over[0][0]} ({_mm(over[0][1])} mm)")
    rule = f"the water must stay {' and '.join(bounds)} over the observed patch"
    for parts, pick, word, side in (
        (under, np.nanargmin, "dips to", "below"),
        (over, np.nanargmax, "reaches", "above"),
    ):
        at = np.unravel_index(pick(z), z.shape)
        z_at = float(z[at])
        hit = [p for p in parts if (z_at <= p[1] if side == "below" else z_at >= p[1])]
        if hit:
            names = ", ".join(f"{n} at {_mm(lv)} mm" for n, lv in hit)
            raise WaiInputError(
                f"{what}: the surface {word} z = {_mm(z_at)} mm (at x = {xs[at[1]]:.0f}, "
                f"y = {ys[at[0]]:.0f} mm), {side} {names}; {rule}"
            )


def _span(points: np.ndarray) -> str:
    """``x from A to B, y from C to D mm`` of points (N, >= 2)."""
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    return f"x from {lo[0]:.0f} to {hi[0]:.0f}, y from {lo[1]:.0f} to {hi[1]:.0f} mm"


def check_rig(cfg: SystemConfig, what: str = "the rig") -> None:
    """Refuse a rig whose geometry cannot work through flat water (module notes).

    Parameters
    ----------
    cfg : SystemConfig
    what : str
        How the message names the rig's source, e.g. ``renders/f1/scene.json``.

    Raises
    ------
    WaiInputError
        E.g. ``renders/f1/scene.json: camera s sees none of the projector's dots on the
        diffuser through flat water (they land at x from 95 to 477, ...; camera s sees x from
        5174 to 5799, ...)``.

    Examples
    --------
    >>> from wai_core import load_system
    >>> cfg = load_system("paper")
    >>> check_rig(cfg)
    >>> moved = cfg.replace("camera_s", translation_mm=(-5286.4, 0.0, 190.0))  # 5 m along x
    >>> try:
    ...     check_rig(moved, "scene.json")
    ... except WaiInputError as exc:
    ...     print(str(exc)[:74])
    scene.json: camera s sees none of the projector's dots on the diffuser thr
    """
    h0, zh = cfg.water.h0_mm, cfg.diffuser.z_mm
    for name, label, ceiling, part in (("projector", "the projector", h0, "the water"),
                                       ("camera_v", "camera v", h0, "the water"),
                                       ("camera_s", "camera s", zh, "the diffuser")):
        z = float(cfg.rig.device(name).pose.center_lab_mm[2])
        if z >= ceiling:
            raise WaiInputError(f"{what}: {label} is at z = {_mm(z)} mm, not below {part} at "
                                f"{_mm(ceiling)} mm: it must look up at it from below")
    cam_s = cfg.rig.camera_s
    o, d = cam_s.pixel_rays(*frame_border_px(cam_s))
    if not np.isfinite(intersect_plane_z(o, d, zh)[0][:, 0]).any():
        raise WaiInputError(f"{what}: camera s does not look up at the diffuser (z = {_mm(zh)} "
                            "mm): none of its rays reaches it")
    _, spots, seen = flat_pattern_hits(cfg)
    if not seen.any():
        landed = spots[np.isfinite(spots[:, 0])]
        where = f"they land at {_span(landed)}" if len(landed) else "none reaches it"
        raise WaiInputError(
            f"{what}: camera s sees none of the projector's dots on the diffuser through flat "
            f"water ({where}; camera s sees {_span(footprint_on_plane(cam_s, zh).T)})")
    try:
        cfg.rig.object_center_mm  # noqa: B018 (its axis must reach the sky)
    except ValueError as exc:
        raise WaiInputError(f"{what}: {exc}") from None
    if not len(snell_window_hits(cfg)):
        raise WaiInputError(f"{what}: camera v sees nothing through the water: every ray is "
                            "totally reflected or misses it")
