"""Alterman's sun-and-pinhole wavefront sensor: configuration, derived geometry, forward model.

Alterman, Swirski & Schechner (STELLA MARIS, ICCP 2014) image the refracted sun through an
array of submerged pinholes onto a diffuser just behind them, like a Shack-Hartmann sensor that
uses the sun as its guide star. Each pinhole sees the sun through one small patch of the surface
(isoplanatic), so its sun spot's offset gives the refracted sun direction ``t`` there; Snell's law
with the known sun direction ``d`` gives the normal ``N ~ d - n t``; the normals are integrated.
This module holds what the renderer and the restoration share: the sensor's configuration and
its geometry (the restoration's calibration), plus the sensor's geometric forward model.

Geometry (``lab`` frame, mm, z up; see :mod:`wai_core.geometry`)
----------------------------------------------------------------
- **Sun.** Zenith angle ``theta_sun`` and azimuth ``phi_sun`` (from +x towards +y) of the
  direction *towards* the sun; sunlight travels along ``d = -(sin t cos p, sin t sin p, cos t)``.
  A delta direction: the sun's 0.53 deg disc is not modelled.
- **Samples.** A square grid of pitch ``p`` covering the flat water that the structured-light
  system observes (:func:`wai_core.layout.observed_patch`): the points where, for flat water,
  the sunlight that passes each pinhole crosses ``z = h0``.
- **Plate.** Horizontal, opaque, at ``z = h0 - depth``, with a square hole of side ``hole`` under
  each sample along the flat-water refracted sun ray. The rig is laid out for the sun it works
  under (as on a sun-tracking mount): the sampled patch is the same for every sun position.
- **Screen.** A diffuser ``gap`` below the plate; each hole's spot is its shadow, shifted by
  ``gap tan(theta_water)`` away from the sun (a horizontal hole projects along parallel rays onto
  a parallel plane without distortion). It covers the flat-water spots plus one pitch.
- **Camera a.** Looks straight up at the screen from below (``R = I``, as camera s), at the
  distance where the screen just fills its image.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wai_core.config import SystemConfig, load_config, parse_section, read_toml
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera, Pose, critical_angle_rad, refract
from wai_core.heightfield import Heightfield
from wai_core.layout import observed_patch

Array = NDArray[np.float64]
UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class SunConfig:
    """The sun: on or off (overcast), where it is, and its irradiance (render units)."""

    enabled: bool = True
    zenith_deg: float = 30.0
    azimuth_deg: float = 0.0
    irradiance: float = 1.0


@dataclass(frozen=True)
class PlateConfig:
    """The pinhole plate: depth below the mean level h0 (mm), hole pitch and side (mm)."""

    depth_mm: float = 30.0
    pitch_mm: float = 8.0
    hole_mm: float = 1.2


@dataclass(frozen=True)
class ScreenConfig:
    """The diffuser: distance below the plate, mm."""

    gap_mm: float = 12.0


@dataclass(frozen=True)
class SensorCameraConfig:
    """Camera a: image size, sensor width and focal length; its pose is derived."""

    width_px: int = 800
    height_px: int = 600
    sensor_width_mm: float = 5.0
    focal_mm: float = 2.0


@dataclass(frozen=True)
class SunRenderConfig:
    """Particle-tracer samples per pixel of the sun-spot image, and the sun's beam: ``holes``
    (only the rays that reach a hole) or ``full`` (every ray that could; see
    :mod:`mitsuba_wai.alterman`)."""

    spp: int = 8
    beam: str = "holes"


@dataclass(frozen=True)
class AltermanConfig:
    """The sensor (everything but the water, the waves and camera v, which come from the base)."""

    sun: SunConfig = field(default_factory=SunConfig)
    plate: PlateConfig = field(default_factory=PlateConfig)
    screen: ScreenConfig = field(default_factory=ScreenConfig)
    camera_a: SensorCameraConfig = field(default_factory=SensorCameraConfig)
    render: SunRenderConfig = field(default_factory=SunRenderConfig)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (JSON/TOML-able)."""
        return dataclasses.asdict(self)

    def replace(self, section: str, **changes: Any) -> AltermanConfig:
        """Copy with some keys of one section changed, e.g. ``replace('sun', zenith_deg=45)``."""
        return dataclasses.replace(
            self, **{section: dataclasses.replace(getattr(self, section), **changes)}
        )


