"""Real cameras in the renderer: :class:`wai_core.lens.DeviceOptics` traced in Dr.Jit.

Mitsuba's ``perspective`` sensor is a centred, undistorted pinhole. A device with a principal
offset, lens distortion or a housing port (``[camera_s]`` / ``[camera_v]`` keys, see
:mod:`wai_core.lens`) is traced exactly instead: every pixel sample's ray goes through the
model (nothing is warped after rendering). :class:`CameraLens` holds one camera's maps:

- :meth:`CameraLens.sample_ray` for camera v (:mod:`mitsuba_wai.view_tracer`): the film
  position's ray into the water, and what the camera records of the radiance along it;
- :meth:`CameraLens.sample_direction` for camera s (:mod:`mitsuba_wai.particles`): a path
  vertex projected to the film, with the importance that keeps the image a radiance image;
- :meth:`CameraLens.undistort` and :meth:`CameraLens.port_ray` for the projector
  (:class:`mitsuba_wai.dots.DotEmitter`): a dot's panel point is the distorted image point,
  its ray the undistorted one's through the port, its flux times the port's transmittance.

Radiometry
----------
Both images stay radiance images: a pixel holds the mean, over its area on the film, of the
radiance the camera receives along each film point's ray (Mitsuba's perspective camera does
the same; no ``cos^4`` fall-off). Without a port the pinhole sits in the water and receives the
water-side radiance ``L_w``. Behind a port it receives ``T L_w / n_water^2``: the Fresnel
transmittance ``T`` of the port's two faces (:func:`wai_core.lens.port_transmittance`) and the
radiance law (``L / n^2`` is invariant along a ray, the housing's air has index 1); so a view
seen through a port is ``n_water^2`` dimmer than the pinhole-in-water view, up to ``T``.

The particle tracer needs the importance ``W`` of the connection from a vertex ``y`` to the
camera, per unit area at ``y`` (Mitsuba's ``sample_direction`` weight, ``W = I(d) / r^2`` for its
pinhole, with ``I = 1 / (A cos^3)``, ``A`` the film's area on the plane ``z = 1``). Here

.. math::

    W = \\frac{f^2 |\\det J_D|}{W_{px} H_{px} \\cos^3\\theta_a}
        \\frac{T}{n_w^2} \\frac{d\\omega_a}{dA_\\perp}

``J_D`` the distortion's Jacobian (film area per unit of undistorted normalised area),
``theta_a`` the pinhole ray's angle to the axis, and ``d omega_a / d A_perp`` the pinhole's solid
angle per unit area across the water ray at ``y``: ``1 / s^2`` without a port (``s`` the distance),
and, through the port (axially symmetric; ``rho(theta_a)`` the exit point's distance from the
axis, ``s`` the water segment's length),

.. math::

    \\frac{d\\omega_a}{dA_\\perp} = \\frac{1}{(\\rho' \\cos\\theta_w + s\\,\\theta_w')
        (g / \\cos\\theta_a + t / (n_p \\cos\\theta_p) + s / n_w)}

(radial times azimuthal spread of the ray bundle at ``y``; ``theta_w' = cos(theta_a) / (n_w
cos(theta_w))``). A tilted port (``port_tilt_deg``) is traced in its own frame, where it is
square to its axis: the angles of this spread and of ``T`` are then taken to the port's normal,
the ``cos^3`` to the camera's axis. The vertex's BSDF is evaluated towards the port's exit
point, the water-side direction, and the connection's water length is ``s``.

Scenes that Mitsuba's own integrators render (``[render] sampling = "independent"``'s view and
projector) cannot carry these effects and are refused (:func:`scene_lenses`). Daylight
(``[ambient]``) carries them: camera v's sky and sun are traced through the lens by
:func:`mitsuba_wai.view_tracer.render_view`, the sun's caustics on the diffuser reach camera s
as the pattern's particles do, and the sky-lit diffuser's uniform radiance is recorded times
:meth:`wai_core.lens.DeviceOptics.radiance_factor`.
``[water_optics]``' view path lengths (:func:`mitsuba_wai.seawater.view_path_lengths`) keep the
pinhole's rays: a port or distortion changes them by a fraction of a millimetre to a few.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from mitsuba_wai.variant import mitsuba
from wai_core.config import DeviceConfig, SystemConfig
from wai_core.distortion import distort, distortion_jacobian, distortion_one_to_one, undistort
from wai_core.errors import WaiInputError
from wai_core.lens import DeviceOptics, port_invert, port_refract, port_transmittance

__all__ = ["CameraLens", "lens_keys", "scene_lenses"]

# Newton steps in float32: both inversions converge quadratically from their starting points,
# and 8 steps leave a residual at float32 rounding for the distortions a lens has.
_STEPS = 8
# Mitsuba's perspective sensor's near clip, mm (scenes.sensor_dict): vertices closer are not
# connected, as there.
_NEAR_MM = 1.0


def lens_keys(dev: DeviceConfig) -> list[str]:
    """The lens and port keys of a device section that are on (empty: Mitsuba's pinhole)."""
    on = []
    if any(v != 0.0 for v in dev.principal_offset_px):
        on.append("principal_offset_px")
    if any(v != 0.0 for v in dev.distortion):
        on.append("distortion")
    if dev.port_thickness_mm > 0:
        on.append("port_thickness_mm")
    if dev.port_thickness_mm > 0 and any(v != 0.0 for v in dev.port_tilt_deg):
        on.append("port_tilt_deg")
    return on


class CameraLens:
    """One camera's :class:`~wai_core.lens.DeviceOptics` as Dr.Jit maps (module notes).

    Parameters
    ----------
    optics : DeviceOptics
        The camera.
    n_water : float
        The water's index at the camera (the port's far side).
    """

    def __init__(self, optics: DeviceOptics, n_water: float) -> None:
        mi = mitsuba()
        cam = optics.camera
        self.optics = optics
        self.n_water = float(n_water)
        self._size = (cam.width_px, cam.height_px)
        self._f = cam.focal_px
        self._c = optics.principal_px
        self._k = optics.distortion
        self._port = (optics.port_gap_mm, optics.port_thickness_mm, optics.port_n,
                      self.n_water)
        # A tilted port's frame (rows: its axes in cam; wai_core.lens.port_axes), else None.
        self._frame = (optics.port_frame.tolist() if optics.port_tilted else None)
        self._center = mi.Point3f(*cam.pose.center_lab_mm.tolist())
        self._axes = [mi.Vector3f(*row.tolist()) for row in cam.pose.R]  # cam axes in lab
        # Mitsuba's importance normalisation: 1 / (film area on the plane z_cam = 1).
        self._norm = self._f**2 / (cam.width_px * cam.height_px)

    def _to_lab(self, v: tuple[Any, Any, Any]) -> Any:
        return self._axes[0] * v[0] + self._axes[1] * v[1] + self._axes[2] * v[2]

    def _to_port(self, v: tuple[Any, Any, Any]) -> tuple[Any, Any, Any]:
        """``cam`` components to the port's frame (unchanged for a port square to the axis)."""
        m = self._frame
        if m is None:
            return v
        return tuple(m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2] for i in range(3))

    def _from_port(self, v: tuple[Any, Any, Any]) -> tuple[Any, Any, Any]:
        """The port frame's components back to ``cam``."""
        m = self._frame
        if m is None:
            return v
        return tuple(m[0][i] * v[0] + m[1][i] * v[1] + m[2][i] * v[2] for i in range(3))

    def _radiance_factor(self, sin_air: Any) -> Any:
        """``T / n_water^2`` behind a port (module notes), 1 without one."""
        import drjit as dr

        if not self.optics.has_port:
            return 1.0
        _, _, n_p, n_w = self._port
        return port_transmittance(sin_air, n_p, n_w, dr.sqrt) / n_w**2

    def undistort(self, x_d: Any, y_d: Any) -> tuple[Any, Any, Any]:
        """Undistorted normalised coordinates of distorted ones
        (:func:`wai_core.distortion.undistort`).

        Parameters
        ----------
        x_d, y_d : mitsuba.Float, (n,)
            Distorted normalised coordinates (image point minus principal point, over ``f``).

        Returns
        -------
        x, y : mitsuba.Float, (n,)
            The pinhole ray's slopes ``X / Z``, ``Y / Z`` (``cam``).
        ok : mitsuba.Bool, (n,)
            False where the distortion cannot be inverted (beyond its fold).
        """
        import drjit as dr

        x, y = undistort(x_d, y_d, self._k, _STEPS)
        rx, ry = distort(x, y, self._k)
        ok = (dr.abs(rx - x_d) + dr.abs(ry - y_d) < 1e-4) & distortion_one_to_one(x, y, self._k)
        return x, y, ok

    def port_ray(self, start: Any, slope: tuple[Any, Any]) -> tuple[Any, Any, Any]:
        """A pinhole-side ray into the water, and the port's transmittance along it.

        Parameters
        ----------
        start : mitsuba.Point2f (n,) or None
            The ray's start on the plane ``z_cam = 0``, mm (a thin lens's point); None: the
            pinhole.
        slope : 2-tuple of mitsuba.Float, (n,)
            Direction ``(x, y, 1)`` of the ray behind the port (``cam``).

        Returns
        -------
        origin : mitsuba.Point3f, (n,)
            Where the ray enters the water, ``lab``, mm.
        direction : mitsuba.Vector3f, (n,)
            Unit direction in the water, ``lab``.
        transmittance : mitsuba.Float or float
            The port's Fresnel transmittance ``T`` (:func:`wai_core.lens.port_transmittance`),
            1 without a port: the share of the flux that passes (the radiance's is
            ``T / n_water^2``, module notes).
        """
        import drjit as dr

        mi = mitsuba()
        x, y = slope
        inv = dr.rsqrt(1.0 + x * x + y * y)
        d = (x * inv, y * inv, inv)
        transmittance = 1.0
        sx, sy = (mi.Float(0.0), mi.Float(0.0)) if start is None else (start.x, start.y)
        if self.optics.has_port:
            _, _, n_p, n_w = self._port
            d = self._to_port(d)
            transmittance = port_transmittance(dr.sqrt(d[0] * d[0] + d[1] * d[1]), n_p, n_w,
                                               dr.sqrt)
            p, d, _ = port_refract(self._to_port((sx, sy, mi.Float(0.0))), d, *self._port,
                                   dr.sqrt)
            p, d = self._from_port(p), self._from_port(d)
            origin = self._center + self._to_lab(p)
        elif start is None:
            origin = mi.Point3f(self._center)
        else:
            origin = self._center + self._to_lab((sx, sy, mi.Float(0.0)))
        return origin, dr.normalize(self._to_lab(d)), transmittance

    def sample_ray(self, time: Any, position: Any) -> tuple[Any, Any]:
        """The rays of film positions, and what the camera records of their radiance.

        Parameters
        ----------
        time : float
            The rays' time.
        position : mitsuba.Point2f, (n,)
            Film positions, pixels, in [0, W) x [0, H) (pixel ``i``'s centre at ``i + 0.5``).

        Returns
        -------
        ray : mitsuba.Ray3f, (n,)
            From where the ray enters the water (the pinhole, or the port's outer face), ``lab``,
            mm, along its water-side unit direction.
        weight : mitsuba.Float, (n,)
            The recorded share of the water-side radiance (module notes); 0 where the
            distortion cannot be inverted.
        """
        import drjit as dr

        mi = mitsuba()
        x = (position.x - 0.5 - self._c[0]) / self._f
        y = (position.y - 0.5 - self._c[1]) / self._f
        ok = mi.Bool(True)
        if self.optics.distorted:
            x, y, ok = self.undistort(x, y)
        origin, d, weight = self.port_ray(None, (x, y))
        if self.optics.has_port:
            weight = weight / self.n_water**2  # the radiance law (module notes)
        ray = mi.Ray3f(origin, d)
        ray.time = time
        return ray, dr.select(ok, weight, 0.0)

    def sample_direction(self, si: Any, sample: Any, active: Any) -> tuple[Any, Any]:
        """Mitsuba's ``Sensor.sample_direction`` for this camera: a vertex to the film.

        Parameters
        ----------
        si : mitsuba.SurfaceInteraction3f, (n,)
            Path vertices in the water.
        sample : mitsuba.Point2f
            Unused (a pinhole), taken so the sampler's stream stays Mitsuba's.
        active : mitsuba.Bool, (n,)

        Returns
        -------
        ds : namespace of (n,) arrays
            ``p`` (where the connection leaves the water: the pinhole, or the port's exit point,
            ``lab``, mm), ``uv`` (film position, pixels), ``dist`` (the water segment's length,
            mm) and ``pdf`` (1 where connected, else 0), as ``_connect`` reads them.
        weight : mitsuba.Float, (n,)
            The importance per unit area at the vertex (module notes).
        """
        import drjit as dr

        mi = mitsuba()
        q = si.p - self._center
        qx, qy, qz = (dr.dot(axis, q) for axis in self._axes)
        g, t, n_p, n_w = self._port
        if not self.optics.has_port:
            dist = dr.norm(q)
            valid = active & (qz >= _NEAR_MM)
            x, y = qx / qz, qy / qz
            cos_a = qz / dist
            cos_film = cos_a
            spread = 1.0 / (dist * dist)
            p = mi.Point3f(self._center)
        else:
            qx, qy, qz = self._to_port((qx, qy, qz))  # the port's frame
            rho = dr.sqrt(qx * qx + qy * qy)
            beyond = qz - g - t
            valid = active & (beyond > 0.0)
            tau, res = port_invert(rho, dr.select(valid, beyond, 1.0), g, t, n_p, n_w,
                                   dr.sqrt, _STEPS)
            valid &= dr.abs(res) < 1e-4 * dr.maximum(1.0, rho)
            unit_x = dr.select(rho > 0.0, qx / rho, 0.0)
            unit_y = dr.select(rho > 0.0, qy / rho, 0.0)
            x, y = tau * unit_x, tau * unit_y
            cos_a = dr.rsqrt(1.0 + tau * tau)
            cos_film = cos_a  # the pinhole ray's angle to the camera's axis
            sin2 = tau * tau * cos_a * cos_a
            cos_p = dr.sqrt(1.0 - sin2 / n_p**2)
            cos_w = dr.sqrt(1.0 - sin2 / n_w**2)
            rho_exit = g * tau + t * tau * cos_a / (n_p * cos_p)
            dist = dr.sqrt(dr.square(rho - rho_exit) + beyond * beyond)
            # d rho_exit / d theta_a, and d theta_w / d theta_a (module notes).
            drho = g / (cos_a * cos_a) + t * cos_a / (n_p * cos_p**3)
            dtheta_w = cos_a / (n_w * cos_w)
            radial = drho * cos_w + dist * dtheta_w
            azimuthal = g / cos_a + t / (n_p * cos_p) + dist / n_w
            spread = self._radiance_factor(tau * cos_a) / (radial * azimuthal)
            p = self._center + self._to_lab(self._from_port(
                (rho_exit * unit_x, rho_exit * unit_y, mi.Float(g + t))))
            if self._frame is not None:  # the pinhole ray (x, y, 1) turned back to cam
                ax, ay, az = self._from_port((x, y, mi.Float(1.0)))
                valid &= az > 0.0
                az = dr.select(az > 0.0, az, 1.0)
                x, y = ax / az, ay / az
                cos_film = dr.rsqrt(1.0 + x * x + y * y)
        det = 1.0
        if self.optics.distorted:
            a, b, d = distortion_jacobian(x, y, self._k)
            det = a * d - b * b
            valid &= distortion_one_to_one(x, y, self._k)
            x, y = distort(x, y, self._k)
        uv = mi.Point2f(self._f * x + self._c[0] + 0.5, self._f * y + self._c[1] + 0.5)
        weight = self._norm * det * spread / (cos_film * cos_film * cos_film)
        ds = SimpleNamespace(p=p, uv=uv, dist=dist, pdf=dr.select(valid, 1.0, 0.0))
        return ds, dr.select(valid, weight, 0.0)


