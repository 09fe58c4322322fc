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
from dataclasses import dataclass
from enum import IntEnum

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
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
# Surface models for the Newton solver: height and slopes at (x, y), cheap and vectorised.
# --------------------------------------------------------------------------------------------


class _FlatWater:
    """Flat water at ``h0``: the surface model of the ground-truth view."""

    def __init__(self, h0_mm: float) -> None:
        self.h0 = float(h0_mm)

    def jet(self, x: Array, y: Array) -> Array:
        """Height and derivatives (N, 6), see :meth:`_SplinePatches.jet`."""
        out = np.zeros((np.size(x), 6))
        out[:, 0] = self.h0
        return out


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


_BASIS_CACHE: dict[bytes, tuple[Array, Array, Array]] = {}


def _cached_interval_polynomials(knots: Array) -> tuple[Array, Array, Array]:
    """:func:`_interval_polynomials`, cached: a sequence of estimates shares one grid."""
    key = knots.tobytes()
    if key not in _BASIS_CACHE:
        if len(_BASIS_CACHE) >= 16:
            _BASIS_CACHE.clear()
        _BASIS_CACHE[key] = _interval_polynomials(knots)
    return _BASIS_CACHE[key]


def _powers(s: Array) -> Array:
    """``[1, s, s^2, s^3]`` and its first two derivatives in ``s``, (N, 3, 4)."""
    out = np.zeros((s.size, 3, 4))
    out[:, 0, 0] = out[:, 1, 1] = 1.0
    out[:, 0, 1], out[:, 0, 2], out[:, 0, 3] = s, s * s, s * s * s
    out[:, 1, 2], out[:, 1, 3] = 2 * s, 3 * s * s
    out[:, 2, 2], out[:, 2, 3] = 2.0, 6 * s
    return out


class _SplinePatches:
    """Fast evaluation of a :class:`Heightfield`'s bicubic spline with its derivatives.

    The spline is ``sum_jl c[j, l] B_j(y) B_l(x)``; on a knot interval the four active B-splines
    are cubics whose power-basis coefficients are tabulated once per grid. A point then needs
    its 4 x 4 block of ``c`` and a few 4 x 4 products: several times faster than FITPACK point
    evaluation (which would dominate the solver), and it gives the second derivatives that the
    Jacobian needs in the same pass. Values equal ``Heightfield.height`` to rounding.
    """

    def __init__(self, surface: Heightfield) -> None:
        self.surface = surface
        # Heightfield exposes no public accessor for its spline; reading it keeps the values
        # identical to Heightfield.height (same fill of unknown samples, same knots).
        spline = surface._spline
        ty, tx = spline.get_knots()
        coeffs = spline.get_coeffs().reshape(ty.size - 4, tx.size - 4)
        self.blocks = sliding_window_view(coeffs, (4, 4))  # a view: (cells y, cells x, 4, 4)
        self.y0, self.wy, self.qy = _cached_interval_polynomials(ty)
        self.x0, self.wx, qx = _cached_interval_polynomials(tx)
        self.qxt = np.ascontiguousarray(qx.transpose(0, 2, 1))

    def jet(self, x: Array, y: Array) -> Array:
        """Height and its derivatives at points (x, y) (N,) mm, lab frame.

        Returns
        -------
        (N, 6) ndarray
            ``h`` (mm), ``h_x``, ``h_y`` (dimensionless), ``h_xx``, ``h_xy``, ``h_yy`` (1/mm);
            NaN rows outside the known surface.
        """
        ix = np.clip(np.searchsorted(self.x0, x, side="right") - 1, 0, self.x0.size - 1)
        iy = np.clip(np.searchsorted(self.y0, y, side="right") - 1, 0, self.y0.size - 1)
        wx, wy = self.wx[ix], self.wy[iy]
        pu = _powers((x - self.x0[ix]) / wx)  # (N, 3, 4): value, first, second derivative
        pv = _powers((y - self.y0[iy]) / wy)
        by = pv @ self.qy[iy]  # B-spline values and derivatives along y, (N, 3, 4)
        bx = self.qxt[ix] @ pu.transpose(0, 2, 1)  # along x, (N, 4, 3)
        m = by @ self.blocks[iy, ix] @ bx  # m[n, i, j]: d^i/dv^i d^j/du^j of h
        out = np.stack(
            [
                m[:, 0, 0],
                m[:, 0, 1] / wx,
                m[:, 1, 0] / wy,
                m[:, 0, 2] / wx**2,
                m[:, 1, 1] / (wx * wy),
                m[:, 2, 0] / wy**2,
            ],
            axis=-1,
        )
        out[~self.surface.contains(x, y)] = np.nan
        return out


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