@dataclass(frozen=True)
class AltermanSystem:
    """The sensor together with the system it shares water, waves and camera v with."""

    base: SystemConfig
    sensor: AltermanConfig


_SECTIONS = {
    "sun": SunConfig,
    "plate": PlateConfig,
    "screen": ScreenConfig,
    "camera_a": SensorCameraConfig,
    "render": SunRenderConfig,
}


def alterman_from_dict(data: dict[str, Any]) -> AltermanConfig:
    """Build and check an :class:`AltermanConfig` from nested dicts (``scene.json``'s
    ``alterman`` entry, or a TOML file's tables without ``[base]``)."""
    unknown = sorted(set(data) - set(_SECTIONS))
    if unknown:
        raise WaiInputError(f"alterman config: unknown section [{unknown[0]}]")
    sensor = AltermanConfig(**{k: parse_section(_SECTIONS[k], v, k) for k, v in data.items()})
    validate_sensor(sensor)
    return sensor


def is_alterman_file(path: str | Path) -> bool:
    """True for a TOML file that describes the sensor (it has a ``[base]`` table)."""
    return "base" in read_toml(path)


def load_alterman(path: str | Path) -> AltermanSystem:
    """Read a sensor TOML file (e.g. ``scenes/alterman.toml``) and the base scene it names.

    ``[base] config`` is a path relative to the sensor file's folder.
    """
    path = Path(path)
    data = read_toml(path)
    base = data.pop("base", None)
    if not isinstance(base, dict) or not isinstance(base.get("config"), str):
        raise WaiInputError(f"{path}: needs [base] config = \"<scene>.toml\"")
    if set(base) != {"config"}:
        raise WaiInputError(f"config: unknown key [base].{sorted(set(base) - {'config'})[0]}")
    return AltermanSystem(load_config(path.parent / base["config"]), alterman_from_dict(data))


def validate_sensor(sensor: AltermanConfig) -> None:
    """Reject impossible sensor geometry with a message naming the problem."""
    sun, plate = sensor.sun, sensor.plate
    if not 0.0 <= sun.zenith_deg < 90.0:
        raise WaiInputError("alterman config: [sun].zenith_deg must lie in [0, 90) (else sun off)")
    if sun.irradiance < 0:
        raise WaiInputError("alterman config: [sun].irradiance must be >= 0")
    if plate.depth_mm <= 0 or plate.hole_mm <= 0:
        raise WaiInputError("alterman config: [plate] needs depth_mm > 0 and hole_mm > 0")
    if plate.pitch_mm <= 2.0 * plate.hole_mm:
        raise WaiInputError("alterman config: [plate].pitch_mm must exceed twice hole_mm")
    if sensor.screen.gap_mm <= 0:
        raise WaiInputError("alterman config: [screen].gap_mm must be positive")
    cam = sensor.camera_a
    if min(cam.width_px, cam.height_px) < 2 or cam.focal_mm <= 0 or cam.sensor_width_mm <= 0:
        raise WaiInputError("alterman config: [camera_a] needs positive size, focal and sensor")
    if sensor.render.spp < 1:
        raise WaiInputError("alterman config: [render].spp must be at least 1")
    if sensor.render.beam not in ("holes", "full"):
        raise WaiInputError("alterman config: [render].beam must be holes or full")


# ----------------------------------------------------------------------------------------------
# Derived geometry (the calibration)
# ----------------------------------------------------------------------------------------------


