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

import re
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from wai.experiments.frame_eval import REFINEMENTS, evaluate_frame  # noqa: E402
from wai.experiments.outputs import (  # noqa: E402
    output_folder,
    publish,
    sweep_command,
    sweep_rows,
)
from wai.figures import save_figure  # noqa: E402
from wai.sweep import SweepOptions  # noqa: E402
from wai_core.io import write_json  # noqa: E402

SPACINGS_PX = (16, 20, 24, 28, 36, 48)
SPPS = (2, 4, 8, 16, 32)
WARP_STEPS = (2, 4, 8, 16, 32)
QUICK = {"spacing": (20, 28, 40), "spp": (4, 8), "warp": (4, 8, 16)}


def integrator_names() -> list[str]:
    """Every registered integrator (:data:`restoration.integrate.INTEGRATORS`)."""
    from restoration import INTEGRATORS

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


def _status(row: dict, suffix: str | None) -> str:
    """A frame's status for one variant (``suffix``) or for the frame, without its detail
    (``failed: <why>`` counts as ``failed``); a point that raised is ``error``."""
    if row.get("status") != "ok":
        return "error"
    key = "frame_status" if suffix is None else f"variant_status_{suffix}"
    return str(row.get(key, row.get("frame_status"))).split(":")[0]


def _stats(rows: list[dict], key: str, suffix: str | None = None) -> dict[str, float]:
    """Mean, standard deviation, min and max of ``key`` over the frames that ended ``ok``: by
    the variant's own status for a variant's column (``suffix``; e.g. an integrator that makes
    its frame inconsistent counts only against itself), by the frame's otherwise. NaN where no
    frame is ``ok``."""
    vals = [r.get(key) for r in rows if _status(r, suffix) == "ok"]
    vals = [float(v) for v in vals if v is not None and np.isfinite(v)]
    if not vals:
        return dict.fromkeys(("mean", "std", "min", "max"), float("nan"))
    a = np.asarray(vals)
    return {"mean": float(a.mean()), "std": float(a.std()), "min": float(a.min()),
            "max": float(a.max())}


def _mean(rows: list[dict], key: str, suffix: str | None = None) -> float:
    """Mean of ``key`` over the ``ok`` frames (see :func:`_stats`)."""
    return _stats(rows, key, suffix)["mean"]


def _entry(label: str, value: Any, rows: list[dict], suffix: str | None,
           columns: dict[str, str], scale: dict[str, float] | None = None) -> dict[str, Any]:
    """One configuration of a chart: its label and value, per measure (``columns``: name in
    the series -> column of the table) the mean over seeds with its spread (``<name>_std``,
    ``_min``, ``_max``), and the frames' statuses (``ok``, ``n``, ``statuses``)."""
    entry: dict[str, Any] = {"label": label, "value": value}
    for name, column in columns.items():
        factor = (scale or {}).get(name, 1.0)
        for stat, v in _stats(rows, column, suffix).items():
            entry[name if stat == "mean" else f"{name}_{stat}"] = factor * v
    statuses: dict[str, int] = {}
    for r in rows:
        st = _status(r, suffix)
        statuses[st] = statuses.get(st, 0) + 1
    entry.update(ok=statuses.get("ok", 0), n=len(rows), statuses=statuses)
    return entry


