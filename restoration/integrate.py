"""From sampled surface slopes to heights (section 3.2.2), and from scattered heights to a grid.

Every integrator shares one interface (:data:`Integrator`) and lives in :data:`INTEGRATORS`, so
new ones can be added and compared by name:

``integrator(ij, xy_mm, slopes) -> heights_mm``

(the built-in ones also take an optional ``weight_xy_mm``, see :func:`integrate`).

``ij`` (K, 2) int
    Grid index ``(i, j)`` of each sample (its dot in the pattern); 4-neighbours in ``(i, j)`` are
    neighbours on the surface. Missing nodes (undetected dots) are simply absent.
``xy_mm`` (K, 2) float
    Horizontal sample positions, mm (irregular: the projector's keystone plus the waves).
``slopes`` (K, 2) float
    ``(dz/dx, dz/dy)`` at the samples, dimensionless.
``heights_mm`` (K,) float
    Heights up to a constant, mm, with zero mean; NaN for samples that the integrator cannot tie
    to the others (outside the largest connected piece of the sample grid).

Integrators
-----------
``"paper"``
    Eq. 10-13: central differences on the ``(i, j)`` grid, one-sided at borders and holes, solved
    by least squares. Eq. 10 divides by ``x`` spacings, which assumes rows of samples run along
    ``x``; the projector's samples form a keystone, so each difference is taken along the actual
    displacement, ``h(c+) - h(c-) = g(c) . (xy(c+) - xy(c-))``, weighted to a residual in slope
    units as in eq. 13. On a rectilinear grid this is eq. 10 exactly.
``"trapezoid"``
    Least squares over the edges of the 4-neighbour graph with the trapezoid rule,
    ``h(b) - h(a) = (g(a) + g(b)) / 2 . (xy(b) - xy(a))``: exact for quadratic surfaces on any
    irregular grid, and free of the odd-even decoupling that central differences suffer.
``"spline"``
    A bicubic B-spline on a regular control grid fitted by sparse least squares straight to the
    slopes, with a weak penalty on third differences of its coefficients (it leaves planes and
    quadratics untouched and only steers coefficients that the data leave free).
``"frankot_chellappa"``
    Frankot & Chellappa (1988) on a regular grid: the slopes are resampled onto nodes half the
    median sample spacing apart (linear on the samples' Delaunay triangles, extended beyond
    their hull by nearest values plus the mean curvature), projected onto the grid's integrable
    Fourier modes (heights mirrored evenly at the borders, so the periodic wrap adds no step),
    and the heights are read back at the samples. Exact for planes; the mirror's slope kinks
    cost accuracy near the grid's borders.
``"dct_poisson"``
    The same resampling, then least squares over the grid's edges with the trapezoid rule: the
    Poisson equation with Neumann borders, solved by DCT (Simchony, Chellappa & Shao 1990).
    Exact for quadratic surfaces.

    Both grid integrators ignore ``weight_xy_mm``. They integrate the interpolated slopes, so
    where the samples leave wide gaps inside their hull (the far field's holes), and near its
    edge, they err more than the lattice integrators; they cost a fixed ~10 ms per call.

:func:`to_heightfield` grids scattered heights (and slopes) onto a regular :class:`Heightfield`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from scipy.fft import dctn, idctn, irfft2, rfft2
from scipy.interpolate import CloughTocher2DInterpolator
from scipy.ndimage import distance_transform_edt
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import SuperLU, splu
from scipy.spatial import Delaunay, QhullError, cKDTree

from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
Integrator = Callable[[ArrayLike, ArrayLike, ArrayLike], Array]

MIN_SAMPLES = 4
"""Fewest samples that integration and gridding accept."""

# Weight of the third-difference penalty relative to the data (dimensionless, see penalty()).
_SPLINE_SMOOTHING = 1e-2
# Spline control spacing in units of the median nearest-neighbour distance of the samples.
_SPLINE_STEP = 1.5
# Largest (i, j) index span, and largest output grid, accepted (a dot pattern has ~10^3 dots).
_MAX_GRID_NODES = 4_000_000


# --------------------------------------------------------------------------------------------
# Input checks and the sample grid
# --------------------------------------------------------------------------------------------


def check_samples(
    ij: ArrayLike, xy_mm: ArrayLike, slopes: ArrayLike
) -> tuple[IntArray, Array, Array]:
    """Validate integrator input and return it as arrays (see the module docstring for shapes).

    Raises
    ------
    WaiInputError
        On wrong shapes, NaN or inf, repeated or absurdly spread grid indices, or fewer than
        :data:`MIN_SAMPLES` samples.
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
        raise WaiInputError(
            f"integrate: too few features to integrate ({ij_arr.shape[0]} < {MIN_SAMPLES})"
        )
    if not np.issubdtype(ij_arr.dtype, np.integer):
        raise WaiInputError("integrate: ij must hold integer grid indices")
    if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(g))):
        raise WaiInputError("integrate: xy_mm or slopes hold NaN or inf")
    ij_arr = ij_arr.astype(np.int64)
    span = ij_arr.max(axis=0) - ij_arr.min(axis=0) + 1
    if span[0] * span[1] > _MAX_GRID_NODES:
        raise WaiInputError(f"integrate: grid indices span {span[0]} x {span[1]}, too wide a grid")
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


def largest_piece(n: int, a: IntArray, b: IntArray) -> NDArray[np.bool_]:
    """Mask (n,) of the nodes in the largest connected piece of the graph with edges ``a-b``.

    Slopes say nothing about the height step between pieces that share no difference, so
    every integrator reports NaN outside this piece rather than guess it.

    Raises
    ------
    WaiInputError
        When that piece holds fewer than :data:`MIN_SAMPLES` nodes.
    """
    adjacency = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n))
    _, labels = connected_components(adjacency, directed=False)
    keep = labels == np.bincount(labels).argmax()
    if keep.sum() < MIN_SAMPLES:
        raise WaiInputError(
            f"integrate: too few connected features to integrate ({keep.sum()} < {MIN_SAMPLES})"
        )
    return keep


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


