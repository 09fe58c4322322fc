"""One frame of a sweep: render it in memory, restore it, score it, and say how it went.

Sweeps (``wai experiment tradeoffs``, ``wai experiment stability``) are many independent frames,
each described by a *point*: a flat dict of JSON-able values (so it can be hashed, shipped to a
Dask worker and written as a table row). :func:`evaluate_frame` turns one point into one row.

Point keys (all optional except ``config`` and ``seed``)
--------------------------------------------------------
``config`` (str)
    Scene TOML, e.g. ``scenes/paper.toml``.
``seed`` (int)
    Wave phases, render noise and sensor noise.
``wind_mps``, ``spacing_px``, ``z_h_mm``, ``spp_pattern``
    Override the wind speed U (m/s), the pattern spacing D (panel pixels), the diffuser height
    z_h (mm) and the pattern's samples per pixel.
``code`` (str, default the scene's)
    The pattern's ``[pattern].code``: ``"none"`` (matched by ordering) or ``"colour"``
    (decoded, :mod:`restoration.features.decode`).
``amplitude`` (float, default 1)
    The waves' ``[waves].height_scale``: heights and slopes scaled at fixed U (steeper waves
    of the same shape).
``signal_e``, ``read_noise_e`` (float, e-), ``bits`` (int)
    Any of them turns the scene's ``[sensor]`` on (:mod:`wai_core.sensor`: shot noise, read
    noise, full well, ADC) with these overrides: ``signal_e`` electrons at the 99.9th
    percentile of each camera's flat-water reference (the full well is raised to twice that
    if it is smaller), ``read_noise_e`` the read noise, ``bits`` the ADC depth. The wavy
    images get one frame's noise, the flat pattern the mean of ``reference_frames``, the view
    truth none (:mod:`mitsuba_wai.degrade`).
``exposure_s`` (float, s)
    Motion blur: the scene's ``[motion].exposure_s`` (the surface moves during the exposure).
``turbidity``, ``forward_fraction`` (float)
    Either turns the scene's ``[water_optics]`` on (sea water, :mod:`mitsuba_wai.seawater`)
    with these values: ``turbidity`` scales the scattering, ``forward_fraction`` is the share
    of the scattered light that arrives as a veiling glow.
``ambient_level`` (float)
    Above 0 turns the scene's ``[ambient]`` on (sky and sun, :mod:`mitsuba_wai.ambient`) with
    its sky radiance and sun irradiance multiplied by this (the defaults: the level is the sky's
    radiance, the object's white = 1, with a sun of 10 times it).
``integrators`` (str, default the pipeline's)
    Comma-separated integrator names: each is run on the same frame, columns get a suffix.
``warp_steps`` (str)
    Comma-separated warp steps (px): the reverse trace is run at each on the same surface.
``refinements`` (str)
    Comma-separated names of :data:`REFINEMENTS` run on the same frame (columns get a suffix).
``render_overrides`` (str)
    JSON object of ``"section.key"`` values (:func:`wai_core.config.with_keys`) that only the
    render gets: physics the restoration does not know (``wai experiment budget``); the
    restoration, its calibration and the correspondence check use the scene without them,
    unless ``modelled``.
``modelled`` (bool, default false)
    The restoration is told the ``render_overrides`` too (its calibration is the rendered
    rig: ports, lenses, the water's index), its images read as a capture's are (resampled
    into the devices' ideal pinholes): the budget's "modelled" column.
``method`` (str, default ``"structured-light"``)
    The restoration: ``structured-light``, or ``structured-light-view`` (its level pinned by
    camera v's view of the object, :mod:`restoration.view_level`; the render's flat-water view
    is its ``view_flat``, as for a folder of ``wai render``). Both take the same options.
``repeats`` (int, default 3)
    Timed restorations per variant; the median is reported.

Row
---
The point's fields, then ``frame_status`` (``ok``; ``failed: <why>`` when the restoration
refused the frame; ``wrong_labels`` when more than 5 % of the kept correspondences are wrong;
otherwise the restoration's own truth-free status: ``sparse``, ``inconsistent``,
``gauge_level``, ``uncertain_level``, ``dark_view``, see :mod:`restoration.result`;
``method_status`` is that status alone, without the truth's ``wrong_labels``), the level and
its standard error (``anchor_mm``, ``anchor_sigma_mm``), the forward-consistency residual
(``residual_median_px``, ``residual_p95_px``, ``residual_threshold_px``, and the tail rule's
``residual_local_p95_px``), the
correspondence counts against the geometric model (``n_in_view``, ``n_matched``,
``n_correct``, ``fraction_correct`` of the dots in view, ``label_precision`` of the kept
ones), eq. 35's effective slope amplitude ``phi_deg``, the
surface and view scores and the timings. A point that runs several variants
(``integrators``, ``warp_steps``, ``refinements``) has their scores and timings under suffixed
names, each with its own truth-free status (``variant_status_<suffix>``); ``frame_status`` and
``method_status`` are the last variant's.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from typing import Any

import numpy as np

from wai_core.config import SystemConfig, with_keys
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield
from wai_core.system import load_rig

# A matched spot farther than this from the model's spot for its label is a wrong label.
CORRECT_RADIUS_PX = 3.0
# More wrong labels than this fraction of the kept ones make the frame's status "wrong_labels".
WRONG_LABEL_FRACTION = 0.05


def frame_config(point: dict[str, Any]) -> SystemConfig:
    """The configuration of one point: the scene file with the point's overrides."""
    cfg = load_rig(point["config"]).replace("waves", seed=int(point["seed"]))
    if point.get("wind_mps") is not None:
        cfg = cfg.replace("waves", wind_speed_m_s=float(point["wind_mps"]))
    if point.get("amplitude") is not None:
        cfg = cfg.replace("waves", height_scale=float(point["amplitude"]))
    if point.get("spacing_px") is not None:
        cfg = cfg.replace("pattern", spacing_px=float(point["spacing_px"]))
    if point.get("code"):
        cfg = cfg.replace("pattern", code=str(point["code"]))
    if point.get("z_h_mm") is not None:
        cfg = cfg.replace("diffuser", z_mm=float(point["z_h_mm"]))
    if point.get("spp_pattern") is not None:
        cfg = cfg.replace("render", spp_pattern=int(point["spp_pattern"]))
    if point.get("exposure_s") is not None:
        cfg = cfg.replace("motion", exposure_s=float(point["exposure_s"]))
    water = {k: float(point[k]) for k in ("turbidity", "forward_fraction")
             if point.get(k) is not None}
    if water:
        cfg = cfg.replace("water_optics", enabled=True, **water)
    if point.get("ambient_level"):
        level, amb = float(point["ambient_level"]), cfg.ambient
        cfg = cfg.replace("ambient", enabled=True, sky_radiance=level * amb.sky_radiance,
                          sun_irradiance=level * amb.sun_irradiance)
    sensor = {k: point[k] for k in ("signal_e", "read_noise_e", "bits") if point.get(k) is not None}
    if sensor:
        changes: dict[str, Any] = {"enabled": True}
        if "signal_e" in sensor:
            full_well = max(cfg.sensor.full_well_e, 2.0 * float(sensor["signal_e"]))
            changes.update(full_well_e=full_well,
                           signal_level=float(sensor["signal_e"]) / full_well)
        if "read_noise_e" in sensor:
            changes["read_noise_e"] = float(sensor["read_noise_e"])
        if "bits" in sensor:
            changes["bits"] = int(sensor["bits"])
        cfg = cfg.replace("sensor", **changes)
    return cfg