def sun_direction(sun: SunConfig) -> Array:
    """Unit direction (3,) along which sunlight travels (downwards), ``lab``."""
    th, ph = np.radians(sun.zenith_deg), np.radians(sun.azimuth_deg)
    return -np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


def sun_is_up(sun: SunConfig) -> bool:
    """True when direct sunlight reaches the water: enabled, above the horizon, not zero."""
    return bool(sun.enabled and sun.irradiance > 0 and sun.zenith_deg < 90.0)


@dataclass(frozen=True)
class SensorLayout:
    """Where every part of the sensor is, for flat water (the restoration's calibration).

    Attributes
    ----------
    sun_dir : (3,) ndarray
        Unit direction of sunlight in air (downwards).
    water_dir : (3,) ndarray
        Unit direction of sunlight refracted by flat water.
    n_water, h0_mm : float
        Refractive index and mean level (mm) of the water.
    ij : (K, 2) ndarray of int
        Grid index ``(i, j)`` of each pinhole (``i`` along x, ``j`` along y).
    samples_mm : (K, 3) ndarray
        Flat-water sample points on ``z = h0``, mm.
    pinholes_mm : (K, 3) ndarray
        Hole centres on the plate, mm.
    flat_spots_mm : (K, 3) ndarray
        Spot centres on the screen for flat water, mm.
    plate_z_mm, screen_z_mm : float
        Heights of the plate and the screen, mm.
    pitch_mm, hole_mm : float
        Hole pitch and side, mm.
    screen_rect_mm, plate_rect_mm : (2, 2) ndarray
        Extents ``[[x0, x1], [y0, y1]]`` of the screen and the plate, mm.
    camera : PinholeCamera
        Camera a, looking up at the screen.
    """

    sun_dir: Array
    water_dir: Array
    n_water: float
    h0_mm: float
    ij: NDArray[np.int64]
    samples_mm: Array
    pinholes_mm: Array
    flat_spots_mm: Array
    plate_z_mm: float
    screen_z_mm: float
    pitch_mm: float
    hole_mm: float
    screen_rect_mm: Array
    plate_rect_mm: Array
    camera: PinholeCamera

    def flat_spots_px(self) -> tuple[Array, NDArray[np.bool_]]:
        """Flat-water spot centres in camera a (K, 2) px, and which lie on the screen in view."""
        cols, rows, front = self.camera.project(self.flat_spots_mm)
        (x0, x1), (y0, y1) = self.screen_rect_mm
        s = self.flat_spots_mm
        seen = front & self.camera.in_image(cols, rows, margin_px=1.0)
        seen &= (s[:, 0] >= x0) & (s[:, 0] <= x1) & (s[:, 1] >= y0) & (s[:, 1] <= y1)
        return np.stack([cols, rows], axis=1), seen

    def index_of(self, ij: NDArray) -> NDArray[np.int64]:
        """Row (K,) in this layout's arrays of the pinholes with grid indices ``ij`` (K, 2)."""
        ij = np.asarray(ij, dtype=np.int64)
        return ij[:, 1] * (int(self.ij[:, 0].max()) + 1) + ij[:, 0]

    @property
    def pitch_px(self) -> float:
        """Hole pitch as imaged by camera a (on the screen plane), px."""
        dist = self.screen_z_mm - self.camera.pose.center_lab_mm[2]
        return float(self.pitch_mm * self.camera.focal_px / dist)


def sample_grid(patch_mm: Array, pitch_mm: float) -> tuple[NDArray[np.int64], Array]:
    """Square grid of pitch ``pitch_mm`` centred on, and inside, ``[[x0, x1], [y0, y1]]``.

    Returns grid indices ``(i, j)`` (K, 2) from 0 and points ``(x, y)`` (K, 2), mm, row by row.
    """
    size = patch_mm[:, 1] - patch_mm[:, 0]
    n = np.floor(size / pitch_mm).astype(int) + 1
    start = patch_mm.mean(axis=1) - (n - 1) * pitch_mm / 2.0
    jj, ii = np.mgrid[0 : n[1], 0 : n[0]]
    ij = np.stack([ii.ravel(), jj.ravel()], axis=1).astype(np.int64)
    return ij, start + ij * pitch_mm


