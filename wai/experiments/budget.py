"""``wai experiment budget``: what each effect the geometric model leaves out costs the restoration.

Every frame is rendered with one renderer-only effect (:data:`wai_core.config.RENDERER_EFFECTS`,
or the render's water index) at one magnitude, and restored by the default restoration on the
scene without it: the model the restoration has. An effect the restoration can be told
(:attr:`Effect.modelled`: the water's index, lenses, ports) is restored a second time on the
scene with it, as a calibrated rig would be (the "modelled" column); the ``real_rig`` effect
renders the realistic magnitudes of the effects that compose into one frame. Per effect and
magnitude the sweep reports the
surface RMSE (absolute and de-meaned), the restored view's corner STD, the status and the
forward-consistency residual, and where the RMSE passes the baseline's by
:data:`ADDED_LIMIT_MM` and passes 1 mm; the frames an
effect ruins (RMSE over 1 mm) must be flagged by the truth-free status.

The magnitudes run from zero (the baseline, every effect off) through a realistic value
(:data:`EFFECTS`, ``realistic``) and beyond. The frames are points of a Dask sweep
(:mod:`wai.sweep`), evaluated by :func:`wai.experiments.frame_eval.evaluate_frame` with the
effect as the point's ``render_overrides``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from wai.experiments.frame_eval import evaluate_frame
from wai.experiments.outputs import output_folder, publish, sweep_command, sweep_rows
from wai.experiments.stability import BAD_RMSE_MM, detection_rates, status_cell
from wai.sweep import SweepOptions
from wai_core.io import write_json

__all__ = [
    "ADDED_LIMIT_MM", "EFFECTS", "OK_SHARE", "Effect", "budget_points", "budget_summary",
    "run_budget",
]


@dataclass(frozen=True)
class Effect:
    """One swept effect.

    Attributes
    ----------
    label : str
        Axis label: what the magnitude is, with its unit.
    values : tuple of float
        Magnitudes of the full sweep (the baseline, magnitude 0, is shared by all effects).
    quick : tuple of float
        Magnitudes of ``--quick``.
    realistic : float
        A magnitude a real rig of the paper's scale has (for the summary table).
    overrides : callable
        The render's ``"section.key"`` changes at magnitude ``m``.
    modelled : bool
        The restoration can be told the effect (its scene keys are a rig's or the water's):
        each frame is restored a second time with them.
    method : str
        The told restoration's method (:func:`~wai.experiments.frame_eval.method_class`).
    """

    label: str
    values: tuple[float, ...]
    quick: tuple[float, ...]
    realistic: float
    overrides: Callable[[float], dict[str, Any]]
    modelled: bool = False
    method: str = "structured-light"


def _both_cameras(key: str, value: Callable[[float], Any]) -> Callable[[float], dict[str, Any]]:
    return lambda m: {f"{cam}.{key}": value(m) for cam in ("camera_s", "camera_v")}


EFFECTS: dict[str, Effect] = {
    "polarisation": Effect(
        "E-field angle on the panel (deg; 0: the panel's x axis)", (0.0, 45.0, 90.0),
        (0.0, 90.0), 0.0,
        lambda m: {"pattern.polarisation": "linear", "pattern.polarisation_deg": m},
    ),
    "index": Effect(
        "water index of the render (the model keeps 4/3)", (1.335, 1.338, 1.340, 1.343),
        (1.340,), 1.340, lambda m: {"water.n_water": m}, modelled=True,
    ),
    "dispersion": Effect(
        "salinity (PSU) of Quan & Fry's index per channel at 20 C", (0.0, 35.0), (35.0,), 35.0,
        # 12 view samples: a channel is picked per sample, so each gets the baseline's 4 (at
        # fewer the view's colour noise, not the index, would set the corners' spread).
        lambda m: {"water.index_model": "quan_fry", "water.salinity_psu": m,
                   "render.spp_view": 12}, modelled=True,
    ),
    "k1_s": Effect("camera s radial distortion -k1", (0.05, 0.1, 0.2, 0.3), (0.2,), 0.2,
                   lambda m: {"camera_s.distortion": [-m, 0.0, 0.0, 0.0, 0.0]},
                   modelled=True),
    "k1_v": Effect("camera v radial distortion -k1", (0.05, 0.1, 0.2, 0.3), (0.2,), 0.2,
                   lambda m: {"camera_v.distortion": [-m, 0.0, 0.0, 0.0, 0.0]},
                   modelled=True),
    "principal_point": Effect(
        "principal point offset of both cameras (px, along x and y)", (2.0, 5.0, 10.0, 20.0),
        (10.0,), 10.0, _both_cameras("principal_offset_px", lambda m: [m, m]), modelled=True,
    ),
    "port": Effect("flat port thickness on both cameras (mm)", (2.0, 5.0, 10.0), (5.0,), 5.0,
                   _both_cameras("port_thickness_mm", lambda m: m), modelled=True),
    "port_projector": Effect("flat port thickness on the projector (mm)", (2.0, 5.0, 10.0),
                             (5.0,), 5.0, lambda m: {"projector.port_thickness_mm": m},
                             modelled=True),
    "aperture": Effect(
        "projector aperture (mm), focused at 400 mm", (1.0, 2.0, 5.0), (2.0,), 2.0,
        lambda m: {"projector.aperture_mm": m, "projector.focus_mm": 400.0},
    ),
    "diffuser_profile": Effect(
        "diffuser lobe half width (deg; Lambertian: none)", (60.0, 30.0, 15.0), (30.0,), 30.0,
        lambda m: {"diffuser.half_width_deg": m},
    ),
    "diffuser_reflectance": Effect("diffuser back-reflection", (0.1, 0.3, 0.5), (0.3,), 0.3,
                                   lambda m: {"diffuser.reflectance": m}),
    "diffuser_blur": Effect("diffuser thickness blur (mm)", (0.2, 0.5, 1.0), (0.5,), 0.5,
                            lambda m: {"diffuser.blur_mm": m}),
    # 64 pattern samples: Mitsuba's roughdielectric picks reflection with probability F, so
    # at 4 a spot keeps F of its particles and the render's noise, not the roughness, would
    # dominate (at alpha 0.005: frames failed at 4 spp, 0.44 mm at 64).
    # Told, the restoration corrects each spot for its microfacets' shift
    # (StructuredLightOptions.spot_bias, on by default where the scene's water is rough) and
    # takes the level from the view, which needs a textured object: the rough spots leave the
    # dots' own level uncertain (docs/results.md, "The level from the view").
    "roughness": Effect("water micro-roughness (GGX alpha), seen on a speckle object",
                        (0.002, 0.005, 0.01, 0.03), (0.005,), 0.01,
                        lambda m: {"water.roughness": m, "render.spp_pattern": 64,
                                   "object.texture": "speckle"},
                        modelled=True, method="structured-light-view"),
    "capillary": Effect(
        "spectrum cutoff (x omega_p), gravity-capillary waves", (3.0, 4.0, 6.0), (4.0,), 4.0,
        lambda m: {"waves.dispersion": "capillary", "waves.omega_max_rel": m},
    ),
    "crosstalk": Effect(
        "the projector's light on the object in camera v's view, x its brightness",
        (1.0, 10.0, 100.0), (10.0,), 1.0,
        lambda m: {"crosstalk.enabled": True, "crosstalk.scale": m},
    ),
    "crosstalk_filtered": Effect(
        "crosstalk x its brightness, camera v behind a red-pass filter (alone: red_filter)",
        (1.0, 10.0, 100.0), (10.0,), 1.0,
        lambda m: {"crosstalk.enabled": True, "crosstalk.scale": m,
                   "crosstalk.camera_v_filter": "red"},
    ),
    "red_filter": Effect(
        "a red-pass filter on camera v, no crosstalk (1: on)", (1.0,), (1.0,), 1.0,
        lambda m: {"crosstalk.camera_v_filter": "red"},
    ),
    "real_rig": Effect(
        "a real rig at once (1: every effect below at its realistic magnitude that composes),"
        " seen on a speckle object; told, with the view's level",
        (1.0,), (1.0,), 1.0, lambda m: {**REAL_RIG, "object.texture": "speckle"}, modelled=True,
        # Roughness and the sensor leave the dots' own level uncertain; a rig with both
        # systems takes it from the view, which needs a textured object (docs/results.md,
        # "The level from the view").
        method="structured-light-view",
    ),
}
"""The effects the budget sweeps, in the order of its table."""

REAL_RIG: dict[str, Any] = {
    **{f"{cam}.port_thickness_mm": 5.0 for cam in ("camera_s", "camera_v")},
    **{f"{cam}.principal_offset_px": [5.0, 5.0] for cam in ("camera_s", "camera_v")},
    "camera_s.distortion": [-0.05, 0.0, 0.0, 0.0, 0.0],
    "camera_v.distortion": [-0.1, 0.0, 0.0, 0.0, 0.0],
    "water.index_model": "quan_fry",
    "water.salinity_psu": 35.0,
    "water.temperature_c": 15.0,
    "water.roughness": 0.006,
    "ambient.enabled": True,
    "ambient.sky_radiance": 0.003,
    "ambient.sun_irradiance": 0.03,
    "render.spp_pattern": 64,
    "render.spp_view": 12,
    "sensor.enabled": True,
}
"""The ``real_rig`` effect: housings, lenses, sea water's index per channel, micro-roughness,
daylight (the sky at 0.003, the sun at 10 times it: the level the pattern holds to, about a
tenth of a spot's peak in the sun's caustics; docs/results.md, "Degradations") and sensor noise
in one render. Left out: polarised light (its own row: it dims spots, it does not move them),
the projector's port (its own row: it narrows the pattern, whose closer dots pass the ordering
limit on steeper seas whatever the model), and crosstalk (its own rows, with and without
camera v's red filter). Camera s keeps the paper's 2 mm lens behind its port, which narrows its
field by about the water's index: the pattern fills the frame, and 6 of seeds 0-23 are not
`ok`, most where the waves carry the pattern past the edge (docs/results.md, "Sixteen more
seeds")."""

ADDED_LIMIT_MM = 0.05
"""Surface RMSE (mm) added to the baseline's at which the report gives each effect's
magnitude (the baseline itself is near 0.05 mm on a few seeds); the other level is
:data:`~wai.experiments.stability.BAD_RMSE_MM`, absolute."""


def budget_points(
    config: Path, seeds: list[int], quick: bool, effects: list[str] | None = None
) -> list[dict[str, Any]]:
    """One point per effect, magnitude and seed, and a baseline (every effect off) per seed."""
    points = [{"effect": "none", "magnitude": 0.0, "config": str(config), "seed": s,
               "repeats": 1} for s in seeds]
    for name in effects or list(EFFECTS):
        effect = EFFECTS[name]
        for m in effect.quick if quick else effect.values:
            overrides = json.dumps(effect.overrides(m), sort_keys=True)
            for modelled in (False, True) if effect.modelled else (False,):
                extra = {"modelled": True} if modelled else {}
                if modelled and effect.method != "structured-light":
                    extra["method"] = effect.method
                points += [{"effect": name, "magnitude": float(m), "config": str(config),
                            "seed": s, "repeats": 1, "render_overrides": overrides, **extra}
                           for s in seeds]
    return points


def _stat(rows: list[dict[str, Any]], key: str, fn: Callable = np.mean) -> float:
    """``fn`` of the finite values of ``key`` over ``rows``; NaN when there are none."""
    vals = [float(r[key]) for r in rows if r.get(key) is not None]
    vals = [v for v in vals if np.isfinite(v)]
    return float(fn(vals)) if vals else float("nan")


def _modelled(row: dict[str, Any]) -> bool:
    """Whether a row's restoration was told its effect (a CSV row holds the flag as text)."""
    return str(row.get("modelled", "")).lower() in ("true", "1")


def _status(row: dict[str, Any]) -> str:
    if row.get("status", "ok") != "ok":
        return "error"
    return str(row.get("method_status") or row.get("frame_status")).split(":")[0]


def budget_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per effect and magnitude: frames, statuses and the shares of frames ``ok``, failed and
    ``sparse``, mean RMSE (absolute, de-meaned; over the frames that gave a surface), corner
    STD, residual; each effect's magnitude at which the RMSE passes the baseline's by
    :data:`ADDED_LIMIT_MM` (``"+0.05"``) and passes
    :data:`~wai.experiments.stability.BAD_RMSE_MM` (``"1"``), and its ``reach`` (the largest
    magnitude up to which every one has :data:`OK_SHARE` of its frames ``ok``; None when the
    first does not); and the detection of ruined frames."""
    base = [r for r in rows if r.get("effect") == "none"]
    out: dict[str, Any] = {"baseline": _entry(0.0, base), "effects": {}}
    for name in EFFECTS:
        told = [r for r in rows if r.get("effect") == name and _modelled(r)]
        sel = [r for r in rows if r.get("effect") == name and not _modelled(r)]
        if not sel:
            continue
        entries = [_entry(m, [r for r in sel if r["magnitude"] == m])
                   for m in sorted({r["magnitude"] for r in sel})]
        modelled = [_entry(m, [r for r in told if r["magnitude"] == m])
                    for m in sorted({r["magnitude"] for r in told})]
        crossing = {}
        limits = {f"+{ADDED_LIMIT_MM:g}": out["baseline"]["rmse_mm"] + ADDED_LIMIT_MM,
                  f"{BAD_RMSE_MM:g}": BAD_RMSE_MM}
        for key, limit in limits.items():
            over = [e["magnitude"] for e in entries if not e["rmse_mm"] <= limit]
            crossing[key] = over[0] if over else None
        # The reach: magnitudes up to the first where fewer than OK_SHARE of frames are ok.
        reach = None
        for e in entries:
            if e["ok_fraction"] < OK_SHARE:
                break
            reach = e["magnitude"]
        out["effects"][name] = {"label": EFFECTS[name].label, "entries": entries,
                                "modelled": modelled, "passes_mm": crossing, "reach": reach}
    effect_rows = [r for r in rows if r.get("effect") != "none"]
    out["detection"] = detection_rates([{**r, "sweep": r.get("effect")} for r in effect_rows])
    return out


OK_SHARE = 0.95
"""The share of frames that must restore ``ok`` at an effect's magnitude for the model to
reach it (a magnitude where more fail is past the restoration's reach, whatever the RMSE of
the frames that gave a surface)."""


def _entry(magnitude: float, group: list[dict[str, Any]]) -> dict[str, Any]:
    statuses: dict[str, int] = {}
    for r in group:
        statuses[_status(r)] = statuses.get(_status(r), 0) + 1
    n = max(len(group), 1)
    return {
        "magnitude": magnitude, "frames": len(group), "statuses": statuses,
        "ok_fraction": statuses.get("ok", 0) / n,
        "failed_fraction": (statuses.get("failed", 0) + statuses.get("error", 0)) / n,
        "sparse_fraction": statuses.get("sparse", 0) / n,
        "rmse_mm": _stat(group, "wai_rmse_mm"),
        "rmse_min_mm": _stat(group, "wai_rmse_mm", np.min),
        "rmse_max_mm": _stat(group, "wai_rmse_mm", np.max),
        "rmse_demeaned_mm": _stat(group, "wai_rmse_demeaned_mm"),
        "corner_std_px": _stat(group, "corner_std_restored_px"),
        "residual_median_px": _stat(group, "residual_median_px"),
    }


def budget_figure(summary: dict[str, Any], path: Path) -> None:
    """One panel per effect: RMSE (absolute and de-meaned) and corner STD against magnitude,
    the baseline and the limits drawn; hollow markers where any frame was not ``ok``."""
    from wai.figures import plt, save_figure

    effects = summary["effects"]
    if not effects:
        return
    cols = min(4, len(effects))
    rows_n = -(-len(effects) // cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(4.6 * cols, 3.6 * rows_n), squeeze=False)
    base = summary["baseline"]
    for ax, (name, eff) in zip(axes.ravel(), effects.items(), strict=False):
        ent = eff["entries"]
        x = np.arange(len(ent) + 1)
        for key, style, label in (("rmse_mm", "o-", "RMSE"),
                                  ("rmse_demeaned_mm", "s--", "RMSE de-meaned")):
            y = [base[key]] + [e[key] for e in ent]
            ax.plot(x, y, style, label=label)
            bad = [i + 1 for i, e in enumerate(ent) if set(e["statuses"]) - {"ok"}]
            ax.plot(bad, [y[i] for i in bad], "x", color="tab:red", ms=9)
        told = {e["magnitude"]: e for e in eff.get("modelled", [])}
        if told:
            y = [base["rmse_mm"]] + [told[e["magnitude"]]["rmse_mm"] if e["magnitude"] in told
                                     else np.nan for e in ent]
            ax.plot(x, y, "D-", color="tab:purple", label="RMSE, modelled")
        for limit in (base["rmse_mm"] + ADDED_LIMIT_MM, BAD_RMSE_MM):
            ax.axhline(limit, color="gray", ls=":", lw=0.8)
        for i, e in enumerate(ent, start=1):
            if e["rmse_mm"] is None or not np.isfinite(e["rmse_mm"]):  # no surface at all
                ax.annotate("all\nfailed", (i, 1.0), xycoords=("data", "axes fraction"),
                            ha="center", va="top", fontsize=7, color="tab:red")
        ax.set_xticks(x, ["off"] + [f"{e['magnitude']:g}" for e in ent])
        ax.set_xlim(-0.3, len(ent) + 0.3)
        ax.set_yscale("log")
        ax.set(title=name, xlabel=eff["label"], ylabel="surface RMSE (mm)")
        tw = ax.twinx()
        tw.plot(x, [base["corner_std_px"]] + [e["corner_std_px"] for e in ent], "^:",
                color="tab:green", label="corner STD (px)")
        tw.set_ylabel("corner STD (px)", fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="upper left")
    for ax in axes.ravel()[len(effects):]:
        ax.set_visible(False)
    fig.suptitle("Error budget: each effect rendered, the default restoration not knowing it "
                 "and (purple) told it (x: a frame not ok; dotted: baseline + 0.05 mm and "
                 "1 mm)")
    fig.tight_layout()
    save_figure(fig, path)


def budget_markdown(summary: dict[str, Any], command: str) -> str:
    """The summary table ("what the model must include") and one table per effect."""
    base = summary["baseline"]
    rates = summary["detection"]
    lines = ["# Error budget: what the geometric model must include", "",
             f"Command: `{command}`", "", "![budget](budget.png)", "",
             f"Baseline (every effect off): RMSE {base['rmse_mm']:.4f} mm, de-meaned "
             f"{base['rmse_demeaned_mm']:.4f} mm, corner STD {base['corner_std_px']:.3f} px, "
             f"statuses {base['statuses']}; per seed {base['rmse_min_mm']:.4f} .. "
             f"{base['rmse_max_mm']:.4f} mm, so differences of a few hundredths of a mm are "
             "the seeds' spread, not the effect.", "",
             f"The RMSE columns average the frames that gave a surface; the share of frames "
             f"`ok` says how many did (an effect is within reach up to the last magnitude "
             f"where at least {OK_SHARE:.0%} of the frames restore `ok`).", "",
             "Unmodelled: restored on the scene without the effect; modelled: restored on the "
             "scene with it (a calibrated rig; `-` where the restoration has nothing to be "
             "told).", "",
             "| effect | realistic magnitude | frames ok there | RMSE there (mm) | modelled: "
             "frames ok | modelled: RMSE (mm) | modelled: corner STD (px) | modelled within "
             f"baseline + {ADDED_LIMIT_MM:g} mm? | reach ({OK_SHARE:.0%} ok) up to | passes "
             f"baseline + {ADDED_LIMIT_MM:g} mm at | passes {BAD_RMSE_MM:g} mm at | must the "
             "model include it? |", "|" + " --- |" * 12]
    for name, eff in summary["effects"].items():
        real = EFFECTS[name].realistic
        at = next((e for e in eff["entries"] if e["magnitude"] == real), None)
        told = next((e for e in eff.get("modelled", []) if e["magnitude"] == real), None)
        rmse = at["rmse_mm"] if at else float("nan")
        share = f"{at['ok_fraction']:.0%} of {at['frames']}" if at else "-"
        verdict = _verdict(at, base)
        p = eff["passes_mm"]
        reach = "none of the magnitudes" if eff.get("reach") is None else f"{eff['reach']:g}"
        if told is None:
            modelled = "- | - | - | -"
        else:
            within = (told["ok_fraction"] >= OK_SHARE
                      and told["rmse_mm"] <= base["rmse_mm"] + ADDED_LIMIT_MM)
            modelled = (f"{told['ok_fraction']:.0%} | {told['rmse_mm']:.4f} | "
                        f"{told['corner_std_px']:.3f} | {'yes' if within else 'no'}")
        lines.append(f"| {name} | {real:g} | {share} | {rmse:.4f} | {modelled} | {reach} | "
                     f"{_fmt(p['+0.05'])} | {_fmt(p['1'])} | {verdict} |")
    lines += ["", f"Ruined frames (RMSE over {rates['bad_rmse_mm']:g} mm or failed): "
              f"{rates['bad']} of {rates['frames']}, flagged by the truth-free status: "
              f"{_pct(rates['detection_rate'])} (statuses {rates['bad_statuses']}); good "
              f"frames flagged: {_pct(rates['false_alarm_rate'])}.", ""]
    for name, eff in summary["effects"].items():
        lines += [f"## {name}: {eff['label']}", "",
                  "| magnitude | frames | ok | failed | sparse | statuses | RMSE (mm) | "
                  "de-meaned (mm) | corner STD (px) | residual (px) |", "|" + " --- |" * 10]
        told = [dict(e, told=True) for e in eff.get("modelled", [])]
        for e in [summary["baseline"]] + eff["entries"] + told:
            st = status_cell(e["statuses"])
            mag = "off" if e is summary["baseline"] else f"{e['magnitude']:g}"
            mag += " (modelled)" if e.get("told") else ""
            lines.append(f"| {mag} | {e['frames']} | {e['ok_fraction']:.0%} | "
                         f"{e['failed_fraction']:.0%} | {e['sparse_fraction']:.0%} | {st} | "
                         f"{e['rmse_mm']:.4f} | {e['rmse_demeaned_mm']:.4f} | "
                         f"{e['corner_std_px']:.3f} | {e['residual_median_px']:.3f} |")
        lines.append("")
    return "\n".join(lines)


VIEW_MARGIN_PX = 0.05
"""Corner STD (px) above the baseline's (and 1.5 times it) that makes an effect matter to the
view."""


def _verdict(at: dict[str, Any] | None, base: dict[str, Any]) -> str:
    """Whether the model must include an effect at its realistic magnitude: when it doubles
    the surface RMSE (and passes 0.05 mm), or raises the corner STD by half and by
    :data:`VIEW_MARGIN_PX`, or leaves frames not ok."""
    if at is None or not at["frames"]:
        return "not measured at it"
    why = []
    if not at["rmse_mm"] <= max(0.05, 2 * base["rmse_mm"]):
        why.append("surface")
    std, std0 = at["corner_std_px"], base["corner_std_px"]
    if std > max(1.5 * std0, std0 + VIEW_MARGIN_PX):
        why.append("view")
    if set(at["statuses"]) - {"ok"}:
        why.append("status")
    return f"yes ({', '.join(why)})" if why else "no"


def _fmt(value: float | None) -> str:
    return "never (in range)" if value is None else f"{value:g}"


def _pct(value: float) -> str:
    return "n/a (none)" if not np.isfinite(value) else f"{value:.0%}"


def run_budget(config: str | Path, out: str | Path, seeds: int, quick: bool = False,
               sweep: SweepOptions | None = None) -> dict[str, Any]:
    """Run the budget's sweep into ``out/budget.csv``; write the chart and the report.

    Parameters
    ----------
    config, out : str or Path
        The scene (a packaged name or a TOML file) and the output folder (made if missing), as
        :func:`wai.experiments.run_experiment` takes them.
    seeds : int
        Seeds 0..seeds-1 of every magnitude.
    quick : bool
        One magnitude per effect (two for polarisation).
    sweep : SweepOptions or None
        Where and how the sweep's points run; None: :class:`SweepOptions`' defaults.

    Returns
    -------
    dict
        :func:`budget_summary` of the sweep's rows.
    """
    out = output_folder(out)
    points = budget_points(config, list(range(seeds)), quick)
    rows = sweep_rows(points, evaluate_frame, out / "budget.csv", sweep)
    summary = budget_summary(rows)
    budget_figure(summary, out / "budget.png")
    text = budget_markdown(summary, sweep_command("budget", seeds, quick))
    write_json(out / "budget_summary.json", summary)
    publish(out / "budget.md", text)
    return summary