def _air_direction(
    optics: _Optics, x: Array, y: Array, h: Array, hx: Array, hy: Array
) -> tuple[Array, Array, Array, BoolArray]:
    """Unit air direction seen through surface point (x, y, h) with slopes (hx, hy): eq. 18-20.

    Component-wise (1-D arrays, N points) because this is the solver's inner loop.

    Returns
    -------
    tx, ty, tz : (N,) ndarray
        The refracted (air) ray direction; meaningless where ``tir``.
    tir : (N,) ndarray of bool
        Total internal reflection.
    """
    cx, cy, cz = optics.center
    vx, vy, vz = x - cx, y - cy, h - cz
    inv = 1.0 / np.sqrt(vx * vx + vy * vy + vz * vz)
    vx, vy, vz = vx * inv, vy * inv, vz * inv
    s = 1.0 / np.sqrt(1.0 + hx * hx + hy * hy)
    mx, my, mz = -hx * s, -hy * s, s  # unit normal, up
    cos = vx * mx + vy * my + vz * mz
    n = optics.n_water
    k = 1.0 - n * n * (1.0 - cos * cos)
    # Vector Snell (eq. 20) with the normal turned against the ray, whichever side it hits.
    g = np.sign(cos) * (n * np.abs(cos) - np.sqrt(np.maximum(k, 0.0)))
    return n * vx - g * mx, n * vy - g * my, n * vz - g * mz, k < 0


def _residual(
    optics: _Optics, x: Array, y: Array, jet: tuple[Array, Array, Array], target: Array
) -> tuple[Array, NDArray[np.int8]]:
    """How far the air ray through surface point (x, y) misses its target, and a status.

    The miss is measured between directions, not on the object plane: the air direction and the
    direction from the surface point to the target, both mapped by the stereographic chart
    ``(t_x, t_y) / (1 + t_z)`` of the upper hemisphere. Object-plane distances grow like
    ``tan`` towards the edge of Snell's window and make Newton crawl there; the chart stays
    smooth up to the horizon.

    Returns
    -------
    r : (N, 2) ndarray
        The residual (dimensionless); zero at the solution.
    status : (N,) ndarray of int8
        :class:`RayStatus` of the ray through (x, y).
    """
    h, hx, hy = jet
    tx, ty, tz, tir = _air_direction(optics, x, y, h, hx, hy)
    dx, dy, dz = target[:, 0] - x, target[:, 1] - y, optics.z_object - h
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    dx, dy, dz = dx * inv, dy * inv, dz * inv
    a, b = 1.0 / (1.0 + tz), 1.0 / (1.0 + dz)
    r = np.stack([tx * a - dx * b, ty * a - dy * b], axis=-1)
    status = np.where(tz > 0, RayStatus.OK, RayStatus.MISSED_OBJECT).astype(np.int8)
    status[tir] = RayStatus.TIR
    status[np.isnan(h)] = RayStatus.MISSED_SURFACE
    return r, status


