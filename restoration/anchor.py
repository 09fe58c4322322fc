"""Absolute height of the surface from integrability: removing the paper's "unrecoverable" bias.

One spot per projector ray fixes the surface only together with its height: assume the
reflection point higher, and the normal that sends the ray to the same spot tilts. In one
dimension this leaves a one-parameter family of surfaces (the paper anchors it with the mean
level h0 from a depth gauge, and calls the rest an unrecoverable bias). In two dimensions the
slopes must also be *integrable*: a wrong anchor tilts the normals by an amount that varies
across the patch in a way no surface can follow, so the least-squares integration leaves a
residual that grows with the anchor error. Minimising that residual over the one anchor
parameter recovers the absolute height from the data alone.

The squared residual is close to a parabola in the anchor (the residual is nearly linear in
it), so a few evaluations and a parabola fit find the minimum.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from restoration.integrate import grid_neighbours
from restoration.surface import SurfaceEstimate

_STEPS = ((1, 0), (0, 1))


def integration_residual_mm(est: SurfaceEstimate) -> float:
    """RMS mismatch (mm) over grid edges between the height difference of neighbouring samples
    and the trapezoid rule on their slopes: zero for an integrable slope field."""
    nb = grid_neighbours(est.ij, _STEPS)
    a = np.concatenate([np.flatnonzero(row >= 0) for row in nb])
    b = np.concatenate([row[row >= 0] for row in nb])
    p, g = est.points_mm, est.slopes
    r = p[b, 2] - p[a, 2] - 0.5 * np.sum((g[a] + g[b]) * (p[b, :2] - p[a, :2]), axis=1)
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


@dataclass(frozen=True)
class AnchorSearch:
    """Result of :func:`find_anchor`.

    Attributes
    ----------
    anchor_mm : float
        Mean height of the samples that makes the slopes most integrable, mm.
    residual_mm : float
        Integration residual at that anchor, mm.
    curvature : float
        Second derivative of the squared residual (mm^2 per mm^2): how sharply the data pin the
        anchor; small values mean a weakly determined height.
    evaluations : int
        Surface reconstructions run.
    estimate : SurfaceEstimate
        The reconstruction at ``anchor_mm``.
    """

    anchor_mm: float
    residual_mm: float
    curvature: float
    evaluations: int
    estimate: SurfaceEstimate


def find_anchor(
    reconstruct: Callable[[float], SurfaceEstimate],
    start_mm: float,
    step_mm: float = 2.0,
    rounds: int = 2,
    max_shift_mm: float = 30.0,
) -> AnchorSearch:
    """Minimise the integration residual over the anchor height.

    Parameters
    ----------
    reconstruct : callable
        ``reconstruct(anchor_mm) -> SurfaceEstimate`` with the samples' mean height pinned at
        ``anchor_mm`` (the mean water level h0 in the paper's method).
    start_mm : float
        First guess, mm (the gauge's h0, or the previous frame's anchor).
    step_mm : float
        Half-width of the first bracket, mm; each later round halves it around the minimum.
    rounds : int
        Parabola fits (3 reconstructions each, sharing the centre).
    max_shift_mm : float
        Largest move from ``start_mm`` accepted; beyond it the start is kept (and flagged by a
        non-positive curvature).
    """
    centre, step, evaluations = start_mm, step_mm, 0
    curvature = float("nan")
    cache: dict[float, tuple[float, SurfaceEstimate]] = {}

    def residual2(anchor: float) -> float:
        nonlocal evaluations
        if anchor not in cache:
            est = reconstruct(anchor)
            evaluations += 1
            cache[anchor] = (integration_residual_mm(est) ** 2, est)
        return cache[anchor][0]

    for _ in range(rounds):
        xs = np.array([centre - step, centre, centre + step])
        ys = np.array([residual2(float(x)) for x in xs])
        a, b, _ = np.polyfit(xs - centre, ys, 2)
        curvature = 2.0 * a
        if a <= 0 or not np.isfinite(a):
            centre = float(xs[np.argmin(ys)])
        else:
            centre = centre + float(np.clip(-b / (2 * a), -2 * step, 2 * step))
        centre = float(np.clip(centre, start_mm - max_shift_mm, start_mm + max_shift_mm))
        step /= 2.0
    r2 = residual2(centre)
    return AnchorSearch(centre, float(np.sqrt(r2)), curvature, evaluations, cache[centre][1])


def anchor_residual_curve(
    reconstruct: Callable[[float], SurfaceEstimate], anchors_mm: NDArray
) -> NDArray:
    """Integration residual (mm) for each anchor height: the curve behind :func:`find_anchor`."""
    return np.array([integration_residual_mm(reconstruct(float(a))) for a in anchors_mm])