def chart_series(rows: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Per chart, one entry per configuration: its label, x (time) and y (accuracy) means over
    the seeds' ``ok`` frames, their spread over seeds, and the frames' statuses."""
    charts = ("spacing", "integrator", "spp", "warp", "refinement")
    by = {c: [r for r in rows if r.get("chart") == c] for c in charts}
    out: dict[str, list[dict[str, Any]]] = {}
    out["spacing"] = [
        _entry(f"D={d:g}", d, [r for r in by["spacing"] if r["spacing_px"] == d], None,
               {"ms": "ms_end_to_end", "rmse_mm": "wai_rmse_mm"})
        for d in sorted({r["spacing_px"] for r in by["spacing"]})
    ]
    out["integrator"] = [
        _entry(name, name, by["integrator"], name,
               {"ms": f"ms_surface_{name}", "rmse_mm": f"wai_rmse_mm_{name}",
                "rmse_demeaned_mm": f"wai_rmse_demeaned_mm_{name}"})
        for name in integrator_names()
    ]
    out["spp"] = [
        _entry(f"{n} spp", n, [r for r in by["spp"] if r["spp_pattern"] == n], None,
               {"ms": "render_s_pattern", "spot_px": "spot_median_px"}, scale={"ms": 1e3})
        for n in sorted({r["spp_pattern"] for r in by["spp"]})
    ]
    found = (re.fullmatch(r"restored_ssim_step(\d+)", k) for r in by["warp"] for k in r)
    steps = sorted({int(m.group(1)) for m in found if m})
    out["warp"] = [
        _entry(f"step {k}", k, by["warp"], f"step{k}",
               {"ms": f"ms_reverse_trace_step{k}", "ssim": f"restored_ssim_step{k}",
                "corner_px": f"corner_std_restored_px_step{k}"})
        for k in steps
    ]
    out["refinement"] = [
        _entry(name, name, by["refinement"], name,
               {"ms": f"ms_surface_{name}", "rmse_mm": f"wai_rmse_mm_{name}",
                "rmse_demeaned_mm": f"wai_rmse_demeaned_mm_{name}"})
        for name in REFINEMENTS
    ]
    return out


def dropped_variants(series: list[dict[str, Any]], y: str) -> list[str]:
    """The configurations a chart of ``y`` cannot show (no ``ok`` frame with a score), each
    as ``label (status count of n, ...)``."""
    out = []
    for s in series:
        if np.isfinite(s[y]) and np.isfinite(s["ms"]):
            continue
        st = ", ".join(f"{k} {v}" for k, v in sorted(s["statuses"].items()))
        out.append(f"{s['label']} ({st} of {s['n']} frames)" if st else f"{s['label']} (no frame)")
    return out


# The smallest span of a linear accuracy axis, per measure: differences below it are not worth
# a full axis (an SSIM of 0.9888 against 0.9891 is noise, not a choice).
MIN_SPAN = {"ssim": 0.01, "spot_px": 0.01, "corner_px": 0.1, "rmse_mm": 0.005}


def _y_limits(series: list[dict], y: str) -> tuple[float, float] | None:
    """Linear y limits that hold every point with its min-max bar over seeds and span at least
    ``MIN_SPAN[y]`` and three times the largest seed-to-seed spread, centred on the data."""
    shown = [s for s in series if np.isfinite(s[y])]
    if not shown:
        return None
    lo = min(s[f"{y}_min"] for s in shown)
    hi = max(s[f"{y}_max"] for s in shown)
    spread = max(s[f"{y}_max"] - s[f"{y}_min"] for s in shown)
    span = max(hi - lo, MIN_SPAN.get(y, 0.0), 3.0 * spread) * 1.15
    mid = 0.5 * (lo + hi)
    bottom, top = mid - span / 2, mid + span / 2
    # Shifted, not cut, into the measure's range: errors are >= 0, an SSIM is <= 1.
    if y == "ssim" and top > 1.0:
        return bottom - (top - 1.0), 1.0
    if y != "ssim" and bottom < 0.0:
        return 0.0, top - bottom
    return bottom, top


def _annotate(ax: Any, shown: list[dict], y: str) -> None:
    """Label the points, one label per group of points that lie within a few pixels of each
    other on the drawn axes (``default, converged`` rather than two labels on top of each
    other)."""
    xy = ax.transData.transform([(s["ms"], s[y]) for s in shown])
    groups: list[list[int]] = []
    for k, p in enumerate(xy):
        near = next((g for g in groups if np.hypot(*(xy[g[0]] - p)) < 12.0), None)
        if near is None:
            groups.append([k])
        else:
            near.append(k)
    for g in groups:
        s = shown[g[0]]
        text = " = ".join(shown[k]["label"] for k in g)
        ax.annotate(text, (s["ms"], s[y]), textcoords="offset points", xytext=(5, 5), fontsize=7)


def _panel(ax: Any, series: list[dict], y: str, default: Any, xlabel: str, ylabel: str,
           title: str, logy: bool = False, ordered: bool = True) -> list[str]:
    """One chart: accuracy ``y`` against time, each point the mean over seeds with min-max bars
    over seeds in both directions; a line joins the points of an ordered setting. Returns the
    configurations not drawn (:func:`dropped_variants`), also noted in the panel."""
    shown = [s for s in series if np.isfinite(s[y]) and np.isfinite(s["ms"])]
    dropped = dropped_variants(series, y)
    if shown:
        xs = np.array([s["ms"] for s in shown])
        ys = np.array([s[y] for s in shown])
        xerr = [xs - [s["ms_min"] for s in shown], [s["ms_max"] for s in shown] - xs]
        yerr = [ys - [s[f"{y}_min"] for s in shown], [s[f"{y}_max"] for s in shown] - ys]
        ax.errorbar(xs, ys, xerr=xerr, yerr=yerr, fmt="o-" if ordered else "o",
                    color="tab:blue", ecolor="tab:gray", elinewidth=1, capsize=3,
                    label="mean, bars: min-max over seeds")
        for s in shown:
            if s["value"] == default:
                ax.plot(s["ms"], s[y], "*", ms=14, color="tab:red", zorder=5,
                        label=f"default ({s['label']})")
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
    if logy:
        ax.set_yscale("log")
    else:
        limits = _y_limits(series, y)
        if limits is not None:
            ax.set_ylim(*limits)
        ax.ticklabel_format(axis="y", useOffset=False)
    if shown:
        _annotate(ax, shown, y)
    if dropped:
        ax.text(0.02, 0.02, "not shown (no ok frame):\n" + "\n".join(dropped),
                transform=ax.transAxes, fontsize=7, va="bottom", color="tab:red")
    ax.grid(alpha=0.3)
    if shown:
        ax.legend(fontsize=7)
    return dropped


def tradeoff_figure(series: dict[str, list[dict]], defaults: dict[str, Any], path: Path) -> None:
    """The speed-accuracy charts in one figure (the warp step twice: restored SSIM and corner
    STD), defaults starred, bars over seeds, and a note naming every configuration left out
    for want of an ``ok`` frame."""
    fig, axes = plt.subplots(2, 3, figsize=(16, 9.5))
    panels = [
        (axes[0, 0], "spacing", "rmse_mm", "restoration end to end (ms)", "surface RMSE (mm)",
         "Pattern spacing D", True, True),
        (axes[0, 1], "integrator", "rmse_mm", "surface stage (ms)", "surface RMSE (mm)",
         "Integrator", True, False),
        (axes[0, 2], "refinement", "rmse_mm", "surface stage (ms)", "surface RMSE (mm)",
         "Surface refinement", False, False),
        (axes[1, 0], "spp", "spot_px", "pattern render (ms)", "spot-centre error, median (px)",
         "Pattern samples per pixel", False, True),
        (axes[1, 1], "warp", "ssim", "reverse trace (ms)", "restored SSIM",
         "Warp step (exactly traced grid): SSIM", False, True),
        (axes[1, 2], "warp", "corner_px", "reverse trace (ms)", "corner STD, restored (px)",
         "Warp step: corner STD", False, True),
    ]
    notes = []
    for ax, chart, y, xlabel, ylabel, title, logy, ordered in panels:
        dropped = _panel(ax, series[chart], y, defaults[chart], xlabel, ylabel, title,
                         logy=logy, ordered=ordered)
        if dropped and f"{chart}:" not in " ".join(notes):
            notes.append(f"{chart}: " + "; ".join(dropped))
    fig.tight_layout()
    if notes:
        fig.text(0.5, 0.0, "Left out for want of an ok frame: " + " | ".join(notes),
                 ha="center", va="top", fontsize=9, color="tab:red", wrap=True)
    save_figure(fig, path)


TABLES = {
    "spacing": ("Pattern spacing D (panel px)", "rmse_mm", ["ms", "rmse_mm", "ok", "n"]),
    "integrator": ("Integrator", "rmse_mm", ["ms", "rmse_mm", "rmse_demeaned_mm", "ok", "n"]),
    "spp": ("Pattern samples per pixel", "spot_px", ["ms", "spot_px", "ok", "n"]),
    "warp": ("Warp step (px)", "ssim", ["ms", "ssim", "corner_px", "ok", "n"]),
    "refinement": ("Surface refinement", "rmse_mm",
                   ["ms", "rmse_mm", "rmse_demeaned_mm", "ok", "n"]),
}
"""Per chart: the report's title, the accuracy it is judged by, and the table's columns."""


def not_ok_summary(series: dict[str, list[dict]]) -> str:
    """One line: how many restorations (a frame under one configuration, by the variant's own
    status) ended other than ``ok``, by status, naming the configurations; the sweep's own
    line counts only the points that raised."""
    counts: dict[str, int] = {}
    where: list[str] = []
    total = 0
    for chart, entries in series.items():
        for s in entries:
            total += s["n"]
            bad = {k: v for k, v in s["statuses"].items() if k != "ok"}
            for k, v in bad.items():
                counts[k] = counts.get(k, 0) + v
            if bad:
                where.append(f"{chart} {s['label']}: "
                             + ", ".join(f"{k} {v}" for k, v in sorted(bad.items())))
    if not counts:
        return f"restorations: all {total} ok"
    by = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    ok = total - sum(counts.values())
    return f"restorations: {ok} of {total} ok; not ok: {by} ({'; '.join(where)})"


def report_markdown(series: dict[str, list[dict]], defaults: dict[str, Any], command: str) -> str:
    """Tables behind the charts (means over seeds, ± their standard deviation), the
    configurations the charts leave out and why, and the defaults."""
    lines = ["# Speed against accuracy", "", f"Command: `{command}`", "",
             "![tradeoffs](tradeoffs.png)", "",
             "Each cell: the mean over the seeds' `ok` frames ± the standard deviation over "
             "them; the chart's bars are the min-max over seeds. `ok`: frames that ended ok "
             "(a variant by its own status), of `n`.", ""]
    for name, (title, key, cols) in TABLES.items():
        lines += [f"## {title} (default: {defaults[name]})", "",
                  "| setting | " + " | ".join(cols) + " | statuses |",
                  "|" + " --- |" * (len(cols) + 2)]
        for s in series[name]:
            cells = []
            for c in cols:
                v = s[c]
                if isinstance(v, float) and not np.isfinite(v):
                    cells.append("n/a")
                elif isinstance(v, float) and np.isfinite(s.get(f"{c}_std", np.nan)):
                    cells.append(f"{v:.4g} ± {s[f'{c}_std']:.2g}")
                else:
                    cells.append(f"{v:.4g}" if isinstance(v, float) else str(v))
            st = ", ".join(f"{k} {v}" for k, v in sorted(s["statuses"].items()))
            lines.append(f"| {s['label']} | " + " | ".join(cells) + f" | {st} |")
        dropped = dropped_variants(series[name], key)
        if dropped:
            lines += ["", "Not in the chart (no `ok` frame): " + "; ".join(dropped) + "."]
        lines.append("")
    lines += ["## The defaults against the alternatives", ""]
    for name, (_, key, _) in TABLES.items():
        lines.append(f"- {name}: " + _verdict(series[name], key, defaults[name],
                                               higher_is_better=(key == "ssim")))
    lines += [
        "",
        "Defaults are picked for accuracy first, then time, with margin against failure: a "
        "setting that is best on a few seeds but sits at the edge where the stability sweep "
        "(`wai experiment stability`) sees frames fail is not taken.",
        "",
        not_ok_summary(series),
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


def run_tradeoffs(config: str | Path, out: str | Path, seeds: int, quick: bool = False,
                  sweep: SweepOptions | None = None) -> dict[str, Any]:
    """Run the sweep into ``out/tradeoffs.csv`` and write the charts and report.

    Parameters
    ----------
    config, out : str or Path
        The scene (a packaged name or a TOML file) and the output folder (made if missing), as
        :func:`wai.experiments.run_experiment` takes them.
    seeds : int
        Seeds 0..seeds-1 of every variant.
    quick : bool
        3 spacings, 2 spp, 3 warp steps, one timed restoration per variant.
    sweep : SweepOptions or None
        Where and how the sweep's points run; None: :class:`SweepOptions`' defaults.

    Returns
    -------
    dict
        ``defaults`` (the default of each choice) and ``series`` (:func:`chart_series`).
    """
    from restoration import StructuredLightOptions
    from wai_core.system import load_rig

    out = output_folder(out)
    rows = sweep_rows(tradeoff_points(config, list(range(seeds)), quick), evaluate_frame,
                      out / "tradeoffs.csv", sweep)
    cfg, opts = load_rig(config), StructuredLightOptions()
    defaults = {
        "spacing": cfg.pattern.spacing_px,
        "integrator": opts.integrator,
        "spp": cfg.render.spp_pattern,
        "warp": opts.warp_step_px,
        "refinement": "fit" if opts.fit_spots else "default",
    }
    series = chart_series(rows)
    tradeoff_figure(series, defaults, out / "tradeoffs.png")
    command = sweep_command("tradeoffs", seeds, quick)
    write_json(out / "tradeoffs_series.json", {"defaults": defaults, "series": series})
    # its last line: not_ok_summary
    publish(out / "tradeoffs.md", report_markdown(series, defaults, command))
    return {"defaults": defaults, "series": series}
