"""The correspondence limits of the structured light (eq. 35-37 of Jian et al. 2022).

The spots keep their order, and so can be matched by proximity, only while neighbouring dots'
reflections do not cross: eq. 35 bounds the slope amplitude Φ of the waves for a pattern
spacing D, and Nyquist bounds the shortest wavelength at 2 D.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from wai_core.config import SystemConfig
from wai_core.layout import flat_pattern_hits

__all__ = ["correspondence_limit", "effective_phi_deg"]


def correspondence_limit(cfg: SystemConfig) -> dict[str, float]:
    """Eq. 35-37 for this geometry: the largest slope amplitude Φ and shortest wavelength λ that
    the pattern spacing D can follow, at the projector's axis."""
    q, _, seen = flat_pattern_hits(cfg)
    ij, _ = cfg.rig.dot_grid
    near_axis = seen & (np.abs(ij[:, 0]) <= 3) & (np.abs(ij[:, 1]) <= 3)
    side = int(round(np.sqrt(len(ij))))
    grid = q.reshape(side, side, 3)
    steps = np.linalg.norm(np.diff(grid[..., :2], axis=1), axis=2).ravel()
    steps_ok = near_axis.reshape(side, side)[:, 1:].ravel()
    d_mm = float(np.median(steps[steps_ok]))
    h0, z_h = cfg.water.h0_mm, cfg.diffuser.z_mm
    cam = cfg.rig.camera_s
    # Δp: one camera-s pixel's footprint on the diffuser.
    dp_mm = abs(z_h - cam.pose.center_lab_mm[2]) * cam.pixel_pitch_mm / cam.focal_mm
    axis = cfg.rig.projector.pose.axis_lab
    theta_flat = float(np.arccos(axis[2]))  # reflected angle from the vertical at the axis
    cos2 = np.cos(theta_flat) ** 2
    # Eq. 35 solved for Φ: D (2 h0 - z_h) / h0 - Δp/2 > (h0 - z_h) / cos² θ · dψ/dθ · 2Φ.
    phi_max = (d_mm * (2 * h0 - z_h) / h0 - dp_mm / 2) * cos2 / (2.0 * (h0 - z_h) * 2.0)
    return {
        "D_mm": d_mm,
        "delta_p_mm": float(dp_mm),
        "theta_flat_deg": float(np.degrees(theta_flat)),
        "phi_max_rad": float(phi_max),
        "phi_max_deg": float(np.degrees(phi_max)),
        "lambda_min_mm": 2.0 * d_mm,  # Nyquist: λ/2 > D
    }


def effective_phi_deg(surface: Any, cfg: SystemConfig) -> float:
    """Half the largest inclination change between neighbouring samples (eq. 35's 2Φ), deg,
    over the dots' flat-water hits."""
    q, _, seen = flat_pattern_hits(cfg)
    side = int(round(np.sqrt(len(q))))
    gx, gy = surface.gradient(q[:, 0], q[:, 1])
    incl = np.arctan(np.hypot(gx, gy)).reshape(side, side)
    seen = seen.reshape(side, side)
    diffs = []
    for axis in (0, 1):
        d = np.abs(np.diff(incl, axis=axis))
        both = np.logical_and(
            *(np.take(seen, r, axis=axis) for r in (range(0, side - 1), range(1, side)))
        )
        diffs.append(d[both])
    return float(np.degrees(np.percentile(np.concatenate(diffs), 99)) / 2.0)
