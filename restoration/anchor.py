"""Absolute height of the surface from integrability: removing the paper's "unrecoverable" bias.

One spot per projector ray fixes the surface only together with its height: assume the
reflection point higher, and the normal that sends the ray to the same spot tilts. In one
dimension this leaves a one-parameter family of surfaces (the paper anchors it with the mean
level h0 from a depth gauge, and calls the rest an unrecoverable bias). In two dimensions the
slopes must also be *integrable*: a wrong anchor tilts the normals by an amount that varies
across the patch in a way no surface can follow, so the least-squares integration leaves a
residual that grows with the anchor error. Minimising that residual over the one anchor
parameter recovers the absolute height from the data alone.

Each edge's residual is nearly linear in the anchor, so two reconstructions give every edge's
residual as a line, the minimum of their loss follows without reconstructing, and secant steps
refine it (:func:`find_anchor`: 3-5 reconstructions a frame). Two things keep that minimum
where the data put it: each edge's step comes from the fourth-order rule
(:mod:`restoration.integrate.rules`; the trapezoid rule's own error, a few microns, moved the
flat valley's minimum by ~0.1 mm), and the residuals are weighed by a Cauchy loss
(:data:`CAUCHY_SCALE`), so a few wrong labels, whose edges' residuals are 10-100x the others',
cannot place it.

The information comes from the surface's curvature: over flat or nearly flat water a wrong
anchor tilts the normals almost exactly like a plane seen from a shifted height would (a mirror
images a point source onto a point), the residual no longer has a minimum above the noise, and
the search would wander. So each search also reports how well the data pin the anchor: the
edges are split into four interleaved sets (by the parity of the dot indices), each set's
linear residuals give their own minimum, and their spread gives a standard error. A search
whose sets find no minimum, or disagree, is not reliable, and the caller falls back to the
gauge.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from restoration.integrate.plans import IntegrationPlans, plan_of
from restoration.integrate.rules import edge_step
from restoration.level import N_SETS
from restoration.refine import edges_and_lines, trapezoid_edges
from restoration.surface import SurfaceEstimate

CAUCHY_SCALE = 2.0
"""Scale of the search's Cauchy loss, in robust standard deviations (1.4826 x the median
absolute value) of the edge residuals of the latest reconstruction, i.e. at the level once the
search has converged.

