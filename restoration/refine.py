"""The surface's refinement passes after the paper's first one: every sample moved along its
projector ray to the reconstructed heights, its normal and slope computed again there and the
slopes integrated again, the passes' fixed point reached with Anderson mixing
(:func:`restoration.surface.reconstruct` calls them). The trapezoid and fourth-order rules run
all their passes in one compiled call; the other rules pass by pass in NumPy."""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from restoration.integrate import (
    check_samples,
    grid_neighbours,
    integrate,
)
from restoration.integrate.lattice import largest_piece, line_neighbours
from restoration.integrate.ldl import ldl_solve, pinned_laplacian_ldl
from restoration.integrate.plans import IntegrationPlans, plan_of
from restoration.integrate.rules import edge_step
from restoration.normals import (
    _KERNEL_ERRORS,
    _reflection_kernel,
    kernel_error,
    ray_origins,
    reflection_slopes,
)
from wai_core.errors import RestorationFailed
from wai_core.timings import Timings

Array = NDArray[np.float64]


def _refinement(
    ij_arr: NDArray[np.int64],
    origin: Array,
    v_p: Array,
    spots: Array,
    h0_mm: float,
    n_refine: int,
    tol_mm: float,
    accelerate: bool,
    weight_xy: Array | None,
    integrator: str,
    timings: Timings,
    plans: IntegrationPlans | None = None,
) -> tuple[NDArray[np.int64], Array, Array, Array, Array, int, float]:
    """The passes of :func:`~restoration.surface.reconstruct` as NumPy steps around
    :func:`~restoration.integrate.integrate`, for any integrator (the ``"trapezoid"`` one runs
    compiled instead, :func:`_compiled_refinement`, to the same result). Adds each pass's
    ``normals`` and ``integrate`` times to ``timings``.

    Returns
    -------
    ij, q, normals, slopes, integrated, iterations, change
        As :func:`_compiled_refinement`.
    """
    heights = np.full(ij_arr.shape[0], float(h0_mm))  # pass 0: the paper's q on z = h0
    origin = ray_origins(origin, len(v_p))
    previous: tuple[Array, Array] | None = None
    change = np.nan
    for it in range(int(n_refine) + 1):
        with timings("normals"):
            q, normals, slopes = reflection_slopes(origin, v_p, spots, heights)
            if not (np.all(np.isfinite(q[:, :2])) and np.all(np.isfinite(slopes))):
                raise RestorationFailed(_REFINE_ERRORS[5])  # a pass that diverged, as compiled
        with timings("integrate"):
            # Every pass weighs the differences by the first pass's geometry: the passes then
            # share one factorisation, and their samples move by only ~mm along the rays.
            weight_xy = q[:, :2] if weight_xy is None else weight_xy
            relative = integrate(ij_arr, q[:, :2], slopes, integrator, weight_xy, plans)
            integrated = _anchored(relative, h0_mm)
        # Samples the integrator could not tie to the rest (NaN) leave for good.
        keep = np.isfinite(integrated)
        if not keep.all():
            ij_arr, origin, v_p, spots, q, normals, slopes, heights, integrated, weight_xy = (
                a[keep] for a in (ij_arr, origin, v_p, spots, q, normals, slopes, heights,
                                  integrated, weight_xy)
            )
            if previous is not None:
                previous = (previous[0][keep], previous[1][keep])
        residual = integrated - heights
        if it > 0:
            change = float(np.max(np.abs(residual)))
            if change < tol_mm:
                break
        step = _anderson_step(heights, residual, previous) if accelerate else integrated
        previous = (heights, residual)
        heights = step
    return ij_arr, q, normals, slopes, integrated, it, change


def _prepared(
    ij: NDArray[np.int64], weight_xy: Array, fourth_order: bool,
    plans: IntegrationPlans | None = None,
) -> tuple:
    """What :func:`_refine_kernel` needs of a sample set, its weights and its rule, kept in
    ``plans`` (one lookup per reconstruction instead of the system's, the weights' and the
    factors').

    Returns
    -------
    keep : (K,) ndarray of bool or None
        The samples in the largest connected piece, None when that is all of them.
    ea, eb, w : (E,) ndarray
        The piece's edges (positions among the kept samples) and weights.
    before, after : (E,) ndarray of int
        The fourth-order rule's samples before and after each edge among the kept ones
        (:func:`~restoration.integrate.line_neighbours`), -1 where absent; all -1 for the
        trapezoid rule.
    factors : tuple
        :attr:`~restoration.integrate.ldl.LdlFactors.arrays` of its pinned Laplacian (the
        matrix of :class:`~restoration.integrate.DifferenceGraph`).
    """
    weight_xy = np.ascontiguousarray(weight_xy, dtype=float)

    def build() -> tuple:
        check_samples(ij, weight_xy, np.zeros_like(weight_xy))
        if fourth_order:
            a, b, before, after = edges_and_lines(ij, plans)
        else:
            a, b = trapezoid_edges(ij)
        length2 = np.empty(a.size)
        _length2_kernel(weight_xy, a, b, length2)
        if not np.all(length2 > 0):
            raise RestorationFailed(
                "integrate: two neighbouring samples sit at the same position"
            )
        keep = largest_piece(ij.shape[0], a, b)
        # The piece's edges, in the order of the trapezoid edges of its own samples.
        inside = keep[a] & keep[b]
        pos = np.cumsum(keep) - 1
        ea, eb, w = pos[a[inside]], pos[b[inside]], 1.0 / length2[inside]
        kept_ij = ij[keep]
        if fourth_order and not keep.all():
            before, after = line_neighbours(kept_ij, ea, eb)
        elif not fourth_order:
            before = after = np.full(ea.size, -1, np.int64)
        factors = pinned_laplacian_ldl(kept_ij, ea, eb, w).arrays
        return None if keep.all() else keep, ea, eb, before, after, w, factors

    return plan_of(plans, "prepared", ij, build, weight_xy.shape, weight_xy.tobytes(),
                   fourth_order)


