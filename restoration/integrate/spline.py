"""The ``"spline"`` integrator: a uniform bicubic B-spline (:class:`SplineGrid`) fitted by sparse
least squares straight to the slopes, with a weak third-difference penalty on its coefficients;
the same spline machinery serves the ``"hermite_spline"`` gridder of
:mod:`restoration.integrate.gridding`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from restoration.integrate._common import Array, IntArray
from restoration.integrate.lattice import check_samples, largest_grid_piece, spd_solve
from wai_core.errors import RestorationFailed

# Weight of the third-difference penalty relative to the data (dimensionless, see penalty()).
_SPLINE_SMOOTHING = 1e-2
# Spline control spacing in units of the median nearest-neighbour distance of the samples.
_SPLINE_STEP = 1.5


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
        raise RestorationFailed("integrate: samples sit at repeated positions")
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
    """Bicubic B-spline fitted by least squares to the slopes (see :data:`INTEGRATORS`).

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
