"""``wai experiment tradeoffs``: speed against accuracy for each choice a user can make.

Four charts, each point the mean over seeds of frames rendered and restored by
:func:`wai.frame_eval.evaluate_frame` (the sweep runs on Dask, :mod:`wai.sweep`):

- pattern spacing D: surface RMSE against restoration time (end to end);
- integrators: surface RMSE against the surface stage's time (integration, anchor search and
  refinement included), every integrator on the same frames;
- pattern samples per pixel: spot-centre error against the geometric model against the
  pattern's render time;
- warp step of the reverse trace (the resolution at which rays are traced exactly before the
  restored image is interpolated): restored SSIM and corner STD against reverse-trace time;
- surface refinement: the default fixed point, the fixed point always converged, and the
  Gauss-Newton fit to the spots (:mod:`restoration.fit`): surface RMSE against the surface
  stage's time.

Each chart marks the default configuration. Timings are taken inside the sweep's workers, one
thread each: compare them with each other, and take absolute speed from ``wai bench``.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from wai.experiments.frame_eval import REFINEMENTS, evaluate_frame  # noqa: E402
from wai.figures import save_figure  # noqa: E402
from wai.sweep import run_sweep, sweep_kwargs  # noqa: E402
from wai_core.io import atomic_write_bytes, write_json  # noqa: E402

SPACINGS_PX = (16, 20, 24, 28, 36, 48)
SPPS = (2, 4, 8, 16, 32)
WARP_STEPS = (2, 4, 8, 16, 32)
QUICK = {"spacing": (20, 28, 40), "spp": (4, 8), "warp": (4, 8, 16)}


def integrator_names() -> list[str]:
    """Every registered integrator (:data:`restoration.integrate.INTEGRATORS`)."""
    from restoration.integrate import INTEGRATORS

    return list(INTEGRATORS)


def tradeoff_points(config: Path, seeds: list[int], quick: bool) -> list[dict[str, Any]]:
    """The sweep: one point per chart value and seed."""
    base = {"config": str(config), "repeats": 1 if quick else 3}
    spacings = QUICK["spacing"] if quick else SPACINGS_PX
    spps = QUICK["spp"] if quick else SPPS
    steps = QUICK["warp"] if quick else WARP_STEPS
    points = []
    for seed in seeds:
        points += [{**base, "chart": "spacing", "seed": seed, "spacing_px": d} for d in spacings]
        names = ",".join(integrator_names())
        points.append({**base, "chart": "integrator", "seed": seed, "integrators": names})
        points += [{**base, "chart": "spp", "seed": seed, "spp_pattern": n} for n in spps]
        points.append(
            {**base, "chart": "warp", "seed": seed, "warp_steps": ",".join(map(str, steps))}
        )
        points.append({**base, "chart": "refinement", "seed": seed,
                       "refinements": ",".join(REFINEMENTS)})
    return points


def _mean(rows: list[dict], key: str, suffix: str | None = None) -> float:
    """Mean of ``key`` over the frames that ended ``ok``: by the variant's own status for a
    variant's column (``suffix``; e.g. an integrator that makes its frame inconsistent counts
    only against itself), by the frame's otherwise."""
    status = "frame_status" if suffix is None else f"variant_status_{suffix}"
    vals = [r.get(key) for r in rows if r.get(status, r.get("frame_status")) == "ok"]
    vals = [float(v) for v in vals if v is not None and np.isfinite(v)]
    return float(np.mean(vals)) if vals else float("nan")