def _along(points: Array, dirs: Array, dz_mm: float | Array) -> Array:
    """Points moved along ``dirs`` until their height changed by ``dz_mm`` (negative: down)."""
    dz = np.asarray(dz_mm, dtype=float)
    return points + (dz / dirs[..., 2])[..., None] * dirs


def _grow(rect: Array, margin_mm: float) -> Array:
    return rect + np.array([-margin_mm, margin_mm])


def _bbox(points: Array) -> Array:
    return np.stack([points[:, :2].min(axis=0), points[:, :2].max(axis=0)], axis=1)


def _camera_below(rect: Array, z_mm: float, cam: SensorCameraConfig) -> PinholeCamera:
    """Camera a: looking up (``R = I``) from below the centre of ``rect``, far enough for the
    rectangle to fill the image (2 % margin)."""
    pitch = cam.sensor_width_mm / cam.width_px
    size = rect[:, 1] - rect[:, 0]
    fill = max(size[0] / (cam.width_px * pitch), size[1] / (cam.height_px * pitch))
    dist = 1.02 * cam.focal_mm * fill
    centre = np.array([rect[0].mean(), rect[1].mean(), z_mm - dist])
    return PinholeCamera(
        cam.width_px, cam.height_px, cam.focal_mm, pitch, Pose.from_center(np.eye(3), centre)
    )


def sensor_layout(system: AltermanSystem) -> SensorLayout:
    """The sensor's geometry for its sun and the base system's water (see the module notes)."""
    cfg, s = system.base, system.sensor
    h0, n = cfg.water.h0_mm, cfg.water.n_water
    sun_dir = sun_direction(s.sun)
    water_dir, _ = refract(sun_dir, UP, 1.0 / n)
    ij, xy = sample_grid(observed_patch(cfg, margin_mm=0.0), s.plate.pitch_mm)
    samples = np.column_stack([xy, np.full(len(xy), h0)])
    plate_z = h0 - s.plate.depth_mm
    screen_z = plate_z - s.screen.gap_mm
    pinholes = _along(samples, water_dir, plate_z - h0)
    spots = _along(pinholes, water_dir, screen_z - plate_z)
    screen = _grow(_bbox(spots), s.plate.pitch_mm)
    # No sunlight in water runs steeper than the critical angle: beyond this margin the plate
    # shades the whole screen whatever the waves do.
    shade = s.screen.gap_mm * np.tan(critical_angle_rad(n)) + s.plate.pitch_mm
    return SensorLayout(
        sun_dir=sun_dir,
        water_dir=water_dir,
        n_water=n,
        h0_mm=h0,
        ij=ij,
        samples_mm=samples,
        pinholes_mm=pinholes,
        flat_spots_mm=spots,
        plate_z_mm=plate_z,
        screen_z_mm=screen_z,
        pitch_mm=s.plate.pitch_mm,
        hole_mm=s.plate.hole_mm,
        screen_rect_mm=screen,
        plate_rect_mm=_grow(screen, shade),
        camera=_camera_below(screen, screen_z, s.camera_a),
    )


def spot_shift_mm_per_rad(layout: SensorLayout, tilt_rad: float = 1e-4) -> float:
    """How far a spot moves on the screen per radian of surface tilt in the sun's plane of
    incidence, mm/rad: the sensor's gain (``gap d tan(theta_t) / d tilt``)."""
    horiz = -layout.sun_dir[:2]
    norm = np.linalg.norm(horiz)
    u = horiz / norm if norm > 1e-12 else np.array([1.0, 0.0])
    normal = np.array([np.sin(tilt_rad) * u[0], np.sin(tilt_rad) * u[1], np.cos(tilt_rad)])
    t, _ = refract(layout.sun_dir, normal, 1.0 / layout.n_water)
    gap = layout.plate_z_mm - layout.screen_z_mm
    shift = _along(np.zeros(3), t, -gap) - _along(np.zeros(3), layout.water_dir, -gap)
    return float(np.linalg.norm(shift) / tilt_rad)


