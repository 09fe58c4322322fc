"""The field's degradations of a render: motion blur (``[motion]``) and the sensor (``[sensor]``).

Sea water (``[water_optics]``, :mod:`mitsuba_wai.seawater`) and daylight (``[ambient]``,
:mod:`mitsuba_wai.ambient`) act inside the renders; this module records their derived values.

Both are off by default and then cost nothing: :func:`render_exposure` is one
:meth:`FrameRenderer.render <mitsuba_wai.render.FrameRenderer.render>` and :func:`sense` is
not called.

Motion blur
-----------
The surface moves during the exposure ``T`` (``[motion].exposure_s``): the image is the mean of
``N`` sub-frames rendered at the midpoints of ``N`` equal slices of ``[t - T/2, t + T/2]``
(``t = [waves].time_s``: the exposure is centred on the frame's time, whose surface is the
truth written beside the images). The sub-frames share the loaded scenes (only the mesh is
swapped) and split the samples per pixel between them (``ceil(spp / N)`` each, at least one):
a blurred frame takes about the sharp frame's samples (more when ``N > spp``) plus, per
sub-frame, a surface, a mesh update and a render launch (~0.1 s each at the paper's size).

The sub-frame rule (:func:`motion_rates`): from the wave model's spectrum, the r.m.s. rates of
the slope vector and of the height are

    sdot = sqrt(sum a^2 k^2 omega^2 / 2)  (1/s),    etadot = sqrt(sum a^2 omega^2 / 2)  (mm/s),

taken at :data:`MOTION_SIGMAS` (3) standard deviations as the practical maximum (the rate's
magnitude exceeds 3 r.m.s. with probability ~exp(-9) = 1e-4 for isotropic seas). They move

- a spot on the diffuser (camera s) by ``2 (h0 - z_h)(1 + tan^2 th) sdot + 2 tan th etadot``
  mm/s (the reflected ray turns by twice the slope change and meets the diffuser obliquely;
  a higher mirror shifts the reflection point and the return path by ``tan th`` each; ``th``:
  the steepest incidence among the dots in view), converted to pixels by camera s's pixel
  footprint on the diffuser;
- the view (camera v) by at most ``(1 - 1/n) sdot / (pitch / f)`` px/s (the refracted ray turns
  by ``(n - 1)`` times the slope change; seen from under water the object's shift subtends at
  most ``1/n`` of that).

``N = ceil(T * max(rate_s, rate_v) / max_shift_px)``, clipped to ``[1, max_subframes]``: the
image moves less than ``max_shift_px`` between consecutive sub-frames (default 1 px, under the
dots' blur: a paper dot is ~1.4 px standard deviation in camera s, and Gaussians spaced under
their sigma average into a smooth streak). The rule is conservative (3 r.m.s., the steepest
dot); when the cap binds, ``scene.json`` says ``capped``.

Sensor
------
:func:`sense` passes the four images through :mod:`wai_core.sensor` with each camera's exposure
(:func:`resolve_exposure`, from its flat-water reference unless configured): the wavy images
(``pattern``, ``view``) get one frame's noise; ``pattern_flat``, a calibration a user would
average, the mean of ``[sensor].reference_frames`` noisy frames (0: noiseless); ``view_truth``,
the ground truth, is noiseless (the sensor's expectation: same exposure, clipped at the well,
not quantised), so restored views and truth stay comparable.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai.waves import sea_surface
from wai_core import sensor as sensors
from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield


class RendersFrames(Protocol):
    """Renders the pattern (camera s) and / or the view (camera v) through a surface: what
    :func:`render_exposure` needs of :class:`mitsuba_wai.render.FrameRenderer` (not imported:
    the renderer imports this module)."""

    def render(
        self, surface: Heightfield, seed: int, which: tuple[str, ...] = ...,
        spp: int | dict[str, int] | None = ..., crosstalk: bool = ...,
    ) -> dict[str, NDArray[np.float32]]: ...


__all__ = [
    "MOTION_SIGMAS",
    "RendersFrames",
    "SubframePlan",
    "degradation_record",
    "motion_rates",
    "render_exposure",
    "resolve_exposure",
    "sense",
    "subframe_plan",
]

MOTION_SIGMAS = 3.0
"""Standard deviations of the slope and height rates taken as their maximum."""

# Sub-frame k's sampler seed is offset by k times this odd constant (distinct noise per slice).
SUBFRAME_SEED_STRIDE = 0x9E3779B1

# Which camera takes which image, and how its noise is drawn: one frame, an averaged
# reference, or none (ground truth).
CAMERA = {"pattern": "s", "pattern_flat": "s", "view": "v", "view_truth": "v"}
_REFERENCE = {"s": "pattern_flat", "v": "view_truth"}


@dataclass(frozen=True)
class SubframePlan:
    """How an exposure is sliced.

    Attributes
    ----------
    times_s : (N,) tuple of float
        Sub-frame times, s (the midpoints of ``N`` equal slices of the exposure).
    shift_rate_px_s : dict of str to float
        Practical maximum image speed of ``pattern`` (camera s) and ``view`` (camera v), px/s.
    capped : bool
        ``N`` was clipped to ``[motion].max_subframes`` (the blur is then under-sampled).
    """

    times_s: tuple[float, ...]
    shift_rate_px_s: dict[str, float]
    capped: bool = False

    @property
    def n(self) -> int:
        """Number of sub-frames."""
        return len(self.times_s)


def motion_rates(cfg: SystemConfig) -> dict[str, float]:
    """The practical maximum image speeds of both systems under ``cfg``'s waves (see the
    module docstring), px/s, with the rates they derive from (they scale with the waves'
    ``height_scale``).

    Parameters
    ----------
    cfg : SystemConfig

    Returns
    -------
    dict
        ``pattern`` and ``view`` (px/s), ``slope_rate_1_s`` and ``height_rate_mm_s`` (at
        :data:`MOTION_SIGMAS` r.m.s.), ``tan_incidence`` (steepest dot in view).
    """
    from wai_core.layout import flat_pattern_hits

    sea = sea_surface(cfg.waves)
    a = sea.amplitudes_mm
    k, w = sea.k_rad_per_mm[:, None], sea.omega_rad_s[:, None]
    sdot = MOTION_SIGMAS * float(np.sqrt(np.sum((a * k * w) ** 2) / 2))
    etadot = MOTION_SIGMAS * float(np.sqrt(np.sum((a * w) ** 2) / 2))
    lever = cfg.water.h0_mm - cfg.diffuser.z_mm
    q, s, seen = flat_pattern_hits(cfg)
    horiz = np.linalg.norm((q - s)[seen, :2], axis=1)
    tan_th = float(horiz.max() / lever) if horiz.size else 0.0
    cam_s = cfg.rig.camera_s
    centre = np.array([*np.mean(s[seen], axis=0)[:2], cfg.diffuser.z_mm]) if seen.any() else (
        np.array([*cam_s.pose.center_lab_mm[:2], cfg.diffuser.z_mm])
    )
    depth = float(cam_s.pose.points_to_cam(centre[None])[0, 2])
    footprint_s = cam_s.pixel_pitch_mm / cfg.camera_s.focal_mm * abs(depth)
    spot_mm_s = 2 * lever * (1 + tan_th**2) * sdot + 2 * tan_th * etadot
    cam_v = cfg.camera_v
    view = (1 - 1 / cfg.water.n_water) * sdot / (cam_v.sensor_width_mm / cam_v.width_px
                                                  / cam_v.focal_mm)
    return {
        "pattern": spot_mm_s / footprint_s, "view": float(view), "slope_rate_1_s": sdot,
        "height_rate_mm_s": etadot, "tan_incidence": tan_th,
    }


def subframe_plan(cfg: SystemConfig) -> SubframePlan:
    """The sub-frames of ``cfg``'s exposure by the rule of the module docstring; one at
    ``time_s`` when ``[motion].exposure_s`` is 0."""
    m, t = cfg.motion, cfg.waves.time_s
    if m.exposure_s <= 0:
        return SubframePlan((t,), {"pattern": 0.0, "view": 0.0})
    rates = motion_rates(cfg)
    shift = {k: rates[k] for k in ("pattern", "view")}
    wanted = math.ceil(m.exposure_s * max(shift.values()) / m.max_shift_px - 1e-9)
    n = min(max(wanted, 1), m.max_subframes)
    times = tuple(t + m.exposure_s * ((i + 0.5) / n - 0.5) for i in range(n))
    return SubframePlan(times, shift, capped=wanted > m.max_subframes)


def render_exposure(
    renderer: RendersFrames,
    cfg: SystemConfig,
    surface: Heightfield,
    seed: int,
    which: tuple[str, ...] = ("pattern", "view"),
    spp: int | None = None,
    surface_at: Callable[[float], Heightfield] | None = None,
    plan: SubframePlan | None = None,
) -> dict[str, NDArray[np.float32]]:
    """Render through ``surface``, blurred over the exposure when ``[motion]`` asks for it.

    Parameters
    ----------
    renderer : RendersFrames
        Loaded for ``cfg``'s geometry (any time).
    cfg : SystemConfig
        The frame's configuration: its ``[waves].time_s``, ``[motion]`` and ``[render]``.
    surface : Heightfield
        The surface at the frame's time (rendered alone when there is no motion).
    seed : int
        Sampler seed; sub-frame ``k`` uses ``seed + k * SUBFRAME_SEED_STRIDE`` (mod 2^32).
    which : tuple of str
        ``"pattern"`` and/or ``"view"``.
    spp : int, optional
        Samples per pixel of the whole exposure (default: the configuration's); sub-frames
        get ``ceil(spp / N)`` each.
    surface_at : callable, optional
        The surface at a time, s, on the renderer's grid; None: a static surface (a given
        heightfield, flat water), never blurred.
    plan : SubframePlan, optional
        The sub-frames (default: :func:`subframe_plan` ``(cfg)``).

    Returns
    -------
    dict of str to (H, W, 3) ndarray of float32
        The mean of the sub-frames' images (exactly the sharp image when ``N = 1``).
    """
    if surface_at is None or cfg.motion.exposure_s <= 0:
        return renderer.render(surface, seed, which, spp)
    plan = subframe_plan(cfg) if plan is None else plan
    if plan.n == 1:
        return renderer.render(surface_at(plan.times_s[0]), seed, which, spp)
    # The samples of the exposure are shared between its slices.
    full = {"pattern": spp or cfg.render.spp_pattern, "view": spp or cfg.render.spp_view}
    sub_spp = {key: max(1, math.ceil(full[key] / plan.n)) for key in which}
    total: dict[str, NDArray[np.float64]] = {}
    for k, t in enumerate(plan.times_s):
        sub_seed = (int(seed) + k * SUBFRAME_SEED_STRIDE) % 2**32
        for key, img in renderer.render(surface_at(t), sub_seed, which, sub_spp).items():
            total[key] = total.get(key, 0.0) + img.astype(np.float64)
    return {key: (v / plan.n).astype(np.float32) for key, v in total.items()}


def resolve_exposure(cfg: SystemConfig, references: dict[str, NDArray]) -> SystemConfig:
    """``cfg`` with each camera's exposure (e- per radiance unit) fixed: the configured one,
    else :func:`wai_core.sensor.exposure_for` its flat-water reference (``pattern_flat`` for
    camera s, ``view_truth`` for camera v, linear radiance). Unchanged when the sensor is off.

    The resolved exposures are part of the configuration, so every frame of a sequence (and
    its ``scene.json``) uses and records the same camera setting.
    """
    s = cfg.sensor
    if not s.enabled:
        return cfg
    changes = {}
    for cam in ("s", "v"):
        key = f"electrons_per_unit_{cam}"
        if getattr(s, key) <= 0 and _REFERENCE[cam] in references:
            changes[key] = sensors.exposure_for(references[_REFERENCE[cam]], s)
    return cfg.replace("sensor", **changes) if changes else cfg


def sense(
    cfg: SystemConfig, images: dict[str, NDArray], frame: str = ""
) -> dict[str, NDArray[np.float32]]:
    """The images as the cameras read them, ``DN / F`` (see the module docstring).

    Parameters
    ----------
    cfg : SystemConfig
        With the sensor enabled and its exposures resolved (:func:`resolve_exposure`).
    images : dict of str to (H, W, 3) ndarray
        Linear radiance, keyed ``pattern``, ``pattern_flat``, ``view``, ``view_truth``.
    frame : str
        Prefix of the noise streams' names (a sequence's ``frameNNN``), so every frame draws
        its own noise from the scene seed.

    Returns
    -------
    dict of str to (H, W, 3) ndarray of float32
        The same keys, in [0, 1].
    """
    s = cfg.sensor
    out = {}
    for name, img in images.items():
        x = getattr(s, f"electrons_per_unit_{CAMERA[name]}")
        if x <= 0:  # unresolved: expose for this image itself
            x = sensors.exposure_for(img, s)
        stream = f"{frame}/{name}" if frame else name
        if name == "view_truth" or (name == "pattern_flat" and s.reference_frames == 0):
            dn = sensors.expose(img, x, s, None)
        else:
            frames = s.reference_frames if name == "pattern_flat" else 1
            dn = sensors.expose(img, x, s, sensors.noise_rng(cfg.waves.seed, stream), frames)
        out[name] = sensors.to_unit(dn, s)
    return out


def degradation_record(cfg: SystemConfig) -> dict[str, Any]:
    """What ``scene.json`` adds about the enabled degradations (empty when none is): the
    sensor's derived gain and full scale, the motion's sub-frames and image speeds."""
    out: dict[str, Any] = {}
    if cfg.sensor.enabled:
        s = cfg.sensor
        out["sensor"] = {
            "gain_e_per_dn": sensors.gain_e_per_dn(s), "full_scale_dn": sensors.full_scale_dn(s),
            "stored_as": "DN / full_scale (EXR, float); integer PNG at the ADC depth",
            "noise": {"pattern": "one frame", "view": "one frame",
                      "pattern_flat": f"mean of {s.reference_frames} frames"
                      if s.reference_frames else "noiseless",
                      "view_truth": "noiseless (ground truth)"},
        }
    if cfg.motion.exposure_s > 0:
        plan = subframe_plan(cfg)
        out["motion"] = dataclasses.asdict(plan) | {"subframes": plan.n}
    if cfg.water_optics.enabled:
        out["water_optics"] = _water_record(cfg)
    if cfg.ambient.enabled:
        out["ambient"] = _ambient_record(cfg)
    return out


def _water_record(cfg: SystemConfig) -> dict[str, Any]:
    """The water's effective coefficients and what they do to system S's mean path."""
    from mitsuba_wai.seawater import coefficients_per_mm, glow_sigma_px, pattern_path_lengths_mm

    a, b = coefficients_per_mm(cfg.water_optics)
    lengths = pattern_path_lengths_mm(cfg)
    mean_mm = float(lengths.mean()) if lengths.size else float("nan")
    return {
        "absorption_per_m": (a * 1000).tolist(), "scattering_per_m": (b * 1000).tolist(),
        "pattern_mean_path_mm": mean_mm,
        "pattern_direct_transmittance": np.exp(-(a + b) * mean_mm).tolist(),
        "glow_sigma_px": {"pattern": glow_sigma_px(cfg, "S"), "view": glow_sigma_px(cfg, "V")},
        "model": "Beer-Lambert exp(-(a+b)L) per particle path (S) and per pixel (V), "
                 "plus forward_fraction of the scattered light as a Gaussian glow",
    }


def _ambient_record(cfg: SystemConfig) -> dict[str, Any]:
    """The daylight's derived values: sun direction, the sky's radiance on the diffuser."""
    from mitsuba_wai.ambient import hemispherical_reflectance, sky_on_diffuser, sun_direction

    return {
        "sun_direction_lab": sun_direction(cfg.ambient).tolist(),
        "sky_hemispherical_reflectance": hemispherical_reflectance(cfg.water.n_water),
        "sky_on_diffuser": sky_on_diffuser(cfg).tolist(),
        "model": "S: sun by particle tracing (directionalarea, refracting surface, flat skirt "
                 "beyond the waves), sky analytic (uniform); V: constant sky, far sun disk",
    }
