"""Reverse ray tracing through a known water surface and the image restoration it gives (sec. 3.3).

Camera v sits under the water and looks up at a horizontal object plane ``z = z_object`` (z_a).
The *forward map* of a pixel (eq. 14-20) is: back-project the pixel, hit the water surface, refract
into the air (Snell, eq. 20), hit the object plane. :func:`trace_to_object` computes it.

The *inverse map* (:func:`find_pixels`) asks which pixel of camera v sees a given object point
through a given surface. It is solved by Newton's method over all targets at once. The unknown is
the surface point ``q = (x, y)`` where the ray crosses the water rather than the pixel itself:
for a candidate ``q`` the ray from the camera centre to ``(x, y, h(x, y))`` and the normal there are
explicit, so each Newton step needs one surface evaluation instead of a nested ray-surface
intersection; the pixel is the projection of ``q``. Newton drives the angle between the refracted
ray and the direction to the target to zero (:func:`_residual`); its Jacobian is a forward finite
difference in ``q``.

Restoration (:func:`restore_view`): the ground-truth view is camera v through *flat* water. For each
truth pixel ``p`` the target ``P`` is the flat-water forward map of ``p``; the distorted image
shows ``P`` at ``u = find_pixels(surface_est, P)``; so ``restored(p) = distorted(u)``. The warp
``u(p)`` is solved on a coarse grid, upsampled bilinearly (the surface is smooth) and applied with
one ``cv2.remap``.

Statuses of a ray or target are :class:`RayStatus` codes. Pixel coordinates are continuous
``(col, row)`` with integer values at pixel centres (see :mod:`wai_core.geometry`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import IntEnum

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import BSpline

from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera, intersect_plane_z, refract
from wai_core.heightfield import Heightfield

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Newton stops when the pixel moves less than this between iterates, pixels.
DEFAULT_TOL_PX = 1e-3
#: Finite-difference step of the Jacobian, mm on the water surface.
_FD_STEP_MM = 1e-4
#: Step halvings tried when a Newton step leaves the surface or hits TIR.
_MAX_HALVINGS = 4
#: Pulls of a TIR start towards the nadir, and the factor of each.
_MAX_PULLS, _PULL = 8, 0.97
#: Below this many rows a damped move tries the full and all halved steps in one batch.
_FUSED_ROWS = 96
#: Tolerance and iterations of the warp solve in restore_view. Convergence is tested on the
#: last Newton step, which is then taken: the error left is second order (below 3e-3 px for
#: 0.05 px on the paper's rig), far below what bilinear interpolation of the warp adds.
_WARP_TOL_PX, _WARP_ITER = 0.05, 12


class RayStatus(IntEnum):
    """Outcome of one ray or one target."""

    OK = 0
    MISSED_SURFACE = 1  # outside the known surface (its extent or its NaN holes)
    TIR = 2  # totally reflected at the surface: no view of the air there
    MISSED_OBJECT = 3  # the air ray never reaches the object plane
    NOT_CONVERGED = 4  # Newton did not settle within its iterations
    OUT_OF_VIEW = 5  # the solved pixel lies outside the image


def status_counts(status: ArrayLike) -> dict[str, int]:
    """Number of entries with each :class:`RayStatus`, keyed by lower-case name."""
    hist = np.bincount(np.asarray(status, dtype=np.int64).ravel(), minlength=len(RayStatus))
    return {s.name.lower(): int(hist[s]) for s in RayStatus}


@dataclass(frozen=True)
class TraceResult:
    """Forward map of a set of pixels (eq. 17-20).

    Attributes
    ----------
    object_mm : (..., 3) ndarray
        Hit points on the object plane, mm, ``lab``; NaN unless status is OK.
    surface_mm : (..., 3) ndarray
        Hit points on the water surface, mm; NaN where the surface was missed.
    status : (...,) ndarray of int8
        :class:`RayStatus` code of each ray.
    """

    object_mm: Array
    surface_mm: Array
    status: NDArray[np.int8]

    @property
    def ok(self) -> BoolArray:
        """True where the ray reached the object plane."""
        return self.status == RayStatus.OK

    @property
    def counts(self) -> dict[str, int]:
        """Rays per status (see :func:`status_counts`)."""
        return status_counts(self.status)


def _check_system(h0_mm: float, n_water: float, z_object_mm: float) -> None:
    if not (np.isfinite(h0_mm) and np.isfinite(n_water) and np.isfinite(z_object_mm)):
        raise WaiInputError("reverse trace: h0, n_water and z_object must be finite")
    if n_water <= 1.0:
        raise WaiInputError(f"reverse trace: n_water must exceed 1, got {n_water}")
    if z_object_mm <= h0_mm:
        raise WaiInputError("reverse trace: the object plane must lie above the water (z > h0)")


def trace_to_object(
    camera: PinholeCamera,
    surface: Heightfield | None,
    h0_mm: float,
    n_water: float,
    z_object_mm: float,
    cols: ArrayLike,
    rows: ArrayLike,
) -> TraceResult:
    """Trace pixels of ``camera`` through the water surface to the object plane (eq. 17-20).

    Parameters
    ----------
    camera : PinholeCamera
        The submerged camera (camera v).
    surface : Heightfield or None
        The water surface; None means flat water at ``h0_mm``.
    h0_mm : float
        Mean water level, mm (used when ``surface`` is None).
    n_water : float
        Refractive index of water (4/3).
    z_object_mm : float
        Height of the object plane, mm (z_a).
    cols, rows : array_like
        Continuous pixel coordinates, broadcast to a common shape (...).

    Returns
    -------
    TraceResult
        Object-plane points (..., 3) mm, surface hits (..., 3) mm and a status per ray.
    """
    _check_system(h0_mm, n_water, z_object_mm)
    origin, dirs = camera.pixel_rays(cols, rows)
    if surface is None:
        hit, _ = intersect_plane_z(origin, dirs, h0_mm)
        normals = np.broadcast_to(np.array([0.0, 0.0, 1.0]), hit.shape)
    else:
        hit, _ = surface.intersect(origin, dirs)
        normals = surface.normal(hit[..., 0], hit[..., 1])
    missed = ~np.all(np.isfinite(hit), axis=-1)
    # Water to air: eta = n_water / 1 (eq. 20).
    air, tir = refract(dirs, normals, n_water)
    points, _ = intersect_plane_z(hit, air, z_object_mm)
    status = np.full(missed.shape, RayStatus.OK, dtype=np.int8)
    status[~np.all(np.isfinite(points), axis=-1)] = RayStatus.MISSED_OBJECT
    status[tir] = RayStatus.TIR
    status[missed] = RayStatus.MISSED_SURFACE
    points[status != RayStatus.OK] = np.nan
    return TraceResult(points, hit, status)


# --------------------------------------------------------------------------------------------
# Surface models for the Newton solver: height and derivatives at (x, y), cheap and vectorised.
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# Inverse map: Newton over surface points.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Optics:
    """What the forward map from a surface point needs: camera centre, index, object plane."""

    center: Array
    n_water: float
    z_object: float


def _residual(
    optics: _Optics, x: Array, y: Array, h: Array, hx: Array, hy: Array, tx: Array, ty: Array
) -> tuple[Array, Array, Array, Array]:
    """How far the air ray through surface point (x, y) misses its target ``(tx, ty)``.

    The air direction seen through surface point ``(x, y, h)`` with slopes ``(hx, hy)`` is
    eq. 18-20: the ray from the camera centre refracted by vector Snell, with the normal turned
    against the ray whichever side it hits. The miss is measured between directions, not on
    the object plane: the air direction and the direction from the surface point to the
    target, both mapped by the stereographic chart ``(t_x, t_y) / (1 + t_z)`` of the upper
    hemisphere. Object-plane distances grow like ``tan`` towards the edge of Snell's window
    and make Newton crawl there; the chart stays smooth up to the horizon.

    Component-wise on arrays of any shape (points broadcast against targets), because this is
    the solver's inner loop.

    Returns
    -------
    r_x, r_y : ndarray
        The residual (dimensionless); zero at the solution.
    t_z : ndarray
        Vertical component of the air direction (the ray misses the object plane unless > 0).
    k : ndarray
        ``1 - n^2 sin^2`` of the incidence: negative under total internal reflection.
    """
    cx, cy, cz = optics.center
    n = optics.n_water
    # Ray w = q - centre and normal m = (-h_x, -h_y, 1), both left unnormalised.
    wx, wy, wz = x - cx, y - cy, h - cz
    inv_w = 1.0 / np.sqrt(wx * wx + wy * wy + wz * wz)
    inv_m = 1.0 / np.sqrt(1.0 + hx * hx + hy * hy)
    cos = (wz - wx * hx - wy * hy) * (inv_w * inv_m)
    k = (1.0 - n * n) + (n * n) * (cos * cos)
    # Vector Snell: air = n w / |w| - g m / |m|, with g = n cos - sign(cos) sqrt(k).
    a_w = n * inv_w
    a_m = (n * cos - np.sign(cos) * np.sqrt(np.maximum(k, 0.0))) * inv_m
    ax, ay, az = a_w * wx + a_m * hx, a_w * wy + a_m * hy, a_w * wz - a_m
    # Unit direction to the target e / |e|, charted: e_xy / (|e| + e_z).
    ex, ey, ez = tx - x, ty - y, optics.z_object - h
    b = 1.0 / (np.sqrt(ex * ex + ey * ey + ez * ez) + ez)
    a = 1.0 / (1.0 + az)
    return ax * a - ex * b, ay * a - ey * b, az, k


# Rows of the solver state (first axis), one column per target.
_QX, _QY, _H, _HX, _HY, _R0, _R1, _J00, _J01, _J10, _J11, _TX, _TY = range(13)


class _Solver:
    """Newton state of all targets, updated in place.

    ``state`` (13, N) holds per target the surface point ``q`` (mm), the height and slopes
    there, the residual and its Jacobian (1/mm) and the target (mm), in the rows named by the
    ``_QX .. _TY`` constants. Targets are gathered and scattered by index rather than
    compacted, so that a few slow ones do not make every iteration copy the whole state.
    """

    def __init__(
        self,
        camera: PinholeCamera,
        model: _FlatWater | _SplinePatches,
        optics: _Optics,
        targets: Array,
    ) -> None:
        self.model, self.optics = model, optics
        n = targets.shape[0]
        self.state = np.full((13, n), np.nan)
        self.state[_TX], self.state[_TY] = targets[:, 0], targets[:, 1]
        self.status = np.full(n, RayStatus.NOT_CONVERGED, dtype=np.int8)
        pose = camera.pose
        self.rot, self.trans = pose.R, pose.t_mm
        self.focal = camera.focal_px
        self.centre_px = ((camera.width_px - 1) / 2.0, (camera.height_px - 1) / 2.0)

    def evaluate(self, qx: Array, qy: Array, tx: Array, ty: Array) -> tuple[Array, NDArray]:
        """State columns (13, R) and status (R,) of targets ``(tx, ty)`` from surface points
        ``(qx, qy)`` mm.

        The Jacobian is a forward difference; the height and slopes at the shifted points come
        from the second derivatives at ``q`` (their error, O(step^2), is far below the
        difference's own), so the base point and both shifts take one pass of
        :func:`_residual` over (3, R) points and one surface evaluation.
        """
        h, hx, hy, hxx, hxy, hyy = self.model.jet(qx, qy)
        d = _FD_STEP_MM
        # Rows: the base point, shifted along x, shifted along y; the targets broadcast.
        r0, r1, tz, k = _residual(
            self.optics,
            qx + np.array([[0.0], [d], [0.0]]),
            qy + np.array([[0.0], [0.0], [d]]),
            np.stack([h, h + d * hx, h + d * hy]),
            np.stack([hx, hx + d * hxx, hx + d * hxy]),
            np.stack([hy, hy + d * hxy, hy + d * hyy]),
            tx,
            ty,
        )
        n = qx.size
        out = np.empty((13, n))
        out[_QX], out[_QY], out[_H], out[_HX], out[_HY] = qx, qy, h, hx, hy
        out[_R0], out[_R1] = r0[0], r1[0]
        np.subtract(r0[1:], r0[0], out=out[_J00 : _J01 + 1])
        np.subtract(r1[1:], r1[0], out=out[_J10 : _J11 + 1])
        out[_J00 : _J11 + 1] /= d
        out[_TX], out[_TY] = tx, ty
        status = np.full(n, RayStatus.MISSED_OBJECT, dtype=np.int8)
        status[tz[0] > 0] = RayStatus.OK
        status[k[0] < 0] = RayStatus.TIR
        status[np.isnan(h)] = RayStatus.MISSED_SURFACE
        return out, status

    def project(self, x: Array, y: Array, z: Array) -> tuple[Array, Array]:
        """Pixels ``(col, row)`` of lab points (N,) mm (:meth:`PinholeCamera.project`)."""
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self.rot
        t0, t1, t2 = self.trans
        zc = r20 * x + r21 * y + r22 * z + t2
        scale = self.focal / np.where(np.abs(zc) > 1e-12, zc, 1e-12)
        cols = (r00 * x + r01 * y + r02 * z + t0) * scale + self.centre_px[0]
        rows = (r10 * x + r11 * y + r12 * z + t1) * scale + self.centre_px[1]
        return cols, rows


def _newton_step(cols: Array) -> tuple[Array, Array]:
    """``-J^{-1} r`` (two (R,) arrays, mm) from state columns (13, R); NaN where J is
    singular."""
    a, b, c, d = cols[_J00], cols[_J01], cols[_J10], cols[_J11]
    r0, r1 = cols[_R0], cols[_R1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / (a * d - b * c)
        inv[~np.isfinite(inv)] = np.nan
        return (b * r1 - d * r0) * inv, (c * r0 - a * r1) * inv


def _first_ok(ok: BoolArray) -> tuple[NDArray[np.intp], BoolArray]:
    """For a (K, R) table of tries, the first good try of each column and whether there is one."""
    return np.argmax(ok, axis=0), ok.any(axis=0)


def _start(solver: _Solver, q0: Array) -> NDArray[np.intp]:
    """First evaluation; starts beyond the edge of Snell's window are pulled towards the nadir.

    A start just past the window's edge (TIR, or an air ray below the horizon) is common for
    targets near it; moving it towards the point above the camera lowers the incidence angle
    until the ray gets out. All pulls are tried in one batch and the mildest that works is kept.
    Returns the targets that start well; the others keep the status of their first try.
    """
    state, status = solver.state, solver.status
    state[:], status[:] = solver.evaluate(q0[:, 0], q0[:, 1], state[_TX], state[_TY])
    out = np.flatnonzero((status == RayStatus.TIR) | (status == RayStatus.MISSED_OBJECT))
    if out.size:
        nadir = solver.optics.center[:2]
        pull = _PULL ** np.arange(1, _MAX_PULLS + 1)[:, None]
        cols = np.take(state, out, axis=1)
        tries, st = solver.evaluate(
            (nadir[0] + pull * (cols[_QX] - nadir[0])).ravel(),
            (nadir[1] + pull * (cols[_QY] - nadir[1])).ravel(),
            np.tile(cols[_TX], pull.size),
            np.tile(cols[_TY], pull.size),
        )
        k, found = _first_ok((st == RayStatus.OK).reshape(pull.size, out.size))
        state[:, out[found]] = tries[:, k[found] * out.size + np.flatnonzero(found)]
        status[out[found]] = RayStatus.OK
    started = np.flatnonzero(status == RayStatus.OK)
    status[started] = RayStatus.NOT_CONVERGED
    return started


def _damped_move(
    solver: _Solver, rows: NDArray[np.intp], cols: Array, sx: Array, sy: Array
) -> NDArray[np.intp]:
    """Take Newton steps ``(sx, sy)`` (R,) mm of ``rows`` (state ``cols`` (13, R)) where they
    reduce the residual, else the longest of the steps halved up to four times that does.

    A step must land on the known surface, without TIR, and shrink ``|r|``; the Newton direction
    always does so when short enough, unless the target is out of reach (beyond the wavy
    window's edge): such rows stop instead of wandering, with the status of their last try.
    Returns the rows that moved.
    """
    finite = np.isfinite(sx) & np.isfinite(sy)
    solver.status[rows[~finite]] = RayStatus.NOT_CONVERGED
    if not finite.all():
        rows, sx, sy = rows[finite], sx[finite], sy[finite]
        cols = np.compress(finite, cols, axis=1)
    r2 = cols[_R0] ** 2 + cols[_R1] ** 2
    frac = 0.5 ** np.arange(_MAX_HALVINGS + 1)[:, None]  # the full step first
    if rows.size <= _FUSED_ROWS:
        # Few rows: per-call overhead dominates, so try every length at once.
        good = np.zeros(rows.size, dtype=bool)
        pending = np.arange(rows.size)
    else:
        tries, st = solver.evaluate(cols[_QX] + sx, cols[_QY] + sy, cols[_TX], cols[_TY])
        good = (st == RayStatus.OK) & (tries[_R0] ** 2 + tries[_R1] ** 2 < r2)
        solver.state[:, rows[good]] = tries[:, good]
        pending = np.flatnonzero(~good)
        frac = frac[1:]
    if not pending.size:
        return rows
    p = np.take(cols, pending, axis=1)
    tries, st = solver.evaluate(
        (p[_QX] + frac * sx[pending]).ravel(),
        (p[_QY] + frac * sy[pending]).ravel(),
        np.tile(p[_TX], frac.size),
        np.tile(p[_TY], frac.size),
    )
    smaller = (tries[_R0] ** 2 + tries[_R1] ** 2).reshape(frac.size, -1) < r2[pending]
    k, found = _first_ok((st.reshape(frac.size, -1) == RayStatus.OK) & smaller)
    moved = rows[pending[found]]
    solver.state[:, moved] = tries[:, k[found] * pending.size + np.flatnonzero(found)]
    # Rows that found no step stop, with the failure of their shortest try.
    last = st[(frac.size - 1) * pending.size :][~found]
    solver.status[rows[pending[~found]]] = np.where(
        last == RayStatus.OK, RayStatus.NOT_CONVERGED, last
    )
    return np.concatenate([rows[good], moved])


def _newton(
    camera: PinholeCamera,
    model: _FlatWater | _SplinePatches,
    optics: _Optics,
    targets: Array,
    q0: Array,
    tol_px: float,
    max_iter: int,
) -> tuple[Array, NDArray[np.int8], Array, int]:
    """Solve targets (N, 2) mm from surface points ``q0`` (N, 2) mm; see :func:`solve_pixels`.

    Returns pixels (N, 2), status (N,), surface points (N, 3) mm and the iterations run.
    """
    n = targets.shape[0]
    solver = _Solver(camera, model, optics, targets)
    px_out = np.full((n, 2), np.nan)
    q_out = np.full((n, 3), np.nan)
    rows = _start(solver, q0)
    count = 0
    while rows.size and count < max_iter:
        count += 1
        cols = np.take(solver.state, rows, axis=1)
        sx, sy = _newton_step(cols)
        # Where the step is below tolerance, take it on the surface's tangent plane without a
        # new evaluation: what remains after it is second order.
        x, y, h = cols[_QX] + sx, cols[_QY] + sy, cols[_H] + cols[_HX] * sx + cols[_HY] * sy
        u, v = solver.project(
            np.concatenate([x, cols[_QX]]),
            np.concatenate([y, cols[_QY]]),
            np.concatenate([h, cols[_H]]),
        )
        m = rows.size
        done = np.hypot(u[:m] - u[m:], v[:m] - v[m:]) < tol_px
        solver.status[rows[done]] = RayStatus.OK
        px_out[rows[done]] = np.column_stack([u[:m][done], v[:m][done]])
        q_out[rows[done]] = np.column_stack([x[done], y[done], h[done]])
        more = ~done
        cols = np.compress(more, cols, axis=1)
        rows = _damped_move(solver, rows[more], cols, sx[more], sy[more])
    return px_out, solver.status, q_out, count


@dataclass(frozen=True)
class PixelSolution:
    """Result of :func:`solve_pixels`.

    Attributes
    ----------
    px : (..., 2) ndarray
        Pixel ``(col, row)`` of camera v that sees each target; NaN unless status is OK.
        May lie outside the image (the pinhole model extends beyond the sensor).
    status : (...,) ndarray of int8
        :class:`RayStatus` code per target.
    surface_mm : (..., 3) ndarray
        Where that pixel's ray crosses the water, mm; NaN unless OK.
    iterations : int
        Newton iterations run (the slowest target's).
    """

    px: Array
    status: NDArray[np.int8]
    surface_mm: Array
    iterations: int

    @property
    def ok(self) -> BoolArray:
        """True where the pixel was found."""
        return self.status == RayStatus.OK


def _flat_hits(camera: PinholeCamera, px: Array, h0_mm: float) -> Array:
    """Where the rays of pixels (N, 2) meet the plane z = h0, (N, 2) mm: Newton's start."""
    origin, dirs = camera.pixel_rays(px[:, 0], px[:, 1])
    hit, _ = intersect_plane_z(origin, dirs, h0_mm)
    return hit[:, :2]


def solve_pixels(
    camera: PinholeCamera,
    surface: Heightfield | None,
    h0_mm: float,
    n_water: float,
    z_object_mm: float,
    targets_xyz: ArrayLike,
    init_px: ArrayLike,
    tol_px: float = DEFAULT_TOL_PX,
    max_iter: int = 12,
) -> PixelSolution:
    """Inverse map with per-target status: which pixel sees each object point through ``surface``.

    Newton's method on the surface crossing point ``q = (x, y)`` mm (see the module docstring),
    started where the ray of ``init_px`` meets the plane ``z = h0``. Steps that leave the known
    surface, hit TIR or do not reduce the residual are halved up to four times. A target
    converges when its pixel moves less than ``tol_px`` in one step. Where the forward map folds
    (caustics) several pixels see one target; the one reached from ``init_px`` is returned.
    Starts beyond the edge of Snell's window are first pulled towards the nadir, and starts off
    a partly known surface are replaced by the flat-water answer.

    Parameters
    ----------
    camera : PinholeCamera
        The submerged camera.
    surface : Heightfield or None
        The water surface; None means flat water at ``h0_mm``.
    h0_mm, n_water, z_object_mm : float
        Mean water level (mm), refractive index, object-plane height (mm).
    targets_xyz : (..., 3) array_like
        Object points, mm, on the plane ``z = z_object_mm``; NaN entries are reported as
        MISSED_OBJECT.
    init_px : (..., 2) array_like
        Starting pixels ``(col, row)``, broadcast against the targets.
    tol_px : float
        Convergence threshold, pixels.
    max_iter : int
        Newton iterations at most.

    Returns
    -------
    PixelSolution
    """
    _check_system(h0_mm, n_water, z_object_mm)
    if not (tol_px > 0 and max_iter >= 1):
        raise WaiInputError("find_pixels: tol_px must be positive and max_iter at least 1")
    tgt = np.asarray(targets_xyz, dtype=float)
    if tgt.ndim < 1 or tgt.shape[-1] != 3:
        raise WaiInputError(f"find_pixels: targets must have shape (..., 3), got {tgt.shape}")
    init = np.asarray(init_px, dtype=float)
    if init.ndim < 1 or init.shape[-1] != 2:
        raise WaiInputError(f"find_pixels: init_px must have shape (..., 2), got {init.shape}")
    try:
        init = np.broadcast_to(init, tgt.shape[:-1] + (2,))
    except ValueError:
        raise WaiInputError("find_pixels: init_px does not broadcast against the targets") from None
    off_plane = np.abs(tgt[..., 2] - z_object_mm) > 1e-6 * max(1.0, abs(z_object_mm))
    if np.any(off_plane & np.isfinite(tgt[..., 2])):
        raise WaiInputError("find_pixels: targets must lie on the object plane z = z_object_mm")
    shape = tgt.shape[:-1]
    t2, p0 = tgt.reshape(-1, 3)[:, :2], init.reshape(-1, 2)
    px = np.full(t2.shape, np.nan)
    q = np.full((t2.shape[0], 3), np.nan)
    status = np.full(t2.shape[0], RayStatus.MISSED_OBJECT, dtype=np.int8)
    optics = _Optics(camera.pose.center_lab_mm, float(n_water), float(z_object_mm))
    q0 = _flat_hits(camera, p0, h0_mm)
    sel = np.flatnonzero(np.all(np.isfinite(t2), axis=1) & np.all(np.isfinite(p0), axis=1))
    status[sel] = RayStatus.MISSED_SURFACE  # the initial pixel's ray never reaches the water
    sel = sel[np.all(np.isfinite(q0[sel]), axis=1)]
    if surface is not None:
        q0[sel] = _start_on_surface(camera, surface, optics, h0_mm, t2[sel], q0[sel], max_iter)
    model = _surface_model(surface, h0_mm)
    px[sel], status[sel], q[sel], iters = _newton(
        camera, model, optics, t2[sel], q0[sel], tol_px, max_iter
    )
    return PixelSolution(
        px.reshape(shape + (2,)), status.reshape(shape), q.reshape(shape + (3,)), iters
    )


def _start_on_surface(
    camera: PinholeCamera,
    surface: Heightfield,
    optics: _Optics,
    h0_mm: float,
    targets: Array,
    q0: Array,
    max_iter: int,
) -> Array:
    """Starts (N, 2) mm moved onto the known surface where they are off it.

    A start off a partly known surface would fail at once although the answer may lie on it;
    the flat-water answer is a close guess (waves move it by a few mm).
    """
    off = np.flatnonzero(~surface.contains(q0[:, 0], q0[:, 1]))
    if off.size:
        _, _, q_flat, _ = _newton(
            camera, _FlatWater(h0_mm), optics, targets[off], q0[off], DEFAULT_TOL_PX, max_iter
        )
        found = np.all(np.isfinite(q_flat), axis=1)
        q0 = q0.copy()
        q0[off[found]] = q_flat[found, :2]
    return q0


def find_pixels(
    camera: PinholeCamera,
    surface: Heightfield | None,
    h0_mm: float,
    n_water: float,
    z_object_mm: float,
    targets_xyz: ArrayLike,
    init_px: ArrayLike,
    tol_px: float = DEFAULT_TOL_PX,
) -> tuple[Array, BoolArray]:
    """Pixel of camera v whose ray, refracted by ``surface``, lands on each object point.

    The inverse of :func:`trace_to_object`; see :func:`solve_pixels` for the method and the
    parameters (this returns only the pixels and the success mask).

    Returns
    -------
    px : (..., 2) ndarray
        Pixel ``(col, row)``; NaN where not found. Not clipped to the image.
    ok : (...,) ndarray of bool
        True where Newton converged to better than ``tol_px``.
    """
    sol = solve_pixels(camera, surface, h0_mm, n_water, z_object_mm, targets_xyz, init_px, tol_px)
    return sol.px, sol.ok


# --------------------------------------------------------------------------------------------
# Restoration.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Restoration:
    """Restored image in the geometry of the flat-water (ground-truth) view.

    Attributes
    ----------
    image : (H, W[, C]) ndarray
        Restored image, float32 or float64 like the input; 0 where not valid.
    valid : (H, W) ndarray of bool
        True where the pixel was restored.
    counts : dict of str to int
        Pixels per :class:`RayStatus` name (they sum to H W): ``ok``; ``tir`` (totally
        reflected in the truth view, or no ray through the estimated surface reaches the
        target); ``missed_surface`` (the estimated surface is unknown there); ``out_of_view``
        (the target is seen outside the distorted image); ``not_converged``; ``missed_object``.
        A pixel takes the cause of the worst of the four warp nodes around it.
    timings_ms : dict of str to float
        Wall times of the stages, ms: ``plan`` (geometry of the truth view, cached between
        calls), ``surface`` (spline tables), ``solve`` (warp on the coarse grid), ``upsample``,
        ``remap`` and ``total``.
    step_px : int
        Spacing of the coarse warp grid, pixels.
    map_cols, map_rows : (H, W) ndarray of float32
        The warp's columns and rows (see :attr:`map_px`).
    """

    image: NDArray
    valid: BoolArray
    counts: dict[str, int]
    timings_ms: dict[str, float]
    step_px: int
    map_cols: NDArray[np.float32] = field(repr=False)
    map_rows: NDArray[np.float32] = field(repr=False)

    @property
    def map_px(self) -> NDArray[np.float32]:
        """(H, W, 2) pixel ``(col, row)`` of the distorted image sampled for each truth pixel
        (the warp); meaningless where not valid (see :attr:`warp_px`). Assembled on each read
        from :attr:`map_cols` and :attr:`map_rows`."""
        return cv2.merge([self.map_cols, self.map_rows])

    @property
    def warp_px(self) -> NDArray[np.float32]:
        """The warp as (H, W, 2) ``(col, row)`` pixels of the distorted image; NaN where not
        valid."""
        warp = self.map_px
        warp[~self.valid] = np.nan
        return warp


@dataclass(frozen=True)
class _Plan:
    """Everything about the truth view that does not depend on the surface."""

    grid_shape: tuple[int, int]  # coarse nodes (rows, cols)
    node_px: Array  # (K, 2) truth pixel of each node that sees the object plane
    node_index: NDArray[np.intp]  # (K,) flat index of those nodes in the coarse grid
    targets: Array  # (K, 3) their object points, mm
    node_q0: Array  # (K, 2) where their rays cross flat water, mm: Newton's start
    truth_status: NDArray[np.int8]  # (rows, cols) status of every node in the truth view
    base_x: NDArray[np.float32]  # (H, W) column of every pixel
    base_y: NDArray[np.float32]  # (H, W) row of every pixel
    cell_area: NDArray[np.float64]  # (rows - 1, cols - 1) pixels in each coarse cell


_PLANS: dict[tuple, _Plan] = {}


def _plan_key(camera: PinholeCamera, h0: float, n: float, z: float, step: int) -> tuple:
    pose = camera.pose
    return (
        camera.width_px,
        camera.height_px,
        camera.focal_mm,
        camera.pixel_pitch_mm,
        pose.R.tobytes(),
        pose.t_mm.tobytes(),
        float(h0),
        float(n),
        float(z),
        int(step),
    )


def _make_plan(camera: PinholeCamera, h0: float, n: float, z: float, step: int) -> _Plan:
    w, h = camera.width_px, camera.height_px
    # Nodes every `step` pixels from 0 up to (or just past) the last pixel: every pixel then lies
    # in a cell of four nodes and bilinear interpolation never extrapolates.
    ncol = -(-(w - 1) // step) + 1
    nrow = -(-(h - 1) // step) + 1
    cols, rows = np.meshgrid(np.arange(ncol) * float(step), np.arange(nrow) * float(step))
    truth = trace_to_object(camera, None, h0, n, z, cols, rows)
    ok = truth.ok.ravel()
    targets = truth.object_mm.reshape(-1, 3)[ok]
    q0 = truth.surface_mm.reshape(-1, 3)[ok, :2]
    base_x, base_y = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return _Plan(
        (nrow, ncol),
        np.column_stack([cols.ravel(), rows.ravel()])[ok],
        np.flatnonzero(ok),
        targets,
        q0,
        truth.status,
        base_x,
        base_y,
        np.outer(_cell_sizes(h, nrow, step), _cell_sizes(w, ncol, step)),
    )


def _cell_sizes(n_px: int, n_nodes: int, step: int) -> NDArray[np.float64]:
    """Pixels in each of the ``n_nodes - 1`` cells along an axis of ``n_px`` pixels: ``step``
    each, the rest in the last (it also holds a last pixel lying exactly on the last node)."""
    sizes = np.full(n_nodes - 1, float(step))
    sizes[-1] = n_px - step * (n_nodes - 2)
    return sizes


def _plan(camera: PinholeCamera, h0: float, n: float, z: float, step: int) -> _Plan:
    key = _plan_key(camera, h0, n, z, step)
    if key not in _PLANS:
        if len(_PLANS) >= 4:
            _PLANS.clear()
        _PLANS[key] = _make_plan(camera, h0, n, z, step)
    return _PLANS[key]


def _check_image(distorted: NDArray, camera: PinholeCamera) -> NDArray:
    """The image as float32 or float64, after checking its shape and values."""
    img = np.asarray(distorted)
    if img.ndim not in (2, 3) or img.shape[:2] != (camera.height_px, camera.width_px):
        raise WaiInputError(
            f"restore_view: image shape {img.shape} does not match the camera "
            f"({camera.height_px}, {camera.width_px}[, C])"
        )
    if not np.issubdtype(img.dtype, np.floating):
        raise WaiInputError(f"restore_view: image must be floating point, got {img.dtype}")
    if img.ndim == 3 and not 1 <= img.shape[2] <= 4:
        raise WaiInputError(f"restore_view: image must have 1 to 4 channels, got {img.shape[2]}")
    if img.dtype not in (np.float32, np.float64):
        img = img.astype(np.float32)
    img = np.ascontiguousarray(img)
    # NaN or inf propagate into the sum (float64 accumulators: finite float32 cannot overflow);
    # several times faster than cv2.checkRange and without a full-size temporary.
    if not np.all(np.isfinite(cv2.sumElems(img))):
        raise WaiInputError("restore_view: image holds NaN or inf")
    return img


# Which status a cell of four nodes reports when some are invalid (most fundamental first).
_PRIORITY = np.array([0, 4, 5, 3, 2, 1], dtype=np.int8)  # rank of each RayStatus code
_BY_RANK = np.array(
    [
        RayStatus.OK,
        RayStatus.OUT_OF_VIEW,
        RayStatus.NOT_CONVERGED,
        RayStatus.MISSED_OBJECT,
        RayStatus.MISSED_SURFACE,
        RayStatus.TIR,
    ],
    dtype=np.int8,
)


def _cell_status(node_status: NDArray[np.int8]) -> NDArray[np.int8]:
    """Status of each coarse cell: OK if its four nodes are, else its worst node's status."""
    r = _PRIORITY[node_status]
    worst = np.maximum(np.maximum(r[:-1, :-1], r[1:, :-1]), np.maximum(r[:-1, 1:], r[1:, 1:]))
    return _BY_RANK[worst]


def _node_warp(
    plan: _Plan, px: Array, status: NDArray[np.int8]
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int8]]:
    """Displacement ``u - p`` in columns and in rows (rows, cols) px at the coarse nodes (0 where
    unsolved) and the status of every node (the truth view's where it sees no object)."""
    node_status = plan.truth_status.copy().ravel()
    node_status[plan.node_index] = status
    disp = np.zeros((2, plan.grid_shape[0] * plan.grid_shape[1]), dtype=np.float32)
    solved = status == RayStatus.OK
    disp[:, plan.node_index[solved]] = (px[solved] - plan.node_px[solved]).T
    dx, dy = disp.reshape((2,) + plan.grid_shape)
    return dx, dy, node_status.reshape(plan.grid_shape)


def _pixel_warp(
    plan: _Plan,
    disp_x: NDArray[np.float32],
    disp_y: NDArray[np.float32],
    node_status: NDArray[np.int8],
    step: int,
) -> tuple[NDArray[np.float32], NDArray[np.float32], BoolArray, dict[str, int]]:
    """Full-resolution sampling columns and rows (H, W), validity (H, W) and counts per cause.

    A pixel is valid when the four nodes of its cell were solved and its sampling position
    lies inside the distorted image.
    """
    h, w = plan.base_x.shape
    # The node grid is a scaled copy of the pixel grid, so an affine warp reads it, one channel
    # at a time: OpenCV's two-channel path is several times slower and rounds the read position
    # to 1/32 of a cell (up to ~0.1 px of warp for steps that do not divide 32); this one is
    # bilinear to ~1e-5 px for any step. Displacements are interpolated, not positions: they
    # vary slowly, so float32 costs nothing.
    scale = np.array([[1.0 / step, 0.0, 0.0], [0.0, 1.0 / step, 0.0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP

    def positions(disp: NDArray[np.float32], base: NDArray[np.float32]) -> NDArray[np.float32]:
        full = cv2.warpAffine(disp, scale, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        return cv2.add(full, base, dst=full)

    map_x, map_y = positions(disp_x, plan.base_x), positions(disp_y, plan.base_y)
    cell = _cell_status(node_status)
    # Each cell's flag over its step x step pixels; a last pixel lying exactly on the last node
    # belongs to the cell before it.
    cell_ok = (cell == RayStatus.OK).view(np.uint8) * np.uint8(255)
    cell_ok = cv2.resize(
        cell_ok, (cell.shape[1] * step, cell.shape[0] * step), interpolation=cv2.INTER_NEAREST
    )
    pad = (max(0, h - cell_ok.shape[0]), max(0, w - cell_ok.shape[1]))
    if any(pad):
        cell_ok = cv2.copyMakeBorder(cell_ok, 0, pad[0], 0, pad[1], cv2.BORDER_REPLICATE)
    cell_ok = cell_ok[:h, :w]
    # 255 inside the image (as PinholeCamera.in_image) and in a solved cell.
    valid = cv2.inRange(map_x, -0.5, w - 0.5)
    cv2.bitwise_and(valid, cv2.inRange(map_y, -0.5, h - 0.5), dst=valid)
    cv2.bitwise_and(valid, cell_ok, dst=valid)
    hist = np.bincount(cell.ravel(), weights=plan.cell_area.ravel(), minlength=len(RayStatus))
    counts = {s.name.lower(): int(round(hist[s])) for s in RayStatus}
    n_valid = cv2.countNonZero(valid)
    counts["out_of_view"] += counts["ok"] - n_valid
    counts["ok"] = n_valid
    return map_x, map_y, valid.view(bool), counts


def restore_view(
    distorted: NDArray,
    camera: PinholeCamera,
    surface_est: Heightfield | None,
    h0_mm: float,
    n_water: float,
    z_object_mm: float,
    warp_step_px: int = 8,
) -> Restoration:
    """Undo the refraction of ``surface_est``: resample the distorted view into the flat-water view.

    For each truth pixel ``p``: ``P`` = flat-water forward map of ``p``; ``u`` = pixel that sees
    ``P`` through ``surface_est`` (:func:`find_pixels`, started at ``p``); ``restored(p) =
    distorted(u)``, sampled bilinearly. ``u`` is solved on nodes every ``warp_step_px`` pixels and
    its displacement ``u - p`` interpolated bilinearly in between. A pixel is restored only if the
    four nodes around it were solved and ``u`` falls inside the distorted image; all others are 0
    in the image, False in ``valid`` and counted by cause, never filled.

    Parameters
    ----------
    distorted : (H, W) or (H, W, C) ndarray of float
        Image of camera v through the wavy water, C <= 4.
    camera : PinholeCamera
        Camera v (H, W must match its size).
    surface_est : Heightfield or None
        The estimated water surface, mm; NaN holes and its limited extent are respected.
        None means flat water (restoration is then the identity).
    h0_mm, n_water, z_object_mm : float
        Mean water level (mm), refractive index, object-plane height (mm).
    warp_step_px : int
        Spacing of the coarse warp grid, pixels. On the paper's rig (800 x 600) 8 px is the
        sweet spot: 4 px solves 4x the nodes for no smaller corner spread, 16 px halves the
        solve but doubles the corner spread.

    Returns
    -------
    Restoration
    """
    t_start = time.perf_counter()
    img = _check_image(distorted, camera)
    if isinstance(warp_step_px, bool) or int(warp_step_px) != warp_step_px or warp_step_px < 1:
        raise WaiInputError(
            f"restore_view: warp_step_px must be a positive integer, got {warp_step_px!r}"
        )
    step = int(warp_step_px)
    _check_system(h0_mm, n_water, z_object_mm)
    t = {"plan": time.perf_counter()}
    plan = _plan(camera, h0_mm, n_water, z_object_mm, step)
    t["surface"] = time.perf_counter()
    model = _surface_model(surface_est, h0_mm)
    optics = _Optics(camera.pose.center_lab_mm, float(n_water), float(z_object_mm))
    t["solve"] = time.perf_counter()
    px, st, _, _ = _newton(
        camera, model, optics, plan.targets[:, :2], plan.node_q0, _WARP_TOL_PX, _WARP_ITER
    )
    t["upsample"] = time.perf_counter()
    map_x, map_y, valid, counts = _pixel_warp(plan, *_node_warp(plan, px, st), step)
    t["remap"] = time.perf_counter()
    # Half-pixel border: replicate rather than blend with black. Sampled straight into the
    # result, whose invalid pixels are then zeroed (x - x under the mask; the image is finite):
    # one full-size array less to allocate and fault in.
    out = np.empty(img.shape, dtype=img.dtype)
    cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, dst=out, borderMode=cv2.BORDER_REPLICATE)
    cv2.subtract(out, out, dst=out, mask=cv2.bitwise_not(valid.view(np.uint8)))
    t["end"] = time.perf_counter()
    names = list(t)
    timings = {a: 1e3 * (t[b] - t[a]) for a, b in zip(names[:-1], names[1:], strict=True)}
    timings["total"] = 1e3 * (t["end"] - t_start)
    return Restoration(out, valid, counts, timings, step, map_x, map_y)
