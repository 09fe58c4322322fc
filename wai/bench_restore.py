"""``wai bench restore``: per-stage and end-to-end time of the restoration of one 800x600 frame."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from wai.bench import machine, summarize, time_runs


def bench_restore(args: argparse.Namespace) -> dict[str, Any]:
    """Time :func:`restoration.pipeline.restore` on a render folder (rendered if not given).

    Loading the images is not timed (a camera delivers them in memory); everything from the
    pattern image to the restored view is.
    """
    from restoration.pipeline import RestoreOptions, load_calibration, load_inputs, restore

    render_dir = args.dir
    if render_dir is None:
        from mitsuba_wai.render import render_folder
        from wai_core.config import load_config

        render_dir = Path("renders/bench")
        if not (render_dir / "scene.json").is_file():
            render_folder(load_config(args.config), render_dir, progress=False)
    cal = load_calibration(render_dir)
    images = load_inputs(render_dir, cal)
    options = RestoreOptions()
    stages: dict[str, list[float]] = {}

    def run(_: int) -> None:
        res = restore(images, cal, options)
        for name, ms in res.timings_ms.items():
            stages.setdefault(name, []).append(ms)
        for name, ms in res.features.timings_ms.items():
            stages.setdefault(f"features.{name}", []).append(ms)
        for name, ms in res.surface.timings_ms.items():
            stages.setdefault(f"surface.{name}", []).append(ms)
        for name, ms in res.view.timings_ms.items():
            stages.setdefault(f"reverse_trace.{name}", []).append(ms)

    warm, samples = time_runs(run, args.runs)
    measured = {k: v[1:] for k, v in stages.items()}  # drop the warm-up's entry
    e2e = summarize(samples)
    return {
        "render_dir": str(render_dir),
        "machine": machine(),
        "options": vars(options),
        "warmup_ms": warm * 1e3,
        "end_to_end_ms": e2e["median_ms"],
        "end_to_end": e2e,
        "fps": 1e3 / e2e["median_ms"],
        "stages_ms": {k: float(np.median(v)) for k, v in measured.items()},
    }


def print_restore(res: dict[str, Any]) -> None:
    """Human-readable report of :func:`bench_restore`."""
    e = res["end_to_end"]
    print(
        f"restore {res['render_dir']}: end to end median {e['median_ms']:.1f} ms "
        f"({res['fps']:.1f} frames/s; min {e['min_ms']:.1f}, max {e['max_ms']:.1f}, "
        f"{e['runs']} runs, {res['machine']['cores']} cores)"
    )
    for name, ms in res["stages_ms"].items():
        print(f"  {name:32s} {ms:8.2f} ms")
