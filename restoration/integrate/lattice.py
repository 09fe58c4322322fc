"""Integrators on the dot lattice: the samples' own ``(i, j)`` grid, with height differences
between lattice neighbours fitted by sparse least squares (``"paper"``, eq. 10-13,
``"trapezoid"`` and ``"fourth_order"``; see :data:`restoration.integrate.INTEGRATORS`), plus
the input checks, grid neighbours, connected pieces and SPD solves that the other integrators
reuse."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy.sparse.linalg import SuperLU, splu

from restoration.integrate._common import _MAX_GRID_NODES, MIN_SAMPLES, Array, IntArray
from restoration.integrate.plans import IntegrationPlans, plan_of
from restoration.integrate.rules import edge_steps
from wai_core.errors import RestorationFailed, WaiInputError

# --------------------------------------------------------------------------------------------
# Input checks and the sample grid
# --------------------------------------------------------------------------------------------


def check_samples(
    ij: ArrayLike, xy_mm: ArrayLike, slopes: ArrayLike
) -> tuple[IntArray, Array, Array]:
    """Validate integrator input and return it as arrays (shapes: see :data:`Integrator`).

    Raises
    ------
    WaiInputError
        On wrong shapes, NaN or inf, or repeated grid indices.
    RestorationFailed
        On absurdly spread grid indices, or fewer than :data:`MIN_SAMPLES` samples.
    """
    ij_arr = np.asarray(ij)
    xy = np.asarray(xy_mm, dtype=float)
    g = np.asarray(slopes, dtype=float)
    for name, arr in (("ij", ij_arr), ("xy_mm", xy), ("slopes", g)):
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise WaiInputError(f"integrate: {name} must have shape (K, 2), got {arr.shape}")
    if not ij_arr.shape[0] == xy.shape[0] == g.shape[0]:
        raise WaiInputError("integrate: ij, xy_mm and slopes must hold the same number of samples")
    if ij_arr.shape[0] < MIN_SAMPLES:
        raise RestorationFailed(
            f"integrate: too few features to integrate ({ij_arr.shape[0]} < {MIN_SAMPLES})"
        )
    if not np.issubdtype(ij_arr.dtype, np.integer):
        raise WaiInputError("integrate: ij must hold integer grid indices")
    if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(g))):
        raise WaiInputError("integrate: xy_mm or slopes hold NaN or inf")
    ij_arr = ij_arr.astype(np.int64)
    span = ij_arr.max(axis=0) - ij_arr.min(axis=0) + 1
    if span[0] * span[1] > _MAX_GRID_NODES:
        raise RestorationFailed(
            f"integrate: grid indices span {span[0]} x {span[1]}, too wide a grid"
        )
    # A table over the index span finds repeated (i, j) without sorting.
    flat = (ij_arr[:, 1] - ij_arr[:, 1].min()) * span[0] + (ij_arr[:, 0] - ij_arr[:, 0].min())
    if np.bincount(flat).max() > 1:
        raise WaiInputError("integrate: two samples share one grid index (i, j)")
    return ij_arr, xy, g


def grid_neighbours(ij: IntArray, offsets: ArrayLike) -> IntArray:
    """Index of the sample at ``(i + di, j + dj)`` for every sample and offset, -1 where absent.

    Parameters
    ----------
    ij : (K, 2) ndarray of int
        Grid indices (unique).
    offsets : (P, 2) array_like of int
        Offsets ``(di, dj)``, each component -1, 0 or 1.

    Returns
    -------
    (P, K) ndarray of int
    """
    off = np.asarray(offsets, dtype=np.int64).reshape(-1, 2)
    lo = ij.min(axis=0) - 1
    shape = ij.max(axis=0) - lo + 2
    # A padded lookup table: the border ring of -1 answers for neighbours past the edge.
    table = np.full((shape[1], shape[0]), -1, dtype=np.int64)
    local = ij - lo
    table[local[:, 1], local[:, 0]] = np.arange(ij.shape[0])
    return table[local[None, :, 1] + off[:, 1:2], local[None, :, 0] + off[:, 0:1]]


def line_neighbours(ij: IntArray, a: IntArray, b: IntArray) -> tuple[IntArray, IntArray]:
    """The sample before ``a`` and the one after ``b`` on the lattice line of each edge
    ``a -> b`` (E,) between 4-neighbours of ``ij`` (K, 2): (E,) each, -1 where absent (what
    the fourth-order rule reads, :func:`restoration.integrate.rules.edge_step`)."""
    nb = grid_neighbours(ij, [(-1, 0), (0, -1), (1, 0), (0, 1)])
    along_j = (ij[b, 1] != ij[a, 1]).astype(np.int64)  # 0: the edge runs along i, 1: along j
    return nb[along_j, a], nb[2 + along_j, b]


def largest_piece(n: int, a: IntArray, b: IntArray) -> NDArray[np.bool_]:
    """Mask (n,) of the nodes in the largest connected piece of the graph with edges ``a-b``
    (of two pieces as large, the one holding the lower node).

    Slopes say nothing about the height step between pieces that share no difference, so
    every integrator reports NaN outside this piece rather than guess it.

    Raises
    ------
    RestorationFailed
        When that piece holds fewer than :data:`MIN_SAMPLES` nodes.
    """
    keep = np.empty(n, np.bool_)
    size = _largest_piece_kernel(
        np.ascontiguousarray(a, dtype=np.int64), np.ascontiguousarray(b, dtype=np.int64), keep
    )
    if size < MIN_SAMPLES:
        raise RestorationFailed(
            f"integrate: too few connected features to integrate ({size} < {MIN_SAMPLES})"
        )
    return keep


@njit(cache=True, nogil=True)
def _largest_piece_kernel(a, b, keep):  # pragma: no cover
    """Mark in ``keep`` (n,) the largest piece of the graph with edges ``a-b`` (E,), by
    union-find with each piece rooted at its lowest node; returns its size. (scipy's sparse
    graph routines took ~0.5 ms a frame here, for ~1500 edges.)"""
    n = keep.size
    root = np.arange(n)
    for e in range(a.size):
        ra, rb = a[e], b[e]
        while root[ra] != ra:
            root[ra] = root[root[ra]]  # path halving
            ra = root[ra]
        while root[rb] != rb:
            root[rb] = root[root[rb]]
            rb = root[rb]
        if ra < rb:
            root[rb] = ra
        elif rb < ra:
            root[ra] = rb
    count = np.zeros(n, np.int64)
    best = 0
    for v in range(n):  # a node's root is lower than the node: already final
        root[v] = root[root[v]]
        count[root[v]] += 1
    for v in range(n):
        if count[v] > count[best]:
            best = v
    for v in range(n):
        keep[v] = root[v] == best
    return count[best] if n else 0


def largest_grid_piece(ij: IntArray) -> NDArray[np.bool_]:
    """Mask (K,) of the samples in the largest 4-connected piece of the ``(i, j)`` grid."""
    plus = grid_neighbours(ij, [(1, 0), (0, 1)]).ravel()
    a = np.tile(np.arange(ij.shape[0]), 2)
    return largest_piece(ij.shape[0], a[plus >= 0], plus[plus >= 0])


# --------------------------------------------------------------------------------------------
# Least squares over height differences (shared by "paper" and "trapezoid")
# --------------------------------------------------------------------------------------------


def _spd_factor(matrix: sp.spmatrix) -> SuperLU:
    """Factorise a sparse symmetric positive definite matrix (SuperLU in symmetric mode)."""
    # Symmetric mode with a minimum-degree ordering of A + A^T and no pivoting: a few times
    # faster than the default unsymmetric LU on these Laplacian-like matrices. (LAPACK's banded
    # Cholesky would be faster still, but OpenBLAS threads it and, next to OpenCV's threads on
    # two cores, it stalls for tens of ms now and then.)
    try:
        return splu(
            sp.csc_matrix(matrix),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError:  # SuperLU: "Factor is exactly singular"
        raise _singular() from None


def spd_solve(matrix: sp.spmatrix, rhs: Array) -> Array:
    """Solve a sparse symmetric positive definite system (SuperLU in symmetric mode)."""
    out = _spd_factor(matrix).solve(rhs)
    if not np.all(np.isfinite(out)):
        raise _singular()
    return out


def _singular() -> RestorationFailed:
    return RestorationFailed("integrate: the samples do not determine the surface (singular fit)")


@dataclass(frozen=True)
class DifferenceGraph:
    """The structure of ``min sum_e w_e (h[b_e] - h[a_e] - d_e)^2``, prepared once per edge set.

    The normal matrix is a weighted graph Laplacian with one null vector (the constant) per
    connected piece. Everything that depends on the edges alone is kept: the largest connected
    piece, and the sparsity pattern of its Laplacian with the first kept node pinned to zero,
    with the scatter indices that fill it from the edge weights. Factorisations are cached by
    weights, so repeated solves with the same weights (the refinement passes of
    :func:`restoration.surface.reconstruct_surface`, which weight every pass by the first
    pass's geometry) cost two triangular solves.

    Attributes
    ----------
    n : int
        Number of samples.
    keep : (n,) ndarray of bool
        Samples in the largest connected piece.
    edges : (E',) ndarray of int
        The edges inside that piece, as indices into the ``a, b`` given to :meth:`build`.
    node : (m,) ndarray of int
        The kept samples, in the order of the unknowns; the first is pinned.
    ea, eb : (E',) ndarray of int
        Positions of the edges' end points in ``node``.
    indptr, indices : ndarray of int
        CSC pattern of the pinned Laplacian, (m - 1, m - 1).
    slot, source, sign : ndarray
        Each Laplacian contribution (an edge's off-diagonal pair and its diagonal terms) adds
        ``sign * w[source]`` to data entry ``slot``.
    """

    n: int
    keep: NDArray[np.bool_]
    edges: IntArray
    node: IntArray
    ea: IntArray
    eb: IntArray
    indptr: IntArray
    indices: IntArray
    slot: IntArray
    source: IntArray
    sign: Array
    _factors: dict[bytes, SuperLU] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def build(cls, n: int, a: IntArray, b: IntArray) -> DifferenceGraph:
        """Prepare the system of ``n`` samples and edges ``a -> b`` (E,)."""
        keep = largest_piece(n, a, b)
        edges = np.flatnonzero(keep[a] & keep[b])
        node = np.flatnonzero(keep)
        pos = np.cumsum(keep) - 1
        ea, eb = pos[a[edges]], pos[b[edges]]
        # Contributions to the Laplacian without row and column 0 (the pinned node), in
        # unknowns 0 .. m - 2 (= position - 1): -w at (a, b) and (b, a), +w at (a, a), (b, b).
        e = np.arange(edges.size)
        both = (ea > 0) & (eb > 0)
        rows = np.r_[ea[both], eb[both], ea[ea > 0], eb[eb > 0]] - 1
        cols = np.r_[eb[both], ea[both], ea[ea > 0], eb[eb > 0]] - 1
        source = np.r_[e[both], e[both], e[ea > 0], e[eb > 0]]
        sign = np.r_[-np.ones(2 * both.sum()), np.ones(source.size - 2 * both.sum())]
        m = node.size - 1
        pattern = sp.csc_matrix((np.ones(rows.size), (rows, cols)), shape=(m, m))
        pattern.sort_indices()
        # Data slot of each contribution: its (column, row) among the sorted CSC entries.
        entry = np.repeat(np.arange(m), np.diff(pattern.indptr)) * m + pattern.indices
        slot = np.searchsorted(entry, cols * m + rows)
        indptr, indices = pattern.indptr, pattern.indices
        return cls(n, keep, edges, node, ea, eb, indptr, indices, slot, source, sign)

    def solve(self, diff_mm: Array, weights: Array) -> Array:
        """Zero-mean heights (n,) in mm minimising the weighted misfit; NaN outside the piece.

        Parameters
        ----------
        diff_mm, weights : (E,) ndarray
            Measured differences (mm) and positive weights of all edges given to
            :meth:`build` (those outside the largest piece are ignored).
        """
        w, d = weights[self.edges], diff_mm[self.edges]
        m = self.node.size
        wd = w * d
        rhs = np.bincount(self.eb, wd, m) - np.bincount(self.ea, wd, m)
        h = np.r_[0.0, self._factor(w).solve(rhs[1:])]
        if not np.all(np.isfinite(h)):
            raise _singular()
        heights = np.full(self.n, np.nan)
        heights[self.node] = h - h.mean()
        return heights

    def _factor(self, w: Array) -> SuperLU:
        """The factorised pinned Laplacian of edge weights ``w`` (E',), cached."""
        key = w.tobytes()
        lu = self._factors.get(key)
        if lu is None:
            data = np.bincount(self.slot, self.sign * w[self.source], self.indices.size)
            m = self.node.size - 1
            lu = _spd_factor(sp.csc_matrix((data, self.indices, self.indptr), shape=(m, m)))
            if len(self._factors) >= 8:
                self._factors.clear()
            self._factors[key] = lu
        return lu


def solve_differences(
    n: int, a: IntArray, b: IntArray, diff_mm: Array, weights: Array
) -> Array:
    """Heights minimising ``sum_e w_e (h[b_e] - h[a_e] - diff_e)^2``, zero mean.

    The normal matrix is a weighted graph Laplacian with one null vector (the constant) per
    connected piece; the largest piece is solved with one node pinned to zero, then shifted to
    zero mean (see :class:`DifferenceGraph`, which callers solving one graph repeatedly should
    keep).

    Parameters
    ----------
    n : int
        Number of samples.
    a, b : (E,) ndarray of int
        End points of each difference (``h[b] - h[a]``).
    diff_mm : (E,) ndarray
        Measured differences, mm.
    weights : (E,) ndarray
        Positive weights.

    Returns
    -------
    (n,) ndarray
        Heights, mm; NaN outside the largest connected piece.
    """
    return DifferenceGraph.build(n, a, b).solve(diff_mm, weights)


@dataclass(frozen=True)
class _EdgePlan:
    """Edges of one finite-difference scheme on one set of grid indices, with their solver.

    Edge ``e`` states ``h[b_e] - h[a_e] = s . (xy[b_e] - xy[a_e])`` with the slope ``s`` the
    mean of the end points' (trapezoid) or that of sample ``slope_at[e]`` (central); the
    fourth-order scheme's steps also read the samples ``before[e]`` and ``after[e]`` on the
    edge's lattice line (:func:`~restoration.integrate.rules.edge_steps`; -1 where absent or
    outside the graph's largest piece).
    """

    a: IntArray
    b: IntArray
    slope_at: IntArray | None
    graph: DifferenceGraph
    before: IntArray | None = None
    after: IntArray | None = None


def _edge_plan(ij: IntArray, scheme: str) -> _EdgePlan:
    """The :class:`_EdgePlan` of ``scheme`` (``"central"``, ``"trapezoid"`` or
    ``"fourth_order"``, the last two on the same edges) on ``ij``.

    ``"central"`` is eq. 10: central where both neighbours exist, else forward or backward
    (slope at the centre).
    """
    centre = np.arange(ij.shape[0])
    neighbours = grid_neighbours(ij, [(1, 0), (-1, 0), (0, 1), (0, -1)])
    parts = []
    for plus, minus in (neighbours[:2], neighbours[2:]):
        if scheme != "central":
            on = plus >= 0
            parts.append((centre[on], plus[on], centre[on]))
        else:
            a = np.where(minus >= 0, minus, centre)
            b = np.where(plus >= 0, plus, centre)
            on = a != b
            parts.append((a[on], b[on], centre[on]))
    a, b, at = (np.concatenate(p) for p in zip(*parts, strict=True))
    graph = DifferenceGraph.build(ij.shape[0], a, b)
    plan = _EdgePlan(a, b, at if scheme == "central" else None, graph)
    if scheme == "fourth_order":
        before, after = (np.where(graph.keep[k], k, -1) for k in line_neighbours(ij, a, b))
        plan = _EdgePlan(a, b, None, graph, before, after)
    return plan


def _integrate_scheme(
    ij: ArrayLike,
    xy_mm: ArrayLike,
    slopes: ArrayLike,
    scheme: str,
    weight_xy_mm: ArrayLike | None = None,
    plans: IntegrationPlans | None = None,
) -> Array:
    """Heights by least squares over the differences of ``scheme`` (see :func:`_edge_plan`).

    Weights ``1 / |xy(b) - xy(a)|^2`` turn each residual into slope units (eq. 13), with the
    positions ``weight_xy_mm`` (K, 2) mm where given, else ``xy_mm``. ``plans`` keeps the
    edges and the graph (with its factorisations) for later calls on the same indices.
    """
    ij_a, xy, g = check_samples(ij, xy_mm, slopes)
    plan = plan_of(plans, "edge_plan", ij_a, lambda: _edge_plan(ij_a, scheme), scheme)
    a, b = plan.a, plan.b
    step = xy[b] - xy[a]
    if weight_xy_mm is not None:
        wxy = np.asarray(weight_xy_mm, dtype=float)
        if wxy.shape != xy.shape or not np.all(np.isfinite(wxy)):
            raise WaiInputError("integrate: weight_xy_mm must be finite and shaped like xy_mm")
        length2 = np.sum((wxy[b] - wxy[a]) ** 2, axis=1)
    else:
        length2 = np.einsum("ij,ij->i", step, step)
    if not np.all(length2 > 0):
        raise RestorationFailed("integrate: two neighbouring samples sit at the same position")
    if plan.before is not None:
        diff = edge_steps(xy, g, a, b, plan.before, plan.after)
    else:
        slope = 0.5 * (g[a] + g[b]) if plan.slope_at is None else g[plan.slope_at]
        diff = np.einsum("ij,ij->i", slope, step)
    return plan.graph.solve(diff, 1.0 / length2)


def integrate_paper(
    ij: ArrayLike,
    xy_mm: ArrayLike,
    slopes: ArrayLike,
    weight_xy_mm: ArrayLike | None = None,
    plans: IntegrationPlans | None = None,
) -> Array:
    """Eq. 10-13: central differences on the sample grid, least squares (see :data:`INTEGRATORS`).

    Parameters
    ----------
    ij : (K, 2) array_like of int
    xy_mm : (K, 2) array_like, mm
    slopes : (K, 2) array_like, dimensionless
    weight_xy_mm : (K, 2) array_like, mm, optional
        Positions that set the weights (eq. 13), default ``xy_mm``. Repeated solves with the
        same weights reuse one factorisation (see :class:`DifferenceGraph`).
    plans : IntegrationPlans, optional
        Where the edges and their graph are kept for later calls on the same ``ij`` (one
        frame's passes); default: built for this call.

    Returns
    -------
    (K,) ndarray
        Zero-mean heights, mm; NaN for samples cut off from the largest connected piece.
    """
    return _integrate_scheme(ij, xy_mm, slopes, "central", weight_xy_mm, plans)


def integrate_fourth_order(
    ij: ArrayLike,
    xy_mm: ArrayLike,
    slopes: ArrayLike,
    weight_xy_mm: ArrayLike | None = None,
    plans: IntegrationPlans | None = None,
) -> Array:
    """Least squares over the trapezoid integrator's edges, each step by the fourth-order rule
    (see :data:`INTEGRATORS` and :mod:`restoration.integrate.rules`).

    Parameters and return as :func:`integrate_paper`.
    """
    return _integrate_scheme(ij, xy_mm, slopes, "fourth_order", weight_xy_mm, plans)


def integrate_trapezoid(
    ij: ArrayLike,
    xy_mm: ArrayLike,
    slopes: ArrayLike,
    weight_xy_mm: ArrayLike | None = None,
    plans: IntegrationPlans | None = None,
) -> Array:
    """Trapezoid-rule least squares over the 4-neighbour edges (see :data:`INTEGRATORS`).

    Parameters and return as :func:`integrate_paper`.
    """
    return _integrate_scheme(ij, xy_mm, slopes, "trapezoid", weight_xy_mm, plans)