def scene_lenses(cfg: SystemConfig) -> dict[str, CameraLens | None]:
    """The cameras' lenses for the renders of ``cfg``: ``{"pattern": camera s, "view":
    camera v}``, None where the camera is Mitsuba's pinhole (its keys off).

    Raises
    ------
    WaiInputError
        A camera's lens or port on in a render that Mitsuba's own integrators make
        (``[render] sampling = "independent"`` for camera v and the projector), which cannot
        carry them. The projector's lens is drawn by :class:`mitsuba_wai.dots.DotEmitter`.
    """
    out: dict[str, CameraLens | None] = {}
    for key, name in (("pattern", "camera_s"), ("view", "camera_v")):
        dev = getattr(cfg, name)
        on = lens_keys(dev)
        if not on:
            out[key] = None
            continue
        if key == "view" and cfg.render.sampling != "stratified":
            raise WaiInputError(
                f"config: [{name}].{on[0]} needs [render].sampling = 'stratified' (Mitsuba's "
                "own view integrator has no lens model)"
            )
        out[key] = CameraLens(cfg.rig.optics(name), cfg.water.n_water)
    on = lens_keys(cfg.projector)
    if on and cfg.render.sampling != "stratified":
        raise WaiInputError(
            f"config: [projector].{on[0]} needs [render].sampling = 'stratified' (Mitsuba's "
            "projector emitter has no lens model; mitsuba_wai.dots draws the dots through it)"
        )
    return out
