"""Surface models for the inverse solver: height and derivatives at (x, y), cheap and vectorised.

:class:`_FlatWater` is the flat water of the ground-truth view; :class:`SplinePatches` evaluates
a :class:`~wai_core.heightfield.Heightfield`'s bicubic spline with its first and second
derivatives from per-cell power-basis tables (:func:`_cell_polynomials`), which is what each
Newton step of :mod:`restoration.reverse_trace.inverse` needs; :func:`_surface_model` picks one.
A frame that evaluates one surface several times (its view and its consistency check) builds
its :class:`SplinePatches` once and passes it to each.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from restoration.reverse_trace._kernels import cell_polynomials, spline_table
from wai_core.errors import WaiInputError
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


class SplinePatches:
    """Fast evaluation of a :class:`Heightfield`'s bicubic spline with its derivatives.

    The spline is ``sum_jl c[j, l] B_j(y) B_l(x)``; on each grid cell it is one bicubic
    polynomial, whose 16 power-basis coefficients (in mm from the cell's corner) are tabulated
    once per surface by a compiled pass (:func:`~restoration.reverse_trace._kernels.spline_table`).
    A point then costs a table lookup and a few Horner steps: far cheaper than FITPACK point
    evaluation (which would dominate the solver), and it gives the second derivatives that the
    Jacobian needs in the same pass.
    Cells with an unknown corner sample hold NaN, so points there (and outside the grid) get
    NaN, as :meth:`Heightfield.contains` says. Values equal ``Heightfield.height`` to rounding.

    Parameters
    ----------
    surface : Heightfield
        The surface (heights, mm, on an (m, n) grid).

    Attributes
    ----------
    surface : Heightfield
        The surface tabulated (the one its users check they were given).
    table : (ncx + 1, ncy, 16) ndarray
        Power-basis coefficients of each cell ``(iy, ix)`` at ``[ix, iy]``; slab ``ncx``
        is NaN (the entry of points off the known surface).
    cell_ok : (ncx ncy,) ndarray of bool
        Cells whose four corner samples are known, by ``ix * ncy + iy``.
    x, y : (n,), (m,) ndarray
        The surface's grid lines, mm.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core.heightfield import Heightfield
    >>> x, y = np.linspace(0.0, 100.0, 51), np.linspace(0.0, 80.0, 41)
    >>> surface = Heightfield(x, y, np.add.outer(0.01 * y, 0.02 * x))
    >>> h, hx, hy = SplinePatches(surface).jet(np.array([33.3]), np.array([21.7]))[:3]
    >>> bool(np.isclose(h[0], surface.height(33.3, 21.7))), bool(np.isclose(hx[0], 0.02))
    (True, True)
    """

    def __init__(self, surface: Heightfield) -> None:
        # Heightfield exposes no public accessor for its spline; reading it keeps the values
        # identical to Heightfield.height (same fill of unknown samples, same knots).
        spline = surface._spline
        ty, tx = spline.get_knots()
        coeffs = spline.get_coeffs().reshape(ty.size - 4, tx.size - 4)
        ky, py = _cell_polynomials(surface.y, ty)
        kx, px = _cell_polynomials(surface.x, tx)
        ncy = ky.size
        # table[ix, iy, 4 * (power of x) + (power of y)]: the coefficients of cell (iy, ix),
        # contiguous (a point's lookup reads two cache lines); slab ncx is the NaN entry of
        # points off the known surface.
        self.table = spline_table(kx, px, ky, py, np.ascontiguousarray(coeffs))
        known = np.isfinite(surface.z)
        cell_ok = known[:-1, :-1] & known[1:, :-1] & known[:-1, 1:] & known[1:, 1:]
        self.cell_ok = cell_ok.T.ravel()  # by cell ix * ncy + iy
        self.offsets = np.arange(16)[:, None]  # of the 16 coefficients from the first
        self.x, self.y = surface.x, surface.y
        self.surface = surface
        self.ncy, self.nan_slab = ncy, self.table[:-1].size

    def jet(self, x: Array, y: Array) -> Jet:
        """Height and derivatives at points (x, y) (N,) mm, lab frame; see :data:`Jet`."""
        ix = np.searchsorted(self.x[1:-1], x)
        iy = np.searchsorted(self.y[1:-1], y)
        inside = (x >= self.x[0]) & (x <= self.x[-1]) & (y >= self.y[0]) & (y <= self.y[-1])
        cell = ix * self.ncy + iy
        # Flat index of coefficient 0 of the cell in table (ncx + 1, ncy, 16): 16 (ix ncy + iy).
        first = np.where(inside & self.cell_ok[cell], 16 * cell, self.nan_slab)
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


def spline_patches(surface: Heightfield) -> SplinePatches:
    """The :class:`SplinePatches` of ``surface``, built anew on each call."""
    return SplinePatches(surface)


def _surface_model(
    surface: Heightfield | None, h0_mm: float, patches: SplinePatches | None = None
) -> _FlatWater | SplinePatches:
    """Flat water at ``h0_mm`` (``surface`` None), else the spline table of ``surface``:
    ``patches`` when given (checked by the caller: :func:`check_patches`), else a new one."""
    if patches is not None:
        return patches
    return _FlatWater(h0_mm) if surface is None else SplinePatches(surface)


def check_patches(patches: SplinePatches, surface: Heightfield | None, caller: str) -> None:
    """Raise :class:`WaiInputError` unless ``patches`` tabulates ``surface`` (the same object)."""
    if not isinstance(patches, SplinePatches):
        raise WaiInputError(f"{caller}: patches must be a SplinePatches, got {type(patches)}")
    if patches.surface is not surface:
        raise WaiInputError(f"{caller}: patches were built from another surface than the one given")
