"""A real device's optics: principal point, Brown-Conrady distortion and a flat housing port.

The geometric model (:class:`wai_core.geometry.PinholeCamera`) is an ideal pinhole in the water.
:class:`DeviceOptics` adds what a real camera or projector does, from the renderer-only keys of
:class:`wai_core.config.DeviceConfig`:

``principal_offset_px``
    The principal point ``(c_x, c_y) = ((W - 1) / 2, (H - 1) / 2) + offset``, pixels.
``distortion``
    ``(k1, k2, p1, p2, k3)``, OpenCV's definition: an undistorted normalised point
    ``(x, y) = (X / Z, Y / Z)`` (``cam`` frame) maps to the image point
    ``(c_x + f x_d, c_y + f y_d)``, with ``r^2 = x^2 + y^2`` and

    .. math::

        x_d = x (1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + 2 p_1 x y + p_2 (r^2 + 2 x^2)

        y_d = y (1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + p_1 (r^2 + 2 y^2) + 2 p_2 x y

``port_thickness_mm``, ``port_gap_mm``, ``port_n``
    A flat window perpendicular to the optical axis: air from the pinhole to ``z_cam = gap``,
    the port's material to ``z_cam = gap + thickness``, then the water. Thickness 0: no housing,
    the pinhole sits in the water (the geometric model's device).
``port_tilt_deg``
    ``(a_x, a_y)``: the port's normal tilted off the optical axis, towards ``+x_cam`` by
    ``a_x`` and towards ``+y_cam`` by ``a_y`` (the normal is ``(tan a_x, tan a_y, 1)``
    normalised; a housing whose window is not square to the lens). The gap is then measured
    along that normal. The port's maps are those of an untilted port in the port's own frame
    (:func:`port_axes`: its z axis the normal), where the rays are again symmetric about an
    axis through the pinhole.

A pixel's ray: the pixel minus the principal point over the focal length is the distorted
normalised point; undistorting it (Newton's method on the map above) gives the pinhole ray's
direction ``(x, y, 1)``, in air behind a port, which refracts at the port's two faces (Snell's
law, ``n sin(theta)`` kept: the faces are parallel, so ``sin(theta_air) = n_port sin(theta_port)
= n_water sin(theta_water)``). A point's projection inverts that: the refraction point is found
by Newton's method on the pinhole ray's slope (the port is axially symmetric), then the
distortion is applied in closed form.

The maps are written once, in arithmetic that works on NumPy arrays and on Dr.Jit arrays alike
(the ``sqrt`` and ``where`` they need are passed in), so the renderer (:mod:`mitsuba_wai.lens`)
traces the same model the restoration and a calibration can use. With every key at its default
the maps are :class:`~wai_core.geometry.PinholeCamera`'s, bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wai_core.distortion import (
    NEWTON_STEPS,
    distort,
    distortion_one_to_one,
    undistort,
)
from wai_core.geometry import PinholeCamera, pinhole_of

Array = NDArray[np.float64]

__all__ = [
    "DeviceOptics",
    "port_axes",
    "port_invert",
    "port_pinhole_xy",
    "port_refract",
    "port_transmittance",
]

def port_axes(tilt_deg: tuple[float, float]) -> Array:
    """The port's frame for a tilt ``(a_x, a_y)``, deg: a (3, 3) rotation whose rows are the
    port frame's axes in ``cam`` (``v_port = M v_cam``), its third row the port's normal
    ``(tan a_x, tan a_y, 1)`` normalised; the smallest rotation that takes the optical axis
    there (about ``axis x normal``). The identity, exactly, for no tilt.

    Examples
    --------
    >>> m = port_axes((10.0, 0.0))
    >>> np.round(m[2], 6).tolist()  # the normal, 10 degrees towards +x
    [0.173648, 0.0, 0.984808]
    >>> bool(np.allclose(m @ m.T, np.eye(3)))
    True
    """
    ax, ay = (float(v) for v in tilt_deg)
    if ax == 0.0 and ay == 0.0:
        return np.eye(3)
    n = np.array([np.tan(np.radians(ax)), np.tan(np.radians(ay)), 1.0])
    n /= np.linalg.norm(n)
    # Rodrigues: the rotation about k = z x n (unit) by the angle between z and n takes z to n;
    # its transpose takes n to z, so its rows are the port's axes in cam.
    k = np.array([-n[1], n[0], 0.0])
    sin = np.linalg.norm(k)
    k /= sin
    cos = n[2]
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    to_n = np.eye(3) + sin * kx + (1.0 - cos) * (kx @ kx)
    return to_n.T


def port_refract(
    origin: tuple[Any, Any, Any], direction: tuple[Any, Any, Any], gap_mm: float,
    thickness_mm: float, n_port: float, n_water: float, sqrt: Callable[[Any], Any],
) -> tuple[tuple[Any, Any, Any], tuple[Any, Any, Any], Any]:
    """A ray in the housing's air through the flat port into the water (``cam`` frame).

    Parameters
    ----------
    origin : 3-tuple of arrays, (...,) each
        Ray origin inside the housing (``z < gap_mm``), mm.
    direction : 3-tuple of arrays
        Unit direction in air, towards the port (``z > 0``).
    gap_mm, thickness_mm : float
        The port's inner face at ``z = gap_mm``, its outer face ``thickness_mm`` beyond.
    n_port, n_water : float
        Refractive indices (the air's is 1).
    sqrt : callable
        Square root of the array type (``numpy.sqrt`` or ``drjit.sqrt``).

    Returns
    -------
    exit_point : 3-tuple of arrays
        Where the ray leaves the outer face into the water, mm.
    water_direction : 3-tuple of arrays
        Unit direction in the water.
    cos_port : array
        Cosine of the ray's angle to the axis inside the port (for the Fresnel terms).

    Notes
    -----
    At a face normal to z, Snell's law keeps the transverse component times the index:
    ``n_1 d_1,xy = n_2 d_2,xy``, ``d_2,z = sqrt(1 - |d_2,xy|^2)``.
    """
    ox, oy, oz = origin
    dx, dy, dz = direction
    s = (gap_mm - oz) / dz  # to the inner face
    px, py = ox + s * dx, oy + s * dy
    sin2 = dx * dx + dy * dy
    cos_port = sqrt(1.0 - sin2 / n_port**2)
    # Across the port: transverse component d_xy / n_port, axial cos_port.
    s = thickness_mm / cos_port
    px, py = px + s * dx / n_port, py + s * dy / n_port
    cos_water = sqrt(1.0 - sin2 / n_water**2)
    exit_point = (px, py, px * 0.0 + (gap_mm + thickness_mm))
    return exit_point, (dx / n_water, dy / n_water, cos_water), cos_port


def port_invert(
    rho_mm: Any, beyond_mm: Any, gap_mm: float, thickness_mm: float, n_port: float,
    n_water: float, sqrt: Callable[[Any], Any], steps: int = NEWTON_STEPS,
) -> tuple[Any, Any]:
    """The pinhole ray's slope ``tan(theta_air)`` whose path through the port reaches a point
    at radial distance ``rho_mm`` from the axis, ``beyond_mm`` past the port's outer face.

    The path's radial distance at the point is

    .. math::

        G(\\tau) = g \\tau + t \\tau / \\sqrt{n_p^2 + (n_p^2 - 1) \\tau^2}
                   + L \\tau / \\sqrt{n_w^2 + (n_w^2 - 1) \\tau^2}

    (``tan`` of the angle in each layer from ``sin(theta_air) = n sin(theta)``), concave and
    increasing in ``tau``; Newton's method from the paraxial slope
    ``rho / (g + t / n_p + L / n_w)``, where ``G <= rho``, climbs to the root monotonically.

    Parameters
    ----------
    rho_mm, beyond_mm : array (NumPy or Dr.Jit), (...,)
        The point's distance from the axis and its axial distance past the outer face, mm.
    gap_mm, thickness_mm, n_port, n_water, sqrt
        As :func:`port_refract`.
    steps : int
        Newton steps.

    Returns
    -------
    tau : array, (...,)
        ``tan(theta_air)`` of the pinhole ray, >= 0.
    residual_mm : array, (...,)
        ``G(tau) - rho``, mm: about 0 where the point is reachable.
    """
    a_p, b_p = n_port**2, n_port**2 - 1.0
    a_w, b_w = n_water**2, n_water**2 - 1.0
    tau = rho_mm / (gap_mm + thickness_mm / n_port + beyond_mm / n_water)
    for i in range(steps + 1):
        q_p = 1.0 / sqrt(a_p + b_p * tau * tau)
        q_w = 1.0 / sqrt(a_w + b_w * tau * tau)
        g = tau * (gap_mm + thickness_mm * q_p + beyond_mm * q_w) - rho_mm
        if i == steps:
            break
        dg = gap_mm + thickness_mm * a_p * q_p**3 + beyond_mm * a_w * q_w**3
        tau = tau - g / dg
    return tau, g


def port_pinhole_xy(points_cam_mm: Any, gap_mm: float, thickness_mm: float, n_port: float,
                    n_water: float, tilt_deg: tuple[float, float] = (0.0, 0.0),
                    ) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Where the pinhole rays that reach ``points_cam_mm`` (..., 3), in the water beyond a
    flat port, cross the plane ``z = 1`` (``cam`` frame): ``x, y`` (...,) and whether each
    point lies beyond the port and its ray exists (:func:`port_invert` converged). A port
    tilted by ``tilt_deg`` (module notes) is solved in its own frame (:func:`port_axes`) and
    the pinhole ray turned back to ``cam``.

    Examples
    --------
    >>> x, y, ok = port_pinhole_xy(np.array([[0.0, 0.0, 100.0]]), 5.0, 5.0, 1.49, 4 / 3)
    >>> x.tolist(), y.tolist(), ok.tolist()
    ([0.0], [0.0], [True])
    """
    p = np.asarray(points_cam_mm, dtype=float)
    tilted = any(float(v) != 0.0 for v in tilt_deg)
    m = port_axes(tilt_deg) if tilted else None
    if tilted:
        p = p @ m.T
    rho = np.hypot(p[..., 0], p[..., 1])
    beyond = p[..., 2] - gap_mm - thickness_mm
    valid = beyond > 0
    tau, res = port_invert(rho, np.where(valid, beyond, 1.0), gap_mm, thickness_mm, n_port,
                           n_water, np.sqrt)
    valid &= np.abs(res) < 1e-9 * np.maximum(1.0, rho)
    scale = np.where(rho > 0, tau / np.where(rho > 0, rho, 1.0), 0.0)
    x, y = p[..., 0] * scale, p[..., 1] * scale
    if not tilted:
        return x, y, valid
    a = np.stack([x, y, np.ones(x.shape)], axis=-1) @ m
    az = a[..., 2]
    safe = np.where(az > 0, az, 1.0)
    return a[..., 0] / safe, a[..., 1] / safe, valid & (az > 0)


def port_transmittance(sin_air: Any, n_port: float, n_water: float,
                       sqrt: Callable[[Any], Any]) -> Any:
    """Fresnel transmittance of unpolarised light through the port's two faces.

    ``(T_s,1 T_s,2 + T_p,1 T_p,2) / 2`` for the faces air | port and port | water at the angles
    ``sin(theta_air) = n_port sin(theta_port) = n_water sin(theta_water)``, each ``T = 1 - R``
    of Fresnel's amplitudes; light reflected back and forth inside the port (a displaced ghost)
    is left out.

    Parameters
    ----------
    sin_air : array (NumPy or Dr.Jit), (...,)
        Sine of the ray's angle to the axis in the housing's air.
    n_port, n_water : float
    sqrt : callable

    Returns
    -------
    array, (...,)
        In (0, 1]. The same for light going either way (reciprocity).
    """
    s2 = sin_air * sin_air
    c_a = sqrt(1.0 - s2)
    c_p = sqrt(1.0 - s2 / n_port**2)
    c_w = sqrt(1.0 - s2 / n_water**2)

    def face(n1: float, c1: Any, n2: float, c2: Any) -> tuple[Any, Any]:
        rs = (n1 * c1 - n2 * c2) / (n1 * c1 + n2 * c2)
        rp = (n2 * c1 - n1 * c2) / (n2 * c1 + n1 * c2)
        return 1.0 - rs * rs, 1.0 - rp * rp

    ts1, tp1 = face(1.0, c_a, n_port, c_p)
    ts2, tp2 = face(n_port, c_p, n_water, c_w)
    return 0.5 * (ts1 * ts2 + tp1 * tp2)


@dataclass(frozen=True)
class DeviceOptics:
    """A device's pinhole with its principal point, lens distortion and housing port.

    Attributes
    ----------
    camera : PinholeCamera
        The ideal device (pose, focal length, image size): :func:`wai_core.rig.pinhole_of`.
    principal_px : (2,) tuple of float
        Principal point ``(c_x, c_y)``, pixels.
    distortion : (5,) tuple of float
        ``(k1, k2, p1, p2, k3)``, OpenCV's definition.
    port_thickness_mm : float
        0: no port (the pinhole in the water).
    port_gap_mm, port_n : float
        Air between the pinhole and the port (along its normal), mm; the port's index.
    port_tilt_deg : (2,) tuple of float
        The port's normal off the optical axis, deg (module notes; (0, 0): square to it).

    Examples
    --------
    >>> from wai_core import load_system
    >>> rig = load_system("paper").rig
    >>> optics = rig.optics("camera_v")
    >>> o, d = optics.pixel_rays(399.5, 299.5, n_water=4 / 3)
    >>> bool(np.allclose(d, rig.camera_v.pose.axis_lab))
    True
    """

    camera: PinholeCamera
    principal_px: tuple[float, float]
    distortion: tuple[float, float, float, float, float] = (0.0,) * 5
    port_thickness_mm: float = 0.0
    port_gap_mm: float = 5.0
    port_n: float = 1.49
    port_tilt_deg: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def from_config(cls, dev: Any) -> DeviceOptics:
        """The optics of a ``[projector]`` / ``[camera_s]`` / ``[camera_v]`` section (a rig
        holds each device's once: :meth:`wai_core.rig.Rig.optics`)."""
        return cls.of(dev, pinhole_of(dev))

    @classmethod
    def of(cls, dev: Any, cam: PinholeCamera) -> DeviceOptics:
        """The optics of section ``dev`` around its pinhole ``cam``."""
        cx = (cam.width_px - 1) / 2.0 + float(dev.principal_offset_px[0])
        cy = (cam.height_px - 1) / 2.0 + float(dev.principal_offset_px[1])
        return cls(cam, (cx, cy), tuple(float(v) for v in dev.distortion),
                   float(dev.port_thickness_mm), float(dev.port_gap_mm), float(dev.port_n),
                   tuple(float(v) for v in dev.port_tilt_deg))

    @property
    def distorted(self) -> bool:
        """True where any distortion coefficient is non-zero."""
        return any(v != 0.0 for v in self.distortion)

    @property
    def has_port(self) -> bool:
        """True with a housing port (``port_thickness_mm > 0``)."""
        return self.port_thickness_mm > 0.0

    @property
    def port_tilted(self) -> bool:
        """True with a port whose normal is off the optical axis."""
        return self.has_port and any(v != 0.0 for v in self.port_tilt_deg)

    @property
    def port_frame(self) -> Array:
        """The port's axes in ``cam`` (:func:`port_axes`), (3, 3)."""
        return port_axes(self.port_tilt_deg)

    @property
    def lens_free(self) -> bool:
        """True where the lens is the pinhole's (centred, undistorted), with or without a
        port."""
        c = self.camera
        centred = self.principal_px == ((c.width_px - 1) / 2.0, (c.height_px - 1) / 2.0)
        return centred and not self.distorted

    @property
    def ideal(self) -> bool:
        """True where the optics are the pinhole's (centred, undistorted, no port)."""
        return self.lens_free and not self.has_port

    def _port(self, n_water: float) -> tuple[float, float, float, float]:
        return self.port_gap_mm, self.port_thickness_mm, self.port_n, float(n_water)

    def rays_cam(self, cols: ArrayLike, rows: ArrayLike,
                 n_water: float) -> tuple[Array, Array, Array]:
        """Rays of continuous pixel coordinates in ``cam``: in the water, and the pinhole's.

        Returns
        -------
        origins_mm : (..., 3) ndarray
            Where the rays enter the water (``cam``, mm): the pinhole (0, 0, 0) without a port,
            the outer face of the port with one.
        dirs : (..., 3) ndarray
            Unit directions in the water; NaN where the distortion cannot be inverted.
        dirs_pinhole : (..., 3) ndarray
            Unit directions of the pinhole rays (in the housing's air with a port).
        """
        cols, rows = np.broadcast_arrays(np.asarray(cols, float), np.asarray(rows, float))
        f = self.camera.focal_px
        u, v = cols - self.principal_px[0], rows - self.principal_px[1]
        ok = np.ones(u.shape, dtype=bool)
        if self.distorted:
            xd, yd = u / f, v / f
            x, y = undistort(xd, yd, self.distortion)
            rx, ry = distort(x, y, self.distortion)
            ok = ((np.hypot(rx - xd, ry - yd) < 1e-9)
                  & distortion_one_to_one(x, y, self.distortion))
            u, v = f * x, f * y
        # (u, v, f) as PinholeCamera.dirs_cam builds it: the same bits with the keys off.
        d = np.stack([u, v, np.full(u.shape, f)], axis=-1)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        d[~ok] = np.nan
        if not self.has_port:
            return np.zeros(d.shape), d, d
        zero = np.zeros(u.shape)
        m = self.port_frame
        dp = d @ m.T if self.port_tilted else d  # in the port's frame
        p, w, _ = port_refract((zero, zero, zero), (dp[..., 0], dp[..., 1], dp[..., 2]),
                               *self._port(n_water), np.sqrt)
        p, w = np.stack(p, axis=-1), np.stack(w, axis=-1)
        if self.port_tilted:
            p, w = p @ m, w @ m
        return p, w, d

    def pinhole_px(self, px: ArrayLike) -> Array:
        """Pixels (K, 2) of the ideal pinhole (:attr:`camera`) whose rays are this device's
        pinhole rays at ``px`` (K, 2): the principal point and the lens's distortion undone
        (a port, whose rays share no centre, is not: see :meth:`rays_cam`); ``px`` itself for
        ideal optics (the same array); NaN where the distortion cannot be inverted.

        Examples
        --------
        >>> from wai_core import load_system, with_keys
        >>> cfg = with_keys(load_system("paper"), {"camera_s.principal_offset_px": [3.0, 0.0]})
        >>> cfg.rig.optics("camera_s").pinhole_px(np.array([[402.5, 299.5]]))
        array([[399.5, 299.5]])
        """
        if self.ideal:
            return np.asarray(px)
        pts = np.asarray(px, dtype=float)
        d = self.rays_cam(pts[:, 0], pts[:, 1], 1.0)[2]
        cam, f = self.camera, self.camera.focal_px
        return np.column_stack([f * d[:, 0] / d[:, 2] + (cam.width_px - 1) / 2.0,
                                f * d[:, 1] / d[:, 2] + (cam.height_px - 1) / 2.0])

    def plane_pinhole_px(self, px: ArrayLike, z_lab_mm: float, n_water: float) -> Array:
        """Pixels (K, 2) of the ideal pinhole (:attr:`camera`) that see the points where this
        device's rays at ``px`` (K, 2) meet the plane ``z = z_lab_mm`` (``lab``, mm): exact for
        a port too, whose rays share no centre, since the points lie on one known plane (the
        diffuser that camera s images); :meth:`pinhole_px` without a port (any plane gives
        the same pixels). NaN where the distortion cannot be inverted or a ray misses the
        plane.

        Examples
        --------
        >>> from wai_core import load_system, with_keys
        >>> cfg = with_keys(load_system("paper"), {"camera_s.port_thickness_mm": 4.0})
        >>> optics = cfg.rig.optics("camera_s")
        >>> optics.plane_pinhole_px(np.array([[399.5, 299.5]]), 60.0, 4 / 3)  # on axis
        array([[399.5, 299.5]])
        """
        if not self.has_port:
            return self.pinhole_px(px)
        pts = np.asarray(px, dtype=float)
        o, d = self.pixel_rays(pts[:, 0], pts[:, 1], n_water)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (z_lab_mm - o[:, 2]) / d[:, 2]
        t = np.where(t > 0, t, np.nan)
        cols, rows, front = self.camera.project(o + t[:, None] * d)
        return np.column_stack([np.where(front, cols, np.nan), np.where(front, rows, np.nan)])

    def pixel_rays(self, cols: ArrayLike, rows: ArrayLike, n_water: float) -> tuple[Array, Array]:
        """Rays in the water through continuous pixel coordinates.

        Parameters
        ----------
        cols, rows : array_like, (...,)
            Pixel coordinates (integers at pixel centres).
        n_water : float
            The water's index (used with a port only).

        Returns
        -------
        origins_lab_mm : (..., 3) ndarray
            Where each ray enters the water, ``lab``, mm (the device centre without a port).
        dirs_lab : (..., 3) ndarray
            Unit directions in the water, ``lab``; NaN where the distortion is not invertible.
        """
        o, d, _ = self.rays_cam(cols, rows, n_water)
        pose = self.camera.pose
        return pose.center_lab_mm + pose.dirs_to_lab(o), pose.dirs_to_lab(d)

    def project(self, points_lab_mm: ArrayLike,
                n_water: float) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Project ``lab`` points in the water to continuous pixel coordinates.

        Parameters
        ----------
        points_lab_mm : (..., 3) array_like
            Points, ``lab``, mm.
        n_water : float
            The water's index (used with a port only).

        Returns
        -------
        cols, rows : (...,) ndarray
            Pixel coordinates.
        valid : (...,) ndarray of bool
            True where the point lies in front of the device (beyond the port) and its ray
            exists (the port reaches it, the distortion is one to one there:
            :func:`distortion_one_to_one`).
        """
        p = self.camera.pose.points_to_cam(points_lab_mm)
        z = p[..., 2]
        f = self.camera.focal_px
        if not self.has_port:
            safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
            x, y = p[..., 0] / safe, p[..., 1] / safe
            valid = z > 0
        else:
            x, y, valid = port_pinhole_xy(p, *self._port(n_water), self.port_tilt_deg)
        if self.distorted:
            valid = valid & distortion_one_to_one(x, y, self.distortion)
            x, y = distort(x, y, self.distortion)
            return f * x + self.principal_px[0], f * y + self.principal_px[1], valid
        if not self.has_port:
            # PinholeCamera.project's expression: the same bits with the keys off.
            return (f * p[..., 0] / safe + self.principal_px[0],
                    f * p[..., 1] / safe + self.principal_px[1], valid)
        return f * x + self.principal_px[0], f * y + self.principal_px[1], valid

    def radiance_factor(self, dirs_pinhole_cam: ArrayLike, n_water: float) -> Array:
        """What the device records of the water-side radiance along its rays, (...,).

        1 without a port (the pinhole in the water). With one, ``T / n_water^2``: the port's
        Fresnel transmittance (:func:`port_transmittance`) times the radiance law (``L / n^2``
        is constant along a ray through lossless interfaces), the housing's air index 1.

        Parameters
        ----------
        dirs_pinhole_cam : (..., 3) array_like
            Unit pinhole-ray directions, ``cam`` (``rays_cam``'s third output).
        n_water : float
        """
        d = np.asarray(dirs_pinhole_cam, dtype=float)
        if not self.has_port:
            return np.ones(d.shape[:-1])
        cos_air = d[..., 2] if not self.port_tilted else d @ self.port_frame[2]
        sin_air = np.sqrt(np.clip(1.0 - cos_air**2, 0.0, None))
        return port_transmittance(sin_air, self.port_n, n_water, np.sqrt) / n_water**2