# Why _refine_kernel stopped, beyond the reflection's codes (restoration.normals).
_REFINE_ERRORS = {
    5: "integrate: xy_mm or slopes hold NaN or inf",
    6: "integrate: the samples do not determine the surface (singular fit)",
}


def _compiled_refinement(
    ij: NDArray[np.int64],
    origin: Array,
    v_p: Array,
    spots: Array,
    h0_mm: float,
    n_refine: int,
    tol_mm: float,
    accelerate: bool,
    weight_xy: Array,
    fourth_order: bool = True,
    plans: IntegrationPlans | None = None,
) -> tuple[NDArray[np.int64], Array, Array, Array, Array, int, float]:
    """The passes of :func:`~restoration.surface.reconstruct_surface` with the
    ``"fourth_order"`` (or, with ``fourth_order=False``, the ``"trapezoid"``) integrator in one
    compiled call
    (:func:`_refine_kernel`).

    The level search runs ~20 passes a frame: as NumPy steps each cost ~0.15 ms of call
    overhead around ~0.03 ms of arithmetic. Same arithmetic, in the same order, as the loop
    (the factorisation's triangular solves, sums and dot products differ only in rounding).
    Samples outside the largest connected piece are dropped first: the loop drops them after
    its first pass, whose results on the piece do not depend on them (same edges, same pinned
    sample, same matrix); that pass's checks are run on them here.

    Returns
    -------
    ij, q, normals, slopes, integrated, iterations, change
        The samples kept (K', 2), the last pass's reflection points (K', 3) mm, normals
        (K', 3), slopes (K', 2), anchored heights (K',) mm, passes run after the first, and
        the last pass's largest height change (mm; NaN when none ran).
    """
    keep, ea, eb, before, after, w, factors = _prepared(ij, weight_xy, fourth_order, plans)
    origin = ray_origins(origin, len(ij))
    if keep is not None:
        _, _, slopes = reflection_slopes(origin, v_p, spots, np.full(len(ij), float(h0_mm)))
        if not np.all(np.isfinite(slopes)):
            raise RestorationFailed(_REFINE_ERRORS[5])
        ij, origin, v_p, spots = ij[keep], origin[keep], v_p[keep], spots[keep]
    k = ij.shape[0]
    q, normals, slopes = np.empty((k, 3)), np.empty((k, 3)), np.empty((k, 2))
    integrated, out = np.empty(k), np.empty(2)
    code = _refine_kernel(
        np.ascontiguousarray(origin), np.ascontiguousarray(v_p, dtype=float),
        np.ascontiguousarray(spots, dtype=float), float(h0_mm), n_refine, float(tol_mm),
        bool(accelerate), ea, eb, before, after, w, *factors, q, normals, slopes, integrated,
        out,
    )
    if code:
        raise kernel_error(code) if code in _KERNEL_ERRORS else RestorationFailed(
            _REFINE_ERRORS[code]
        )
    return ij, q, normals, slopes, integrated, int(out[0]), float(out[1])