def render_frame(cfg: SystemConfig) -> tuple[dict[str, Any], Any]:
    """Render the four images of one frame in memory, blurred (``[motion]``) and read by the
    sensor (``[sensor]``) when enabled; returns them (with ``render_s_pattern`` and
    ``render_s_view``, the wavy renders' wall times, and ``subframes``) and the true surface
    (at mid-exposure)."""
    from mitsuba_wai import (
        FrameRenderer,
        flat_like,
        render_exposure,
        render_seed,
        resolve_exposure,
        sense,
        subframe_plan,
        wave_surface,
    )

    h0 = cfg.water.h0_mm

    def surface_at(t: float) -> Heightfield:
        return wave_surface(cfg.replace("waves", time_s=t))

    surface = surface_at(cfg.waves.time_s)
    renderer = FrameRenderer(cfg, surface)
    seed = render_seed(cfg)
    plan = subframe_plan(cfg)
    images: dict[str, Any] = {}
    for system in ("pattern", "view"):
        t0 = time.perf_counter()
        images[system] = render_exposure(
            renderer, cfg, surface, seed, (system,), surface_at=surface_at, plan=plan
        )[system]
        images[f"render_s_{system}"] = time.perf_counter() - t0
    flat = renderer.render(flat_like(surface, h0), seed, crosstalk=False)
    images["pattern_flat"], images["view_truth"] = flat["pattern"], flat["view"]
    if cfg.sensor.enabled:
        names = ("pattern", "pattern_flat", "view", "view_truth")
        cfg = resolve_exposure(cfg, images)
        images.update(sense(cfg, {k: images[k] for k in names}))
    images["subframes"] = plan.n
    return images, surface


