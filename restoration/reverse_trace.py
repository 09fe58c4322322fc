"""Reverse ray tracing through a known water surface and the image restoration it gives (sec. 3.3).

Camera v sits under the water and looks up at a horizontal object plane ``z = z_object`` (z_a).
The *forward map* of a pixel (eq. 14-20) is: back-project the pixel, hit the water surface, refract
into the air (Snell, eq. 20), hit the object plane. :func:`trace_to_object` computes it.

The *inverse map* (:func:`find_pixels`) asks which pixel of camera v sees a given object point
through a given surface. It is solved by Newton's method over all targets at once. The unknown is
the surface point ``q = (x, y)`` where the ray crosses the water rather than the pixel itself:
for a candidate ``q`` the ray from the camera centre to ``(x, y, h(x, y))`` and the normal there are
explicit, so each Newton step needs one surface evaluation instead of a nested ray-surface
intersection; the pixel is the projection of ``q``. The Jacobian is a forward finite difference of
the forward map in ``q``.

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
_MAX_HALVINGS = 5


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
    """Fast evaluation of a :class:`Heightfield`'s bicubic spline with its slopes.

    The spline is ``sum_jl c[j, l] B_j(y) B_l(x)``; on a knot interval the four active B-splines
    are cubics whose power-basis coefficients are tabulated once per grid. A point then needs
    its 4 x 4 block of ``c`` and a few small products, several times faster than FITPACK point
    evaluation (which would dominate the solver), and gives the second derivatives that the
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
        m = by @ self.blocks[iy, ix] @ bx  # m[n, i, j] = d^i/dv^i d^j/du^j of h
        out = np.stack([m[:, 0, 0], m[:, 0, 1] / wx, m[:, 1, 0] / wy, m[:, 0, 2] / wx**2,
                        m[:, 1, 1] / (wx * wy), m[:, 2, 0] / wy**2], axis=-1)
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


