"""``wai bench``: wall-time benchmarks that print figures (median and spread of several runs).

Dr.Jit compiles kernels on first use, so every benchmark runs one warm-up that is reported apart
from the measured runs. ``wai bench`` (``all``) times every stage, rendering and restoration,
and writes ``bench.json`` and ``bench.png``; ``render`` and ``restore`` print their part only.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from wai_core.errors import WaiInputError
from wai_core.io import write_json

DEFAULT_OUT = {
    "all": Path("renders/bench"),
    "accuracy": Path("renders/bench_accuracy"),
    "video": Path("renders/bench_video"),
}
"""Output folder of the benchmarks that write files, when ``--out`` is not given."""

RENDER_STAGES = {"render_s": "pattern", "render_v": "view"}
"""Report stage of each scene of :func:`bench_render` (system S: pattern, system V: view)."""
_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "DRJIT_NUM_THREADS")


def _cpu_model() -> str | None:
    """``model name`` of the first CPU in /proc/cpuinfo (Linux), else None."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def _blas() -> str | None:
    """Name and version of the BLAS NumPy was built against."""
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        return f"{blas['name']} {blas.get('version', '')}".strip()
    except Exception:  # the layout of numpy's build record is not an API
        return None


def machine() -> dict[str, Any]:
    """What the numbers were measured on: CPU, core count and library versions."""
    return {
        "cpu": platform.processor() or platform.machine(),
        "cpu_model": _cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "blas": _blas(),
    }


