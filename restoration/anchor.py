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
it), so a few evaluations and a parabola fit find the minimum. Two things keep that minimum
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
parabola gives its own minimum, and their spread gives a standard error. A search whose sets
find no minimum, or disagree, is not reliable, and the caller falls back to the gauge.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from restoration.integrate import edge_step, line_neighbours
from restoration.surface import SurfaceEstimate, trapezoid_edges

N_SETS = 4
"""Interleaved edge sets whose separate minima measure the anchor's standard error."""

CAUCHY_SCALE = 2.0
"""Scale of the search's Cauchy loss, in robust standard deviations (1.4826 x the median
absolute value) of the first probe's edge residuals.

A few wrong labels (a decoded pattern keeps ~0.4 % of them) give their edges residuals 10-100x
the others', and in a least-squares objective those edges alone placed the level: 1-2 mm off
on three of ten coded frames of the paper's rig. Under the Cauchy loss an edge's weight falls
as its residual passes the scale, so they no longer count; on the plain pattern's frames,
without such outliers, the level moved by 0.01 mm at most (docs/results.md)."""


def edge_residuals_mm(est: SurfaceEstimate) -> tuple[NDArray, NDArray]:
    """Per grid edge: the mismatch (mm) between the height difference of neighbouring samples
    and the step their slopes give (zero for an integrable slope field, to the rule's error),
    and the edge's set in ``0 .. N_SETS - 1`` (parity of its first dot's ``i`` and ``j``).
    Finite edges only.

    The step is the fourth-order rule's (:func:`~restoration.integrate.edge_step`), or the
    trapezoid rule's for an estimate the ``"trapezoid"`` integrator made: the reconstruction's
    own least-squares misfit. (The trapezoid rule's error, ~2 um rms on the paper's rig, is
    systematic and biased the level by ~0.1 mm; docs/results.md.)"""
    a, b, before, after, sets = _edges(est.ij, est.integrator == "trapezoid")
    r, kept = np.empty(a.size), np.empty_like(sets)
    n = _edge_residual_kernel(
        np.ascontiguousarray(est.points_mm, dtype=float),
        np.ascontiguousarray(est.slopes, dtype=float), a, b, before, after, sets, r, kept,
    )
    return r[:n], kept[:n]


@njit(cache=True, nogil=True)
def _edge_residual_kernel(points, slopes, a, b, before, after, sets, r, kept):  # pragma: no cover
    """Write the finite residuals of edges ``a -> b`` (E,) and their sets into ``r``, ``kept``
    (E,), in edge order; return how many."""
    n = 0
    for e in range(a.size):
        i, j = a[e], b[e]
        step = edge_step(points, slopes, before[e], i, j, after[e])
        value = points[j, 2] - points[i, 2] - step
        if np.isfinite(value):
            r[n] = value
            kept[n] = sets[e]
            n += 1
    return n


def _edges(ij: NDArray, trapezoid: bool = False) -> tuple[NDArray, ...]:
    """:func:`~restoration.surface.trapezoid_edges` of ``ij``, the samples before and after
    each on its lattice line (all -1 for the ``trapezoid`` rule), and each edge's set, cached:
    a search evaluates every probe on the same samples."""
    key = (ij.shape, ij.tobytes(), trapezoid)
    if key not in _EDGES:
        if len(_EDGES) >= 16:
            _EDGES.clear()
        a, b = trapezoid_edges(ij)
        if trapezoid:
            before = after = np.full(a.size, -1, np.int64)
        else:
            before, after = line_neighbours(ij, a, b)
        sets = ((ij[a, 0] % 2) + 2 * (ij[a, 1] % 2)).astype(np.int64)
        _EDGES[key] = (a, b, before, after, sets)
    return _EDGES[key]


_EDGES: dict[tuple, tuple[NDArray, NDArray, NDArray]] = {}


def integration_residual_mm(est: SurfaceEstimate) -> float:
    """RMS of :func:`edge_residuals_mm` over all edges, mm (NaN when there are none)."""
    r, _ = edge_residuals_mm(est)
    return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


def robust_scale_mm(r: NDArray) -> float:
    """1.4826 x the median absolute value of the residuals ``r`` (E,), mm: their standard
    deviation were they Gaussian, which a few outliers do not move."""
    return 1.4826 * float(np.median(np.abs(r))) if r.size else 0.0