@dataclass
class _Solver:
    """Newton state of all targets, updated in place (first axis: target, N).

    Rows are gathered and scattered by index rather than compacted, so that a few slow
    targets do not make every iteration copy the whole state.
    """

    model: _FlatWater | _SplinePatches
    optics: _Optics
    target: Array  # (N, 2) object-plane x, y, mm
    q: Array  # (N, 2) surface point x, y, mm
    jet: Array  # (N, 3) height (mm) and slopes at q
    r: Array  # (N, 2) residual at q (see _residual)
    jac: Array  # (N, 2, 2) dr/dq, 1/mm
    status: NDArray[np.int8]  # (N,) final status, NOT_CONVERGED while running

    def evaluate(self, rows: NDArray[np.intp], q: Array) -> tuple[Array, Array, Array, NDArray]:
        """Residual (R, 2), Jacobian (R, 2, 2), jet (R, 3) and status (R,) of ``rows`` moved to
        surface points ``q`` (R, 2) mm; the Jacobian by forward differences, with the height and
        slopes at the shifted points taken from the second derivatives at ``q`` (their error,
        O(step^2), is far below the difference's own)."""
        x, y = q[:, 0], q[:, 1]
        j = self.model.jet(x, y)
        h, hx, hy, hxx, hxy, hyy = j.T
        d = _FD_STEP_MM
        # Base point and its two shifts in one call.
        r3, status3 = _residual(
            self.optics,
            np.concatenate([x, x + d, x]),
            np.concatenate([y, y, y + d]),
            (
                np.concatenate([h, h + d * hx, h + d * hy]),
                np.concatenate([hx, hx + d * hxx, hx + d * hxy]),
                np.concatenate([hy, hy + d * hxy, hy + d * hyy]),
            ),
            np.tile(self.target[rows], (3, 1)),
        )
        r, rx, ry = np.split(r3, 3)
        return r, np.stack([rx - r, ry - r], axis=-1) / d, j[:, :3], status3[: rows.size]

    def store(self, rows: NDArray[np.intp], q: Array, r: Array, jac: Array, jet: Array) -> None:
        self.q[rows], self.r[rows], self.jac[rows], self.jet[rows] = q, r, jac, jet


