"""Surface normals of the water-air interface from structured-light correspondences (section 3.2.1).

Each feature ``k`` pairs a projector ray (its dot's panel position) with the spot it lights on
the diffuser (its detected pixel in camera s). The ray leaves the projector along ``v_p``, meets
the surface at ``q`` and reflects towards the spot ``s``. The law of reflection (eq. 4) makes the
normal parallel to ``v_p - v`` with ``v = (s - q) / |s - q|``: eq. 6-7 state it as the null space
of a skew matrix, :func:`reflection_normals` uses the closed form.

All positions are in the ``lab`` frame (origin at the projector centre, z up), mm; directions
are unit vectors. Normals point up, into the air.

:func:`reflection_slopes` is the per-pass step of the surface refinement: the three steps
:func:`points_on_rays`, :func:`reflection_normals` and :func:`slopes_from_normals` fused into
one compiled loop, with the same arithmetic.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from wai_core.errors import RestorationFailed, WaiInputError
from wai_core.geometry import PinholeCamera, intersect_plane_z

Array = NDArray[np.float64]


def _as_points(a: ArrayLike, width: int, name: str) -> Array:
    """``a`` as a finite float array of shape (K, width), or a WaiInputError naming ``name``."""
    arr = np.asarray(a, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != width:
        raise WaiInputError(f"{name} must have shape (K, {width}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise WaiInputError(f"{name} holds NaN or inf")
    return arr


def spots_on_diffuser(
    spot_px: ArrayLike, camera_s: PinholeCamera, z_h_mm: float
) -> Array:
    """Back-project detected spot pixels of camera s onto the diffuser plane ``z = z_h``.

    Parameters
    ----------
    spot_px : (K, 2) array_like
        Continuous pixel coordinates ``(col, row)`` of the spots in camera s.
    camera_s : PinholeCamera
        The camera that images the diffuser from below.
    z_h_mm : float
        Height of the diffuser plane, mm.

    Returns
    -------
    (K, 3) ndarray
        Spot positions ``s_k`` on the diffuser, mm.
    """
    px = _as_points(spot_px, 2, "spot_px")
    origin, dirs = camera_s.pixel_rays(px[:, 0], px[:, 1])
    points, _ = intersect_plane_z(origin, dirs, z_h_mm)
    if not np.all(np.isfinite(points)):
        raise WaiInputError("spots_on_diffuser: some camera-s rays never reach the diffuser plane")
    return points


def projector_rays(panel_px: ArrayLike, projector: PinholeCamera) -> tuple[Array, Array]:
    """Projector rays of the features (the calibration of section 3.2.1).

    Parameters
    ----------
    panel_px : (K, 2) array_like
        Panel pixel coordinates ``(col, row)`` of the dots.
    projector : PinholeCamera
        The projector as a pinhole device.

    Returns
    -------
    origin_mm : (3,) ndarray
        The projector centre ``o_p`` in ``lab``, mm.
    dirs : (K, 3) ndarray
        Unit directions ``v_p`` in ``lab``.
    """
    px = _as_points(panel_px, 2, "panel_px")
    return projector.pixel_rays(px[:, 0], px[:, 1])


def ray_origins(origin_mm: ArrayLike, n: int) -> Array:
    """Rays' origins as a contiguous (n, 3) array, mm: one origin (3,) for all (a pinhole
    projector's centre), or each ray's own (n, 3) (a projector behind a port: its rays share no
    centre).

    Examples
    --------
    >>> ray_origins([0.0, 0.0, 0.0], 2).tolist()
    [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    """
    o = np.asarray(origin_mm, dtype=float)
    if o.shape not in ((3,), (n, 3)):
        raise WaiInputError(f"origin_mm must have shape (3,) or ({n}, 3), got {o.shape}")
    return np.ascontiguousarray(np.broadcast_to(o, (n, 3)))


def points_on_rays(origin_mm: ArrayLike, dirs: ArrayLike, heights_mm: ArrayLike) -> Array:
    """Points of given heights on upward rays (eq. 3, with ``h0`` generalised to any height).

    Parameters
    ----------
    origin_mm : (3,) or (K, 3) array_like
        The rays' common origin, or each ray's own (:func:`ray_origins`), mm.
    dirs : (K, 3) array_like
        Ray directions (need not be unit); their z components must be positive.
    heights_mm : float or (K,) array_like
        Height ``z`` of the wanted point on each ray, mm.

    Returns
    -------
    (K, 3) ndarray
        ``q_k = o + (h_k - o_z) / v_z * v``, mm.
    """
    d = _as_points(dirs, 3, "dirs")
    o = ray_origins(origin_mm, len(d))
    if np.any(d[:, 2] <= 0):
        raise WaiInputError("points_on_rays: every ray must point upwards (positive z component)")
    h = np.broadcast_to(np.asarray(heights_mm, dtype=float), d.shape[:1])
    return o + ((h - o[:, 2]) / d[:, 2])[:, None] * d


def reflected_dirs(q_mm: ArrayLike, s_mm: ArrayLike) -> Array:
    """Unit directions ``v = (s - q) / |s - q|`` of the reflected rays, shape (K, 3)."""
    q = _as_points(q_mm, 3, "q_mm")
    s = _as_points(s_mm, 3, "s_mm")
    if q.shape != s.shape:
        raise WaiInputError(f"q_mm {q.shape} and s_mm {s.shape} must have the same shape")
    v = s - q
    length = np.linalg.norm(v, axis=1, keepdims=True)
    if np.any(length <= 0):
        raise RestorationFailed("reflected_dirs: a reflection point coincides with its spot")
    return v / length


def normal_matrix(v_p: ArrayLike, v: ArrayLike) -> Array:
    """The matrices ``A`` of eq. 7, whose null space is the surface normal.

    ``A`` is the skew (cross-product) matrix of ``w = v_p - v``: ``A N = w x N``, which vanishes
    exactly for normals parallel to ``w`` (eq. 4).

    Parameters
    ----------
    v_p, v : (K, 3) array_like
        Unit incident (projector) and reflected directions.

    Returns
    -------
    (K, 3, 3) ndarray
    """
    w = _as_points(v_p, 3, "v_p") - _as_points(v, 3, "v")
    a, b, c = w[:, 0], w[:, 1], w[:, 2]
    zero = np.zeros_like(a)
    rows = [
        np.stack([zero, -c, b], axis=-1),
        np.stack([c, zero, -a], axis=-1),
        np.stack([-b, a, zero], axis=-1),
    ]
    return np.stack(rows, axis=1)


def reflection_normals(v_p: ArrayLike, q_mm: ArrayLike, s_mm: ArrayLike) -> Array:
    """Surface normals that reflect the projector rays at ``q`` onto the spots ``s``.

    The closed-form null space of eq. 7: ``N = (v_p - v) / |v_p - v|``, oriented up.

    Parameters
    ----------
    v_p : (K, 3) array_like
        Unit projector-ray directions.
    q_mm : (K, 3) array_like
        Assumed reflection points on the rays, mm.
    s_mm : (K, 3) array_like
        Spots on the diffuser, mm.

    Returns
    -------
    (K, 3) ndarray
        Unit normals with ``N_z > 0`` (pointing into the air).
    """
    vp = _as_points(v_p, 3, "v_p")
    w = vp - reflected_dirs(q_mm, s_mm)
    length = np.linalg.norm(w, axis=1, keepdims=True)
    # |v_p - v| = 2 cos(incidence): zero only for a grazing ray, which fixes no normal.
    if np.any(length < 1e-9):
        raise RestorationFailed(
            "reflection_normals: a reflected ray is parallel to its incident ray"
        )
    n = w / length
    return n * np.where(n[:, 2:3] < 0, -1.0, 1.0)


def slopes_from_normals(normals: ArrayLike) -> Array:
    """Surface slopes ``(dz/dx, dz/dy) = (-N_x / N_z, -N_y / N_z)``, shape (K, 2), dimensionless.

    Parameters
    ----------
    normals : (K, 3) array_like
        Unit normals; ``N_z`` must be non-zero (a surface ``z = h(x, y)`` is never vertical).
    """
    n = _as_points(normals, 3, "normals")
    if np.any(np.abs(n[:, 2]) < 1e-9):
        raise RestorationFailed("slopes_from_normals: a normal is horizontal (vertical surface)")
    return -n[:, :2] / n[:, 2:3]


# Why _reflection_kernel stopped (0: it did not), with the messages of the NumPy steps.
_KERNEL_ERRORS = {
    1: "points_on_rays: every ray must point upwards (positive z component)",
    2: "reflected_dirs: a reflection point coincides with its spot",
    3: "reflection_normals: a reflected ray is parallel to its incident ray",
    4: "slopes_from_normals: a normal is horizontal (vertical surface)",
}


def kernel_error(code: int) -> Exception:
    """The exception of a :data:`_KERNEL_ERRORS` code: rays that do not point up are the
    caller's geometry (:class:`~wai_core.errors.WaiInputError`); the other codes are a frame's
    degenerate reflections (:class:`~wai_core.errors.RestorationFailed`)."""
    return (WaiInputError if code == 1 else RestorationFailed)(_KERNEL_ERRORS[code])


@njit(cache=True, nogil=True, error_model="numpy")
def _reflection_kernel(origin, dirs, spots, heights, q, normals, slopes):  # pragma: no cover
    """Fill ``q``, ``normals`` (K, 3) and ``slopes`` (K, 2) row by row; return 0 or the code
    of the first failed check (:data:`_KERNEL_ERRORS`). Expressions as in the NumPy steps, in
    the same order, so the results are the same to the last bit."""
    for k in range(heights.size):
        ox, oy, oz = origin[k, 0], origin[k, 1], origin[k, 2]
        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        if not dz > 0.0:
            return 1
        t = (heights[k] - oz) / dz
        qx, qy, qz = ox + t * dx, oy + t * dy, oz + t * dz
        vx, vy, vz = spots[k, 0] - qx, spots[k, 1] - qy, spots[k, 2] - qz
        length = math.sqrt(vx * vx + vy * vy + vz * vz)
        if not length > 0.0:
            return 2
        wx, wy, wz = dx - vx / length, dy - vy / length, dz - vz / length
        length = math.sqrt(wx * wx + wy * wy + wz * wz)
        if length < 1e-9:
            return 3
        nx, ny, nz = wx / length, wy / length, wz / length
        if nz < 0.0:
            nx, ny, nz = nx * -1.0, ny * -1.0, nz * -1.0
        if abs(nz) < 1e-9:
            return 4
        q[k, 0], q[k, 1], q[k, 2] = qx, qy, qz
        normals[k, 0], normals[k, 1], normals[k, 2] = nx, ny, nz
        slopes[k, 0], slopes[k, 1] = -nx / nz, -ny / nz
    return 0


def reflection_slopes(
    origin_mm: Array, dirs: Array, spots_mm: Array, heights_mm: Array
) -> tuple[Array, Array, Array]:
    """Reflection points, normals and slopes for assumed heights on the projector rays.

    The same as ``q = points_on_rays(origin_mm, dirs, heights_mm)``, ``n =
    reflection_normals(dirs, q, spots_mm)``, ``slopes_from_normals(n)`` (and the same errors),
    in one compiled pass: the surface refinement runs it for every pass of every anchor probe.

    Parameters
    ----------
    origin_mm : (3,) or (K, 3) ndarray
        The projector centre, or each ray's origin (:func:`ray_origins`), mm.
    dirs : (K, 3) ndarray
        Unit projector-ray directions ``v_p`` (positive z components).
    spots_mm : (K, 3) ndarray
        Spots on the diffuser, mm.
    heights_mm : (K,) ndarray
        Assumed height of each reflection point, mm.

    Returns
    -------
    q : (K, 3) ndarray
        Reflection points, mm.
    normals : (K, 3) ndarray
        Unit normals, pointing up.
    slopes : (K, 2) ndarray
        ``(dz/dx, dz/dy)``, dimensionless.
    """
    n = len(heights_mm)
    q, normals, slopes = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 2))
    code = _reflection_kernel(
        ray_origins(origin_mm, n), np.ascontiguousarray(dirs, dtype=float),
        np.ascontiguousarray(spots_mm, dtype=float), np.ascontiguousarray(heights_mm, float),
        q, normals, slopes,
    )
    if code:
        raise kernel_error(code)
    return q, normals, slopes
