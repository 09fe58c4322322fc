"""Surface models for the inverse solver: height and derivatives at (x, y), cheap and vectorised.

:class:`_FlatWater` is the flat water of the ground-truth view; :class:`_SplinePatches` evaluates
a :class:`~wai_core.heightfield.Heightfield`'s bicubic spline with its first and second
derivatives from per-cell power-basis tables (:func:`_cell_polynomials`), which is what each
Newton step of :mod:`restoration.reverse_trace.inverse` needs; :func:`_surface_model` picks one.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline

from wai_core.heightfield import Heightfield

Array = NDArray[np.float64]


#: Height (mm), slopes and second derivatives (1/mm) at N points: six (N,) arrays
#: ``h, h_x, h_y, h_xx, h_xy, h_yy``; NaN outside the known surface.
Jet = tuple[Array, Array, Array, Array, Array, Array]


class _FlatWater:
    """Flat water at ``h0``: the surface model of the ground-truth view."""

    def __init__(self, h0_mm: float) -> None:
        self.h0 = float(h0_mm)

    def jet(self, x: Array, y: Array) -> Jet:
        """Height and derivatives at points (x, y) (N,) mm, see :data:`Jet`."""
        zero = np.zeros(np.size(x))
        return np.full(np.size(x), self.h0), zero, zero, zero, zero, zero


def _interval_polynomials(knots: Array) -> tuple[Array, Array, Array]:
    """Power-basis form of the four cubic B-splines active on each knot interval.

    Returns
    -------
    starts : (k,) ndarray
        Left end of each interval, mm.
    widths : (k,) ndarray
        Interval widths, mm.
    poly : (k, 4, 4) ndarray
        ``B_{i+j}(starts[i] + s widths[i]) = sum_a poly[i, a, j] s^a`` for ``s`` in [0, 1].
    """
    breaks = knots[3:-3]
    starts, widths = breaks[:-1], np.diff(breaks)
    # Any four distinct points of an interval fix the cubic pieces exactly.
    frac = np.array([0.125, 0.375, 0.625, 0.875])
    pts = (starts[:, None] + frac[None, :] * widths[:, None]).ravel()
    basis = BSpline.design_matrix(pts, knots, 3).toarray().reshape(starts.size, 4, -1)
    k = np.arange(starts.size)[:, None, None]
    vals = basis[k, np.arange(4)[None, :, None], k + np.arange(4)]
    vinv = np.linalg.inv(np.vander(frac, 4, increasing=True))
    return starts, widths, vinv[None] @ vals


_BINOMIAL = np.array([[1, 0, 0, 0], [1, 1, 0, 0], [1, 2, 1, 0], [1, 3, 3, 1]], dtype=float)


def _cell_polynomials(grid: Array, knots: Array) -> tuple[NDArray[np.intp], Array]:
    """The four cubic B-splines active on each cell of ``grid``, as cubics in mm from its start.

    Every cell ``[grid[c], grid[c + 1]]`` lies in one knot interval (the spline interpolates
    at the grid points, so its knots are a subset of them).

    Returns
    -------
    first : (n - 1,) ndarray of int
        Index of the first active B-spline of each cell.
    poly : (n - 1, 4, 4) ndarray
        ``B_{first[c] + j}(grid[c] + t) = sum_b poly[c, b, j] t^b``, ``t`` in mm.
    """
    starts, widths, poly = _interval_polynomials(knots)
    k = np.clip(np.searchsorted(starts, grid[:-1], side="right") - 1, 0, starts.size - 1)
    # s = s0 + s1 t in the interval's unit variable, so s^a = sum_b C(a, b) s0^(a-b) s1^b t^b.
    s0 = ((grid[:-1] - starts[k]) / widths[k])[:, None, None]
    s1 = (1.0 / widths[k])[:, None, None]
    a = np.arange(4)
    shift = _BINOMIAL * s0 ** np.maximum(a[:, None] - a, 0) * s1 ** a  # (c, a, b)
    return k, np.einsum("cab,caj->cbj", shift, poly[k])


_CELL_CACHE: dict[bytes, tuple[NDArray[np.intp], Array]] = {}


def _cached_cell_polynomials(grid: Array, knots: Array) -> tuple[NDArray[np.intp], Array]:
    """:func:`_cell_polynomials`, cached: a sequence of estimates often shares one grid."""
    key = grid.tobytes() + knots.tobytes()
    if key not in _CELL_CACHE:
        if len(_CELL_CACHE) >= 16:
            _CELL_CACHE.clear()
        _CELL_CACHE[key] = _cell_polynomials(grid, knots)
    return _CELL_CACHE[key]


class _SplinePatches:
    """Fast evaluation of a :class:`Heightfield`'s bicubic spline with its derivatives.

    The spline is ``sum_jl c[j, l] B_j(y) B_l(x)``; on each grid cell it is one bicubic
    polynomial, whose 16 power-basis coefficients (in mm from the cell's corner) are tabulated
    once per surface by two small batched products. A point then costs a table lookup and a
    few Horner steps: far cheaper than FITPACK point evaluation (which would dominate the
    solver), and it gives the second derivatives that the Jacobian needs in the same pass.
    Cells with an unknown corner sample hold NaN, so points there (and outside the grid) get
    NaN, as :meth:`Heightfield.contains` says. Values equal ``Heightfield.height`` to rounding.
    """

    def __init__(self, surface: Heightfield) -> None:
        # Heightfield exposes no public accessor for its spline; reading it keeps the values
        # identical to Heightfield.height (same fill of unknown samples, same knots).
        spline = surface._spline
        ty, tx = spline.get_knots()
        coeffs = spline.get_coeffs().reshape(ty.size - 4, tx.size - 4)
        ky, py = _cached_cell_polynomials(surface.y, ty)
        kx, px = _cached_cell_polynomials(surface.x, tx)
        ncy, ncx = ky.size, kx.size
        window = np.arange(4)
        rows = py @ coeffs[ky[:, None] + window]  # (ncy, 4 powers of y, x coefficients)
        # Per x cell: (4 powers of x, 4 B-splines) @ (4 B-splines, 4 powers of y x ncy cells).
        cols = rows[:, :, kx[:, None] + window].transpose(2, 3, 1, 0).reshape(ncx, 4, 4 * ncy)
        # table[ix, 4 * (power of x) + (power of y), iy]: the coefficients of cell (iy, ix),
        # laid out so that looking up N cells gives 16 contiguous rows of N; slab ncx is the
        # NaN entry of points off the known surface.
        self.table = np.empty((ncx + 1, 16, ncy))
        np.matmul(px, cols, out=self.table[:-1].reshape(ncx, 4, 4 * ncy))
        self.table[-1] = np.nan
        known = np.isfinite(surface.z)
        cell_ok = known[:-1, :-1] & known[1:, :-1] & known[:-1, 1:] & known[1:, 1:]
        self.cell_ok = cell_ok.T.ravel()  # by cell ix * ncy + iy
        self.offsets = (np.arange(16) * ncy)[:, None]  # of the 16 coefficients from the first
        self.x, self.y = surface.x, surface.y
        self.ncy, self.nan_slab = ncy, self.table[:-1].size

    def jet(self, x: Array, y: Array) -> Jet:
        """Height and derivatives at points (x, y) (N,) mm, lab frame; see :data:`Jet`."""
        ix = np.searchsorted(self.x[1:-1], x)
        iy = np.searchsorted(self.y[1:-1], y)
        inside = (x >= self.x[0]) & (x <= self.x[-1]) & (y >= self.y[0]) & (y <= self.y[-1])
        cell = ix * self.ncy + iy
        # Flat index of coefficient 0 of the cell in table (ncx + 1, 16, ncy): ix 16 ncy + iy.
        first = np.where(inside & self.cell_ok[cell], cell + 15 * self.ncy * ix, self.nan_slab)
        c = np.take(self.table, first + self.offsets)  # (16, N)
        u = x - self.x[ix]
        v = y - self.y[iy]
        # Along x, for the 4 powers of y at once: value and first two derivatives, (4, N) each.
        c0, c1, c2, c3 = c[0:4], c[4:8], c[8:12], c[12:16]
        r0 = c0 + u * (c1 + u * (c2 + u * c3))
        r1 = c1 + u * (2.0 * c2 + 3.0 * u * c3)
        r2 = 2.0 * c2 + 6.0 * u * c3
        # Along y.
        a0, a1, a2, a3 = r0
        h = a0 + v * (a1 + v * (a2 + v * a3))
        hy = a1 + v * (2.0 * a2 + 3.0 * v * a3)
        hyy = 2.0 * a2 + 6.0 * v * a3
        a0, a1, a2, a3 = r1
        hx = a0 + v * (a1 + v * (a2 + v * a3))
        hxy = a1 + v * (2.0 * a2 + 3.0 * v * a3)
        a0, a1, a2, a3 = r2
        hxx = a0 + v * (a1 + v * (a2 + v * a3))
        return h, hx, hy, hxx, hxy, hyy


def _surface_model(surface: Heightfield | None, h0_mm: float) -> _FlatWater | _SplinePatches:
    return _FlatWater(h0_mm) if surface is None else _SplinePatches(surface)