A few wrong labels (a decoded pattern keeps ~0.4 % of them) give their edges residuals 10-100x
the others', and in a least-squares objective those edges alone placed the level: 1-2 mm off
on three of ten coded frames of the paper's rig. Under the Cauchy loss an edge's weight falls
as its residual passes the scale, so they no longer count. Taking the scale at the level rather
than at a probe a few millimetres off also discounts the edges across sharp crests, whose
steps the rule gets least right (docs/results.md, "Accuracy")."""


def edge_residuals_mm(
    est: SurfaceEstimate, plans: IntegrationPlans | None = None
) -> tuple[NDArray, NDArray]:
    """Per grid edge: the mismatch (mm) between the height difference of neighbouring samples
    and the step their slopes give (zero for an integrable slope field, to the rule's error),
    and the edge's set in ``0 .. N_SETS - 1`` (parity of its first dot's ``i`` and ``j``).
    Every edge of the samples' lattice, in one order for one sample set (so the residuals of
    reconstructions at different anchors line up); NaN where not finite.

    The step is the fourth-order rule's (:func:`~restoration.integrate.edge_step`), or the
    trapezoid rule's for an estimate the ``"trapezoid"`` integrator made: the reconstruction's
    own least-squares misfit. (The trapezoid rule's error, ~2 um rms on the paper's rig, is
    systematic and biased the level by ~0.1 mm; docs/results.md.)"""
    a, b, before, after, sets = _edges(est.ij, est.integrator == "trapezoid", plans)
    r = np.empty(a.size)
    _edge_residual_kernel(
        np.ascontiguousarray(est.points_mm, dtype=float),
        np.ascontiguousarray(est.slopes, dtype=float), a, b, before, after, r,
    )
    return r, sets


@njit(cache=True, nogil=True)
def _edge_residual_kernel(points, slopes, a, b, before, after, r):  # pragma: no cover
    """Write the residuals of edges ``a -> b`` (E,) into ``r`` (E,)."""
    for e in range(a.size):
        i, j = a[e], b[e]
        r[e] = points[j, 2] - points[i, 2] - edge_step(points, slopes, before[e], i, j, after[e])


def _edges(
    ij: NDArray, trapezoid: bool = False, plans: IntegrationPlans | None = None
) -> tuple[NDArray, ...]:
    """:func:`~restoration.refine.trapezoid_edges` of ``ij``, the samples before and after
    each on its lattice line (all -1 for the ``trapezoid`` rule), and each edge's set, kept
    in ``plans`` when given: a search evaluates every probe on the same samples."""
    return plan_of(plans, "anchor_edges", ij, lambda: _build_edges(ij, trapezoid, plans),
                   trapezoid)


def _build_edges(
    ij: NDArray, trapezoid: bool, plans: IntegrationPlans | None
) -> tuple[NDArray, ...]:
    if trapezoid:
        a, b = trapezoid_edges(ij)
        before = after = np.full(a.size, -1, np.int64)
    else:
        a, b, before, after = edges_and_lines(ij, plans)
    sets = ((ij[a, 0] % 2) + 2 * (ij[a, 1] % 2)).astype(np.int64)
    return a, b, before, after, sets


def integration_residual_mm(est: SurfaceEstimate, plans: IntegrationPlans | None = None) -> float:
    """RMS of :func:`edge_residuals_mm` over the finite edges, mm (NaN when there are none)."""
    r, _ = edge_residuals_mm(est, plans)
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


def robust_scale_mm(r: NDArray) -> float:
    """1.4826 x the median absolute value of the finite residuals ``r`` (E,), mm: their
    standard deviation were they Gaussian, which a few outliers do not move."""
    r = r[np.isfinite(r)]
    return 1.4826 * float(np.median(np.abs(r))) if r.size else 0.0


@dataclass(frozen=True)
class AnchorSearch:
    """Result of :func:`find_anchor`.

    Attributes
    ----------
    anchor_mm : float
        Mean height of the samples that makes the slopes most integrable, mm.
    residual_mm : float
        Integration residual at that anchor: the root of the edges' mean loss, mm.
    curvature : float
        Second derivative of the mean loss in the anchor (its Gauss-Newton value, mm^2 per
        mm^2): how sharply the data pin the anchor; small values mean a weakly determined
        height.
    sigma_mm : float
        Standard error of ``anchor_mm``: the spread of the edge sets' own minima over
        ``sqrt(N_SETS)``, mm; infinite when the data do not pin it (flat or nearly flat water:
        a set without a minimum within two steps, or no convergence).
    evaluations : int
        Surface reconstructions run.
    estimate : SurfaceEstimate
        The reconstruction at ``anchor_mm``.
    """

    anchor_mm: float
    residual_mm: float
    curvature: float
    sigma_mm: float
    evaluations: int
    estimate: SurfaceEstimate


@njit(cache=True, nogil=True, error_model="numpy")
def _linear_minima(r, g, sets, scale, out):  # pragma: no cover
    """Offsets ``t`` minimising the mean Cauchy loss (scale ``scale``; squares when 0) of the
    linear residuals ``r + g t`` (E,), over all finite edges and over each set of ``sets``,
    by iteratively reweighted least squares. Writes ``out`` (N_SETS + 1, 3): per problem (all
    edges first) the offset, the weighted ``sum g^2 / n`` at it (the loss's half curvature)
    and the mean loss at ``t = 0``; an offset is NaN when its edges carry no slope."""
    k = out.shape[0]
    t = np.zeros(k)
    for p in range(k):
        out[p, 2] = 0.0
    count = np.zeros(k)
    for e in range(r.size):
        if np.isfinite(r[e]) and np.isfinite(g[e]):
            loss = r[e] * r[e] if scale <= 0 else scale * scale * np.log1p((r[e] / scale) ** 2)
            for p in (0, sets[e] + 1):
                out[p, 2] += loss
                count[p] += 1.0
    for _ in range(100):
        num, den = np.zeros(k), np.zeros(k)
        for e in range(r.size):
            if not (np.isfinite(r[e]) and np.isfinite(g[e])):
                continue
            for p in (0, sets[e] + 1):
                res = r[e] + g[e] * t[p]
                w = 1.0 if scale <= 0 else 1.0 / (1.0 + (res / scale) ** 2)
                num[p] += w * res * g[e]
                den[p] += w * g[e] * g[e]
        moved = 0.0
        for p in range(k):
            step = -num[p] / den[p] if den[p] > 0 else np.nan
            t[p] += step
            moved = max(moved, abs(step)) if np.isfinite(step) else np.inf
            out[p, 1] = den[p] / count[p] if count[p] > 0 else 0.0
        if moved < 1e-7 or not np.isfinite(moved):
            break
    for p in range(k):
        out[p, 0] = t[p]
        out[p, 2] = out[p, 2] / count[p] if count[p] > 0 else np.nan


def find_anchor(
    reconstruct: Callable[[float], SurfaceEstimate],
    start_mm: float,
    step_mm: float,
    max_shift_mm: float = 60.0,
    tol_mm: float = 0.02,
    max_evaluations: int = 12,
    cauchy_scale: float = CAUCHY_SCALE,
    plans: IntegrationPlans | None = None,
) -> AnchorSearch:
    """Minimise the integration residual over the anchor height.

    Each edge's residual is nearly linear in the anchor, so the residuals of the last two
    reconstructions give each edge's slope, and the minimum of the loss of those linear
    residuals (a one-dimensional reweighted least-squares problem, no reconstruction) is where
    the next reconstruction goes: secant steps, from ``start_mm - step_mm`` and ``start_mm``,
    until a step is shorter than ``tol_mm``. On the paper's rig that takes 3-5 reconstructions
    where parabola fits on halving brackets took 7-14. Each edge set's own minimum of the same
    linear model gives the anchor's standard error.

    Parameters
    ----------
    reconstruct : callable
        ``reconstruct(anchor_mm) -> SurfaceEstimate`` with the samples' mean height pinned at
        ``anchor_mm`` (the mean water level h0 in the paper's method).
    start_mm : float
        First guess, mm (the gauge's h0, or the previous frame's anchor).
    step_mm : float
        How far below ``start_mm`` the first reconstruction is, mm; one step moves at most 8
        times this.
    max_shift_mm : float
        Farthest from ``start_mm`` the search looks, mm; a minimum beyond it is not found: the
        start is kept and ``sigma_mm`` is infinite.
    tol_mm : float
        Step below which the search has converged, mm.
    max_evaluations : int
        Most reconstructions; a search that has not converged by then keeps the start, with
        an infinite ``sigma_mm``.
    cauchy_scale : float
        The objective is the mean Cauchy loss of the edge residuals with this scale in robust
        standard deviations of the latest reconstruction's residuals (:data:`CAUCHY_SCALE`);
        0: the mean squared residual.
    plans : IntegrationPlans, optional
        Where the probes' edges are kept (the frame's observations' plans).
    """
    anchors: list[float] = []
    residuals: list[NDArray] = []
    estimates: list[SurfaceEstimate] = []
    sets = np.zeros(0, np.int64)

    def probe(anchor: float) -> None:
        nonlocal sets
        est = reconstruct(anchor)
        r, sets = edge_residuals_mm(est, plans)
        anchors.append(anchor)
        residuals.append(np.asarray(r, dtype=float))
        estimates.append(est)

    probe(start_mm - step_mm)
    probe(start_mm)
    minima = np.full((N_SETS + 1, 3), np.nan)
    converged = False
    while True:
        slope = (residuals[-1] - residuals[-2]) / (anchors[-1] - anchors[-2])
        # The scale is the latest residuals' spread, i.e. the spread at the level once the
        # search has converged (an M-estimate with its scale estimated along).
        scale = cauchy_scale * robust_scale_mm(residuals[-1])
        _linear_minima(residuals[-1], slope, np.asarray(sets, np.int64), scale, minima)
        step = float(np.clip(minima[0, 0], -8.0 * step_mm, 8.0 * step_mm))
        if not np.isfinite(step) or abs(anchors[-1] + step - start_mm) > max_shift_mm:
            break
        if abs(step) < tol_mm:
            converged = True
            break
        if len(anchors) >= max_evaluations:
            break
        probe(anchors[-1] + step)
    if not converged:
        return AnchorSearch(
            start_mm, float(np.sqrt(minima[0, 2])), float("nan"), float("inf"), len(anchors),
            estimates[1],
        )
    offsets = minima[1:, 0]
    reach = 2.0 * abs(step_mm)
    if np.isfinite(offsets).all() and np.all(np.abs(offsets) <= reach):
        sigma = float(np.std(offsets, ddof=1) / np.sqrt(N_SETS))
    else:
        sigma = float("inf")
    return AnchorSearch(
        anchors[-1], float(np.sqrt(minima[0, 2])), 2.0 * float(minima[0, 1]), sigma,
        len(anchors), estimates[-1],
    )