def _singular() -> WaiInputError:
    return WaiInputError("integrate: the samples do not determine the surface (singular fit)")


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
    mean of the end points' (trapezoid) or that of sample ``slope_at[e]`` (central).
    """

    a: IntArray
    b: IntArray
    slope_at: IntArray | None
    graph: DifferenceGraph


# Plans by (scheme, grid indices): the refinement passes of one frame, and the anchor search's
# reconstructions, integrate the same samples many times.
_EDGE_PLANS: dict[tuple, _EdgePlan] = {}


def _edge_plan(ij: IntArray, scheme: str) -> _EdgePlan:
    """The :class:`_EdgePlan` of ``scheme`` (``"central"`` or ``"trapezoid"``) on ``ij``, cached.

    ``"central"`` is eq. 10: central where both neighbours exist, else forward or backward
    (slope at the centre).
    """
    key = (scheme, ij.shape, ij.tobytes())
    plan = _EDGE_PLANS.get(key)
    if plan is not None:
        return plan
    centre = np.arange(ij.shape[0])
    neighbours = grid_neighbours(ij, [(1, 0), (-1, 0), (0, 1), (0, -1)])
    parts = []
    for plus, minus in (neighbours[:2], neighbours[2:]):
        if scheme == "trapezoid":
            on = plus >= 0
            parts.append((centre[on], plus[on], centre[on]))
        else:
            a = np.where(minus >= 0, minus, centre)
            b = np.where(plus >= 0, plus, centre)
            on = a != b
            parts.append((a[on], b[on], centre[on]))
    a, b, at = (np.concatenate(p) for p in zip(*parts, strict=True))
    graph = DifferenceGraph.build(ij.shape[0], a, b)
    plan = _EdgePlan(a, b, None if scheme == "trapezoid" else at, graph)
    if len(_EDGE_PLANS) >= 16:
        _EDGE_PLANS.clear()
    _EDGE_PLANS[key] = plan
    return plan


def _integrate_scheme(
    ij: ArrayLike,
    xy_mm: ArrayLike,
    slopes: ArrayLike,
    scheme: str,
    weight_xy_mm: ArrayLike | None = None,
) -> Array:
    """Heights by least squares over the differences of ``scheme`` (see :func:`_edge_plan`).

    Weights ``1 / |xy(b) - xy(a)|^2`` turn each residual into slope units (eq. 13), with the
    positions ``weight_xy_mm`` (K, 2) mm where given, else ``xy_mm``.
    """
    ij_a, xy, g = check_samples(ij, xy_mm, slopes)
    plan = _edge_plan(ij_a, scheme)
    a, b = plan.a, plan.b
    slope = 0.5 * (g[a] + g[b]) if plan.slope_at is None else g[plan.slope_at]
    step = xy[b] - xy[a]
    if weight_xy_mm is not None:
        wxy = np.asarray(weight_xy_mm, dtype=float)
        if wxy.shape != xy.shape or not np.all(np.isfinite(wxy)):
            raise WaiInputError("integrate: weight_xy_mm must be finite and shaped like xy_mm")
        length2 = np.sum((wxy[b] - wxy[a]) ** 2, axis=1)
    else:
        length2 = np.einsum("ij,ij->i", step, step)
    if not np.all(length2 > 0):
        raise WaiInputError("integrate: two neighbouring samples sit at the same position")
    return plan.graph.solve(np.einsum("ij,ij->i", slope, step), 1.0 / length2)


def integrate_paper(
    ij: ArrayLike, xy_mm: ArrayLike, slopes: ArrayLike, weight_xy_mm: ArrayLike | None = None
) -> Array:
    """Eq. 10-13: central differences on the sample grid, least squares (see module docstring).

    Parameters
    ----------
    ij : (K, 2) array_like of int
    xy_mm : (K, 2) array_like, mm
    slopes : (K, 2) array_like, dimensionless
    weight_xy_mm : (K, 2) array_like, mm, optional
        Positions that set the weights (eq. 13), default ``xy_mm``. Repeated solves with the
        same weights reuse one factorisation (see :class:`DifferenceGraph`).

    Returns
    -------
    (K,) ndarray
        Zero-mean heights, mm; NaN for samples cut off from the largest connected piece.
    """
    return _integrate_scheme(ij, xy_mm, slopes, "central", weight_xy_mm)


def integrate_trapezoid(
    ij: ArrayLike, xy_mm: ArrayLike, slopes: ArrayLike, weight_xy_mm: ArrayLike | None = None
) -> Array:
    """Trapezoid-rule least squares over the 4-neighbour edges (see module docstring).

    Parameters and return as :func:`integrate_paper`.
    """
    return _integrate_scheme(ij, xy_mm, slopes, "trapezoid", weight_xy_mm)


# --------------------------------------------------------------------------------------------
# Uniform bicubic B-splines (the "spline" integrator and "hermite_spline" gridding)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SplineGrid:
    """A uniform bicubic B-spline: cell ``(cx, cy)`` spans ``[x0 + cx h, x0 + (cx + 1) h)``.

    Coefficient ``(a, b)`` (row-major, ``a`` along y) scales the basis function centred on the
    knot ``(x0 + (b - 1) h, y0 + (a - 1) h)``; there are ``(ncy + 3) x (ncx + 3)`` of them.
    """

    x0: float
    y0: float
    step_mm: float
    ncx: int
    ncy: int

    @classmethod
    def covering(cls, xy_mm: Array, step_mm: float) -> SplineGrid:
        """Smallest grid of cells of size ``step_mm`` covering points of shape (K, 2)."""
        lo = xy_mm.min(axis=0)
        span = xy_mm.max(axis=0) - lo
        ncx, ncy = (np.floor(span / step_mm).astype(int) + 1).tolist()
        return cls(float(lo[0]), float(lo[1]), float(step_mm), ncx, ncy)

    @property
    def shape(self) -> tuple[int, int]:
        """Coefficient array shape ``(ny, nx)``."""
        return self.ncy + 3, self.ncx + 3

    def design(self, x: Array, y: Array, dx: int = 0, dy: int = 0) -> sp.csr_matrix:
        """Sparse matrix (N, ny * nx) mapping coefficients to the ``(dx, dy)`` derivative at points.

        Parameters
        ----------
        x, y : (N,) ndarray
            Points, mm (clamped into the grid's cells).
        dx, dy : int
            Derivative order along x and y, 0 or 1 (1 gives per-mm values).
        """
        cx, bx = self._axis(x, self.x0, self.ncx, dx)
        cy, by = self._axis(y, self.y0, self.ncy, dy)
        nx = self.shape[1]
        offs = np.arange(4)
        cols = (cy[:, None, None] + offs[None, :, None]) * nx + (cx[:, None, None] + offs)
        vals = by[:, :, None] * bx[:, None, :]
        rows = np.repeat(np.arange(x.size), 16)
        return sp.csr_matrix(
            (vals.ravel(), (rows, cols.ravel())), shape=(x.size, self.shape[0] * nx)
        )

    def coef_index(self, x: float, y: float) -> int:
        """Flat index of the coefficient whose basis function peaks nearest ``(x, y)``, mm."""
        cx, _ = self._axis(np.array([x]), self.x0, self.ncx, 0)
        cy, _ = self._axis(np.array([y]), self.y0, self.ncy, 0)
        return int((cy[0] + 1) * self.shape[1] + cx[0] + 1)

    def dense_axis(self, coords: Array, along_x: bool) -> Array:
        """Dense (N, n_coef_axis) basis matrix along one axis (for tensor-product evaluation)."""
        origin, ncell = (self.x0, self.ncx) if along_x else (self.y0, self.ncy)
        cell, basis = self._axis(coords, origin, ncell, 0)
        out = np.zeros((coords.size, ncell + 3))
        np.put_along_axis(out, cell[:, None] + np.arange(4), basis, axis=1)
        return out

    def _axis(self, u_mm: Array, origin: float, ncell: int, order: int) -> tuple[IntArray, Array]:
        u = (u_mm - origin) / self.step_mm
        cell = np.clip(np.floor(u).astype(np.int64), 0, ncell - 1)
        t = (u - cell)[:, None]
        if order == 0:
            parts = [(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1, t**3]
            basis = np.hstack(parts) / 6.0
        else:
            parts = [-((1 - t) ** 2), 3 * t**2 - 4 * t, -3 * t**2 + 2 * t + 1, t**2]
            basis = np.hstack(parts) / (2.0 * self.step_mm)
        return cell, basis

    def penalty(self) -> sp.csr_matrix:
        """Third differences of the coefficients along x and y, divided by ``step^2``.

        Zero for any biquadratic (hence for planes and paraboloids), so it never biases them; per
        row it is about ``step * d3z/dx3`` (dimensionless, comparable with a slope residual).
        """
        ny, nx = self.shape
        stencil = np.array([-1.0, 3.0, -3.0, 1.0])

        def d3(n: int) -> sp.csr_matrix:
            return sp.diags(stencil, np.arange(4), shape=(max(n - 3, 0), n))

        return (
            sp.vstack([sp.kron(sp.eye(ny), d3(nx)), sp.kron(d3(ny), sp.eye(nx))]).tocsr()
            / self.step_mm**2
        )


def _median_spacing(xy: Array) -> float:
    """Median distance from each sample to its nearest other sample, mm."""
    dist, _ = cKDTree(xy).query(xy, k=2)
    spacing = float(np.median(dist[:, 1]))
    if spacing <= 0:
        raise WaiInputError("integrate: samples sit at repeated positions")
    return spacing


def _solve_normal(rows: sp.csr_matrix, rhs: Array, pin: int | None = None) -> Array:
    """Least squares ``rows c ~ rhs`` by sparse normal equations (optionally ``c[pin] = 0``)."""
    # No ridge is needed: the penalty's null space is the biquadratics, and a biquadratic whose
    # slopes vanish at scattered samples is a constant, which the pin (or height rows) fixes.
    normal = (rows.T @ rows).tocsc()
    b = rows.T @ rhs
    if pin is None:
        return spd_solve(normal, b)
    keep = np.arange(rows.shape[1]) != pin
    coef = np.zeros(rows.shape[1])
    coef[keep] = spd_solve(normal.tocsr()[keep][:, keep], b[keep])
    return coef


def integrate_spline(
    ij: ArrayLike, xy_mm: ArrayLike, slopes: ArrayLike, weight_xy_mm: ArrayLike | None = None
) -> Array:
    """Bicubic B-spline fitted by least squares to the slopes (see module docstring).

    The control spacing is 1.5 times the median nearest-neighbour distance of the samples
    (about the mean grid spacing, as the samples lie closer across than along the keystone).

    Parameters and return as :func:`integrate_paper`; ``weight_xy_mm`` is unused (all slope
    residuals weigh the same).
    """
    ij_a, xy_all, g_all = check_samples(ij, xy_mm, slopes)
    keep = largest_grid_piece(ij_a)
    xy, g = xy_all[keep], g_all[keep]
    grid = SplineGrid.covering(xy, _SPLINE_STEP * _median_spacing(xy))
    rows = sp.vstack(
        [
            grid.design(xy[:, 0], xy[:, 1], dx=1),
            grid.design(xy[:, 0], xy[:, 1], dy=1),
            _SPLINE_SMOOTHING * grid.penalty(),
        ]
    ).tocsr()
    rhs = np.r_[g[:, 0], g[:, 1], np.zeros(rows.shape[0] - 2 * xy.shape[0])]
    # Slopes fix no constant: pin the coefficient under the sample nearest the centroid.
    centre = np.argmin(np.sum((xy - xy.mean(axis=0)) ** 2, axis=1))
    pin = grid.coef_index(xy[centre, 0], xy[centre, 1])
    h = grid.design(xy[:, 0], xy[:, 1]) @ _solve_normal(rows, rhs, pin)
    heights = np.full(ij_a.shape[0], np.nan)
    heights[keep] = h - h.mean()
    return heights


# --------------------------------------------------------------------------------------------
# Fourier-domain integrators on a regular grid ("frankot_chellappa" and "dct_poisson")
# --------------------------------------------------------------------------------------------


# Slope-grid node spacing in units of the median nearest-neighbour distance of the samples (about
# the smallest lattice spacing, across the keystone): at least two nodes per sample spacing, so
# the grid resolves the piecewise-linear slopes between samples. Measured on the tests' surfaces:
# 1.0 doubles FC's border error (0.30 vs 0.13 mm on the jittered paraboloid) and the DCT's error
# on the jittered sinusoid (0.31 vs 0.17 mm); 1/3 and 1/4 do not help consistently (better on
# one footprint, worse on another) while the cost grows as 1 / step^2.
_FOURIER_STEP = 0.5


@dataclass(frozen=True)
class SlopeGrid:
    """Slopes resampled onto a regular grid; node ``(r, c)`` sits at ``(x0 + c h, y0 + r h)``.

    Attributes
    ----------
    x0, y0 : float
        Position of node ``(0, 0)``, mm.
    step_mm : float
        Node spacing ``h``, mm.
    p, q : (ny, nx) ndarray
        ``dz/dx`` and ``dz/dy`` at the nodes, dimensionless.
    inside : (ny, nx) ndarray of bool
        Nodes inside the samples' convex hull (the others hold extrapolated slopes, see
        :func:`_extrapolate_slopes`).
    """

    x0: float
    y0: float
    step_mm: float
    p: Array
    q: Array
    inside: NDArray[np.bool_]


def _regular_axes(xy: Array, step_mm: float) -> tuple[Array, Array]:
    """Node coordinates (nx,), (ny,) in mm from the samples' minimum x and y past their maximum.

    Raises
    ------
    WaiInputError
        When the grid would exceed :data:`_MAX_GRID_NODES` (samples spread far beyond their
        spacing).
    """
    lo = xy.min(axis=0)
    n = np.maximum(np.ceil((xy.max(axis=0) - lo) / step_mm).astype(np.int64) + 1, 2)
    if n[0] * n[1] > _MAX_GRID_NODES:
        raise WaiInputError(
            f"integrate: samples {step_mm:.3g} mm apart span a {n[0]} x {n[1]} grid, too large"
        )
    # (Rounding the node counts up to FFT-friendly sizes would save ~1 ms but add nodes outside
    # the hull, whose extrapolated slopes cost accuracy: 0.07 -> 0.39 mm on the unjittered test
    # sinusoid; see _extrapolate_slopes.)
    return lo[0] + step_mm * np.arange(n[0]), lo[1] + step_mm * np.arange(n[1])


def _triangulate(xy: Array) -> Delaunay:
    """Delaunay triangulation of sample positions (K, 2), mm.

    Raises
    ------
    WaiInputError
        When the samples are collinear.
    """
    try:
        return Delaunay(xy)
    except QhullError:
        raise WaiInputError("integrate: samples are collinear (no area to grid)") from None


def _median_neighbour_distance(tri: Delaunay) -> float:
    """Median distance from each sample to its nearest other sample, mm.

    Every nearest neighbour is a Delaunay neighbour, so the triangles' edges suffice (no search
    tree); samples left out of the triangulation (repeated positions) are skipped.
    """
    s, pts = tri.simplices, tri.points
    edge = pts[s] - pts[np.roll(s, -1, axis=1)]
    length = np.hypot(edge[..., 0], edge[..., 1])  # (T, 3): corner v to corner v + 1
    nearest = np.full(pts.shape[0], np.inf)
    np.minimum.at(nearest, s.ravel(), np.minimum(length, np.roll(length, 1, axis=1)).ravel())
    return float(np.median(nearest[np.isfinite(nearest)]))


def _linear_on_grid(tri: Delaunay, values: Array, gx: Array, gy: Array) -> Array:
    """Piecewise-linear interpolation on a Delaunay triangulation of scattered samples.

    Parameters
    ----------
    tri : Delaunay
        Triangulation of the sample positions, mm.
    values : (K, C) ndarray
        Values at the samples.
    gx, gy : (nx,), (ny,) ndarray
        Regular node coordinates, mm, equally spaced along both axes.

    Returns
    -------
    (C, ny, nx) ndarray
        Interpolated values; NaN at nodes outside the convex hull.
    """
    xy = tri.points
    verts = tri.simplices
    spans = _scan_triangles(xy[verts], gx, gy)
    corner_values = values[verts].transpose(2, 1, 0)  # (C, 3, T)
    # On each triangle the interpolant is v_0 + dv/dx (x - x_0) + dv/dy (y - y_0), with the
    # derivatives from the barycentric weights' gradients (see _Spans); it is evaluated at the
    # first node of each run and stepped along the run, so each node costs one multiply-add.
    dv_dx = np.sum(spans.bx * corner_values, axis=1)  # (C, T)
    dv_dy = np.sum(spans.by * corner_values, axis=1)
    t = spans.tri
    first = verts[t, 0]
    rx = gx[spans.col] - xy[first, 0]
    ry = gy[spans.row] - xy[first, 1]
    start = corner_values[:, 0, t] + dv_dx[:, t] * rx + dv_dy[:, t] * ry  # (C, runs)
    along = dv_dx[:, t] * (gx[1] - gx[0])
    node, _, k = spans.nodes(gx.size)
    out = np.full((values.shape[1], gy.size * gx.size), np.nan)
    for c in range(values.shape[1]):  # per channel: 1-D gathers are several times faster
        out[c, node] = np.repeat(start[c], spans.count) + k * np.repeat(along[c], spans.count)
    return out.reshape(values.shape[1], gy.size, gx.size)


def _mean_hessian(xy: Array, slopes: Array) -> Array:
    """Symmetric 2 x 2 Hessian (1/mm) of the quadratic surface whose slopes fit ``slopes`` best.

    Least squares of ``slopes ~ a + H (xy - mean)``: with centred positions the constant ``a``
    is the mean slope, and ``(H_xx, H_xy, H_yy)`` solve 3 x 3 normal equations built from the
    second moments.
    """
    x, y = (xy - xy.mean(axis=0)).T
    p, q = (slopes - slopes.mean(axis=0)).T
    sxx, sxy, syy = x @ x, x @ y, y @ y
    normal = np.array([[sxx, sxy, 0.0], [sxy, sxx + syy, sxy], [0.0, sxy, syy]])
    hxx, hxy, hyy = np.linalg.lstsq(normal, [x @ p, y @ p + x @ q, y @ q], rcond=None)[0]
    return np.array([[hxx, hxy], [hxy, hyy]])


def _extrapolate_slopes(
    field: Array, inside: NDArray[np.bool_], hessian: Array, step_mm: float
) -> Array:
    """Fill the nodes outside ``inside`` (ny, nx) of a slope grid ``field`` (2, ny, nx).

    Each outside node ``x`` takes the slopes of its nearest inside node ``n`` plus
    ``hessian (x - n)``. Nearest values alone are not a gradient field (they are constant along
    lines that fan out from the hull), and their curl leaks into the solution inside the hull
    (0.8 mm on a paraboloid over a keystoned footprint); with the mean curvature added, the
    extension of a quadratic surface's slopes is that surface's exact gradient, and where the
    curvature averages out (waves) it is the plain nearest value.
    """
    _, (rows, cols) = distance_transform_edt(~inside, return_indices=True)
    r, c = np.nonzero(~inside)
    near_r, near_c = rows[r, c], cols[r, c]
    dx, dy = (c - near_c) * step_mm, (r - near_r) * step_mm  # x - n, mm
    out = field.copy()
    for k in range(2):  # the Hessian is symmetric: row k is the gradient of slope k
        out[k, r, c] = field[k, near_r, near_c] + hessian[k, 0] * dx + hessian[k, 1] * dy
    return out


def resample_slopes(xy_mm: Array, slopes: Array, step_mm: float | None = None) -> SlopeGrid:
    """Slopes at scattered samples resampled onto a regular grid covering their bounding box.

    Inside the convex hull the slopes are interpolated linearly on the Delaunay triangles of
    the samples (holes are bridged). Outside, each node takes the slopes of the nearest inside
    node, extrapolated with the mean curvature of the samples (see
    :func:`_extrapolate_slopes`): unlike zeros this adds no jump in slope along the hull, and
    planes and quadratic surfaces remain exact gradient fields over the whole grid.

    Parameters
    ----------
    xy_mm : (K, 2) ndarray
        Sample positions, mm.
    slopes : (K, 2) ndarray
        ``(dz/dx, dz/dy)`` at the samples.
    step_mm : float, optional
        Node spacing, mm; default half the median nearest-neighbour distance of the samples
        (see :data:`_FOURIER_STEP`).

    Returns
    -------
    SlopeGrid

    Raises
    ------
    WaiInputError
        When the samples are collinear, leave no node inside their hull, or need too large a
        grid.
    """
    tri = _triangulate(xy_mm)
    if step_mm is None:
        step_mm = _FOURIER_STEP * _median_neighbour_distance(tri)
    gx, gy = _regular_axes(xy_mm, step_mm)
    field = _linear_on_grid(tri, slopes, gx, gy)
    inside = np.isfinite(field[0])
    if not inside.any():
        raise WaiInputError("integrate: no grid node falls inside the samples' hull")
    p, q = _extrapolate_slopes(field, inside, _mean_hessian(xy_mm, slopes), step_mm)
    return SlopeGrid(float(gx[0]), float(gy[0]), float(step_mm), p, q, inside)


def sample_heights(grid: SlopeGrid, z_mm: Array, xy_mm: Array) -> Array:
    """Heights on the grid read back at scattered positions inside it.

    Each corner ``c`` of the cell holding a point ``x`` predicts ``z_c + g_c . (x - c) / 2``
    (its half-step tangent plane), blended with bilinear weights. Since the bilinear weights
    reproduce ``x`` from the corners, this equals the blend of trapezoid-rule steps
    ``z_c + (g_c + g(x)) . (x - c) / 2``, exact for quadratic surfaces. Plain bilinear reading
    errs by up to ``h^2 |z''| / 8`` (a few µm on the tests' paraboloid): small next to the
    resampling's errors, but the blend keeps quadratics exact end to end.

    Parameters
    ----------
    grid : SlopeGrid
        The grid and its slopes.
    z_mm : (ny, nx) ndarray
        Heights at the nodes, mm.
    xy_mm : (K, 2) ndarray
        Positions, mm, within the grid's extent.

    Returns
    -------
    (K,) ndarray
        Heights, mm.
    """
    ny, nx = z_mm.shape
    u = (xy_mm - [grid.x0, grid.y0]) / grid.step_mm  # grid units
    cell = np.clip(np.floor(u).astype(np.int64), 0, [nx - 2, ny - 2])
    out = np.zeros(xy_mm.shape[0])
    for corner in ((0, 0), (1, 0), (0, 1), (1, 1)):  # vectorised over the points
        c, r = (cell + corner).T
        du, dv = (u - cell - corner).T  # x - corner, grid units
        weight = (1.0 - np.abs(du)) * (1.0 - np.abs(dv))
        tangent = 0.5 * grid.step_mm * (grid.p[r, c] * du + grid.q[r, c] * dv)
        out += weight * (z_mm[r, c] + tangent)
    return out


def poisson_dct(p: Array, q: Array, step_mm: float) -> Array:
    """Least-squares heights of a gridded slope field: Neumann Poisson equation solved by DCT.

    Minimises the squared misfit of every grid edge to its trapezoid-rule rise,
    ``z[r, c+1] - z[r, c] = h (p[r, c] + p[r, c+1]) / 2`` and likewise along y. The normal
    equations are ``L z = b``: ``L`` is the grid's 5-point graph Laplacian with free (Neumann)
    borders and ``b`` minus the divergence of the rises. The DCT-II diagonalises ``L`` exactly,
    with eigenvalues ``(2 - 2 cos(pi k / nx)) + (2 - 2 cos(pi l / ny))``, so the solve is two
    transforms and a division (Simchony, Chellappa & Shao 1990). Exact for quadratic surfaces
    sampled without error.

    Parameters
    ----------
    p, q : (ny, nx) ndarray
        ``dz/dx`` and ``dz/dy`` at the nodes, dimensionless.
    step_mm : float
        Node spacing, mm.

    Returns
    -------
    (ny, nx) ndarray
        Heights, mm, zero mean.
    """
    ny, nx = p.shape
    rise_x = 0.5 * step_mm * (p[:, 1:] + p[:, :-1])
    rise_y = 0.5 * step_mm * (q[1:] + q[:-1])
    b = np.zeros_like(p)
    b[:, 1:] += rise_x
    b[:, :-1] -= rise_x
    b[1:] += rise_y
    b[:-1] -= rise_y
    eig = (2.0 - 2.0 * np.cos(np.pi * np.arange(ny) / ny))[:, None] + (
        2.0 - 2.0 * np.cos(np.pi * np.arange(nx) / nx)
    )
    eig[0, 0] = 1.0  # the constant mode: its coefficient (the mean) is set to zero below
    coef = dctn(b, type=2, norm="ortho") / eig
    coef[0, 0] = 0.0
    return idctn(coef, type=2, norm="ortho")


def _mirrored(a: Array, sign_x: float, sign_y: float) -> Array:
    """``a`` (ny, nx) extended to (2 ny, 2 nx) by half-sample mirrors about its right and top
    borders, the copies mirrored across x times ``sign_x`` and those across y times ``sign_y``."""
    ny, nx = a.shape
    out = np.empty((2 * ny, 2 * nx))
    out[:ny, :nx] = a
    out[:ny, nx:] = sign_x * a[:, ::-1]
    out[ny:] = sign_y * out[ny - 1 :: -1]
    return out


def frankot_chellappa(p: Array, q: Array, step_mm: float) -> Array:
    """Heights of a gridded slope field by projection onto integrable Fourier modes.

    Frankot & Chellappa (1988): each Fourier mode of the height, ``Z exp(i (u x + v y))``, has
    slopes ``(i u Z, i v Z)``; the ``Z`` nearest in least squares to the slopes' transforms
    ``P, Q`` is ``Z = -i (u P + v Q) / (u^2 + v^2)``.

    The Fourier series is periodic, and the field is not. Its mean slope (a tilt) is removed
    first and added back as a plane, so planes are exact. The rest is extended to twice the
    size by mirroring the heights evenly about each border (half-sample mirrors, the DCT-II's
    symmetry), which makes ``p`` odd in x and even in y (``q`` the other way round): the
    extended surface is periodic and continuous, so the wrap adds no height step (plain
    periodic FC would spread one over the whole grid). What remains is a kink in the extended
    surface wherever ``p`` (or ``q``) is not zero at the left and right (bottom and top)
    borders; its sampled spectrum aliases, which costs an error near the borders of first
    order in the node spacing (0.1-0.35 mm on the tests' paraboloid, whose border slopes reach
    0.4). Modes whose even extension is smooth (DCT-II modes) are recovered exactly.

    Parameters
    ----------
    p, q : (ny, nx) ndarray
        ``dz/dx`` and ``dz/dy`` at the nodes, dimensionless.
    step_mm : float
        Node spacing, mm.

    Returns
    -------
    (ny, nx) ndarray
        Heights, mm, zero mean.
    """
    ny, nx = p.shape
    tilt_x, tilt_y = float(p.mean()), float(q.mean())
    p0, q0 = p - tilt_x, q - tilt_y
    u = 2.0 * np.pi * np.fft.rfftfreq(2 * nx, d=step_mm)  # rad/mm, along x (last axis)
    v = 2.0 * np.pi * np.fft.fftfreq(2 * ny, d=step_mm)[:, None]
    norm = u**2 + v**2
    norm[0, 0] = 1.0  # the mean height, unknown from slopes: set to zero below
    spectrum = rfft2(_mirrored(p0, -1.0, 1.0))
    spectrum *= u
    spectrum += v * rfft2(_mirrored(q0, 1.0, -1.0))
    spectrum *= -1j / norm
    spectrum[0, 0] = 0.0
    z = irfft2(spectrum, s=(2 * ny, 2 * nx))[:ny, :nx]
    plane = tilt_x * step_mm * np.arange(nx) + tilt_y * step_mm * np.arange(ny)[:, None]
    return z + plane - plane.mean()


def _integrate_on_grid(
    ij: ArrayLike,
    xy_mm: ArrayLike,
    slopes: ArrayLike,
    solve: Callable[[Array, Array, float], Array],
) -> Array:
    """Heights (K,) mm: the largest connected piece's slopes resampled onto a grid (see
    :func:`resample_slopes`), integrated there by ``solve(p, q, step_mm) -> z``, read back at
    the samples (see :func:`sample_heights`); zero mean, NaN off the piece."""
    ij_a, xy_all, g_all = check_samples(ij, xy_mm, slopes)
    keep = largest_grid_piece(ij_a)
    xy, g = xy_all[keep], g_all[keep]
    grid = resample_slopes(xy, g)
    h = sample_heights(grid, solve(grid.p, grid.q, grid.step_mm), xy)
    heights = np.full(ij_a.shape[0], np.nan)
    heights[keep] = h - h.mean()
    return heights


def integrate_frankot_chellappa(
    ij: ArrayLike, xy_mm: ArrayLike, slopes: ArrayLike, weight_xy_mm: ArrayLike | None = None
) -> Array:
    """Frankot-Chellappa on slopes resampled to a regular grid (see :func:`frankot_chellappa`).

    Parameters and return as :func:`integrate_paper`; ``weight_xy_mm`` is unused (every grid
    node weighs the same). Samples outside the largest 4-connected piece of the ``(i, j)`` grid
    are NaN, as for the other integrators, although the grid could bridge the gap.

    Raises
    ------
    WaiInputError
        As :func:`check_samples` and :func:`largest_grid_piece`, and when the samples are
        collinear (see :func:`resample_slopes`).
    """
    return _integrate_on_grid(ij, xy_mm, slopes, frankot_chellappa)


def integrate_dct_poisson(
    ij: ArrayLike, xy_mm: ArrayLike, slopes: ArrayLike, weight_xy_mm: ArrayLike | None = None
) -> Array:
    """Least squares on slopes resampled to a regular grid, by DCT (see :func:`poisson_dct`).

    Parameters, return and errors as :func:`integrate_frankot_chellappa`.
    """
    return _integrate_on_grid(ij, xy_mm, slopes, poisson_dct)


INTEGRATORS: dict[str, Integrator] = {
    "paper": integrate_paper,
    "trapezoid": integrate_trapezoid,
    "spline": integrate_spline,
    "frankot_chellappa": integrate_frankot_chellappa,
    "dct_poisson": integrate_dct_poisson,
}
"""Registered integrators by name; add an entry to make a new one selectable."""


def integrate(
    ij: ArrayLike,
    xy_mm: ArrayLike,
    slopes: ArrayLike,
    method: str = "trapezoid",
    weight_xy_mm: ArrayLike | None = None,
) -> Array:
    """Heights (K,) in mm, zero mean, from slopes with the integrator named ``method``.

    ``weight_xy_mm`` (K, 2) mm, optional: positions that set the difference weights of
    ``"paper"`` and ``"trapezoid"`` (default ``xy_mm``; see :func:`integrate_paper`).
    """
    try:
        integrator = INTEGRATORS[method]
    except KeyError:
        raise WaiInputError(
            f"integrate: unknown integrator {method!r} (known: {', '.join(INTEGRATORS)})"
        ) from None
    if weight_xy_mm is None:
        return integrator(ij, xy_mm, slopes)
    return integrator(ij, xy_mm, slopes, weight_xy_mm=weight_xy_mm)


# --------------------------------------------------------------------------------------------
# Gridding
# --------------------------------------------------------------------------------------------


def _grid_axes(xy: Array, spacing_mm: float) -> tuple[Array, Array]:
    """Regular node coordinates covering the bounding box of ``xy``, mm."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    n = np.ceil((hi - lo) / spacing_mm).astype(int) + 1
    if n[0] * n[1] > _MAX_GRID_NODES:
        raise WaiInputError(f"to_heightfield: a {spacing_mm} mm grid needs too many nodes")
    if np.any(n < 4):
        raise WaiInputError(
            f"to_heightfield: samples span too little for a {spacing_mm} mm grid (need 4 nodes)"
        )
    return lo[0] + spacing_mm * np.arange(n[0]), lo[1] + spacing_mm * np.arange(n[1])