@njit(cache=True, nogil=True, error_model="numpy")
def _refine_kernel(
    origin, dirs, spots, h0, n_refine, tol, accelerate, ea, eb, before, after, w,
    rank, l_ptr, l_idx, l_val, l_diag, q, normals, slopes, integrated, out,
):  # pragma: no cover
    """All passes of the trapezoid refinement (see :func:`_compiled_refinement`).

    ``ea, eb`` (E,) are the edges (every sample kept, sample 0 pinned), ``w`` (E,) their
    weights, then the factors of the pinned Laplacian (:class:`LdlFactors`). Fills
    ``q``, ``normals``, ``slopes``, ``integrated`` and ``out = (iterations, change)``;
    returns 0 or an error code (:data:`_KERNEL_ERRORS`, :data:`_REFINE_ERRORS`).
    """
    k = dirs.shape[0]
    n_edges = ea.size
    heights = np.full(k, h0)  # pass 0: the paper's q on z = h0
    prev_h, prev_r = np.empty(k), np.empty(k)
    residual, step = np.empty(k), np.empty(k)
    plus, minus = np.zeros(k), np.zeros(k)
    rhs, sol = np.empty(k - 1), np.empty(k - 1)
    has_previous = False
    change = np.nan
    it = 0
    for it in range(n_refine + 1):
        code = _reflection_kernel(origin, dirs, spots, heights, q, normals, slopes)
        if code:
            return code
        if it == 0:
            for i in range(k):
                if not (np.isfinite(q[i, 0]) and np.isfinite(q[i, 1])
                        and np.isfinite(slopes[i, 0]) and np.isfinite(slopes[i, 1])):
                    return 5
        # DifferenceGraph.solve: right-hand side as two sums in edge order, pinned solve.
        plus[:] = 0.0
        minus[:] = 0.0
        for e in range(n_edges):
            i, j = ea[e], eb[e]
            wd = w[e] * edge_step(q, slopes, before[e], i, j, after[e])
            plus[j] += wd
            minus[i] += wd
        for i in range(k - 1):
            rhs[i] = plus[i + 1] - minus[i + 1]
        ldl_solve(rank, l_ptr, l_idx, l_val, l_diag, rhs, sol)
        total = 0.0
        for i in range(k - 1):
            if not np.isfinite(sol[i]):
                return 6
            total += sol[i]
        mean = total / k  # of (0, sol): zero-mean heights, then anchored at h0
        integrated[0] = -mean
        for i in range(k - 1):
            integrated[i + 1] = sol[i] - mean
        total = 0.0
        for i in range(k):
            total += integrated[i]
        mean = total / k
        for i in range(k):
            integrated[i] = integrated[i] - mean + h0
            residual[i] = integrated[i] - heights[i]
        if it > 0:
            change = 0.0
            for i in range(k):
                change = max(change, abs(residual[i]))
            if change < tol:
                break
        # _anderson_step
        gamma = 0.0
        if accelerate and has_previous:
            denom, num, rr, pp = 0.0, 0.0, 0.0, 0.0
            for i in range(k):
                df = residual[i] - prev_r[i]
                denom += df * df
                num += df * residual[i]
                rr += residual[i] * residual[i]
                pp += prev_r[i] * prev_r[i]
            if denom != 0.0 and not rr > pp:
                gamma = num / denom
        for i in range(k):
            plain = heights[i] + residual[i]
            if gamma != 0.0:
                plain = plain - gamma * ((heights[i] - prev_h[i]) + (residual[i] - prev_r[i]))
            step[i] = plain
        for i in range(k):
            prev_h[i], prev_r[i], heights[i] = heights[i], residual[i], step[i]
        has_previous = True
    out[0] = it
    out[1] = change
    return 0


@njit(cache=True, nogil=True)
def _length2_kernel(xy, a, b, out):  # pragma: no cover
    """``out[e] = |xy[b] - xy[a]|^2`` for every edge ``e``."""
    for e in range(a.size):
        dx = xy[b[e], 0] - xy[a[e], 0]
        dy = xy[b[e], 1] - xy[a[e], 1]
        out[e] = dx * dx + dy * dy


def trapezoid_edges(ij: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The ``"trapezoid"`` integrator's edges ``a -> b`` (E,) on grid indices ``ij`` (K, 2):
    every ``(i, j) -> (i + 1, j)``, then every ``(i, j) -> (i, j + 1)``, in sample order."""
    nb = grid_neighbours(ij, [(1, 0), (0, 1)])
    a = np.concatenate([np.flatnonzero(row >= 0) for row in nb])
    b = np.concatenate([row[row >= 0] for row in nb])
    return a, b


def edges_and_lines(
    ij: NDArray[np.int64], plans: IntegrationPlans | None = None
) -> tuple[NDArray[np.int64], ...]:
    """:func:`trapezoid_edges` ``a, b`` of ``ij`` (K, 2) and the samples before and after each
    edge on its lattice line (:func:`~restoration.integrate.line_neighbours`), kept in
    ``plans``: the integration and the level search's residuals read the same ones."""

    def build() -> tuple[NDArray[np.int64], ...]:
        a, b = trapezoid_edges(ij)
        return (a, b, *line_neighbours(ij, a, b))

    return plan_of(plans, "edges_and_lines", ij, build)


def _anchored(relative_mm: Array, h0_mm: float) -> Array:
    """Absolute heights whose mean (over the finite ones) is the known level ``h0``, mm."""
    return relative_mm - np.nanmean(relative_mm) + h0_mm


def _anderson_step(
    heights: Array, residual: Array, previous: tuple[Array, Array] | None
) -> Array:
    """Next iterate of ``h = G(h)`` by Anderson mixing of depth 1, mm.

    With ``f = G(h) - h`` and the differences ``dh, df`` from the previous pass, the step
    ``h + f - gamma (dh + df)`` with ``gamma = (df . f) / (df . df)`` cancels the residual's
    component along its last change (a secant step). Falls back to the plain step ``G(h)``
    on the first pass, or when the residual grew (the secant model is then not trusted).
    All terms keep the mean, so the anchor holds.
    """
    plain = heights + residual
    if previous is None:
        return plain
    dh, df = heights - previous[0], residual - previous[1]
    denom = float(df @ df)
    if denom == 0.0 or residual @ residual > previous[1] @ previous[1]:
        return plain
    return plain - (df @ residual) / denom * (dh + df)
