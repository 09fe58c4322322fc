"""The two systems' light paths, each written once, for every stage that follows one.

**System S** (the structured light): a dot's ray leaves the projector through its real optics
(:func:`dot_rays`), meets the water surface, reflects about the surface's normal there, meets
the diffuser plane and is imaged by camera s (:func:`spots_from_hits`); :func:`spots_through`
is the whole path through a surface (or flat water), :func:`flat_spots` the flat-water path of
every dot of the grid. The forward model (:mod:`wai_core.forward`), the rig's layout
(:mod:`wai_core.layout`), the flat-water reference and the fit to the spots
(:mod:`restoration`) call these. The compiled per-frame check of a surface
(:mod:`restoration.consistency`) follows the same path one ray at a time:
:func:`reflected_spot_px` is that step in compiled form, beside its vectorised twin, and the
two agree to rounding (``tests/wai_core/test_light_paths.py``).

**System V** (the observation): camera v's ray through a pixel refracts at the surface and
meets the object plane (:func:`wai_core.optics.trace_to_object`); back, through flat water, an
object point is seen at one pixel (:func:`flat_pixel_of`).

A camera enters a compiled kernel as one packed vector (:func:`pack_camera`).

The functions take a configuration's rig (``cfg.rig``, :class:`wai_core.rig.Rig`); the rig is
built on this module, so the parameters are annotated ``Any`` rather than imported back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from wai_core.geometry import PinholeCamera, intersect_plane_z, reflect

if TYPE_CHECKING:
    from wai_core.heightfield import Heightfield

__all__ = [
    "FlatSpots", "SpotHits", "dot_rays", "flat_pixel_of", "flat_spots", "pack_camera",
    "real_spot_px", "reflect_to_diffuser", "reflected_spot_px", "spots_from_hits", "spots_through",
    "view_warp_px",
]

Array = NDArray[np.float64]
UP = np.array([0.0, 0.0, 1.0])


def pack_camera(camera: PinholeCamera) -> Array:
    """A pinhole camera as the (15,) vector compiled kernels take: its rotation ``R``
    (row-major, lab to camera), translation ``t`` (mm), focal length and image centre (px).

    Examples
    --------
    >>> from wai_core import load_system
    >>> pack_camera(load_system("paper").rig.camera_s)[9:].round(1).tolist()
    [-286.4, 0.0, 190.0, 320.0, 399.5, 299.5]
    """
    pose = camera.pose
    return np.r_[pose.R.ravel(), pose.t_mm, camera.focal_px,
                 (camera.width_px - 1) / 2.0, (camera.height_px - 1) / 2.0]


def dot_rays(rig: Any, panel_px: ArrayLike) -> tuple[Array, Array]:
    """The rays in the water of projector dots at ``panel_px`` (K, 2) panel pixels, through
    the projector's real optics: its principal point and distortion
    (:meth:`~wai_core.lens.DeviceOptics.pinhole_px`, as rays of its ideal pinhole) and its
    port (:meth:`~wai_core.lens.DeviceOptics.pixel_rays`: each ray leaves the port at its own
    point).

    Returns
    -------
    origin_mm : (3,) or (K, 3) ndarray
        The projector's centre, or behind a port where each ray enters the water, mm.
    dirs : (K, 3) ndarray
        Unit directions, lab frame.
    """
    optics = rig.optics("projector")
    if optics.has_port:
        px = np.asarray(panel_px, dtype=float)
        return optics.pixel_rays(px[:, 0], px[:, 1], rig.port_index("projector"))
    px = optics.pinhole_px(np.asarray(panel_px, dtype=float))
    return rig.projector.pixel_rays(px[:, 0], px[:, 1])


@dataclass(frozen=True)
class SpotHits:
    """Where reflected dot rays land: on the diffuser and in camera s.

    Attributes
    ----------
    diffuser_mm : (K, 3) ndarray
        The hit on the diffuser plane, mm (NaN where the reflected ray never reaches it).
    px : (K, 2) ndarray
        Camera s's continuous pixel ``(col, row)`` of the hit (NaN where there is none or it
        lies behind the camera).
    in_front : (K,) ndarray of bool
        The hit lies in front of camera s.
    """

    diffuser_mm: Array
    px: Array
    in_front: NDArray[np.bool_]


def reflect_to_diffuser(hits_mm: ArrayLike, dirs: ArrayLike, normals: ArrayLike,
                        z_h_mm: float) -> Array:
    """Where rays of directions ``dirs`` (K, 3), reflected at surface points ``hits_mm``
    (K, 3) about unit ``normals`` (K, 3), meet the diffuser plane ``z = z_h_mm``: (K, 3) mm,
    NaN where a reflected ray never reaches it ahead."""
    return intersect_plane_z(hits_mm, reflect(dirs, normals), z_h_mm)[0]


def spots_from_hits(rig: Any, hits_mm: ArrayLike, dirs: ArrayLike,
                    normals: ArrayLike) -> SpotHits:
    """Reflect rays of directions ``dirs`` (K, 3) at surface points ``hits_mm`` (K, 3) about
    unit ``normals`` (K, 3) onto the diffuser plane, and image the hits in camera s.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system
    >>> rig = load_system("paper").rig
    >>> o, d = dot_rays(rig, rig.dot_panel_px[:3])
    >>> q, _ = intersect_plane_z(o, d, rig.cfg.water.h0_mm)
    >>> hits = spots_from_hits(rig, q, d, np.tile(UP, (3, 1)))
    >>> bool(np.allclose(hits.diffuser_mm[:, 2], rig.cfg.diffuser.z_mm))
    True
    """
    on_diffuser = reflect_to_diffuser(hits_mm, dirs, normals, rig.cfg.diffuser.z_mm)
    cols, rows, front = rig.camera_s.project(on_diffuser)
    px = np.stack([cols, rows], axis=-1)
    px[~front] = np.nan
    return SpotHits(on_diffuser, px, front)


def real_spot_px(rig: Any, pinhole_px: ArrayLike) -> Array:
    """Camera s's real-image pixels (K, 2) of spots at its ideal pinhole's pixels ``pinhole_px``
    (K, 2): the diffuser point each pixel sees, projected through the camera's lens and port
    (:meth:`~wai_core.lens.DeviceOptics.project`); ``pinhole_px`` itself for an ideal camera
    (the same array); NaN where no ray reaches the point.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system, with_keys
    >>> cfg = with_keys(load_system("paper"), {"camera_s.principal_offset_px": [3.0, 0.0]})
    >>> real_spot_px(cfg.rig, np.array([[399.5, 299.5]]))
    array([[402.5, 299.5]])
    """
    optics = rig.optics("camera_s")
    px = np.asarray(pinhole_px, dtype=float)
    if optics.ideal:
        return px
    o, d = rig.camera_s.pixel_rays(px[:, 0], px[:, 1])
    points, _ = intersect_plane_z(o, d, float(rig.cfg.diffuser.z_mm))
    cols, rows, valid = optics.project(points, rig.port_index("camera_s"))
    out = np.column_stack([cols, rows])
    out[~valid] = np.nan
    return out


def spots_through(rig: Any, surface: Heightfield | None, panel_px: ArrayLike) -> Array:
    """Camera-s pixels (K, 2) where the dots at ``panel_px`` (K, 2) land after reflecting off
    ``surface`` (absolute heights, mm; None: flat water at the rig's ``h0``); NaN where a ray
    misses the surface, the diffuser or camera s's front."""
    o, d = dot_rays(rig, panel_px)
    if surface is None:
        q, _ = intersect_plane_z(o, d, rig.cfg.water.h0_mm)
        n = np.broadcast_to(UP, q.shape)
        ok = np.isfinite(q[:, 0])
    else:
        q, ok, n = surface.intersect_normals(o, d)
    px = spots_from_hits(rig, q, d, n).px
    px[~ok] = np.nan
    return px


@dataclass(frozen=True)
class FlatSpots:
    """The flat-water path of every dot of the grid (:func:`flat_spots`).

    Attributes
    ----------
    dirs : (G, 3) ndarray
        Each dot's ray direction from the projector (unit, lab frame).
    water_mm, diffuser_mm : (G, 3) ndarray
        Where each dot's ray meets the water at ``h0`` and, reflected, the diffuser, mm.
    px : (G, 2) ndarray
        Camera s's pixel of each spot (NaN behind it).
    upward : (G,) ndarray of bool
        The dot's ray goes up (it meets the water at all).
    in_front : (G,) ndarray of bool
        The spot lies in front of camera s.
    """

    dirs: Array
    water_mm: Array
    diffuser_mm: Array
    px: Array
    upward: NDArray[np.bool_]
    in_front: NDArray[np.bool_]

    def on_diffuser(self, rect_mm: Array, margin_mm: float = 0.0) -> NDArray[np.bool_]:
        """(G,) bool: the spots on the diffuser's extent ``[[x0, x1], [y0, y1]]`` (mm) grown
        by ``margin_mm``."""
        x, y = self.diffuser_mm[:, 0], self.diffuser_mm[:, 1]
        with np.errstate(invalid="ignore"):
            return ((x >= rect_mm[0, 0] - margin_mm) & (x <= rect_mm[0, 1] + margin_mm)
                    & (y >= rect_mm[1, 0] - margin_mm) & (y <= rect_mm[1, 1] + margin_mm))


def flat_spots(rig: Any, panel_px: Array | None = None) -> FlatSpots:
    """Every dot's path through flat water at the rig's ``h0``: projector (real optics) ->
    water -> mirror reflection about the vertical -> diffuser -> camera s. Panel -> camera s
    is then a plane projective map (a homography) for a pinhole projector; behind a port, not
    quite. ``panel_px`` (K, 2): those panel positions' paths instead of the dots' (e.g. grid
    nodes past the panel's edge, :func:`wai_core.pattern.grid_panel_px`)."""
    o, d = dot_rays(rig, rig.dot_panel_px if panel_px is None else panel_px)
    q, _ = intersect_plane_z(o, d, rig.cfg.water.h0_mm)
    hits = spots_from_hits(rig, q, d, UP)
    return FlatSpots(d, q, hits.diffuser_mm, hits.px, d[:, 2] > 0, hits.in_front)


@njit(cache=True, nogil=True, error_model="numpy")
def reflected_spot_px(x, y, z, dx, dy, dz, hx, hy, z_h, camera):  # pragma: no cover
    """:func:`spots_from_hits` for one ray, compiled, with the vectorised steps' expressions in
    their order: the ray of unit direction ``(dx, dy, dz)`` at the surface point ``(x, y, z)``
    whose slopes are ``(hx, hy)``, reflected onto the diffuser plane ``z = z_h`` (NaN where
    the reflected ray never reaches it ahead) and imaged by the packed camera ``camera``
    (:func:`pack_camera`); ``(col, row)``, NaN behind the camera."""
    norm = math.sqrt(hx * hx + hy * hy + 1.0)
    nx, ny, nz = -hx / norm, -hy / norm, 1.0 / norm
    dot = 2.0 * (dx * nx + dy * ny + dz * nz)
    rx, ry, rz = dx - dot * nx, dy - dot * ny, dz - dot * nz
    s = (z_h - z) / rz
    if not (np.isfinite(s) and s > 0.0):
        s = np.nan
    sx, sy, sz = x + s * rx, y + s * ry, z + s * rz
    cx = sx * camera[0] + sy * camera[1] + sz * camera[2] + camera[9]
    cy = sx * camera[3] + sy * camera[4] + sz * camera[5] + camera[10]
    cz = sx * camera[6] + sy * camera[7] + sz * camera[8] + camera[11]
    if not cz > 0.0:  # behind the camera (or NaN)
        return np.nan, np.nan
    safe = cz if abs(cz) > 1e-12 else 1e-12
    return camera[12] * cx / safe + camera[13], camera[12] * cy / safe + camera[14]


def flat_pixel_of(
    rig: Any, points_mm: ArrayLike, iterations: int = 5
) -> tuple[Array, Array]:
    """The camera-v pixel that sees object-plane points through flat water at ``h0``.

    The inverse of :func:`wai_core.optics.trace_to_object` with ``surface=None``: the ray from
    the camera centre ``C`` to a point ``P`` refracts once, at a point of the plane ``z = h0``
    on the segment below ``C``-``P`` at radial distance ``r`` from ``C``, where Snell's law
    ``n r / sqrt(r^2 + a^2) = (d - r) / sqrt((d - r)^2 + b^2)`` holds (``a``: the camera's
    depth, ``b``: the object's height above the water, ``d``: the horizontal distance). In the
    tangent of the air-side angle ``v = (d - r) / b``, ``g(v) = a v / sqrt(n^2 + (n^2 - 1)
    v^2) + b v - d`` is increasing and concave, so Newton's method from a lower bound of its
    root climbs to it without overshooting, and past the first steps ``g`` is nearly linear
    (the water's term saturates): a few steps reach float64 rounding.

    Parameters
    ----------
    rig : Any
    points_mm : (..., 3) array_like
        Points above the water (NaN passes through), mm.
    iterations : int
        Newton steps.

    Returns
    -------
    cols, rows : (...,) ndarray
        Continuous pixel coordinates (may lie outside the image), NaN where the point is NaN.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system
    >>> from wai_core.optics import trace_to_object
    >>> cfg = load_system("paper")
    >>> p = trace_to_object(cfg.rig.camera_v, None, cfg.water.h0_mm, cfg.water.n_water,
    ...                     cfg.object_z_mm, np.array([10.0, 400.0]),
    ...                     np.array([20.0, 300.0])).object_mm
    >>> np.round(np.stack(flat_pixel_of(cfg.rig, p)), 6)
    array([[ 10., 400.],
           [ 20., 300.]])
    """
    cam = rig.camera_v
    p = np.asarray(points_mm, dtype=float)
    flat = np.ascontiguousarray(p.reshape(-1, 3))
    out = np.empty((flat.shape[0], 2))
    _flat_pixels(flat, cam.pose.center_lab_mm, rig.cfg.water.h0_mm, rig.cfg.water.n_water,
                 pack_camera(cam), int(iterations), out)
    return out[:, 0].reshape(p.shape[:-1]), out[:, 1].reshape(p.shape[:-1])


def view_warp_px(rig: Any, hits_mm: ArrayLike, normals: ArrayLike, dirs: ArrayLike,
                 valid: ArrayLike, iterations: int = 5) -> NDArray[np.float32]:
    """Camera v's rays, met by the water at ``hits_mm`` with unit ``normals``, refracted into
    the air (eq. 20), carried to the object plane and taken back to the pixel that sees that
    object point through flat water (:func:`flat_pixel_of`): the exact warp between the
    wavy and the flat-water views, one compiled pass per ray.

    Parameters
    ----------
    rig : Any
    hits_mm, normals, dirs : (..., 3) array_like
        The rays' hits on the surface (mm), the surface's unit normals there and the rays'
        unit directions (in the water, towards the surface).
    valid : (...,) array_like of bool
        The rays that hit the surface.
    iterations : int
        Newton steps of the flat-water inverse.

    Returns
    -------
    (..., 2) ndarray of float32
        The flat-water view's (col, row) of each ray; NaN where it is invalid, totally
        reflected or misses the object plane.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system
    >>> rig = load_system("paper").rig
    >>> o, d = rig.camera_v.pixel_rays(np.array([100.0, 400.0]), np.array([50.0, 300.0]))
    >>> t = (rig.cfg.water.h0_mm - o[2]) / d[:, 2]
    >>> hits = o + t[:, None] * d
    >>> up = np.tile([0.0, 0.0, 1.0], (2, 1))
    >>> view_warp_px(rig, hits, up, d, np.ones(2, bool)).round(3).tolist()
    [[100.0, 50.0], [400.0, 300.0]]
    """
    d = np.asarray(dirs, dtype=float)
    shape = d.shape[:-1]
    out = np.empty((int(np.prod(shape, dtype=np.int64)), 2), dtype=np.float32)
    cfg = rig.cfg
    _view_warp(np.ascontiguousarray(np.broadcast_to(hits_mm, d.shape).reshape(-1, 3), float),
               np.ascontiguousarray(np.reshape(normals, (-1, 3)), float),
               np.ascontiguousarray(d.reshape(-1, 3)),
               np.ascontiguousarray(np.reshape(valid, -1), bool), cfg.water.n_water,
               cfg.object_z_mm, rig.camera_v.pose.center_lab_mm, cfg.water.h0_mm,
               pack_camera(rig.camera_v), int(iterations), out)
    return out.reshape(*shape, 2)


@njit(cache=True, nogil=True, error_model="numpy")
def _flat_pixel(px, py, pz, c, h0, n, camera, iterations):  # pragma: no cover
    """:func:`flat_pixel_of` for one point ``(px, py, pz)``: (col, row)."""
    dx, dy = px - c[0], py - c[1]
    d = math.hypot(dx, dy)
    a = h0 - c[2]
    b = pz - h0
    k = n * n - 1.0
    # Lower bounds of the root: the tangent at 0, and the water term at its supremum.
    v1 = d / (a / n + b)
    v2 = (d - a / math.sqrt(k)) / b
    v = np.nan if (v1 != v1 or v2 != v2) else max(v1, v2)
    for _ in range(iterations):
        q = math.sqrt(n * n + k * v * v)
        g = a * v / q + b * v - d
        v = v - g / (a * n * n / q**3 + b)
    r = d - b * v
    scale = r / d if d > 0 else r
    qx, qy, qz = c[0] + scale * dx, c[1] + scale * dy, h0
    cx = qx * camera[0] + qy * camera[1] + qz * camera[2] + camera[9]
    cy = qx * camera[3] + qy * camera[4] + qz * camera[5] + camera[10]
    cz = qx * camera[6] + qy * camera[7] + qz * camera[8] + camera[11]
    safe = cz if abs(cz) > 1e-12 else 1e-12
    return camera[12] * cx / safe + camera[13], camera[12] * cy / safe + camera[14]


@njit(cache=True, nogil=True, error_model="numpy")
def _flat_pixels(points, c, h0, n, camera, iterations, out):  # pragma: no cover
    for i in range(points.shape[0]):
        out[i, 0], out[i, 1] = _flat_pixel(points[i, 0], points[i, 1], points[i, 2], c, h0, n,
                                           camera, iterations)


@njit(cache=True, nogil=True, error_model="numpy")
def _view_warp(hits, normals, dirs, valid, n, object_z, c, h0, camera, iterations,
               out):  # pragma: no cover
    for i in range(dirs.shape[0]):
        out[i, 0] = out[i, 1] = np.nan
        if not valid[i]:
            continue
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        cos_i = dx * nx + dy * ny + dz * nz
        if cos_i > 0:  # the normal against the ray (geometry.refract)
            nx, ny, nz, cos_i = -nx, -ny, -nz, -cos_i
        cos_i = abs(cos_i)
        k = 1.0 - n * n * (1.0 - cos_i * cos_i)
        if not k >= 0.0:  # totally reflected
            continue
        m = n * cos_i - math.sqrt(k)
        tx, ty, tz = n * dx + m * nx, n * dy + m * ny, n * dz + m * nz
        t = (object_z - hits[i, 2]) / tz
        if not (np.isfinite(t) and t > 0):
            continue
        px, py = hits[i, 0] + t * tx, hits[i, 1] + t * ty
        pz = hits[i, 2] + t * tz
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
            continue
        col, row = _flat_pixel(px, py, pz, c, h0, n, camera, iterations)
        out[i, 0], out[i, 1] = col, row