def _hermite_spline_grid(
    xy: Array, heights: Array, slopes: Array, gx: Array, gy: Array
) -> Array:
    """Bicubic B-spline fitted to heights and slopes, evaluated on the grid (ny, nx), mm."""
    grid = SplineGrid.covering(xy, _SPLINE_STEP * _median_spacing(xy))
    x, y = xy[:, 0], xy[:, 1]
    # Slope residuals scaled by the control spacing: a slope error over one cell weighs like
    # the height error it causes there.
    rows = sp.vstack(
        [
            grid.design(x, y),
            grid.step_mm * grid.design(x, y, dx=1),
            grid.step_mm * grid.design(x, y, dy=1),
            grid.step_mm * _SPLINE_SMOOTHING * grid.penalty(),
        ]
    ).tocsr()
    mean = heights.mean()
    rhs = np.r_[heights - mean, grid.step_mm * slopes[:, 0], grid.step_mm * slopes[:, 1]]
    rhs = np.r_[rhs, np.zeros(rows.shape[0] - rhs.size)]
    coef = _solve_normal(rows, rhs).reshape(grid.shape)
    return grid.dense_axis(gy, along_x=False) @ coef @ grid.dense_axis(gx, along_x=True).T + mean


@dataclass(frozen=True)
class _Spans:
    """Grid nodes inside triangles, as runs along node rows (see :func:`_scan_triangles`).

    Run ``s`` holds the ``count[s]`` nodes ``(row[s], col[s] + k)``, ``k = 0 .. count[s] - 1``,
    of triangle ``tri[s]``. ``bx, by`` (3, T) give each triangle's barycentric weights as
    ``lam_v(p) = [v == 0] + bx[v] (p_x - x_0) + by[v] (p_y - y_0)`` about its first corner
    ``(x_0, y_0)``, 1/mm.
    """

    tri: IntArray
    row: IntArray
    col: IntArray
    count: IntArray
    bx: Array
    by: Array

    def nodes(self, n_cols: int) -> tuple[IntArray, IntArray, IntArray]:
        """Flat index ``row * n_cols + col`` (P,), run (P,) and offset ``k`` (P,) of each node."""
        run = np.repeat(np.arange(self.count.size), self.count)
        k = np.arange(run.size) - np.repeat(np.cumsum(self.count) - self.count, self.count)
        return (self.row * n_cols + self.col)[run] + k, run, k