def correspondence_counts(cfg: SystemConfig, surface: Heightfield, features: Any) -> dict:
    """Kept correspondences checked against the geometric model's spot for each label."""
    from wai_core.forward import predict_spots

    ij_true, px_true = predict_spots(cfg, surface)
    index = {tuple(k): n for n, k in enumerate(ij_true.tolist())}
    rows = np.array([index.get(tuple(k), -1) for k in features.ij.tolist()], dtype=np.int64)
    known = rows >= 0
    err = np.full(len(rows), np.inf)
    err[known] = np.linalg.norm(features.spot_px[known] - px_true[rows[known]], axis=1)
    n_correct = int(np.sum(err < CORRECT_RADIUS_PX))
    return {
        "n_in_view": int(len(px_true)),
        "n_matched": int(len(rows)),
        "n_correct": n_correct,
        "n_wrong": int(len(rows) - n_correct),
        "fraction_correct": n_correct / max(len(px_true), 1),
        "label_precision": n_correct / len(rows) if len(rows) else None,
        "spot_median_px": float(np.median(err[err < CORRECT_RADIUS_PX])) if n_correct else None,
    }


def _names(value: Any, default: str) -> list[str]:
    return [s.strip() for s in str(value or default).split(",") if s.strip()]


_WARMED: set[str] = set()
"""Restoration variants (options' repr) this process has run once: a sweep's worker compiles
each variant's kernels on its first frame, which would otherwise be timed (hundreds of ms)."""


WARM_TRIES = 3
"""Restorations of one timed repeat until one runs no kernel that was not loaded yet."""


def _timed_restore(images: dict, cal: Any, method: Any, repeats: int) -> tuple[Any, dict]:
    """Restore ``repeats`` times with ``method``; the last result and the median time of each
    stage, ms (the result alone when the frame failed). Each variant runs once untimed in a
    process, and a timed restoration that loaded or compiled a kernel all the same (a code path
    this variant's first frame did not take) is run again: the timings are of warm code."""
    from restoration import kernel_activity

    if repr(method) not in _WARMED:  # compile this variant's kernels outside the timing
        method(images, cal)
        _WARMED.add(repr(method))
    stages: dict[str, list[float]] = {}
    result = None
    for _ in range(max(int(repeats), 1)):
        for _ in range(WARM_TRIES):
            with kernel_activity() as activity:
                result = method(images, cal)
            if activity.warm:
                break
        if not result.restored:
            return result, {}
        for name, ms in result.timings_ms.items():
            stages.setdefault(name, []).append(ms)
        for name, ms in result.surface.timings_ms.items():
            stages.setdefault(f"surface.{name}", []).append(ms)
    return result, {k: float(np.median(v)) for k, v in stages.items()}


def _scores(result: Any, images: dict, cal: Any, surface: Heightfield) -> dict[str, Any]:
    from restoration import Truth, score

    s = score(
        result, images["view"] / cal.view_gain, cal,
        Truth(surface, images["view_truth"] / cal.view_gain),
    )
    return {
        "variant_status": result.status,
        "wai_rmse_mm": s.surface["rmse_mm"],
        "wai_rmse_demeaned_mm": s.surface["rmse_demeaned_mm"],
        "wai_max_abs_mm": s.surface["max_abs_mm"],
        # None where the view was restored nowhere on the object
        "distorted_ssim": (s.distorted or {}).get("ssim"),
        "restored_ssim": (s.restored or {}).get("ssim"),
        "corner_std_distorted_px": s.corner_std_distorted_px,
        "corner_std_restored_px": s.corner_std_restored_px,
        "anchor_method": result.surface.anchor.method,
        "anchor_mm": result.surface.anchor.anchor_mm,
        "anchor_sigma_mm": result.surface.anchor.sigma_mm,
        "refine_passes": result.surface.anchor.refine_passes,
        "residual_median_px": result.consistency.median_px,
        "residual_p95_px": result.consistency.p95_px,
        "residual_local_p95_px": result.consistency.local_p95_px,
        "residual_threshold_px": result.consistency.threshold_px,
    }


