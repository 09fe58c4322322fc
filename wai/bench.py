"""``wai bench``: wall-time benchmarks that print figures (median and spread of several runs).

Dr.Jit compiles kernels on first use, so every benchmark runs one warm-up that is reported apart
from the measured runs.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Callable
from typing import Any

import numpy as np


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    return {
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
    }


def summarize(samples_s: list[float]) -> dict[str, float]:
    """Median, min, max and interquartile range of run times, milliseconds."""
    ms = np.asarray(samples_s) * 1e3
    q1, q3 = np.percentile(ms, [25, 75])
    return {
        "median_ms": float(np.median(ms)),
        "min_ms": float(ms.min()),
        "max_ms": float(ms.max()),
        "iqr_ms": float(q3 - q1),
        "runs": int(ms.size),
    }


def time_runs(fn: Callable[[int], Any], runs: int) -> tuple[float, list[float]]:
    """One warm-up call, then ``runs`` timed calls; ``fn`` receives the run index."""
    t0 = time.perf_counter()
    fn(-1)
    warm = time.perf_counter() - t0
    samples = []
    for i in range(runs):
        t0 = time.perf_counter()
        fn(i)
        samples.append(time.perf_counter() - t0)
    return warm, samples


def bench_render(args: argparse.Namespace) -> dict[str, Any]:
    """Median wall time per frame of each scene (pattern: camera s, view: camera v)."""
    import drjit as dr

    from mitsuba_wai.mesh import flat_like
    from mitsuba_wai.render import FrameRenderer, render_seed, wave_surface
    from mitsuba_wai.variant import mitsuba, select_variant
    from wai_core.config import load_config

    variant = select_variant(args.variant)
    mi = mitsuba()
    cfg = load_config(args.config)
    surface = wave_surface(cfg)
    renderer = FrameRenderer(cfg, surface)
    renderer._set_surface(surface)
    out: dict[str, Any] = {"variant": variant, "machine": machine(), "scenes": {}}
    scenes = {
        "pattern": (renderer._scene_s, cfg.render.spp_pattern, cfg.camera_s),
        "view": (renderer._scene_v, cfg.render.spp_view, cfg.camera_v),
    }
    for name, (scene, spp, cam) in scenes.items():

        def frame(i: int, scene=scene, spp=spp) -> None:
            img = mi.render(scene, spp=spp, seed=render_seed(cfg) + i + 1)
            dr.eval(img)
            dr.sync_thread()

        warm, samples = time_runs(frame, args.runs)
        out["scenes"][name] = {
            "resolution": [cam.width_px, cam.height_px],
            "spp": spp,
            "warmup_ms": warm * 1e3,
            **summarize(samples),
        }
    # Swapping the surface between frames (mesh upload) is part of a frame's cost too.
    flat = flat_like(surface, cfg.water.h0_mm)
    warm, samples = time_runs(
        lambda i: renderer._set_surface(flat if i % 2 else surface), args.runs
    )
    out["surface_update"] = {"vertices": int(surface.z.size), **summarize(samples)}
    return out


def _print_render(res: dict[str, Any]) -> None:
    print(f"variant {res['variant']}, {res['machine']['cores']} cores")
    for name, r in res["scenes"].items():
        w, h = r["resolution"]
        print(
            f"{name:8s} {w}x{h} {r['spp']:4d} spp: median {r['median_ms']:8.1f} ms/frame "
            f"(min {r['min_ms']:.1f}, max {r['max_ms']:.1f}, {r['runs']} runs; "
            f"warm-up {r['warmup_ms']:.0f} ms)"
        )
    u = res["surface_update"]
    print(f"surface update ({u['vertices']} vertices): median {u['median_ms']:.1f} ms")


def run_bench(args: argparse.Namespace) -> None:
    """Dispatch ``wai bench WHAT`` and print the figures (or one JSON object)."""
    if args.what == "render":
        res = bench_render(args)
        printer = _print_render
    elif args.what == "accuracy":
        from wai.accuracy import print_accuracy, run_accuracy

        res = run_accuracy(args)
        printer = print_accuracy
    else:
        from wai.bench_restore import bench_restore, print_restore

        res = bench_restore(args)
        printer = print_restore
    if args.json:
        print(json.dumps(res))
    else:
        printer(res)