def _scan_triangles(corners: Array, gx: Array, gy: Array) -> _Spans:
    """Find the grid nodes inside each triangle (a vectorised scan conversion).

    Each triangle is cut by the node rows it spans: with its corners sorted by y, a row meets
    the long edge (first to last corner) and one of the two short ones, and the nodes between
    the two crossings form one run. Only inside nodes are generated (no bounding-box
    candidates to test). A node on a shared edge may fall in two runs (with equal interpolated
    values). Flat slivers (qhull may leave them on the hull) are skipped: their neighbours
    cover their nodes.

    Parameters
    ----------
    corners : (T, 3, 2) ndarray
        Triangle vertices, mm.
    gx, gy : (n,), (m,) ndarray
        Regular node coordinates along x and y, mm.

    Returns
    -------
    _Spans
    """
    tol = 1e-9  # slack on node positions, grid units
    step = gx[1] - gx[0]
    px, py = np.ascontiguousarray(corners.transpose(2, 1, 0))  # (3, T) each
    e1x, e1y, e2x, e2y = px[1] - px[0], py[1] - py[0], px[2] - px[0], py[2] - py[0]
    det = e1x * e2y - e1y * e2x
    flat = np.abs(det) <= 1e-12 * (e1x**2 + e1y**2 + e2x**2 + e2y**2)
    inv = 1.0 / np.where(flat, 1.0, det)
    # Cramer's rule: lam_1 = (r x e2) / det, lam_2 = (e1 x r) / det with r = p - corner_0.
    bx = np.stack([(e1y - e2y) * inv, e2y * inv, -e1y * inv])
    by = np.stack([(e2x - e1x) * inv, -e2x * inv, e1x * inv])
    # Corners sorted by y: a (top), b, c (bottom); slopes dx/dy of the edges (0 if horizontal).
    order = np.argsort(py, axis=0)
    (xa, xb, xc), (ya, yb, yc) = np.take_along_axis(px, order, 0), np.take_along_axis(py, order, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_ab = np.where(yb > ya, (xb - xa) / (yb - ya), 0.0)
        s_bc = np.where(yc > yb, (xc - xb) / (yc - yb), 0.0)
        s_ac = np.where(yc > ya, (xc - xa) / (yc - ya), 0.0)
    first = np.maximum(np.ceil((ya - gy[0]) / step - tol), 0).astype(np.int64)
    last = np.minimum(np.floor((yc - gy[0]) / step + tol), gy.size - 1).astype(np.int64)
    n_rows = np.where(flat, 0, np.maximum(last - first + 1, 0))
    tri = np.repeat(np.arange(det.size), n_rows)
    row = first[tri] + np.arange(tri.size) - np.repeat(np.cumsum(n_rows) - n_rows, n_rows)
    y = np.clip(gy[row], ya[tri], yc[tri])
    x_long = xa[tri] + (y - ya[tri]) * s_ac[tri]
    x_short = np.where(
        y < yb[tri], xa[tri] + (y - ya[tri]) * s_ab[tri], xb[tri] + (y - yb[tri]) * s_bc[tri]
    )
    col_lo = np.maximum(np.ceil((np.minimum(x_long, x_short) - gx[0]) / step - tol), 0)
    col_hi = np.minimum(np.floor((np.maximum(x_long, x_short) - gx[0]) / step + tol), gx.size - 1)
    count = col_hi - col_lo + 1
    runs = count > 0
    return _Spans(
        tri[runs], row[runs], col_lo[runs].astype(np.int64), count[runs].astype(np.int64), bx, by
    )


def _tangent_blend(
    xy: Array,
    heights: Array,
    slopes: Array,
    verts: IntArray,
    spans: _Spans,
    gx: Array,
    gy: Array,
) -> tuple[IntArray, Array]:
    """Barycentric blend of each triangle's vertex predictions ``h_v + g_v . (p - x_v) / 2``.

    For a quadratic ``f``, ``f(p) = f(x_v) + (g_v + g(p)) . (p - x_v) / 2`` (the trapezoid rule)
    and the barycentric weights sum ``p - x_v`` to zero, so the ``g(p)`` terms cancel: the blend
    is exact for quadratics. It is continuous (C0) and local.

    The blend is a quadratic in ``p`` on each triangle; it is expanded once per triangle (about
    its first vertex) and once per run of nodes (in the run's column offset ``k``), so each node
    costs a few multiply-adds.

    Parameters
    ----------
    xy, heights, slopes : (K, 2), (K,), (K, 2) ndarray
        The samples (mm, mm, dimensionless).
    verts : (T, 3) ndarray of int
        Vertices of the triangles.
    spans : _Spans
        Their nodes (:func:`_scan_triangles`).
    gx, gy : (n,), (m,) ndarray
        Node coordinates, mm.

    Returns
    -------
    node : (P,) ndarray of int
        Flat node indices ``row * n + col``.
    z : (P,) ndarray
        Heights at the nodes, mm.
    """
    x0 = xy[verts[:, 0]]
    dx, dy = (xy[verts] - x0[:, None]).transpose(2, 1, 0)  # (3, T) each, mm
    gvx, gvy = slopes[verts].transpose(2, 1, 0)
    bx, by = spans.bx, spans.by
    # z(r) = sum_v lam_v(r) (c_v + g_v . r / 2), r = p - x_0, lam_v = [v == 0] + b_v . r
    c = heights[verts].T - 0.5 * (gvx * dx + gvy * dy)  # (3, T)
    lin_x = 0.5 * gvx[0] + np.sum(c * bx, axis=0)
    lin_y = 0.5 * gvy[0] + np.sum(c * by, axis=0)
    qxx = 0.5 * np.sum(bx * gvx, axis=0)
    qyy = 0.5 * np.sum(by * gvy, axis=0)
    qxy = 0.5 * np.sum(bx * gvy + by * gvx, axis=0)
    t = spans.tri
    eta = gy[spans.row] - x0[t, 1]
    xi = gx[spans.col] - x0[t, 0]
    # Along the run: z = a0 + b0 rx + c0 rx^2 with rx = xi + step k.
    a0 = c[0, t] + eta * (lin_y[t] + qyy[t] * eta)
    b0 = lin_x[t] + qxy[t] * eta
    c0 = qxx[t]
    step = gx[1] - gx[0]
    a = a0 + xi * (b0 + c0 * xi)
    b = step * (b0 + 2.0 * c0 * xi)
    c2 = c0 * step**2
    node, run, k = spans.nodes(gx.size)
    return node, a[run] + k * (b[run] + c2[run] * k)


def gap_free_triangles(tri: Delaunay, max_edge_ratio: float | None) -> IntArray:
    """Delaunay triangles (T, 3) less those that bridge gaps in the samples.

    A triangle is dropped when its longest edge exceeds ``max_edge_ratio`` times the largest
    nearest-neighbour distance among its vertices. Such triangles span concave bays of the
    sampled footprint and large holes, where any interpolant extrapolates far. On a grid of
    spacings ``a >= b`` the ratio is ``sqrt(1 + (a / b)^2)``: 1.4 when square, about 3.1 for the
    projector's keystone far field (29 x 10 mm); a single missing sample adds a factor 2.
    ``None`` keeps the whole convex hull.
    """
    simplices = tri.simplices
    if max_edge_ratio is None:
        return simplices
    corners = tri.points[simplices]
    length = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2)  # (T, 3)
    # The Delaunay graph holds every nearest neighbour: the shortest edge at each vertex.
    nearest = np.full(tri.points.shape[0], np.inf)
    np.minimum.at(nearest, simplices.ravel(), np.minimum(length, np.roll(length, 1, 1)).ravel())
    return simplices[length.max(axis=1) <= max_edge_ratio * nearest[simplices].max(axis=1)]


