"""Ray geometry shared by the renderer, the restoration and the scoring.

Frames
------
``lab``
    The global frame of the paper (its Fig. 6): origin at the projector centre, z up, millimetres.
    The mean water surface is the plane ``z = h0``.
``cam``
    A device frame (camera or projector), OpenCV convention: +z along the optical axis (the viewing
    direction), +x to the right of the image, +y down the image. Table 1 of the paper gives poses as
    ``u_cam = R u_lab + t``, so ``u_lab = R^T (u_cam - t)`` and the centre is ``-R^T t``.

The paper writes the pixel as ``[u, -f]`` (an image plane behind the centre, eq. 14) and the
back-projected ray as ``u_lab - o_lab`` (eq. 18); read together, the ray leaves the centre along
``R^T [x, y, f]``. That is the physically consistent reading used here: with Table 1's matrices it
makes camera s look straight up and the projector and camera v look up and towards +x.

Pixel coordinates are continuous ``(col, row)`` with integer values at pixel centres (the OpenCV and
scikit-image convention), so pixel ``(0, 0)`` covers ``[-0.5, 0.5)`` in both axes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def rotation_y(angle_rad: float) -> Array:
    """Rotation matrix of Table 1's form: ``[[c, 0, -s], [0, 1, 0], [s, 0, c]]``.

    Parameters
    ----------
    angle_rad : float
        Angle between the device's optical axis and the lab's +z axis, radians; positive tilts the
        axis towards +x.
    """
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


@dataclass(frozen=True)
class Pose:
    """Rigid pose ``u_cam = R u_lab + t`` (Table 1 of the paper).

    Attributes
    ----------
    R : (3, 3) ndarray
        Rotation from ``lab`` to ``cam`` axes.
    t_mm : (3,) ndarray
        Translation, mm.
    """

    R: Array
    t_mm: Array

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=float)
        t = np.asarray(self.t_mm, dtype=float)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError("pose needs R of shape (3, 3) and t of shape (3,)")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
            raise ValueError("pose rotation is not a proper rotation matrix")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t_mm", t)

    @classmethod
    def from_center(cls, R: ArrayLike, center_lab_mm: ArrayLike) -> Pose:
        """Pose from a rotation and the device centre in ``lab`` (mm)."""
        R = np.asarray(R, dtype=float)
        return cls(R, -R @ np.asarray(center_lab_mm, dtype=float))

    @property
    def center_lab_mm(self) -> Array:
        """Device centre in ``lab``, mm (eq. 16: ``-R^T t``)."""
        return -self.R.T @ self.t_mm

    @property
    def axis_lab(self) -> Array:
        """Unit optical axis (viewing direction) in ``lab``."""
        return self.R[2].copy()

    def dirs_to_lab(self, dirs_cam: ArrayLike) -> Array:
        """Rotate directions of shape (..., 3) from ``cam`` to ``lab``."""
        return np.asarray(dirs_cam, dtype=float) @ self.R

    def points_to_cam(self, points_lab_mm: ArrayLike) -> Array:
        """Map points of shape (..., 3) from ``lab`` to ``cam``, mm."""
        return np.asarray(points_lab_mm, dtype=float) @ self.R.T + self.t_mm


@dataclass(frozen=True)
class PinholeCamera:
    """Ideal pinhole device (camera or projector panel) with square pixels.

    Attributes
    ----------
    width_px, height_px : int
        Image size, pixels.
    focal_mm : float
        Focal length, mm.
    pixel_pitch_mm : float
        Pixel size on the sensor or panel, mm (square pixels).
    pose : Pose
        Pose of the device in ``lab``.
    """

    width_px: int
    height_px: int
    focal_mm: float
    pixel_pitch_mm: float
    pose: Pose

    @property
    def sensor_size_mm(self) -> tuple[float, float]:
        """Width and height of the sensor or panel, mm."""
        return self.width_px * self.pixel_pitch_mm, self.height_px * self.pixel_pitch_mm

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view, degrees (Mitsuba's ``fov`` with ``fov_axis='x'``)."""
        return float(np.degrees(2 * np.arctan(self.sensor_size_mm[0] / (2 * self.focal_mm))))

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        return self.focal_mm / self.pixel_pitch_mm

    def pixel_grid(self, step: float = 1.0) -> tuple[Array, Array]:
        """Column and row coordinates of every ``step``-th pixel centre, each of shape (h, w)."""
        cols = np.arange(0, self.width_px, step, dtype=float)
        rows = np.arange(0, self.height_px, step, dtype=float)
        return np.meshgrid(cols, rows)

    def dirs_cam(self, cols: ArrayLike, rows: ArrayLike) -> Array:
        """Unit ray directions in ``cam`` for continuous pixel coordinates, shape (..., 3)."""
        cols, rows = np.broadcast_arrays(np.asarray(cols, float), np.asarray(rows, float))
        d = np.stack(
            [
                cols - (self.width_px - 1) / 2.0,
                rows - (self.height_px - 1) / 2.0,
                np.full(cols.shape, self.focal_px),
            ],
            axis=-1,
        )
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def pixel_rays(self, cols: ArrayLike, rows: ArrayLike) -> tuple[Array, Array]:
        """Rays through continuous pixel coordinates.

        Returns
        -------
        origin_lab_mm : (3,) ndarray
            The device centre, mm (all rays share it).
        dirs_lab : (..., 3) ndarray
            Unit directions in ``lab``.
        """
        return self.pose.center_lab_mm, self.pose.dirs_to_lab(self.dirs_cam(cols, rows))

    def project(self, points_lab_mm: ArrayLike) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Project ``lab`` points of shape (..., 3) to continuous pixel coordinates.

        Returns
        -------
        cols, rows : ndarray
            Pixel coordinates, shape (...,).
        in_front : ndarray of bool
            True where the point lies in front of the device (z_cam > 0).
        """
        p = self.pose.points_to_cam(points_lab_mm)
        z = p[..., 2]
        safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
        cols = self.focal_px * p[..., 0] / safe + (self.width_px - 1) / 2.0
        rows = self.focal_px * p[..., 1] / safe + (self.height_px - 1) / 2.0
        return cols, rows, z > 0

    def in_image(self, cols: ArrayLike, rows: ArrayLike, margin_px: float = 0.0) -> NDArray:
        """True where continuous pixel coordinates fall inside the image less ``margin_px``."""
        cols, rows = np.asarray(cols), np.asarray(rows)
        lo = margin_px - 0.5
        return (
            (cols >= lo)
            & (rows >= lo)
            & (cols <= self.width_px - 0.5 - margin_px)
            & (rows <= self.height_px - 0.5 - margin_px)
        )


def normalize(v: ArrayLike) -> Array:
    """Unit vectors along the last axis."""
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def reflect(d: ArrayLike, n: ArrayLike) -> Array:
    """Mirror reflection of directions ``d`` about unit normals ``n`` (eq. 21), shape (..., 3)."""
    d = np.asarray(d, dtype=float)
    n = np.asarray(n, dtype=float)
    return d - 2.0 * np.sum(d * n, axis=-1, keepdims=True) * n


def refract(d: ArrayLike, n: ArrayLike, eta: float) -> tuple[Array, NDArray[np.bool_]]:
    """Refract unit directions ``d`` at unit normals ``n`` (vector Snell's law, eq. 20).

    Parameters
    ----------
    d : (..., 3) array_like
        Incident unit directions (travelling towards the surface).
    n : (..., 3) array_like
        Unit surface normals; either orientation is accepted.
    eta : float
        Ratio ``n_incident / n_transmitted`` (4/3 from water into air).

    Returns
    -------
    t : (..., 3) ndarray
        Transmitted unit directions; NaN where total internal reflection occurs.
    tir : (...,) ndarray of bool
        True where the ray is totally internally reflected.
    """
    d = np.asarray(d, dtype=float)
    n = np.asarray(n, dtype=float)
    cos_i = np.sum(d * n, axis=-1, keepdims=True)
    # Orient the normal against the incident ray so the formula holds for either input side.
    n = np.where(cos_i > 0, -n, n)
    cos_i = np.abs(cos_i)
    k = 1.0 - eta**2 * (1.0 - cos_i**2)
    tir = k[..., 0] < 0
    t = eta * d + (eta * cos_i - np.sqrt(np.clip(k, 0.0, None))) * n
    t[tir] = np.nan
    return t, tir


def fresnel_reflectance(cos_i: ArrayLike, eta: float) -> Array:
    """Unpolarised Fresnel reflectance for light inside a medium of relative index ``eta``
    (``n_incident / n_transmitted``, 4/3 from water to air) at incidence cosine ``cos_i``;
    1 beyond the critical angle (total internal reflection)."""
    cos_i = np.clip(np.abs(np.asarray(cos_i, dtype=float)), 0.0, 1.0)
    sin_t2 = eta**2 * (1.0 - cos_i**2)
    cos_t = np.sqrt(np.clip(1.0 - sin_t2, 0.0, None))
    rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return np.where(sin_t2 >= 1.0, 1.0, 0.5 * (rs**2 + rp**2))


def critical_angle_rad(n_water: float) -> float:
    """Critical angle for light leaving water of index ``n_water`` into air, radians."""
    return float(np.arcsin(1.0 / n_water))


def intersect_plane_z(
    origins: ArrayLike, dirs: ArrayLike, z_mm: float
) -> tuple[Array, Array]:
    """Intersect rays with the horizontal plane ``z = z_mm``.

    Returns
    -------
    points_mm : (..., 3) ndarray
        Hit points; NaN where the ray is parallel to the plane or the hit lies behind the origin.
    t_mm : (...,) ndarray
        Ray parameter of the hit (distance for unit directions); NaN likewise.
    """
    o = np.asarray(origins, dtype=float)
    d = np.asarray(dirs, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z_mm - o[..., 2]) / d[..., 2]
    t = np.where(np.isfinite(t) & (t > 0), t, np.nan)
    return o + t[..., None] * d, t


def pinhole_of(dev: Any) -> PinholeCamera:
    """A device section (:class:`~wai_core.config.DeviceConfig`) as the ideal pinhole it
    models (the rotation re-orthonormalised): the one place a :class:`PinholeCamera` is made
    from a configuration (a rig makes each of its devices once: :class:`wai_core.rig.Rig`).

    Examples
    --------
    >>> from wai_core import load_system
    >>> cam = pinhole_of(load_system("paper").camera_s)
    >>> cam.width_px, round(cam.focal_px, 3)
    (800, 320.0)
    """
    u, _, vt = np.linalg.svd(np.asarray(dev.rotation, dtype=float))
    pose = Pose(u @ vt, np.asarray(dev.translation_mm, dtype=float))
    return PinholeCamera(dev.width_px, dev.height_px, dev.focal_mm,
                         dev.sensor_width_mm / dev.width_px, pose)