def runtime() -> dict[str, Any]:
    """Variant and thread counts of the libraries this process has loaded.

    Only modules already imported are asked (importing Mitsuba just to report on it would pick
    a variant): a restoration-only benchmark has no variant, since it never runs Dr.Jit.
    """
    out: dict[str, Any] = {"variant": None, "drjit_threads": None}
    if "mitsuba" in sys.modules:
        mi = sys.modules["mitsuba"]
        out["mitsuba"] = mi.__version__
        out["variant"] = mi.variant()
    if "drjit" in sys.modules:
        dr = sys.modules["drjit"]
        out["drjit"] = dr.__version__
        if hasattr(dr, "thread_count"):
            out["drjit_threads"] = int(dr.thread_count())
    if "cv2" in sys.modules:
        out["opencv_threads"] = int(sys.modules["cv2"].getNumThreads())
    # BLAS pools are sized by these when set (threadpoolctl would ask BLAS itself; not a dep).
    out["thread_env"] = {k: os.environ[k] for k in _THREAD_ENV if k in os.environ}
    return out


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far, MiB (``ru_maxrss`` is KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def summarize(samples_s: list[float]) -> dict[str, float]:
    """Median, min, max, quartiles and interquartile range of run times, milliseconds."""
    ms = np.asarray(samples_s) * 1e3
    q1, q3 = np.percentile(ms, [25, 75])
    return {
        "median_ms": float(np.median(ms)),
        "min_ms": float(ms.min()),
        "max_ms": float(ms.max()),
        "iqr_ms": float(q3 - q1),
        "q1_ms": float(q1),
        "q3_ms": float(q3),
        "runs": int(ms.size),
    }


def time_runs(fn: Callable[[int], Any], runs: int) -> tuple[float, list[float]]:
    """One warm-up call (index -1), then ``runs`` timed calls; ``fn`` receives the run index."""
    t0 = time.perf_counter()
    fn(-1)
    warm = time.perf_counter() - t0
    samples = []
    for i in range(runs):
        t0 = time.perf_counter()
        fn(i)
        samples.append(time.perf_counter() - t0)
    return warm, samples


def _bench_system(cfg: Any, surface: Any, system: str, runs: int) -> dict[str, Any]:
    """Frames of one system through its own renderer: the surface upload, then the render."""
    from mitsuba_wai.mesh import flat_like
    from mitsuba_wai.render import FrameRenderer, render_seed

    renderer = FrameRenderer(cfg, surface, systems=(system,))
    seed = render_seed(cfg)
    warm, samples = time_runs(
        lambda i: renderer.render(surface, seed + i + 1, which=(system,)), runs
    )
    # The upload alone (alternating surfaces, so every call really changes the mesh).
    flat = flat_like(surface, cfg.water.h0_mm)
    _, upload = time_runs(lambda i: renderer._set_surface(flat if i % 2 else surface), runs)
    cam = cfg.camera_s if system == "pattern" else cfg.camera_v
    spp = cfg.render.spp_pattern if system == "pattern" else cfg.render.spp_view
    return {
        "resolution": [cam.width_px, cam.height_px],
        "spp": spp,
        "warmup_ms": warm * 1e3,
        **summarize(samples),
        "surface_update": summarize(upload),
    }


def bench_render(args: argparse.Namespace) -> dict[str, Any]:
    """Wall time per frame of each scene (pattern: camera s, view: camera v).

    A frame is what a sweep pays for it: the new surface's upload (mesh buffers and BVH) and
    the render, read back to a NumPy image. ``surface_update`` is the upload alone.
    """
    from mitsuba_wai.render import wave_surface
    from mitsuba_wai.variant import select_variant
    from wai_core.config import load_config

    variant = select_variant(args.variant)
    cfg = load_config(args.config)
    surface = wave_surface(cfg)
    scenes = {name: _bench_system(cfg, surface, name, args.runs) for name in ("pattern", "view")}
    return {
        "variant": variant,
        "machine": machine(),
        "runtime": runtime(),
        "scenes": scenes,
        "surface_update": {"vertices": int(surface.z.size), **scenes["pattern"]["surface_update"]},
        "peak_rss_mib": peak_rss_mib(),
    }


def _print_render(res: dict[str, Any]) -> None:
    print(
        f"variant {res['variant']}, {res['machine']['cores']} cores, "
        f"{res['runtime']['drjit_threads']} Dr.Jit threads"
    )
    for name, r in res["scenes"].items():
        w, h = r["resolution"]
        print(
            f"{name:8s} {w}x{h} {r['spp']:4d} spp: median {r['median_ms']:8.1f} ms/frame "
            f"(min {r['min_ms']:.1f}, max {r['max_ms']:.1f}, {r['runs']} runs; "
            f"warm-up {r['warmup_ms']:.0f} ms)"
        )
    u = res["surface_update"]
    print(f"surface update ({u['vertices']} vertices): median {u['median_ms']:.1f} ms")
    print(f"peak RSS {res['peak_rss_mib']:.0f} MiB")


def _render_stages(render: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``render_s``/``render_v`` and their uploads from :func:`bench_render`'s scenes."""
    stages: dict[str, dict[str, Any]] = {}
    for stage, scene in RENDER_STAGES.items():
        r = render["scenes"][scene]
        summary = {k: v for k, v in r.items() if k.endswith("_ms") and k != "warmup_ms"}
        stages[stage] = {"group": "render", **summary, "runs": r["runs"]}
        stages[f"{stage}.surface_update"] = {"group": "render", **r["surface_update"]}
    return stages


def bench_all(args: argparse.Namespace) -> dict[str, Any]:
    """Every stage: rendering (system S and V) and restoration, with memory and the setup.

    The restoration runs first so that the peak RSS recorded after it is its own (unless the
    render folder had to be rendered first), not the renderer's.
    """
    from wai.bench_restore import bench_restore

    restore = bench_restore(args)
    render = bench_render(args)
    stages = _render_stages(render)
    stages.update({k: {"group": "restore", **v} for k, v in restore["stages"].items()})
    return {
        "format": "wai-bench/1",
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "runs": args.runs,
        "config": str(args.config),
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


def _stage_panel(ax: Any, stages: dict[str, dict[str, Any]], title: str) -> None:
    """Horizontal bars of the median, a thick line from Q1 to Q3 and min-max whiskers, ms."""
    names = list(stages)[::-1]  # first stage on top
    keys = ("median_ms", "min_ms", "max_ms", "q1_ms", "q3_ms")
    get = {k: np.array([stages[n][k] for n in names]) for k in keys}
    med = get["median_ms"]
    y = np.arange(len(names))
    whiskers = [med - get["min_ms"], get["max_ms"] - med]
    ax.barh(y, med, color="#9ecae1", xerr=whiskers, capsize=3, error_kw={"elinewidth": 1})
    ax.hlines(y, get["q1_ms"], get["q3_ms"], color="#08519c", lw=4)
    for yi, m in zip(y, med, strict=True):
        ax.annotate(f"{m:.1f}", (m, yi), xytext=(4, 5), textcoords="offset points", fontsize=7)
    ax.set_yticks(y, names, fontsize=8)
    ax.set_xlabel("ms: bar median, thick line Q1-Q3, whiskers min-max")
    ax.set_title(title, fontsize=10)
    ax.set_xlim(0, 1.12 * float(get["max_ms"].max(initial=1.0)))  # room for the labels


def bench_chart(report: dict[str, Any], path: str | Path) -> None:
    """``bench.png``: restoration and render stages in two panels (their scales differ ~100x)."""
    from wai.bench_restore import CHART_HIDDEN
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
    return paths


def print_stage_table(
    stages: dict[str, dict[str, Any]], derived: list[str], notes: dict[str, str], runs: int
) -> None:
    """One line per stage: median, min, max and IQR in ms; derived stages marked and explained."""
    print(f"{'stage':28s} {'median':>9s} {'min':>9s} {'max':>9s} {'IQR':>8s}  (ms, {runs} runs)")
    for name, s in stages.items():
        mark = " *" if name in derived else ""
        label = f"  {name}" if "." in name else name  # parts under their stage
        print(
            f"{label:28s} {s['median_ms']:9.2f} {s['min_ms']:9.2f} {s['max_ms']:9.2f} "
            f"{s['iqr_ms']:8.2f}{mark}"
        )
    for name in derived:
        print(f"  * {name} = {notes.get(name, '')}")


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


def run_bench(args: argparse.Namespace) -> None:
    """Dispatch ``wai bench [WHAT]`` and print the figures (or one JSON object)."""
    what = args.what or "all"
    if what != "accuracy" and args.runs < 1:
        raise WaiInputError(f"--runs must be at least 1, got {args.runs}")
    if getattr(args, "out", None) is None and what in DEFAULT_OUT:
        args.out = DEFAULT_OUT[what]
    paths: list[Path] = []
    if what == "all":
        res = bench_all(args)
        paths = write_report(res, args.out)
        printer = print_report
    elif what == "render":
        res = bench_render(args)
        printer = _print_render
    elif what == "accuracy":
        from wai.accuracy import print_accuracy, run_accuracy

        res = run_accuracy(args)
        printer = print_accuracy
    elif what == "video":
        from wai.bench_video import bench_video, print_video

        res = bench_video(args)
        printer = print_video
    else:
        from wai.bench_restore import bench_restore, print_restore

        res = bench_restore(args)
        printer = print_restore
    if args.json:
        print(json.dumps(res))
        return
    printer(res)
    for path in paths:
        print(f"wrote {path}")