def _map_from_surface(
    optics: _Optics, x: Array, y: Array, h: Array, hx: Array, hy: Array
) -> tuple[Array, Array, Array, BoolArray]:
    """Object-plane point seen through surface point (x, y, h) with slopes (hx, hy): eq. 18-20.

    Component-wise (1-D arrays, N points) because this is the solver's inner loop.

    Returns
    -------
    px, py : (N,) ndarray
        Object-plane x and y, mm; NaN or meaningless where not ``reached``.
    lam : (N,) ndarray
        Air path length to the object plane, mm (positive where reached).
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
    tx, ty, tz = n * vx - g * mx, n * vy - g * my, n * vz - g * mz
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (optics.z_object - h) / tz
    return x + lam * tx, y + lam * ty, lam, k < 0


def _status(h: Array, lam: Array, tir: BoolArray, px: Array, py: Array) -> NDArray[np.int8]:
    """RayStatus of each forward-mapped surface point."""
    reached = (lam > 0) & np.isfinite(px) & np.isfinite(py)
    status = np.where(reached, RayStatus.OK, RayStatus.MISSED_OBJECT).astype(np.int8)
    status[tir] = RayStatus.TIR
    status[np.isnan(h)] = RayStatus.MISSED_SURFACE
    return status


@dataclass
class _State:
    """Newton state of the targets being solved (all arrays share the first axis, N)."""

    idx: NDArray[np.intp]  # position in the caller's arrays
    target: Array  # (N, 2) object-plane x, y, mm
    q: Array  # (N, 2) surface point x, y, mm
    jet: Array  # (N, 3) height (mm) and slopes there
    p: Array  # (N, 2) object-plane point seen there, mm
    jac: Array  # (N, 2, 2) dp/dq
    status: NDArray[np.int8]  # (N,) status at q

    def take(self, keep: BoolArray | NDArray[np.intp]) -> _State:
        return _State(*(getattr(self, f)[keep] for f in self.__dataclass_fields__))


def _evaluate(
    model: _FlatWater | _SplinePatches, optics: _Optics, idx: NDArray, target: Array, q: Array
) -> _State:
    """Forward map at surface points ``q`` (N, 2) mm and its Jacobian by forward differences.

    The height and slopes at the shifted points come from the second derivatives at ``q``
    (their error, O(step^2), is far below the difference's own).
    """
    x, y = q[:, 0], q[:, 1]
    j = model.jet(x, y)
    h, hx, hy, hxx, hxy, hyy = j.T
    px, py, lam, tir = _map_from_surface(optics, x, y, h, hx, hy)
    d = _FD_STEP_MM
    ax, ay, _, _ = _map_from_surface(optics, x + d, y, h + d * hx, hx + d * hxx, hy + d * hxy)
    bx, by, _, _ = _map_from_surface(optics, x, y + d, h + d * hy, hx + d * hxy, hy + d * hyy)
    jac = np.stack([np.stack([ax - px, bx - px], -1), np.stack([ay - py, by - py], -1)], 1) / d
    return _State(idx, target, q, j[:, :3], np.stack([px, py], -1), jac,
                  _status(h, lam, tir, px, py))


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


def _damped_move(
    model: _FlatWater | _SplinePatches, optics: _Optics, st: _State, step: Array
) -> tuple[_State, NDArray[np.int8]]:
    """Take Newton steps (N, 2) mm, halving those that leave the surface or hit TIR.

    Returns the moved state (rows that could not move keep their old values) and the status of
    each row's last try (OK where it moved).
    """
    new = st.take(np.arange(st.idx.size))
    tried = np.full(st.idx.size, RayStatus.NOT_CONVERGED, dtype=np.int8)
    pending = np.all(np.isfinite(step), axis=1)
    for _ in range(_MAX_HALVINGS + 1):
        sel = np.flatnonzero(pending)
        if not sel.size:
            break
        trial = _evaluate(model, optics, st.idx[sel], st.target[sel], st.q[sel] + step[sel])
        tried[sel] = trial.status
        good = trial.status == RayStatus.OK
        for f in ("q", "jet", "p", "jac", "status"):
            getattr(new, f)[sel[good]] = getattr(trial, f)[good]
        pending[sel[good]] = False
        step[sel[~good]] *= 0.5
    return new, tried


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
    px_out = np.full((n, 2), np.nan)
    q_out = np.full((n, 3), np.nan)
    st = _evaluate(model, optics, np.arange(n), targets, q0)
    status_out = np.where(st.status == RayStatus.OK, RayStatus.NOT_CONVERGED, st.status)
    status_out = status_out.astype(np.int8)
    st = st.take(st.status == RayStatus.OK)
    count = 0
    while st.idx.size and count < max_iter:
        count += 1
        step = _newton_step(st.jac, st.p - st.target)
        # Where the step is below tolerance, take it on the surface's tangent plane without a
        # new evaluation: what remains after it is second order.
        q_next = st.q + step
        h_next = st.jet[:, 0] + np.sum(st.jet[:, 1:] * step, axis=1)
        px_next = _project(camera, q_next, h_next)
        moved_px = np.linalg.norm(px_next - _project(camera, st.q, st.jet[:, 0]), axis=1)
        done = moved_px < tol_px
        status_out[st.idx[done]] = RayStatus.OK
        px_out[st.idx[done]] = px_next[done]
        q_out[st.idx[done]] = np.column_stack([q_next[done], h_next[done]])
        st, step = st.take(~done), step[~done]
        st, tried = _damped_move(model, optics, st, step)
        moved = tried == RayStatus.OK
        status_out[st.idx[~moved]] = tried[~moved]
        st = st.take(moved)
    return px_out, status_out, q_out, count


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
    started where the ray of ``init_px`` meets the plane ``z = h0``. Failing steps (off the known
    surface, TIR) are halved up to five times. A target converges when its pixel moves less than
    ``tol_px`` in one step. Where the forward map folds (caustics) several pixels see one target;
    the one reached from ``init_px`` is returned.

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
    good = np.all(np.isfinite(t2), axis=1) & np.all(np.isfinite(p0), axis=1)
    px = np.full(t2.shape, np.nan)
    q = np.full((t2.shape[0], 3), np.nan)
    status = np.full(t2.shape[0], RayStatus.MISSED_OBJECT, dtype=np.int8)
    optics = _Optics(camera.pose.center_lab_mm, float(n_water), float(z_object_mm))
    model = _surface_model(surface, h0_mm)
    q0 = _flat_hits(camera, p0[good], h0_mm)
    start_ok = np.all(np.isfinite(q0), axis=1)
    sel = np.flatnonzero(good)
    status[sel[~start_ok]] = RayStatus.MISSED_SURFACE
    sel = sel[start_ok]
    px[sel], status[sel], q[sel], iters = _newton(
        camera, model, optics, t2[sel], q0[start_ok], tol_px, max_iter
    )
    return PixelSolution(px.reshape(shape + (2,)), status.reshape(shape), q.reshape(shape + (3,)),
                         iters)


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
        Restored image, same dtype as the input; 0 where not valid.
    valid : (H, W) ndarray of bool
        True where the pixel was restored.
    warp_px : (H, W, 2) ndarray of float32
        Pixel ``(col, row)`` of the distorted image sampled for each truth pixel; NaN where not
        valid.
    counts : dict of str to int
        Pixels per :class:`RayStatus` name (they sum to H W): ``tir`` (totally reflected in the
        truth view, or no ray through the estimated surface reaches the target),
        ``missed_surface`` (the estimated surface is unknown there), ``out_of_view`` (the target
        is seen outside the distorted image), ``not_converged``, ``missed_object``, ``ok``.
    timings_ms : dict of str to float
        Wall times of the stages, ms: ``plan`` (geometry of the truth view; cached between
        calls), ``surface`` (spline to cell polynomials), ``solve`` (coarse warp), ``upsample``,
        ``remap``, ``total``.
    step_px : int
        Spacing of the coarse warp grid, pixels.
    """

    image: NDArray
    valid: BoolArray
    warp_px: NDArray[np.float32]
    counts: dict[str, int]
    timings_ms: dict[str, float]
    step_px: int


@dataclass(frozen=True)
class _Plan:
    """Everything about the truth view that does not depend on the surface."""

    grid_shape: tuple[int, int]  # coarse nodes (rows, cols)
    node_px: Array  # (K, 2) truth pixel of each node that sees the object plane
    node_index: NDArray[np.intp]  # (K,) flat index of those nodes in the coarse grid
    targets: Array  # (K, 3) their object points, mm
    truth_status: NDArray[np.int8]  # (rows, cols) status of every node in the truth view
    base_cols: NDArray[np.float32]  # (H, W) column of every pixel
    base_rows: NDArray[np.float32]  # (H, W) row of every pixel


_PLANS: dict[tuple, _Plan] = {}


def _plan_key(camera: PinholeCamera, h0: float, n: float, z: float, step: int) -> tuple:
    pose = camera.pose
    return (camera.width_px, camera.height_px, camera.focal_mm, camera.pixel_pitch_mm,
            pose.R.tobytes(), pose.t_mm.tobytes(), float(h0), float(n), float(z), int(step))


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
    base_cols, base_rows = np.meshgrid(np.arange(w, dtype=np.float32),
                                       np.arange(h, dtype=np.float32))
    return _Plan((nrow, ncol), node_px, np.flatnonzero(ok), truth.object_mm.reshape(-1, 3)[ok],
                 truth.status, base_cols, base_rows)


def _plan(camera: PinholeCamera, h0: float, n: float, z: float, step: int) -> _Plan:
    key = _plan_key(camera, h0, n, z, step)
    if key not in _PLANS:
        if len(_PLANS) >= 8:
            _PLANS.clear()
        _PLANS[key] = _make_plan(camera, h0, n, z, step)
    return _PLANS[key]


def _check_image(distorted: NDArray, camera: PinholeCamera) -> NDArray:
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
    if not np.all(np.isfinite(img)):
        raise WaiInputError("restore_view: image holds NaN or inf")
    return img


# Which status a cell of four nodes reports when some are invalid (most fundamental first).
_PRIORITY = np.array([0, 4, 5, 3, 2, 1], dtype=np.int8)  # rank of each RayStatus code
_BY_RANK = np.array([RayStatus.OK, RayStatus.OUT_OF_VIEW, RayStatus.NOT_CONVERGED,
                     RayStatus.MISSED_OBJECT, RayStatus.MISSED_SURFACE, RayStatus.TIR],
                    dtype=np.int8)


def _cell_status(node_status: NDArray[np.int8]) -> NDArray[np.int8]:
    """Status of each coarse cell: OK if its four nodes are, else its worst node's status."""
    r = _PRIORITY[node_status]
    worst = np.maximum(np.maximum(r[:-1, :-1], r[1:, :-1]), np.maximum(r[:-1, 1:], r[1:, 1:]))
    return _BY_RANK[worst]


def _upsample(
    disp: NDArray[np.float32], cell: NDArray[np.int8], step: int, shape: tuple[int, int]
) -> tuple[NDArray[np.float32], NDArray[np.int8]]:
    """Bilinear displacement (H, W, 2) from nodes every ``step`` px; cell status per pixel."""
    h, w = shape
    scale = np.array([[1.0 / step, 0.0, 0.0], [0.0, 1.0 / step, 0.0]])
    # Pixel (c, r) reads node coordinates (c/step, r/step): exact for steps dividing 32
    # (OpenCV interpolates at 1/32 of a source cell).
    full = cv2.warpAffine(disp, scale, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)
    status = np.repeat(np.repeat(cell, step, axis=0), step, axis=1)[:h, :w]
    return full, status


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
        raise WaiInputError(f"restore_view: warp_step_px must be a positive integer, got "
                            f"{warp_step_px!r}")
    step = int(warp_step_px)
    _check_system(h0_mm, n_water, z_object_mm)
    t = {"plan": time.perf_counter()}
    plan = _plan(camera, h0_mm, n_water, z_object_mm, step)
    t["surface"] = time.perf_counter()
    model = _surface_model(surface_est, h0_mm)
    optics = _Optics(camera.pose.center_lab_mm, float(n_water), float(z_object_mm))
    t["solve"] = time.perf_counter()
    px, st, _, _ = _newton(camera, model, optics, plan.targets[:, :2],
                               _flat_hits(camera, plan.node_px, h0_mm), DEFAULT_TOL_PX, 12)
    node_status = plan.truth_status.copy().ravel()
    node_status[plan.node_index] = st
    node_status = node_status.reshape(plan.grid_shape)
    disp = np.zeros(plan.grid_shape + (2,), dtype=np.float32)
    solved = st == RayStatus.OK
    disp.reshape(-1, 2)[plan.node_index[solved]] = px[solved] - plan.node_px[solved]
    t["upsample"] = time.perf_counter()
    shape = (camera.height_px, camera.width_px)
    full, status = _upsample(disp, _cell_status(node_status), step, shape)
    map_c = plan.base_cols + full[..., 0]
    map_r = plan.base_rows + full[..., 1]
    inside = camera.in_image(map_c, map_r)
    status = np.where((status == RayStatus.OK) & ~inside, np.int8(RayStatus.OUT_OF_VIEW), status)
    valid = status == RayStatus.OK
    t["remap"] = time.perf_counter()
    # Half-pixel border: replicate rather than blend with black.
    out = cv2.remap(img, map_c, map_r, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(img.shape)
    out[~valid] = 0
    warp = np.stack([map_c, map_r], axis=-1)
    warp[~valid] = np.nan
    t["end"] = time.perf_counter()
    names = list(t)
    timings = {a: 1e3 * (t[b] - t[a]) for a, b in zip(names[:-1], names[1:], strict=True)}
    timings["total"] = 1e3 * (t["end"] - t_start)
    return Restoration(out, valid, warp, status_counts(status), timings, step)