def evaluate_frame(point: dict[str, Any]) -> dict[str, Any]:
    """Render, restore and score the frame of ``point`` (see the module docstring)."""
    from restoration import RestorationFailed, StructuredLightOptions
    from wai_core.limits import correspondence_limit, effective_phi_deg
    from wai_core.optics import radiance_gain

    cfg = frame_config(point)
    method_cls = method_class(point.get("method"))
    row: dict[str, Any] = {"phi_max_deg": correspondence_limit(cfg)["phi_max_deg"]}
    rendered = cfg
    if point.get("render_overrides"):
        rendered = with_keys(cfg, json.loads(point["render_overrides"]))
    try:
        images, surface = render_frame(rendered)
    except (WaiInputError, ValueError) as exc:  # e.g. waves that reach the diffuser
        row["frame_status"] = f"failed: cannot render: {exc}"
        return row
    for key in ("render_s_pattern", "render_s_view", "subframes"):
        row[key] = images.pop(key)
    row["phi_deg"] = effective_phi_deg(surface, cfg)
    if point.get("modelled"):
        cfg = rendered
    cal = method_cls.calibration_type(cfg, radiance_gain(cfg.water.n_water))
    if "view_flat" in cal.IMAGES:  # a render's flat-water view, as a render folder's
        images["view_flat"] = images["view_truth"]
    images.update({name: cal.to_pinhole(name, images[name])
                   for name in ("view", "view_flat", "view_truth") if name in images})
    base = StructuredLightOptions()
    integrators = _names(point.get("integrators"), base.integrator)
    steps = [int(s) for s in _names(point.get("warp_steps"), str(base.warp_step_px))]
    refinements = _names(point.get("refinements"), "default")
    repeats = int(point.get("repeats", 3))
    try:
        cal.prepare(images["pattern_flat"])
        for name in integrators:
            for step in steps:
                for ref in refinements:
                    options = replace(base, integrator=name, warp_step_px=step,
                                      **REFINEMENTS[ref])
                    result, ms = _timed_restore(images, cal, method_cls(options), repeats)
                    if result.status == "failed":
                        raise RestorationFailed(result.message)
                    suffix = _suffix(name, step, integrators, steps)
                    suffix += f"_{ref}" if len(refinements) > 1 else ""
                    scores = _scores(result, images, cal, surface)
                    row.update({f"{k}{suffix}": v for k, v in scores.items()})
                    row.update({f"ms_{k}{suffix}": v for k, v in ms.items()})
        row.update(correspondence_counts(cfg, surface, result.features))
        row.update({f"count_{k}": v for k, v in result.features.counts.items()})
    except (WaiInputError, RestorationFailed) as exc:
        # A refused frame yields no usable correspondence: it counts as none correct.
        row.update(n_correct=0, fraction_correct=0.0, frame_status=f"failed: {exc}")
        return row
    # Wrong labels need the truth; every other verdict is the restoration's own (truth-free).
    wrong = row["n_wrong"] > WRONG_LABEL_FRACTION * max(row["n_matched"], 1)
    row["method_status"] = result.status
    row["frame_status"] = "wrong_labels" if wrong else result.status
    return row


def method_class(name: str | None) -> type:
    """The restoration a point names (``method``, found by
    :func:`restoration.methods.method_class`): one of the structured light's family (it takes
    the structured light's options), :class:`~restoration.StructuredLight` by default.

    >>> method_class("structured-light-view").name
    'structured-light-view'
    """
    from restoration import METHODS, StructuredLight
    from restoration.methods import method_class as named

    cls = named(name or StructuredLight.name)
    if not (isinstance(cls, type) and issubclass(cls, StructuredLight)):
        family = [n for n, c in METHODS.items() if issubclass(c, StructuredLight)]
        raise WaiInputError(f"point: method must be one of {', '.join(family)}, not {name!r}")
    return cls


REFINEMENTS: dict[str, dict[str, Any]] = {
    "default": {},
    "converged": {"converge_mm": 0.0},
    "fit": {"fit_spots": True},
    "spot_bias": {"spot_bias": True},
}
"""Surface refinements a point may compare (``refinements``): the default (up to 8 passes
until converged to ``refine_tol_mm``, more only when they leave heights moving by
``converge_mm``), the fixed point always converged to 40 passes, the Gauss-Newton fit to
the spots (:mod:`restoration.fit`), and the spots corrected for their light centre's bias
(:mod:`restoration.spot_bias`)."""


def _suffix(name: str, step: int, names: list[str], steps: list[int]) -> str:
    """Column suffix of one variant: empty when only one variant runs."""
    parts = ([name] if len(names) > 1 else []) + ([f"step{step}"] if len(steps) > 1 else [])
    return "".join(f"_{p}" for p in parts)
