"""``wai bench`` (all): every stage of rendering and restoration, ``bench.json`` and a chart."""

from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any

import numpy as np

from wai.bench.render import RENDER_STAGES, bench_render, render_stages
from wai.bench.restore import CHART_HIDDEN, bench_restore
from wai.bench.timing import machine, print_stage_table, runtime
from wai_core.io import write_json
from wai_core.report import write_report as write_index

__all__ = ["bench_all", "bench_chart", "print_report", "write_report"]


def bench_all(config: str | Path, runs: int, render_dir: str | Path | None = None,
              variant: str = "auto") -> dict[str, Any]:
    """Every stage: rendering (system S and V) and restoration, with memory and the setup.

    The restoration runs first so that the peak RSS recorded after it is its own (unless the
    render folder had to be rendered first), not the renderer's. The parameters are those of
    :func:`~wai.bench.restore.bench_restore` (``render_dir``: the folder it restores).
    """
    restore = bench_restore(config, runs, render_dir, variant)
    render = bench_render(config, runs, variant)
    stages = render_stages(render)
    stages.update({k: {"group": "restore", **v} for k, v in restore["stages"].items()})
    return {
        "format": "wai-bench/1",
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "runs": runs,
        "config": str(config),
        "render_dir": restore["render_dir"],
        "machine": machine(),
        "runtime": runtime(),
        "render": {
            stage: {k: render["scenes"][scene][k] for k in ("resolution", "spp")}
            for stage, scene in RENDER_STAGES.items()
        },
        "stages": stages,
        "warmup_ms": {
            **{
                stage: render["scenes"][scene]["warmup_ms"]
                for stage, scene in RENDER_STAGES.items()
            },
            "restore": restore["warmup_ms"],
        },
        "fps": restore["fps"],
        "peak_memory_mib": {
            "rss_after_restore": restore["peak_rss_mib"],
            "rss_after_render": render["peak_rss_mib"],
            "tracemalloc_restore": restore["tracemalloc_peak_mib"],
        },
        "derived": restore["derived"],
        "notes": restore["notes"],
    }


CHART_MIN_MS = 0.05
"""Stages whose median is under this (ms) are left out of the chart (a bar that reads 0.0);
the table and ``bench.json`` keep them."""


def chart_rows(stages: dict[str, dict[str, Any]]) -> list[tuple[str, str, bool]]:
    """The chart's rows, top to bottom: ``(stage, label, nested)``, a stage inside another
    (``parent.part``) drawn under its parent, indented; stages under :data:`CHART_MIN_MS`
    left out."""
    rows = []
    for name, v in stages.items():
        if v["median_ms"] < CHART_MIN_MS:
            continue
        nested = "." in name
        label = "   \u2514 " + name.split(".", 1)[1] if nested else name
        rows.append((name, label, nested))
    return rows


def _stage_panel(ax: Any, stages: dict[str, dict[str, Any]], title: str) -> None:
    """Horizontal bars of the median, a thick line from Q1 to Q3 and min-max whiskers, ms;
    a stage's parts under it, indented and paler (their time is part of the parent's)."""
    rows = chart_rows(stages)[::-1]  # first stage on top
    names = [r[0] for r in rows]
    keys = ("median_ms", "min_ms", "max_ms", "q1_ms", "q3_ms")
    get = {k: np.array([stages[n][k] for n in names]) for k in keys}
    med = get["median_ms"]
    y = np.arange(len(names))
    whiskers = [med - get["min_ms"], get["max_ms"] - med]
    colours = ["#deebf7" if nested else "#9ecae1" for _, _, nested in rows]
    ax.barh(y, med, color=colours, xerr=whiskers, capsize=3, error_kw={"elinewidth": 1})
    ax.hlines(y, get["q1_ms"], get["q3_ms"], color="#08519c", lw=4)
    for yi, m in zip(y, med, strict=True):
        ax.annotate(f"{m:.1f}", (m, yi), xytext=(4, 5), textcoords="offset points", fontsize=7)
    ax.set_yticks(y, [r[1] for r in rows], fontsize=8)
    ax.set_xlabel(f"ms: bar median, thick line Q1-Q3, whiskers min-max (indented: part of "
                  f"the stage above; under {CHART_MIN_MS} ms: in bench.json)", fontsize=8)
    ax.set_title(title, fontsize=10)
    ax.set_xlim(0, 1.12 * float(get["max_ms"].max(initial=1.0)))  # room for the labels


def bench_chart(report: dict[str, Any], path: str | Path) -> None:
    """``bench.png``: restoration and render stages in two panels (their scales differ ~100x)."""
    from wai.figures import plt, save_figure

    groups = {
        g: {k: v for k, v in report["stages"].items() if v["group"] == g and k not in CHART_HIDDEN}
        for g in ("restore", "render")
    }
    heights = [max(len(v), 1) for v in groups.values()]
    fig, axes = plt.subplots(
        2, 1, figsize=(9, 1.6 + 0.32 * sum(heights)), gridspec_kw={"height_ratios": heights}
    )
    _stage_panel(axes[0], groups["restore"], f"restoration ({report['render_dir']})")
    _stage_panel(
        axes[1],
        groups["render"],
        "rendering: a frame, its surface upload included (.surface_update: the upload alone)",
    )
    m, rt = report["machine"], report["runtime"]
    fig.suptitle(
        f"wai bench {report['date'][:10]}: {m['cpu_model'] or m['cpu']}, {m['cores']} cores\n"
        f"{rt['variant']}, {rt['drjit_threads']} Dr.Jit threads, {report['runs']} runs "
        f"(after a warm-up)",
        fontsize=10,
    )
    fig.tight_layout()
    save_figure(fig, path)


def write_report(report: dict[str, Any], out: str | Path) -> list[Path]:
    """Write ``bench.json`` and ``bench.png`` into ``out`` (each atomically); their paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "bench.json", out / "bench.png"]
    bench_chart(report, paths[1])
    write_json(paths[0], report)
    write_index(out)  # the folder's index.html, with the bench's figure
    return paths


def print_report(report: dict[str, Any]) -> None:
    """Table of every stage of :func:`bench_all`, with the setup, warm-ups and memory."""
    m, rt = report["machine"], report["runtime"]
    print(
        f"{m['cpu_model'] or m['cpu']}, {m['cores']} cores; {rt['variant']}, "
        f"{rt['drjit_threads']} Dr.Jit threads, {rt.get('opencv_threads')} OpenCV threads; "
        f"BLAS {m['blas']}; {report['date']}"
    )
    print_stage_table(report["stages"], report["derived"], report["notes"], report["runs"])
    w = report["warmup_ms"]
    print("warm-up (not in the figures): " + ", ".join(f"{k} {v:.0f} ms" for k, v in w.items()))
    mem = report["peak_memory_mib"]
    print(
        f"peak RSS {mem['rss_after_restore']:.0f} MiB after restoring, "
        f"{mem['rss_after_render']:.0f} MiB after rendering; Python/NumPy allocations in one "
        f"restoration peak at {mem['tracemalloc_restore']:.1f} MiB (tracemalloc)"
    )
    print(f"restoration: {report['fps']:.1f} frames/s")


