"""The inverse map: which pixel of camera v sees a given object point through a given surface.

:func:`solve_pixels` (and :func:`find_pixels`, its pixels and success mask only) solves it by
Newton's method, one compiled loop over the targets in chunks that the restoration's threads
share (:mod:`restoration.reverse_trace._kernels`). The unknown is the surface point ``q = (x,
y)`` where the ray crosses the water rather than the pixel itself: for a candidate ``q`` the
ray from the camera centre to ``(x, y, h(x, y))`` and the normal there are explicit, so each
Newton step needs one surface evaluation instead of a nested ray-surface intersection; the
pixel is the projection of ``q``. Newton drives the angle between the refracted ray and the
direction to the target to zero (``_kernels._residual``, which carries its Jacobian in ``q``
along). It inverts :func:`wai_core.optics.trace_to_object`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from restoration.reverse_trace._kernels import newton_chunk
from restoration.reverse_trace._surface import SplinePatches, _FlatWater, _surface_model
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera, intersect_plane_z
from wai_core.heightfield import Heightfield
from wai_core.light_paths import pack_camera
from wai_core.optics import RayStatus, _check_system
from wai_core.parallel import restore_threads, run_chunks
from wai_core.port import pack_port

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Newton stops when the pixel moves less than this between iterates, pixels.
DEFAULT_TOL_PX = 1e-3
#: Step halvings tried when a Newton step leaves the surface or hits TIR.
_MAX_HALVINGS = 4
#: Pulls of a TIR start towards the nadir, and the factor of each.
_MAX_PULLS, _PULL = 8, 0.97
_PULLS = _PULL ** np.arange(1, _MAX_PULLS + 1)
_FRACS = 0.5 ** np.arange(_MAX_HALVINGS + 1)  # the full step first
# The table arguments of a flat-water solve (ignored by the kernel).
_NO_SURFACE = (np.full((1, 16, 1), np.nan), np.zeros(1, bool), np.zeros(2), np.zeros(2))


@dataclass(frozen=True)
class _Optics:
    """What the forward map from a surface point needs: camera centre, index, object plane."""

    center: Array
    n_water: float
    z_object: float


def _newton(
    camera: PinholeCamera,
    model: _FlatWater | SplinePatches,
    optics: _Optics,
    targets: Array,
    q0: Array,
    tol_px: float,
    max_iter: int,
) -> tuple[Array, NDArray[np.int8], Array, int]:
    """Solve targets (N, 2) mm from surface points ``q0`` (N, 2) mm; see :func:`solve_pixels`.

    Per target (the compiled loop of :func:`~restoration.reverse_trace._kernels.newton_chunk`,
    in chunks shared by the restoration's threads):
    a start beyond the edge of Snell's window (TIR, or an air ray below the horizon) is first
    pulled towards the nadir, the mildest of :data:`_MAX_PULLS` pulls that gets out kept. Each
    Newton step must then land on the known surface, without TIR, and shrink ``|r|``, else the
    longest of the step halved up to :data:`_MAX_HALVINGS` times that does; a target with no
    such step is out of reach (beyond the wavy window's edge) and stops with the status of its
    shortest try. A step whose pixel moves less than ``tol_px`` is taken on the surface's
    tangent plane without a new evaluation (what remains after it is second order) and ends
    the iteration.

    Returns pixels (N, 2), status (N,), surface points (N, 3) mm and the iterations run.
    """
    if isinstance(model, _FlatWater):
        flat, h0, surf = True, model.h0, _NO_SURFACE
    else:
        flat, h0, surf = False, 0.0, (model.table, model.cell_ok, model.x, model.y)
    proj = pack_camera(camera)
    targets = np.ascontiguousarray(targets, dtype=float)
    n = len(targets)
    px, q = np.full((n, 2), np.nan), np.full((n, 3), np.nan)
    status, iters = np.empty(n, np.int8), np.zeros(n, np.int64)
    # A few chunks per thread: targets near the edge of Snell's window take more steps, and a
    # thread that finishes its run early takes the next.
    run_chunks(
        newton_chunk, max(min(4 * restore_threads(), n), 1), flat, h0, *surf,
        np.r_[optics.center, optics.n_water, optics.z_object], pack_port(camera), proj, _PULLS,
        _FRACS, float(tol_px), int(max_iter), targets, np.ascontiguousarray(q0, dtype=float),
        px, status, q, iters,
    )
    return px, status, q, (int(iters.max()) if n else 0)


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
