"""From scattered heights (and slopes) to a regular :class:`~wai_core.heightfield.Heightfield`:
:func:`to_heightfield` fills the grid nodes inside the samples' gap-free Delaunay triangles
(:func:`gap_free_triangles`, found by a vectorised triangle scan) with one of the
:data:`GRIDDERS`: the tangent blend, a Hermite-fitted bicubic spline, or Clough-Tocher.
With the samples' lattice indices, the tangent blend's triangles are found on the lattice
(:func:`~restoration.integrate.triangulate.lattice_delaunay`, qhull's where the lattice
leaves them ambiguous).
The default tangent blend runs the gap filter, the scan and the blend as one compiled pass
(:func:`_blend_kernel`, the NumPy steps' arithmetic: ~1 ms of array passes become ~0.1 ms)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CloughTocher2DInterpolator
from scipy.spatial import Delaunay, QhullError

from restoration.integrate._common import (
    _MAX_GRID_NODES,
    MIN_SAMPLES,
    Array,
    BoolArray,
    IntArray,
)
from restoration.integrate.spline import (
    _SPLINE_SMOOTHING,
    _SPLINE_STEP,
    SplineGrid,
    _median_spacing,
    _solve_normal,
)
from restoration.integrate.triangulate import lattice_delaunay
from wai_core.errors import RestorationFailed, WaiInputError
from wai_core.heightfield import Heightfield


def _grid_axes(xy: Array, spacing_mm: float) -> tuple[Array, Array]:
    """Regular node coordinates covering the bounding box of ``xy``, mm."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    n = np.ceil((hi - lo) / spacing_mm).astype(int) + 1
    if n[0] * n[1] > _MAX_GRID_NODES:
        raise RestorationFailed(f"to_heightfield: a {spacing_mm} mm grid needs too many nodes")
    if np.any(n < 4):
        raise RestorationFailed(
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


MAX_LATTICE_STEP = 2
"""Farthest apart, in dots along either lattice axis, that a gridding triangle's corners may be
(:func:`lattice_bridges`): 2 bridges a single missing dot, as the edge ratio does."""


def lattice_bridges(simplices: IntArray, lattice_ij: ArrayLike, max_step: int) -> BoolArray:
    """Which triangles (T, 3) of samples with lattice indices ``lattice_ij`` (K, 2) join
    corners more than ``max_step`` dots apart along either lattice axis (T,).

    Such a triangle bridges a gap of at least ``max_step`` missing dots. The edge ratio of
    :func:`gap_free_triangles` cannot always tell: the dots' spacing on the water varies
    3x across the paper's patch (keystone), so a gap in the dense part can be as short as
    an ordinary edge of the sparse part. Over such a gap the blend extrapolates the slopes
    of its corners for 2-3 spacings (slope errors of ~0.01, restored corners moved by 3-5 px
    on a 1600 x 1200 frame: docs/results.md, "Accuracy").
    """
    corners = np.asarray(lattice_ij)[simplices]  # (T, 3, 2)
    step = np.abs(corners - np.roll(corners, -1, axis=1)).max(axis=(1, 2))
    return step > max_step


def gap_free_triangles(
    tri: Delaunay, max_edge_ratio: float | None, keep: BoolArray | None = None
) -> IntArray:
    """Delaunay triangles (T, 3) less those that bridge gaps in the samples (and, if given,
    those not in ``keep`` (T,)).

    A triangle is dropped when its longest edge exceeds ``max_edge_ratio`` times the largest
    nearest-neighbour distance among its vertices. Such triangles span concave bays of the
    sampled footprint and large holes, where any interpolant extrapolates far. On a grid of
    spacings ``a >= b`` the ratio is ``sqrt(1 + (a / b)^2)``: 1.4 when square, about 3.1 for the
    projector's keystone far field (29 x 10 mm); a single missing sample adds a factor 2.
    ``None`` keeps the whole convex hull.
    """
    simplices = tri.simplices
    if max_edge_ratio is None:
        return simplices if keep is None else simplices[keep]
    corners = tri.points[simplices]
    length = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2)  # (T, 3)
    # The Delaunay graph holds every nearest neighbour: the shortest edge at each vertex.
    nearest = np.full(tri.points.shape[0], np.inf)
    np.minimum.at(nearest, simplices.ravel(), np.minimum(length, np.roll(length, 1, 1)).ravel())
    short = length.max(axis=1) <= max_edge_ratio * nearest[simplices].max(axis=1)
    return simplices[short if keep is None else short & keep]