def chart_series(rows: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Per chart, one entry per configuration: its label, x (time) and y (accuracy) means."""
    charts = ("spacing", "integrator", "spp", "warp", "refinement")
    by = {c: [r for r in rows if r.get("chart") == c] for c in charts}
    out: dict[str, list[dict[str, Any]]] = {}
    out["spacing"] = [
        {
            "label": f"D={d:g}",
            "value": d,
            "ms": _mean(sel, "ms_end_to_end"),
            "rmse_mm": _mean(sel, "wai_rmse_mm"),
            "ok": sum(r.get("frame_status") == "ok" for r in sel),
            "n": len(sel),
        }
        for d in sorted({r["spacing_px"] for r in by["spacing"]})
        for sel in [[r for r in by["spacing"] if r["spacing_px"] == d]]
    ]
    out["integrator"] = [
        {
            "label": name,
            "value": name,
            "ms": _mean(by["integrator"], f"ms_surface_{name}", name),
            "rmse_mm": _mean(by["integrator"], f"wai_rmse_mm_{name}", name),
            "rmse_demeaned_mm": _mean(by["integrator"], f"wai_rmse_demeaned_mm_{name}", name),
            "ok": sum(r.get(f"variant_status_{name}") == "ok" for r in by["integrator"]),
            "n": len(by["integrator"]),
        }
        for name in integrator_names()
    ]
    out["spp"] = [
        {
            "label": f"{n} spp",
            "value": n,
            "ms": 1e3 * _mean(sel, "render_s_pattern"),
            "spot_px": _mean(sel, "spot_median_px"),
            "n": len(sel),
        }
        for n in sorted({r["spp_pattern"] for r in by["spp"]})
        for sel in [[r for r in by["spp"] if r["spp_pattern"] == n]]
    ]
    found = (re.fullmatch(r"restored_ssim_step(\d+)", k) for r in by["warp"] for k in r)
    steps = sorted({int(m.group(1)) for m in found if m})
    out["warp"] = [
        {
            "label": f"step {k}",
            "value": k,
            "ms": _mean(by["warp"], f"ms_reverse_trace_step{k}", f"step{k}"),
            "ssim": _mean(by["warp"], f"restored_ssim_step{k}", f"step{k}"),
            "corner_px": _mean(by["warp"], f"corner_std_restored_px_step{k}", f"step{k}"),
            "n": len(by["warp"]),
        }
        for k in steps
    ]
    out["refinement"] = [
        {
            "label": name,
            "value": name,
            "ms": _mean(by["refinement"], f"ms_surface_{name}", name),
            "rmse_mm": _mean(by["refinement"], f"wai_rmse_mm_{name}", name),
            "rmse_demeaned_mm": _mean(by["refinement"], f"wai_rmse_demeaned_mm_{name}", name),
            "ok": sum(r.get(f"variant_status_{name}") == "ok" for r in by["refinement"]),
            "n": len(by["refinement"]),
        }
        for name in REFINEMENTS
    ]
    return out


def _panel(ax: Any, series: list[dict], y: str, default: Any, xlabel: str, ylabel: str,
           title: str, logy: bool = False, ordered: bool = True) -> None:
    """One chart: accuracy ``y`` against time; a line joins the points of an ordered setting."""
    xs = [s["ms"] for s in series]
    ys = [s[y] for s in series]
    ax.plot(xs, ys, "o-" if ordered else "o", color="tab:blue")
    for s in series:
        ax.annotate(s["label"], (s["ms"], s[y]), textcoords="offset points", xytext=(4, 4),
                    fontsize=7)
        if s["value"] == default:
            ax.plot(s["ms"], s[y], "*", ms=14, color="tab:red", label=f"default ({s['label']})")
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
    if logy:
        ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)


def tradeoff_figure(series: dict[str, list[dict]], defaults: dict[str, Any], path: Path) -> None:
    """The five speed-accuracy charts in one figure, defaults starred."""
    fig, axes = plt.subplots(2, 3, figsize=(16, 8.5))
    _panel(axes[0, 0], series["spacing"], "rmse_mm", defaults["spacing"],
           "restoration end to end (ms)", "surface RMSE (mm)", "Pattern spacing D", logy=True)
    _panel(axes[0, 1], series["integrator"], "rmse_mm", defaults["integrator"],
           "surface stage (ms)", "surface RMSE (mm)", "Integrator", logy=True,
           ordered=False)
    _panel(axes[1, 0], series["spp"], "spot_px", defaults["spp"],
           "pattern render (ms)", "spot-centre error, median (px)", "Pattern samples per pixel")
    _panel(axes[1, 1], series["warp"], "ssim", defaults["warp"],
           "reverse trace (ms)", "restored SSIM", "Warp step (exactly traced grid)")
    _panel(axes[0, 2], series["refinement"], "rmse_mm", defaults["refinement"],
           "surface stage (ms)", "surface RMSE (mm)", "Surface refinement", ordered=False)
    axes[1, 2].set_visible(False)
    fig.tight_layout()
    save_figure(fig, path)


def report_markdown(series: dict[str, list[dict]], defaults: dict[str, Any], command: str) -> str:
    """Tables behind the charts, with the defaults and why."""
    lines = ["# Speed against accuracy", "", f"Command: `{command}`", "",
             "![tradeoffs](tradeoffs.png)", ""]
    tables = {
        "spacing": ("Pattern spacing D (panel px)", ["ms", "rmse_mm", "ok", "n"]),
        "integrator": ("Integrator", ["ms", "rmse_mm", "rmse_demeaned_mm", "ok", "n"]),
        "spp": ("Pattern samples per pixel", ["ms", "spot_px", "n"]),
        "warp": ("Warp step (px)", ["ms", "ssim", "corner_px", "n"]),
        "refinement": ("Surface refinement", ["ms", "rmse_mm", "rmse_demeaned_mm", "ok", "n"]),
    }
    for name, (title, cols) in tables.items():
        lines += [f"## {title} (default: {defaults[name]})", "",
                  "| setting | " + " | ".join(cols) + " |", "|" + " --- |" * (len(cols) + 1)]
        for s in series[name]:
            cells = [f"{s[c]:.4g}" if isinstance(s[c], float) else str(s[c]) for c in cols]
            lines.append(f"| {s['label']} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["## The defaults against the alternatives", ""]
    for name, key in (("spacing", "rmse_mm"), ("integrator", "rmse_mm"), ("spp", "spot_px"),
                      ("warp", "ssim"), ("refinement", "rmse_mm")):
        lines.append(f"- {name}: " + _verdict(series[name], key, defaults[name],
                                               higher_is_better=(key == "ssim")))
    lines += [
        "",
        "Defaults are picked for accuracy first, then time, with margin against failure: a "
        "setting that is best on a few seeds but sits at the edge where the stability sweep "
        "(`wai experiment stability`) sees frames fail is not taken.",
        "",
    ]
    return "\n".join(lines)


def _verdict(series: list[dict], key: str, default: Any, higher_is_better: bool) -> str:
    """One line: the default's accuracy and time against the most accurate and the fastest."""
    ok = [s for s in series if np.isfinite(s[key]) and np.isfinite(s["ms"])]
    if not ok:
        return "no setting produced a score"
    best = (max if higher_is_better else min)(ok, key=lambda s: s[key])
    fastest = min(ok, key=lambda s: s["ms"])
    mine = next((s for s in ok if s["value"] == default), None)
    here = "no score" if mine is None else f"{mine[key]:.4g} in {mine['ms']:.4g} ms"
    return (
        f"default {default}: {here}; most accurate {best['label']} ({best[key]:.4g} in "
        f"{best['ms']:.4g} ms); fastest {fastest['label']} ({fastest[key]:.4g} in "
        f"{fastest['ms']:.4g} ms)"
    )


def run_tradeoffs(args: argparse.Namespace) -> dict[str, Any]:
    """Run the sweep into ``args.out/tradeoffs.csv`` and write the charts and report."""
    from restoration import RestoreOptions
    from wai_core.system import load_rig

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = list(range(args.seeds))
    rows = run_sweep(
        tradeoff_points(args.config, seeds, args.quick), evaluate_frame, out / "tradeoffs.csv",
        **sweep_kwargs(args),
    )
    cfg, opts = load_rig(args.config), RestoreOptions()
    defaults = {
        "spacing": cfg.pattern.spacing_px,
        "integrator": opts.integrator,
        "spp": cfg.render.spp_pattern,
        "warp": opts.warp_step_px,
        "refinement": "fit" if opts.fit_spots else "default",
    }
    series = chart_series(rows)
    tradeoff_figure(series, defaults, out / "tradeoffs.png")
    command = f"wai experiment tradeoffs --seeds {args.seeds}" + (" --quick" if args.quick else "")
    atomic_write_bytes(out / "tradeoffs.md", report_markdown(series, defaults, command).encode())
    write_json(out / "tradeoffs_series.json", {"defaults": defaults, "series": series})
    print(report_markdown(series, defaults, command))
    return {"defaults": defaults, "series": series}