def _mean_squares(r: NDArray, sets: NDArray, scale_mm: float = 0.0) -> tuple[float, NDArray]:
    """Mean Cauchy loss ``c^2 log(1 + r^2 / c^2)`` of the edge residuals ``r`` (E,) over all
    edges (mm^2; NaN without edges) and over each edge set of ``sets`` (E,) (N_SETS,), with
    ``c = scale_mm``; the mean squared residual when ``scale_mm`` is 0 (the loss tends to
    ``r^2`` for ``r << c``)."""
    r = np.ascontiguousarray(r, dtype=float)
    if scale_mm > 0:
        r = scale_mm * np.sqrt(np.log1p((r / scale_mm) ** 2))
    per_set = np.empty(N_SETS)
    total = _set_means(r, np.asarray(sets, np.int64), per_set)
    return total, per_set


@njit(cache=True, nogil=True, error_model="numpy")
def _set_means(r, sets, per_set):  # pragma: no cover
    """Mean of ``r**2`` (E,) overall (returned; NaN when empty) and per set into ``per_set``
    (N_SETS,) (NaN for an empty set)."""
    sums = np.zeros(per_set.size)
    counts = np.zeros(per_set.size)
    total = 0.0
    for e in range(r.size):
        r2 = r[e] * r[e]
        total += r2
        sums[sets[e]] += r2
        counts[sets[e]] += 1.0
    for k in range(per_set.size):
        per_set[k] = sums[k] / counts[k] if counts[k] > 0 else np.nan
    return total / r.size if r.size else np.nan


def parabola_vertex(x: NDArray, y: NDArray) -> float:
    """Abscissa of the minimum of the least-squares parabola through ``(x, y)``; NaN when the
    parabola opens downwards or the fit is undetermined."""
    if x.size < 3 or not np.isfinite(y).all():
        return float("nan")
    a, b, _ = np.polyfit(x - x.mean(), y, 2)
    return float(x.mean() - b / (2 * a)) if a > 0 else float("nan")


def anchor_sigma_mm(anchors_mm: NDArray, set_ms: NDArray, reach_mm: float) -> float:
    """Standard error of the anchor from the spread of the edge sets' own minima, mm.

    Parameters
    ----------
    anchors_mm : (A,) ndarray
        Anchors evaluated, mm.
    set_ms : (A, N_SETS) ndarray
        Mean squared residual of each edge set at each anchor, mm^2.
    reach_mm : float
        A set's minimum further than this outside the evaluated anchors counts as not found.

    Returns
    -------
    float
        ``std(minima) / sqrt(N_SETS)``, mm; infinite when any set has no minimum in reach (the
        data do not pin the anchor).
    """
    vertices = np.array([parabola_vertex(anchors_mm, set_ms[:, k]) for k in range(N_SETS)])
    lo, hi = anchors_mm.min() - reach_mm, anchors_mm.max() + reach_mm
    if not (np.isfinite(vertices).all() and np.all((vertices >= lo) & (vertices <= hi))):
        return float("inf")
    return float(np.std(vertices, ddof=1) / np.sqrt(N_SETS))


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
    sigma_mm : float
        Standard error of ``anchor_mm`` (:func:`anchor_sigma_mm`), mm; infinite when the data do
        not pin it (flat or nearly flat water).
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


def _bracket(
    f: Callable[[float], float], start: float, step: float, max_shift: float
) -> tuple[float, float, float] | None:
    """Three anchors ``lo < mid < hi`` with ``f(mid)`` the lowest, found by walking downhill
    from ``start`` with doubling strides; None when the walk leaves ``start +- max_shift``."""
    lo, mid, hi = start - step, start, start + step
    while max(start - lo, hi - start) <= max_shift:
        flo, fmid, fhi = f(lo), f(mid), f(hi)
        if fmid <= flo and fmid <= fhi:
            return lo, mid, hi
        if flo < fhi:
            lo, mid, hi = lo - 2.0 * (mid - lo), lo, mid
        else:
            lo, mid, hi = mid, hi, hi + 2.0 * (hi - mid)
    return None


def _clipped_vertex(xs: NDArray, ys: NDArray) -> float:
    """Minimum of the parabola through three points ``xs`` (ascending), kept within them; the
    lowest point when the parabola opens downwards."""
    a, b, _ = np.polyfit(xs - xs[1], ys, 2)
    if a <= 0 or not np.isfinite(a):
        return float(xs[np.argmin(ys)])
    return float(np.clip(xs[1] - b / (2 * a), xs[0], xs[2]))