@njit(cache=True, nogil=True)
def _nearest_kernel(xy, simplices, nearest):  # pragma: no cover
    """Each sample's shortest triangle edge, ``nearest`` (K,) mm (inf where none): over a
    Delaunay triangulation, the nearest-neighbour distance."""
    nearest[:] = np.inf
    for t in range(simplices.shape[0]):  # edge k joins corners k and k + 1
        for k in range(3):
            i, j = simplices[t, k], simplices[t, (k + 1) % 3]
            ex, ey = xy[i, 0] - xy[j, 0], xy[i, 1] - xy[j, 1]
            length = math.sqrt(ex * ex + ey * ey)
            nearest[i] = min(nearest[i], length)
            nearest[j] = min(nearest[j], length)


@njit(cache=True, nogil=True, error_model="numpy")
def _blend_kernel(
    xy, heights, slopes, simplices, keep, ratio, nearest, gx, gy, z
):  # pragma: no cover
    """:func:`gap_free_triangles`, :func:`_scan_triangles` and :func:`_tangent_blend` in one
    pass over the triangles, writing the blend into ``z`` (m * n,) (NaN elsewhere untouched).

    The same expressions in the same order as the NumPy steps (corners sorted stably by y,
    later triangles overwriting a shared edge's nodes), so the heights agree to the last bit
    or to rounding. An infinite ``ratio`` keeps every triangle (``max_edge_ratio=None``).

    Parameters
    ----------
    xy, heights, slopes : (K, 2), (K,), (K, 2) ndarray
        Samples (mm, mm, dimensionless).
    simplices : (T, 3) ndarray of int
        Delaunay triangles.
    keep : (T,) ndarray of bool
        Triangles that may be blended.
    ratio : float
        The gap threshold of :func:`gap_free_triangles`.
    nearest : (K,) ndarray
        Each sample's nearest-neighbour distance, mm (:func:`_nearest_kernel` of the whole
        triangulation).
    gx, gy : (n,), (m,) ndarray
        Node coordinates, mm.
    z : (m * n,) ndarray
        Heights, written at the nodes inside kept triangles, mm.
    """
    tol = 1e-9  # slack on node positions, grid units (as _scan_triangles)
    n_tri = simplices.shape[0]
    nx, ny = gx.size, gy.size
    step = gx[1] - gx[0]
    gx0, gy0 = gx[0], gy[0]
    length = np.empty((n_tri, 3))
    for t in range(n_tri):  # edge k joins corners k and k + 1
        for k in range(3):
            i, j = simplices[t, k], simplices[t, (k + 1) % 3]
            ex, ey = xy[i, 0] - xy[j, 0], xy[i, 1] - xy[j, 1]
            length[t, k] = math.sqrt(ex * ex + ey * ey)
    px, py = np.empty(3), np.empty(3)
    gvx, gvy, dx, dy, c = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    bx, by = np.empty(3), np.empty(3)
    for t in range(n_tri):
        longest = max(length[t, 0], max(length[t, 1], length[t, 2]))
        near = max(nearest[simplices[t, 0]],
                   max(nearest[simplices[t, 1]], nearest[simplices[t, 2]]))
        if not (keep[t] and longest <= ratio * near):
            continue
        for k in range(3):
            px[k], py[k] = xy[simplices[t, k], 0], xy[simplices[t, k], 1]
        e1x, e1y, e2x, e2y = px[1] - px[0], py[1] - py[0], px[2] - px[0], py[2] - py[0]
        det = e1x * e2y - e1y * e2x
        if abs(det) <= 1e-12 * (e1x**2 + e1y**2 + e2x**2 + e2y**2):
            continue  # a flat sliver: its neighbours cover its nodes
        inv = 1.0 / det
        bx[0], bx[1], bx[2] = (e1y - e2y) * inv, e2y * inv, -e1y * inv
        by[0], by[1], by[2] = (e2x - e1x) * inv, -e2x * inv, e1x * inv
        # The blend's quadratic about corner 0 (as _tangent_blend).
        x0x, x0y = px[0], py[0]
        for k in range(3):
            v = simplices[t, k]
            dx[k], dy[k] = px[k] - x0x, py[k] - x0y
            gvx[k], gvy[k] = slopes[v, 0], slopes[v, 1]
            c[k] = heights[v] - 0.5 * (gvx[k] * dx[k] + gvy[k] * dy[k])
        lin_x = 0.5 * gvx[0] + (c[0] * bx[0] + c[1] * bx[1] + c[2] * bx[2])
        lin_y = 0.5 * gvy[0] + (c[0] * by[0] + c[1] * by[1] + c[2] * by[2])
        qxx = 0.5 * (bx[0] * gvx[0] + bx[1] * gvx[1] + bx[2] * gvx[2])
        qyy = 0.5 * (by[0] * gvy[0] + by[1] * gvy[1] + by[2] * gvy[2])
        qxy = 0.5 * ((bx[0] * gvy[0] + by[0] * gvx[0]) + (bx[1] * gvy[1] + by[1] * gvx[1])
                     + (bx[2] * gvy[2] + by[2] * gvx[2]))
        c2 = qxx * step**2
        # Corners sorted by y, stably (as np.argsort on three values): a (top), b, c (bottom).
        ia, ib, ic = 0, 1, 2
        if py[ib] < py[ia]:
            ia, ib = ib, ia
        if py[ic] < py[ib]:
            ib, ic = ic, ib
            if py[ib] < py[ia]:
                ia, ib = ib, ia
        xa, xb, xc, ya, yb, yc = px[ia], px[ib], px[ic], py[ia], py[ib], py[ic]
        s_ab = (xb - xa) / (yb - ya) if yb > ya else 0.0
        s_bc = (xc - xb) / (yc - yb) if yc > yb else 0.0
        s_ac = (xc - xa) / (yc - ya) if yc > ya else 0.0
        first = max(math.ceil((ya - gy0) / step - tol), 0)
        last = min(math.floor((yc - gy0) / step + tol), ny - 1)
        for row in range(first, last + 1):
            y = min(max(gy[row], ya), yc)
            x_long = xa + (y - ya) * s_ac
            x_short = xa + (y - ya) * s_ab if y < yb else xb + (y - yb) * s_bc
            col_lo = max(math.ceil((min(x_long, x_short) - gx0) / step - tol), 0)
            col_hi = min(math.floor((max(x_long, x_short) - gx0) / step + tol), nx - 1)
            if col_hi < col_lo:
                continue
            eta = gy[row] - x0y
            xi = gx[col_lo] - x0x
            a0 = c[0] + eta * (lin_y + qyy * eta)
            b0 = lin_x + qxy * eta
            a = a0 + xi * (b0 + qxx * xi)
            b = step * (b0 + 2.0 * qxx * xi)
            base = row * nx + col_lo
            for k in range(col_hi - col_lo + 1):
                z[base + k] = a + k * (b + c2 * k)