GRIDDERS = ("tangent_blend", "hermite_spline", "clough_tocher")
"""Methods of :func:`to_heightfield`."""


def _check_grid_input(xy: Array, h: Array, spacing_mm: float, method: str) -> None:
    """Raise WaiInputError for unusable :func:`to_heightfield` input."""
    if xy.ndim != 2 or xy.shape[1] != 2 or h.shape != xy.shape[:1]:
        raise WaiInputError(
            f"to_heightfield: need xy_mm (K, 2) and heights_mm (K,), got {xy.shape}, {h.shape}"
        )
    if xy.shape[0] < MIN_SAMPLES:
        raise WaiInputError(
            f"to_heightfield: too few samples to grid ({xy.shape[0]} < {MIN_SAMPLES})"
        )
    if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(h))):
        raise WaiInputError("to_heightfield: xy_mm or heights_mm hold NaN or inf")
    if not spacing_mm > 0:
        raise WaiInputError("to_heightfield: spacing_mm must be positive")
    if method not in GRIDDERS:
        raise WaiInputError(f"to_heightfield: unknown method {method!r} (known: {GRIDDERS})")


def to_heightfield(
    xy_mm: ArrayLike,
    heights_mm: ArrayLike,
    slopes: ArrayLike | None,
    spacing_mm: float,
    method: str = "tangent_blend",
    max_edge_ratio: float | None = 4.0,
) -> Heightfield:
    """Grid scattered surface samples onto a regular :class:`Heightfield`.

    The grid has nodes every ``spacing_mm`` from the samples' minimum x and y, covering their
    bounding box. Nodes outside the samples' convex hull are NaN, and so are nodes in Delaunay
    triangles that bridge gaps in the samples (see :func:`gap_free_triangles`).

    Parameters
    ----------
    xy_mm : (K, 2) array_like
        Sample positions, mm.
    heights_mm : (K,) array_like
        Sample heights, mm (absolute or relative).
    slopes : (K, 2) array_like or None
        Slopes ``(dz/dx, dz/dy)`` at the samples; needed except by ``"clough_tocher"``.
    spacing_mm : float
        Grid node spacing, mm.
    method : {"tangent_blend", "hermite_spline", "clough_tocher"}
        ``"tangent_blend"`` (default, fastest): on the Delaunay triangulation of the samples,
        the barycentric blend of the vertices' half-step tangent-plane predictions
        ``h_v + g_v . (p - x_v) / 2``; continuous, exact for quadratic surfaces, with the
        trapezoid rule's error (``d^3 |f'''| / 12`` over triangles of size ``d``).
        ``"hermite_spline"`` (most accurate, slower): a bicubic B-spline (control spacing 1.5
        times the median nearest-neighbour distance) fitted by least squares to heights and
        slopes together, with a weak third-difference penalty; C2, exact for quadratics.
        ``"clough_tocher"``: scipy's ``CloughTocher2DInterpolator`` on heights only (it
        estimates its own gradients), the paper's "bicubic interpolation" baseline.
    max_edge_ratio : float or None
        Gap threshold of :func:`gap_free_triangles`; None masks only outside the convex hull.

    Returns
    -------
    Heightfield
        ``x`` (n,), ``y`` (m,), ``z`` (m, n) in mm.
    """
    xy = np.asarray(xy_mm, dtype=float)
    h = np.asarray(heights_mm, dtype=float)
    _check_grid_input(xy, h, spacing_mm, method)
    g = None
    if method != "clough_tocher":
        g = np.asarray(slopes, dtype=float) if slopes is not None else None
        if g is None or g.shape != xy.shape or not np.all(np.isfinite(g)):
            raise WaiInputError(f"to_heightfield: {method} needs finite slopes of shape (K, 2)")
    gx, gy = _grid_axes(xy, spacing_mm)
    try:
        tri = Delaunay(xy)
    except QhullError:
        raise WaiInputError("to_heightfield: samples are collinear (no area to grid)") from None
    simplices = gap_free_triangles(tri, max_edge_ratio)
    spans = _scan_triangles(xy[simplices], gx, gy)
    z = np.full(gy.size * gx.size, np.nan)
    if method == "tangent_blend":
        node, values = _tangent_blend(xy, h, g, simplices, spans, gx, gy)
        z[node] = values
    else:
        node, _, _ = spans.nodes(gx.size)
        if method == "clough_tocher":
            nodes = np.column_stack([gx[node % gx.size], gy[node // gx.size]])
            z[node] = CloughTocher2DInterpolator(tri, h)(nodes)
        else:
            z[node] = _hermite_spline_grid(xy, h, g, gx, gy).ravel()[node]
    return Heightfield(gx, gy, z.reshape(gy.size, gx.size))