def _newton_step(jac: Array, resid: Array) -> Array:
    """``-J^{-1} r`` for a stack of 2x2 systems (N, 2, 2), (N, 2); NaN where J is singular."""
    a, b, c, d = jac[:, 0, 0], jac[:, 0, 1], jac[:, 1, 0], jac[:, 1, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / (a * d - b * c)
    inv[~np.isfinite(inv)] = np.nan
    dx = d * resid[:, 0] - b * resid[:, 1]
    dy = a * resid[:, 1] - c * resid[:, 0]
    return -np.stack([dx, dy], axis=1) * inv[:, None]


def _project(camera: PinholeCamera, q: Array, h: Array) -> Array:
    """Pixels (N, 2) of surface points (x, y) = ``q`` (N, 2) at heights ``h`` (N,), mm."""
    cols, rows, _ = camera.project(np.column_stack([q, h]))
    return np.stack([cols, rows], axis=-1)


def _first_ok(ok: BoolArray) -> tuple[NDArray[np.intp], BoolArray]:
    """For a (K, R) table of tries, the first good try of each column and whether there is one."""
    return np.argmax(ok, axis=0), ok.any(axis=0)


def _start(solver: _Solver) -> NDArray[np.intp]:
    """First evaluation; starts beyond the edge of Snell's window are pulled towards the nadir.

    A start just past the window's edge (TIR, or an air ray below the horizon) is common for
    targets near it; moving it towards the point above the camera lowers the incidence angle
    until the ray gets out. All pulls are tried in one batch and the mildest that works is kept.
    Returns the rows that start well; the others keep the status of their first try.
    """
    rows = np.arange(solver.q.shape[0])
    r, jac, jet, status = solver.evaluate(rows, solver.q)
    solver.store(rows, solver.q, r, jac, jet)
    solver.status[:] = status
    out = np.flatnonzero((status == RayStatus.TIR) | (status == RayStatus.MISSED_OBJECT))
    if out.size:
        nadir = solver.optics.center[:2]
        pull = _PULL ** np.arange(1, _MAX_PULLS + 1)
        q = (nadir + pull[:, None, None] * (solver.q[out] - nadir)).reshape(-1, 2)
        tries = np.tile(out, pull.size)
        r, jac, jet, status = solver.evaluate(tries, q)
        k, found = _first_ok((status == RayStatus.OK).reshape(pull.size, out.size))
        pick = k[found] * out.size + np.flatnonzero(found)
        solver.store(out[found], q[pick], r[pick], jac[pick], jet[pick])
        solver.status[out[found]] = RayStatus.OK
    started = np.flatnonzero(solver.status == RayStatus.OK)
    solver.status[started] = RayStatus.NOT_CONVERGED
    return started


def _damped_move(solver: _Solver, rows: NDArray[np.intp], step: Array) -> NDArray[np.intp]:
    """Take Newton steps (R, 2) mm where they reduce the residual, else the longest of the
    steps halved up to four times that does.

    A step must land on the known surface, without TIR, and shrink ``|r|``; the Newton direction
    always does so when short enough, unless the target is out of reach (beyond the wavy
    window's edge): such rows stop instead of wandering, with the status of their last try.
    The halved steps are tried in one batch. Returns the rows that moved.
    """
    finite = np.all(np.isfinite(step), axis=1)
    solver.status[rows[~finite]] = RayStatus.NOT_CONVERGED
    rows, step = rows[finite], step[finite]
    r2 = np.sum(solver.r[rows] ** 2, axis=1)
    q = solver.q[rows] + step
    r, jac, jet, status = solver.evaluate(rows, q)
    good = (status == RayStatus.OK) & (np.sum(r**2, axis=1) < r2)
    solver.store(rows[good], q[good], r[good], jac[good], jet[good])
    bad = np.flatnonzero(~good)
    if not bad.size:
        return rows
    frac = 0.5 ** np.arange(1, _MAX_HALVINGS + 1)
    qb = (solver.q[rows[bad]] + frac[:, None, None] * step[bad]).reshape(-1, 2)
    rb, jb, jetb, sb = solver.evaluate(np.tile(rows[bad], frac.size), qb)
    ok = (sb == RayStatus.OK) & (np.sum(rb**2, axis=1) < np.tile(r2[bad], frac.size))
    k, found = _first_ok(ok.reshape(frac.size, bad.size))
    pick = k[found] * bad.size + np.flatnonzero(found)
    solver.store(rows[bad[found]], qb[pick], rb[pick], jb[pick], jetb[pick])
    # Rows that found no step stop, with the failure of their shortest try.
    last = sb[(frac.size - 1) * bad.size :][~found]
    solver.status[rows[bad[~found]]] = np.where(last == RayStatus.OK, RayStatus.NOT_CONVERGED, last)
    return np.concatenate([rows[good], rows[bad[found]]])


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
    solver = _Solver(
        model,
        optics,
        targets,
        q0.copy(),
        np.full((n, 3), np.nan),
        np.full((n, 2), np.nan),
        np.full((n, 2, 2), np.nan),
        np.full(n, RayStatus.NOT_CONVERGED, dtype=np.int8),
    )
    px_out = np.full((n, 2), np.nan)
    q_out = np.full((n, 3), np.nan)
    rows = _start(solver)
    count = 0
    while rows.size and count < max_iter:
        count += 1
        step = _newton_step(solver.jac[rows], solver.r[rows])
        # Where the step is below tolerance, take it on the surface's tangent plane without a
        # new evaluation: what remains after it is second order.
        q, jet = solver.q[rows], solver.jet[rows]
        q_next = q + step
        h_next = jet[:, 0] + np.sum(jet[:, 1:] * step, axis=1)
        px_next = _project(camera, q_next, h_next)
        done = np.linalg.norm(px_next - _project(camera, q, jet[:, 0]), axis=1) < tol_px
        solver.status[rows[done]] = RayStatus.OK
        px_out[rows[done]] = px_next[done]
        q_out[rows[done]] = np.column_stack([q_next[done], h_next[done]])
        rows = _damped_move(solver, rows[~done], step[~done])
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
    map_px : (H, W, 2) ndarray of float32
        Pixel ``(col, row)`` of the distorted image sampled for each truth pixel (the warp);
        meaningless where not valid (see :attr:`warp_px`).
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
    """

    image: NDArray
    valid: BoolArray
    map_px: NDArray[np.float32]
    counts: dict[str, int]
    timings_ms: dict[str, float]
    step_px: int

    @property
    def warp_px(self) -> NDArray[np.float32]:
        """The warp as (H, W, 2) ``(col, row)`` pixels of the distorted image; NaN where not
        valid."""
        warp = self.map_px.copy()
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
    base_px: NDArray[np.float32]  # (H, W, 2) (col, row) of every pixel
    node_coords: NDArray[np.float32]  # (H, W, 2) the same in node units: (col, row) / step
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
    node_px = np.column_stack([cols.ravel(), rows.ravel()])[ok]
    base = np.stack(
        np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)), axis=-1
    )
    return _Plan(
        (nrow, ncol),
        node_px,
        np.flatnonzero(ok),
        truth.object_mm.reshape(-1, 3)[ok],
        truth.surface_mm.reshape(-1, 3)[ok, :2],
        truth.status,
        base,
        base / np.float32(step),
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
    if not cv2.checkRange(img)[0]:  # NaN or inf, without a full-size temporary
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
) -> tuple[NDArray[np.float32], NDArray[np.int8]]:
    """Displacement ``u - p`` (rows, cols, 2) px at the coarse nodes (0 where unsolved) and the
    status of every node (the truth view's where it sees no object)."""
    node_status = plan.truth_status.copy().ravel()
    node_status[plan.node_index] = status
    disp = np.zeros(plan.grid_shape + (2,), dtype=np.float32)
    solved = status == RayStatus.OK
    disp.reshape(-1, 2)[plan.node_index[solved]] = px[solved] - plan.node_px[solved]
    return disp, node_status.reshape(plan.grid_shape)


def _pixel_warp(
    plan: _Plan, disp: NDArray[np.float32], node_status: NDArray[np.int8], step: int
) -> tuple[NDArray[np.float32], BoolArray, dict[str, int]]:
    """Full-resolution sampling positions (H, W, 2), validity (H, W) and counts per cause.

    A pixel is valid when the four nodes of its cell were solved and its sampling position
    lies inside the distorted image.
    """
    h, w = plan.base_px.shape[:2]
    # Displacements, not positions, are interpolated: they vary slowly, so OpenCV's rounding of
    # the read position (to 1/32 of a cell; none for steps dividing 32) costs far less than a px.
    disp_full = cv2.remap(
        disp, plan.node_coords, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    maps = plan.base_px + disp_full
    cell = _cell_status(node_status)
    cell_ok = np.repeat(np.repeat((cell == RayStatus.OK).view(np.uint8), step, 0), step, 1)
    # A last pixel lying exactly on the last node belongs to the cell before it.
    cell_ok = np.pad(
        cell_ok[:h, :w],
        ((0, max(0, h - cell_ok.shape[0])), (0, max(0, w - cell_ok.shape[1]))),
        mode="edge",
    )
    inside = cv2.inRange(maps, (-0.5, -0.5), (w - 0.5, h - 0.5))  # 255 inside, as in_image
    valid = cv2.bitwise_and(inside, cell_ok * np.uint8(255)) > 0
    hist = np.bincount(cell.ravel(), weights=plan.cell_area.ravel(), minlength=len(RayStatus))
    counts = {s.name.lower(): int(round(hist[s])) for s in RayStatus}
    n_valid = int(np.count_nonzero(valid))
    counts["out_of_view"] += counts["ok"] - n_valid
    counts["ok"] = n_valid
    return maps, valid, counts


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
        Spacing of the coarse warp grid, pixels (4, 8 or 16 are exact for the interpolation).

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
        camera,
        model,
        optics,
        plan.targets[:, :2],
        plan.node_q0,
        DEFAULT_TOL_PX,
        12,
    )
    t["upsample"] = time.perf_counter()
    maps, valid, counts = _pixel_warp(plan, *_node_warp(plan, px, st), step)
    t["remap"] = time.perf_counter()
    # Half-pixel border: replicate rather than blend with black.
    sampled = cv2.remap(img, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out = np.zeros(img.shape, dtype=img.dtype)
    cv2.copyTo(sampled.reshape(img.shape), valid.view(np.uint8), out)
    t["end"] = time.perf_counter()
    names = list(t)
    timings = {a: 1e3 * (t[b] - t[a]) for a, b in zip(names[:-1], names[1:], strict=True)}
    timings["total"] = 1e3 * (t["end"] - t_start)
    return Restoration(out, valid, maps, counts, timings, step)
