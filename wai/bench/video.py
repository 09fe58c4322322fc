"""``wai bench video``: restoration latency and throughput over a rendered frame sequence.

A video restorer sees one frame after another. Latency is the time one process takes per frame
(what ``wai bench restore`` measures); throughput is how many frames per second the machine
restores when frames are spread over worker processes, one per core, each holding the
calibration (the flat-water reference is prepared once per worker, not per frame). The
restored frame travels back to the parent as 8-bit RGB (what a display or an encoder takes).

The sequence is rendered once into ``--out`` (default ``renders/bench_video``): consecutive
frames 1/30 s apart, so the waves move as in a real recording.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time
from pathlib import Path
from typing import Any

import numpy as np

from wai.bench.timing import machine, reference_workload, summarize
from wai.sweep import THREAD_VARIABLES, limit_native_threads, scoped_environ
from wai_core.errors import WaiInputError

FRAME_INTERVAL_S = 1.0 / 30.0

# Per worker process: the calibration and the frames' images, loaded by _init_worker.
_STATE: dict[str, Any] = {}


def render_sequence(config: Path, out: Path, n_frames: int) -> list[Path]:
    """Render (once) ``n_frames`` consecutive frames into ``out/frameNN``; returns the folders."""
    from mitsuba_wai.render import render_folder
    from wai_core.system import load_rig

    cfg = load_rig(config)
    folders = []
    for k in range(n_frames):
        folder = out / f"frame{k:02d}"
        if not (folder / "scene.json").is_file():
            t = cfg.waves.time_s + k * FRAME_INTERVAL_S
            render_folder(cfg.replace("waves", time_s=t), folder, progress=False)
        folders.append(folder)
    return folders


def _init_worker(folders: list[str]) -> None:
    """Load the calibration and every frame's images; prepare the reference; warm up."""
    from restoration import Calibration, LevelTrack, StructuredLight

    limit_native_threads(1)
    cal = Calibration.from_folder(folders[0])
    frames = [cal.load_images(f) for f in folders]
    restore = StructuredLight()
    restore(frames[0], cal)  # prepares the reference and warms every code path
    _STATE.update(cal=cal, frames=frames, restore=restore, track=LevelTrack())


def _restore_frame(index: int) -> tuple[np.ndarray, float]:
    """Restore frame ``index`` (modulo the sequence); the 8-bit image and the worker's ms."""
    frames = _STATE["frames"]
    t0 = time.perf_counter()
    res = _STATE["restore"](frames[index % len(frames)], _STATE["cal"], _STATE["track"])
    ms = 1e3 * (time.perf_counter() - t0)
    img8 = (np.clip(res.view.image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return img8, ms


def throughput(folders: list[Path], workers: int, n_frames: int) -> dict[str, Any]:
    """Frames per second over ``n_frames`` restorations spread over ``workers`` processes."""
    # Spawned workers load OpenBLAS before any task: they must inherit one thread each.
    with scoped_environ({name: "1" for name in THREAD_VARIABLES}):
        ctx = mp.get_context("spawn")
        with ctx.Pool(workers, _init_worker, ([str(f) for f in folders],)) as pool:
            pool.map(_restore_frame, range(workers), chunksize=1)  # every worker is ready
            t0 = time.perf_counter()
            worker_ms = [ms for _, ms in pool.imap(_restore_frame, range(n_frames), chunksize=1)]
            wall = time.perf_counter() - t0
    return {
        "workers": workers,
        "frames": n_frames,
        "wall_s": wall,
        "fps": n_frames / wall,
        "worker_ms_median": float(np.median(worker_ms)),
    }


def bench_video(args: argparse.Namespace) -> dict[str, Any]:
    """Latency (one process) and throughput for 1 .. ``args.workers`` worker processes."""
    for name in ("workers", "frames", "sequence"):
        if getattr(args, name) < 1:
            raise WaiInputError(f"--{name} must be at least 1, got {getattr(args, name)}")
    out = Path(args.out or "renders/bench_video")
    folders = render_sequence(args.config, out, args.sequence)
    from restoration import Calibration, LevelTrack, StructuredLight

    cal = Calibration.from_folder(folders[0])
    frames = [cal.load_images(f) for f in folders]
    restore, track = StructuredLight(), LevelTrack()
    restore(frames[0], cal, track)
    reference = reference_workload()
    samples = []
    for k in range(args.runs * len(frames)):
        t0 = time.perf_counter()
        restore(frames[k % len(frames)], cal, track)
        samples.append(time.perf_counter() - t0)
    counts = sorted({1, args.workers})
    return {
        "machine": machine(),
        "reference": reference,
        "sequence": [str(f) for f in folders],
        "latency": summarize(samples),
        "throughput": [throughput(folders, w, args.frames) for w in counts],
    }


def print_video(res: dict[str, Any]) -> None:
    """Human-readable report of :func:`bench_video`."""
    lat = res["latency"]
    print(
        f"latency (one process): median {lat['median_ms']:.1f} ms "
        f"({1e3 / lat['median_ms']:.1f} frames/s), IQR {lat['iqr_ms']:.1f} ms, "
        f"{lat['runs']} restorations of {len(res['sequence'])} frames, "
        f"{res['machine']['cores']} cores"
    )
    ref = res["reference"]
    print(
        f"reference workload ({ref['workload']}) in the same run: median {ref['median_ms']:.1f} "
        f"ms; latency = {lat['median_ms'] / ref['median_ms']:.2f} x reference"
    )
    for t in res["throughput"]:
        print(
            f"throughput, {t['workers']} worker(s): {t['fps']:.1f} frames/s "
            f"({t['frames']} frames in {t['wall_s']:.2f} s; {t['worker_ms_median']:.1f} ms "
            "per frame inside a worker)"
        )
