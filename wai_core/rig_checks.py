"""Checks of a water surface against the rig, before anything is rendered.

The rig (``lab`` frame, z up, mm) stacks, in the paper's configuration: camera s (z = -190),
the projector and camera v (z = 0), the diffuser (z_h = 60), the water (h0 = 150) and the object
plane (z_a = h0 + 1000). Every device and the diffuser look at the water from below, the object
is seen through it from below, so over the patch both systems observe the surface must stay
above each of them and below the object plane. A surface that does not (a file at the wrong
height, waves taller than the rig) would render black or meaningless images without any error;
:func:`check_surface_in_rig` refuses it in one line that says what is wrong and where.
"""

from __future__ import annotations

import numpy as np

from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield
from wai_core.layout import observed_patch

__all__ = ["rig_levels", "check_surface_in_rig"]


def rig_levels(cfg: SystemConfig) -> list[tuple[str, float]]:
    """The rig's parts the surface must not reach: ``(name, z_mm)`` for the projector, the
    cameras (their centres), the diffuser and the object plane."""
    levels = [
        (label, float(getattr(cfg, name).camera().pose.center_lab_mm[2]))
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