def layout_record(layout: SensorLayout) -> dict[str, Any]:
    """The layout as plain data (for ``scene.json``)."""
    cam = layout.camera
    return {
        "sun_dir": layout.sun_dir,
        "water_dir": layout.water_dir,
        "plate_z_mm": layout.plate_z_mm,
        "screen_z_mm": layout.screen_z_mm,
        "pinholes": int(len(layout.ij)),
        "grid_shape": (layout.ij.max(axis=0) + 1).tolist(),
        "pinhole_first_mm": layout.pinholes_mm[0],
        "sample_first_mm": layout.samples_mm[0],
        "screen_rect_mm": layout.screen_rect_mm,
        "plate_rect_mm": layout.plate_rect_mm,
        "camera_a": {
            "center_lab_mm": cam.pose.center_lab_mm,
            "R": cam.pose.R,
            "focal_px": cam.focal_px,
            "pixel_pitch_mm": cam.pixel_pitch_mm,
        },
        "pitch_px": layout.pitch_px,
        "spot_shift_mm_per_rad": spot_shift_mm_per_rad(layout),
    }


# ----------------------------------------------------------------------------------------------
# Forward model: the sensor's chief rays through a known surface
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ChiefRays:
    """Sunlight through each pinhole's centre (the chief ray of its spot).

    Attributes
    ----------
    surface_mm : (K, 3) ndarray
        Where the ray crossed the water surface, mm.
    normals : (K, 3) ndarray
        Unit surface normals there, pointing up.
    water_dirs : (K, 3) ndarray
        Refracted directions (unit, downwards).
    spots_mm : (K, 3) ndarray
        Spot centres on the screen, mm.
    ok : (K,) ndarray of bool
        The fixed point converged on the known surface.
    """

    surface_mm: Array
    normals: Array
    water_dirs: Array
    spots_mm: Array
    ok: NDArray[np.bool_]


def chief_rays(layout: SensorLayout, surface: Heightfield, n_iter: int = 40) -> ChiefRays:
    """Solve, for every pinhole ``P``, the surface point ``q`` whose refracted sunlight passes
    through ``P``: the fixed point ``q = P + t(q) (h(q) - z_P) / t_z(q)`` (``t``: the sun refracted
    by the surface's normal at ``q``), started from the flat-water sample. It contracts by about
    ``depth x curvature + tan(theta_water) x slope`` per step (well below 1 for sea waves)."""
    P = layout.pinholes_mm
    xy = layout.samples_mm[:, :2].copy()
    for _ in range(n_iter):
        h = surface.height(xy[:, 0], xy[:, 1])
        t, _ = refract(layout.sun_dir, surface.normal(xy[:, 0], xy[:, 1]), 1.0 / layout.n_water)
        xy = P[:, :2] + t[:, :2] * ((h - P[:, 2]) / t[:, 2])[:, None]
    h = surface.height(xy[:, 0], xy[:, 1])
    normals = surface.normal(xy[:, 0], xy[:, 1])
    t, _ = refract(layout.sun_dir, normals, 1.0 / layout.n_water)
    q = np.column_stack([xy, h])
    # Converged when the refracted ray from q really passes through the pinhole.
    miss = np.linalg.norm(_along(q, t, P[:, 2] - h)[:, :2] - P[:, :2], axis=1)
    ok = np.isfinite(miss) & (miss < 1e-6)
    spots = _along(P, t, layout.screen_z_mm - layout.plate_z_mm)
    return ChiefRays(q, normals, t, spots, ok)