def find_anchor(
    reconstruct: Callable[[float], SurfaceEstimate],
    start_mm: float,
    step_mm: float = 2.0,
    rounds: int = 2,
    max_shift_mm: float = 60.0,
    tol_mm: float = 0.1,
    max_rounds: int = 5,
    cauchy_scale: float = CAUCHY_SCALE,
) -> AnchorSearch:
    """Minimise the integration residual over the anchor height.

    The minimum is first bracketed by walking downhill from ``start_mm`` with doubling strides
    (the mean level of a patch smaller than the waves can sit 10-20 mm off h0 at U = 1 m/s),
    then located by parabola fits on brackets that halve each round.

    Parameters
    ----------
    reconstruct : callable
        ``reconstruct(anchor_mm) -> SurfaceEstimate`` with the samples' mean height pinned at
        ``anchor_mm`` (the mean water level h0 in the paper's method).
    start_mm : float
        First guess, mm (the gauge's h0, or the previous frame's anchor).
    step_mm : float
        Half-width of the first bracket, mm.
    rounds : int
        Fewest parabola fits after bracketing (2 new reconstructions each); more follow, up to
        ``max_rounds``, while a fit still moves the level by ``tol_mm`` or more.
    max_shift_mm : float
        Farthest from ``start_mm`` the search looks, mm; a minimum beyond it is not found: the
        start is kept and ``sigma_mm`` is infinite.
    tol_mm, max_rounds : float, int
        See ``rounds``.
    cauchy_scale : float
        The objective is the mean Cauchy loss of the edge residuals with this scale in robust
        standard deviations of the first probe's residuals (:data:`CAUCHY_SCALE`; fixed for
        the whole search, so every probe is weighed alike); 0: the mean squared residual.
    """
    evaluations = 0
    scale_mm: list[float] = []  # set by the first probe
    cache: dict[float, tuple[float, NDArray, SurfaceEstimate]] = {}

    def residual2(anchor: float) -> float:
        nonlocal evaluations
        if anchor not in cache:
            est = reconstruct(anchor)
            evaluations += 1
            r, sets = edge_residuals_mm(est)
            if not scale_mm:
                scale_mm.append(cauchy_scale * robust_scale_mm(r))
            cache[anchor] = (*_mean_squares(r, sets, scale_mm[0]), est)
        return cache[anchor][0]

    found = _bracket(residual2, start_mm, step_mm, max_shift_mm)
    if found is None:
        r2 = residual2(start_mm)
        return AnchorSearch(
            start_mm, float(np.sqrt(r2)), float("nan"), float("inf"), evaluations,
            cache[start_mm][2],
        )
    lo, centre, hi = found
    if hi - lo > 2.0 * step_mm:
        # A walk's bracket is wide: its parabola places the first refined bracket, whose
        # half-width is the first step again, so every search ends on the same fine scale.
        centre = _clipped_vertex(np.array(found), np.array([residual2(x) for x in found]))
    step = step_mm
    curvature = float("nan")
    for k in range(max_rounds):
        xs = np.array([centre - step, centre, centre + step])
        ys = np.array([residual2(float(x)) for x in xs])
        a = np.polyfit(xs - centre, ys, 2)[0]
        curvature = 2.0 * a
        moved = _clipped_vertex(xs, ys) - centre
        centre += moved
        step /= 2.0
        if k + 1 >= rounds and abs(moved) < tol_mm:
            break
    r2 = residual2(centre)
    # The sets' parabolas are fitted near the minimum, where the squared residual is one.
    near = np.array(sorted(a for a in cache if abs(a - centre) <= 2.0 * step_mm))
    sigma = anchor_sigma_mm(near, np.array([cache[a][1] for a in near]), step_mm)
    if not curvature > 0:
        sigma = float("inf")
    return AnchorSearch(
        centre, float(np.sqrt(r2)), curvature, sigma, evaluations, cache[centre][2]
    )


def anchor_residual_curve(
    reconstruct: Callable[[float], SurfaceEstimate], anchors_mm: NDArray
) -> NDArray:
    """Integration residual (mm) for each anchor height: the curve behind :func:`find_anchor`."""
    return np.array([integration_residual_mm(reconstruct(float(a))) for a in anchors_mm])
