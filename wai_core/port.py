"""A pinhole behind a flat housing port, in the water: the non-central camera of a real rig.

A flat port (:mod:`wai_core.lens`) bends every ray twice, so the rays in the water share no
centre (Treibitz, Schechner, Kunz & Singh, PAMI 2012): a pinhole is wrong off axis. Every water
ray still meets the port's normal through the pinhole (the camera is *axial*: Agrawal,
Ramalingam, Taguchi & Chari, CVPR 2012), at a point that moves along that line with the ray's
angle: the optical axis for a port square to it, a line ``port_tilt_deg`` off it otherwise.
:class:`PortCamera` is that camera once a lens's principal point and distortion are undone (an
image resampled into its ideal pinhole's geometry, :class:`restoration.undistort.PinholeRemap`):
the ideal pinhole's pixels, the port's rays. It answers as
:class:`~wai_core.geometry.PinholeCamera` does (``pixel_rays``, ``project``, ``pose``, sizes),
with one origin per ray, so the stages that trace camera v take either.

Compiled kernels take the port as a (13,) vector (:func:`pack_port`: gap, thickness, the port's
index, the water's, then the port's frame; thickness 0 for a pinhole) and find a point's ray
with :func:`port_ray`.

How wrong the pinhole is here: at the paper's camera v (f = 3 mm on a 5 mm sensor, 40 degrees
to the image's corners) behind 10 mm of acrylic 10 mm from the pinhole, a pinhole fitted at the
mean water level misplaces points 10 mm above or below it by up to 0.64 px; behind 2 mm
at 0.5 mm, 0.004 px (``tests/wai_core/test_port.py`` measures it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from wai_core.geometry import PinholeCamera, Pose
from wai_core.lens import DeviceOptics, port_invert

__all__ = ["PORT_PACKED", "PortCamera", "camera_model", "pack_port", "port_ray"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PortCamera:
    """An ideal pinhole behind a flat port, in water of index ``n_water``.

    Attributes
    ----------
    optics : DeviceOptics
        The device with its port (its principal point and distortion are not used: the image
        is in the ideal pinhole's geometry).
    n_water : float

    Examples
    --------
    >>> from wai_core import load_system, with_keys
    >>> cfg = with_keys(load_system("paper"), {"camera_v.port_thickness_mm": 5.0})
    >>> cam = PortCamera(cfg.rig.optics("camera_v"), 4 / 3)
    >>> o, d = cam.pixel_rays(np.array([10.0]), np.array([20.0]))
    >>> cols, rows, ok = cam.project(o + 250.0 * d)
    >>> np.round([cols[0], rows[0]], 9).tolist(), bool(ok[0])
    ([10.0, 20.0], True)
    """

    optics: DeviceOptics
    n_water: float

    @property
    def camera(self) -> PinholeCamera:
        """The ideal pinhole behind the port."""
        return self.optics.camera

    @property
    def pose(self) -> Pose:
        return self.optics.camera.pose

    @property
    def width_px(self) -> int:
        return self.optics.camera.width_px

    @property
    def height_px(self) -> int:
        return self.optics.camera.height_px

    @property
    def focal_px(self) -> float:
        return self.optics.camera.focal_px

    @property
    def focal_mm(self) -> float:
        return self.optics.camera.focal_mm

    @property
    def pixel_pitch_mm(self) -> float:
        return self.optics.camera.pixel_pitch_mm

    @property
    def _lens_free(self) -> DeviceOptics:
        cam = self.camera
        centre = ((cam.width_px - 1) / 2.0, (cam.height_px - 1) / 2.0)
        o = self.optics
        return DeviceOptics(cam, centre, (0.0,) * 5, o.port_thickness_mm, o.port_gap_mm,
                            o.port_n, o.port_tilt_deg)

    def pixel_rays(self, cols: ArrayLike, rows: ArrayLike) -> tuple[Array, Array]:
        """Rays in the water through continuous pixel coordinates of the ideal pinhole.

        Returns
        -------
        origins_lab_mm : (..., 3) ndarray
            Where each ray leaves the port, mm.
        dirs_lab : (..., 3) ndarray
            Unit directions in the water.
        """
        return self._lens_free.pixel_rays(cols, rows, self.n_water)

    def project(self, points_lab_mm: ArrayLike) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Ideal-pinhole pixels of ``lab`` points in the water (..., 3) mm: ``cols, rows``
        (...,) and whether the point lies beyond the port, reachable."""
        return self._lens_free.project(points_lab_mm, self.n_water)

    def pixel_grid(self, step: int = 1) -> tuple[Array, Array]:
        """Pixel-centre coordinates every ``step`` pixels (the pinhole's)."""
        return self.camera.pixel_grid(step)

    def in_image(self, cols: ArrayLike, rows: ArrayLike, margin_px: float = 0.0) -> NDArray:
        """True where pixel coordinates fall inside the image less ``margin_px``."""
        return self.camera.in_image(cols, rows, margin_px)


def camera_model(optics: DeviceOptics, n_water: float) -> PinholeCamera | PortCamera:
    """The restoration's model of a device once its lens is undone: its ideal pinhole, or
    with a port the :class:`PortCamera` behind it."""
    return PortCamera(optics, float(n_water)) if optics.has_port else optics.camera


PORT_PACKED = 13
"""Length of :func:`pack_port`'s vector."""


def pack_port(camera: PinholeCamera | PortCamera) -> Array:
    """A camera's port as the (13,) vector compiled kernels take: gap (mm), thickness (mm),
    the port's and the water's index, then the port's frame (:func:`wai_core.lens.port_axes`,
    row by row: the identity for a port square to the axis); thickness 0 for a pinhole.

    Examples
    --------
    >>> from wai_core import load_system
    >>> pack_port(load_system("paper").rig.camera_v)[:4].tolist()
    [0.0, 0.0, 1.0, 1.0]
    """
    if isinstance(camera, PortCamera):
        o = camera.optics
        head = [o.port_gap_mm, o.port_thickness_mm, o.port_n, camera.n_water]
        return np.concatenate([head, o.port_frame.ravel()])
    return np.concatenate([[0.0, 0.0, 1.0, 1.0], np.eye(3).ravel()])


_port_invert = njit(cache=True, nogil=True, error_model="numpy")(port_invert)


@njit(cache=True, nogil=True, error_model="numpy")
def port_ray(port: Any, camera: Any, x: float, y: float, z: float
             ) -> tuple[float, float, float, float, float]:  # pragma: no cover
    """The ray of a port camera that reaches lab point ``(x, y, z)`` mm: where its water
    segment meets the optical axis (lab, mm) and the pixel ``(col, row)`` that sees the point.

    ``port`` (13,): :func:`pack_port` (thickness > 0); ``camera`` (15,): the packed pinhole
    (:func:`wai_core.light_paths.pack_camera`; its centre is ``-R^T t``). In the port's frame
    (``M``, the packed port's last nine numbers) the pinhole ray's slope ``tau`` comes from
    :func:`wai_core.lens.port_invert`; the water ray's slope is
    ``tau / sqrt(n_w^2 + (n_w^2 - 1) tau^2)`` (Snell across parallel faces), so it crosses the
    port's axis (its normal through the pinhole) ``rho`` over that before the point (on the
    axis: the paraxial limit). The pinhole ray ``(tau q_x / rho, tau q_y / rho, 1)``, turned
    back to ``cam`` by ``M^T``, gives the pixel.
    """
    gap, thick, n_p, n_w = port[0], port[1], port[2], port[3]
    m = port[4:13]
    r = camera
    cx_ = r[0] * x + r[1] * y + r[2] * z + r[9]
    cy_ = r[3] * x + r[4] * y + r[5] * z + r[10]
    cz_ = r[6] * x + r[7] * y + r[8] * z + r[11]
    px = m[0] * cx_ + m[1] * cy_ + m[2] * cz_
    py = m[3] * cx_ + m[4] * cy_ + m[5] * cz_
    pz = m[6] * cx_ + m[7] * cy_ + m[8] * cz_
    rho = math.sqrt(px * px + py * py)
    beyond = pz - gap - thick
    tau, _ = _port_invert(rho, beyond, gap, thick, n_p, n_w, math.sqrt, 12)
    if tau > 1e-12 and rho > 0.0:
        za = pz - rho * math.sqrt(n_w * n_w + (n_w * n_w - 1.0) * tau * tau) / tau
        ax, ay = tau * px / rho, tau * py / rho
    else:
        za = gap + thick - n_w * gap - n_w * thick / n_p
        ax, ay = 0.0, 0.0
    # The pinhole ray in cam (M^T (ax, ay, 1)), and its pixel.
    dx = m[0] * ax + m[3] * ay + m[6]
    dy = m[1] * ax + m[4] * ay + m[7]
    dz = m[2] * ax + m[5] * ay + m[8]
    col = r[12] * dx / dz + r[13]
    row = r[12] * dy / dz + r[14]
    # The port's axis in lab: R^T times its normal in cam (M's third row).
    nx = r[0] * m[6] + r[3] * m[7] + r[6] * m[8]
    ny = r[1] * m[6] + r[4] * m[7] + r[7] * m[8]
    nz = r[2] * m[6] + r[5] * m[7] + r[8] * m[8]
    # The centre -R^T t, plus za along the port's axis.
    cx = -(r[0] * r[9] + r[3] * r[10] + r[6] * r[11])
    cy = -(r[1] * r[9] + r[4] * r[10] + r[7] * r[11])
    cz = -(r[2] * r[9] + r[5] * r[10] + r[8] * r[11])
    return cx + za * nx, cy + za * ny, cz + za * nz, col, row
