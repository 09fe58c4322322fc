"""Surface models for the inverse solver: height and derivatives at (x, y), cheap and vectorised.

:class:`_FlatWater` is the flat water of the ground-truth view; :class:`_SplinePatches` evaluates
a :class:`~wai_core.heightfield.Heightfield`'s bicubic spline with its first and second
derivatives from per-cell power-basis tables (:func:`_cell_polynomials`), which is what each
Newton step of :mod:`restoration.reverse_trace.inverse` needs; :func:`_surface_model` picks one.
"""

from __future__ import annotations

import weakref

import numpy as np
from numpy.typing import NDArray

from restoration.reverse_trace._kernels import cell_polynomials, spline_table
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


# Points of a cell at which its cubics are sampled, and the inverse of their Vandermonde matrix:
# any four distinct points fix a cubic exactly.
_FRAC = np.array([0.125, 0.375, 0.625, 0.875])
_VINV = np.linalg.inv(np.vander(_FRAC, 4, increasing=True))


def _cell_polynomials(grid: Array, knots: Array) -> tuple[NDArray[np.intp], Array]:
    """The four cubic B-splines active on each cell of ``grid``, as cubics in mm from its start.

    Every cell ``[grid[c], grid[c + 1]]`` lies in one knot interval (the spline interpolates
    at the grid points, so its knots are a subset of them). One compiled pass
    (:func:`~restoration.reverse_trace._kernels.cell_polynomials`).

    Parameters
    ----------
    grid : (n,) ndarray
        Grid lines, mm, increasing.
    knots : (m,) ndarray
        The cubic spline's knots along that axis (4 repeated at each end), mm.

    Returns
    -------
    first : (n - 1,) ndarray of int
        Index of the first active B-spline of each cell.
    poly : (n - 1, 4, 4) ndarray
        ``B_{first[c] + j}(grid[c] + t) = sum_b poly[c, b, j] t^b``, ``t`` in mm.
    """
    return cell_polynomials(
        np.ascontiguousarray(grid, dtype=float), np.ascontiguousarray(knots, dtype=float), _VINV
    )


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
    once per surface by a compiled pass (:func:`~restoration.reverse_trace._kernels.spline_table`).
    A point then costs a table lookup and a few Horner steps: far cheaper than FITPACK point
    evaluation (which would dominate the solver), and it gives the second derivatives that the
    Jacobian needs in the same pass.
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
        ncy = ky.size
        # table[ix, 4 * (power of x) + (power of y), iy]: the coefficients of cell (iy, ix),
        # laid out so that looking up N cells gives 16 contiguous rows of N; slab ncx is the
        # NaN entry of points off the known surface.
        self.table = spline_table(kx, px, ky, py, np.ascontiguousarray(coeffs))
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


def spline_patches(surface: Heightfield) -> _SplinePatches:
    """The :class:`_SplinePatches` of ``surface``, kept while the surface lives: a frame's
    consistency check and its view both evaluate the one restored surface."""
    key = id(surface)
    found = _PATCHES.get(key)
    if found is not None and found[0]() is surface:
        return found[1]
    patches = _SplinePatches(surface)
    try:  # forgotten with the surface (the id may then be reused)
        ref = weakref.ref(surface, lambda _, key=key: _PATCHES.pop(key, None))
    except TypeError:  # not weakly referable: no caching
        return patches
    if len(_PATCHES) >= 8:
        _PATCHES.clear()
    _PATCHES[key] = (ref, patches)
    return patches


# By id of the Heightfield, with a weak reference to check it is still that object.
_PATCHES: dict[int, tuple[weakref.ref, _SplinePatches]] = {}


def _surface_model(surface: Heightfield | None, h0_mm: float) -> _FlatWater | _SplinePatches:
    return _FlatWater(h0_mm) if surface is None else spline_patches(surface)