GRIDDERS = ("tangent_blend", "hermite_spline", "clough_tocher")
"""Methods of :func:`to_heightfield`."""


def _check_grid_input(xy: Array, h: Array, spacing_mm: float, method: str) -> None:
    """Raise WaiInputError for unusable :func:`to_heightfield` input."""
    if xy.ndim != 2 or xy.shape[1] != 2 or h.shape != xy.shape[:1]:
        raise WaiInputError(
            f"to_heightfield: need xy_mm (K, 2) and heights_mm (K,), got {xy.shape}, {h.shape}"
        )
    if xy.shape[0] < MIN_SAMPLES:
        raise RestorationFailed(
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
    lattice_ij: ArrayLike | None = None,
    max_lattice_step: int = MAX_LATTICE_STEP,
) -> Heightfield:
    """Grid scattered surface samples onto a regular :class:`Heightfield`.

    The grid has nodes every ``spacing_mm`` from the samples' minimum x and y, covering their
    bounding box. Nodes outside the samples' convex hull are NaN, and so are nodes in Delaunay
    triangles that bridge gaps in the samples (see :func:`gap_free_triangles`; with
    ``lattice_ij``, also :func:`lattice_bridges`).

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
    lattice_ij : (K, 2) array_like of int, optional
        The samples' dot indices on the projector lattice, when they have them: triangles whose
        corners lie more than ``max_lattice_step`` dots apart are dropped too
        (:func:`lattice_bridges`). The tangent blend then finds the others on the lattice
        (:func:`~restoration.integrate.triangulate.lattice_delaunay`: the same triangles,
        without qhull).
    max_lattice_step : int
        See ``lattice_ij``.

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
    z = np.full(gy.size * gx.size, np.nan)
    ratio = np.inf if max_edge_ratio is None else float(max_edge_ratio)
    found = None
    if method == "tangent_blend" and lattice_ij is not None:
        found = lattice_delaunay(xy, np.asarray(lattice_ij), max_lattice_step)
    if found is not None:  # qhull's triangles of small lattice span, found on the lattice
        simplices, nearest = found
        _blend_kernel(xy, h, np.ascontiguousarray(g), simplices, np.ones(len(simplices), bool),
                      ratio, nearest, gx, gy, z)
        return _gridded(gx, gy, z)
    try:
        tri = Delaunay(xy)
    except QhullError:
        raise RestorationFailed(
            "to_heightfield: samples are collinear (no area to grid)"
        ) from None
    keep = None if lattice_ij is None else ~lattice_bridges(tri.simplices, lattice_ij,
                                                             max_lattice_step)
    if method == "tangent_blend":  # gaps, scan and blend in one compiled pass
        simplices = tri.simplices.astype(np.int64)
        nearest = np.empty(xy.shape[0])
        _nearest_kernel(xy, simplices, nearest)
        _blend_kernel(xy, h, np.ascontiguousarray(g), simplices,
                      np.ones(len(simplices), bool) if keep is None else keep, ratio,
                      nearest, gx, gy, z)
    else:
        simplices = gap_free_triangles(tri, max_edge_ratio, keep)
        spans = _scan_triangles(xy[simplices], gx, gy)
        node, _, _ = spans.nodes(gx.size)
        if method == "clough_tocher":
            nodes = np.column_stack([gx[node % gx.size], gy[node // gx.size]])
            z[node] = CloughTocher2DInterpolator(tri, h)(nodes)
        else:
            z[node] = _hermite_spline_grid(xy, h, g, gx, gy).ravel()[node]
    return _gridded(gx, gy, z)


def _gridded(gx: NDArray, gy: NDArray, z: NDArray) -> Heightfield:
    """The grid's heightfield; :class:`RestorationFailed` where no node got a height (every
    triangle of the samples spans a gap or bridges the lattice: nothing to grid)."""
    if not np.isfinite(z).any():
        raise RestorationFailed("to_heightfield: every triangle of the samples spans a gap "
                                "(no grid node inside one)")
    return Heightfield(gx, gy, z.reshape(gy.size, gx.size))
