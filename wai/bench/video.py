"""``wai bench video``: restoration latency and throughput over a rendered frame sequence.

A video restorer sees one frame after another. Latency is the time one process takes per frame
(what ``wai bench restore`` measures); throughput is how many frames per second the machine
restores when frames are spread over worker processes, one per core, each holding the
calibration (the flat-water reference is prepared once per worker, not per frame) and
restoring with one thread: the restoration's parallel kernels would otherwise run one thread
per core in every worker. The restored frame travels back to the parent as 8-bit RGB (what a
display or an encoder takes).

The sequence is rendered once into ``--out`` (default ``renders/bench_video``): consecutive
frames 1/30 s apart, so the waves move as in a real recording.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path
from typing import Any

import numpy as np

from wai.bench.timing import check_runs, machine, reference_workload, summarize
from wai.sweep import THREAD_VARIABLES, limit_native_threads, scoped_environ
from wai_core.errors import WaiInputError

FPS = 30.0
"""Frame rate of the rendered sequence."""

# Per worker process: the calibration and the frames' images, loaded by _init_worker.
_STATE: dict[str, Any] = {}


def sequence_folder(config: str, out: Path, n_frames: int) -> Path:
    """The sequence of ``n_frames`` frames at :data:`FPS` in ``out/sequence``, rendered once
    (by :func:`mitsuba_wai.sequence.render_sequence`, what ``wai render --frames`` runs)."""
    from mitsuba_wai.sequence import render_sequence
    from wai_core.sequence import is_sequence, read_sequence
    from wai_core.system import load_rig

    folder = out / "sequence"
    if not (is_sequence(folder) and len(read_sequence(folder).frames) == n_frames):
        render_sequence(load_rig(config), folder, n_frames, FPS, progress=False)
    return folder


def _init_worker(folder: str) -> None:
    """Load the calibration and every frame's images; prepare the reference; warm up."""
    from restoration import LevelTrack, StructuredLight
    from restoration.sequence import load_sequence

    limit_native_threads(1)  # numba's pool too: the workers are the parallelism here
    cal, frames = load_sequence(folder)
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


def throughput(folder: Path, workers: int, n_frames: int) -> dict[str, Any]:
    """Frames per second over ``n_frames`` restorations spread over ``workers`` processes."""
    # Spawned workers load OpenBLAS and numba's pool before any task: they must inherit one
    # thread each.
    with scoped_environ({name: "1" for name in THREAD_VARIABLES}):
        ctx = mp.get_context("spawn")
        with ctx.Pool(workers, _init_worker, (str(folder),)) as pool:
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


def bench_video(config: str | Path, out: str | Path | None, runs: int, workers: int,
                frames: int, sequence: int) -> dict[str, Any]:
    """Latency (one process) and throughput for 1 .. ``workers`` worker processes.

    Parameters
    ----------
    config : str or Path
        The scene: a packaged name or a TOML file.
    out : str, Path or None
        The folder of the rendered sequence; None: ``renders/bench_video``.
    runs : int
        Measured passes over the sequence for the latency.
    workers : int
        The most worker processes (throughput is measured for 1 and ``workers``).
    frames : int
        Frames restored per worker count.
    sequence : int
        Distinct frames rendered.
    """
    check_runs(runs)
    for name, value in (("workers", workers), ("frames", frames), ("sequence", sequence)):
        if value < 1:
            raise WaiInputError(f"--{name} must be at least 1, got {value}")
    out = Path(out or "renders/bench_video")
    folder = sequence_folder(config, out, sequence)
    from restoration import LevelTrack, StructuredLight
    from restoration.sequence import load_sequence

    cal, images = load_sequence(folder)
    restore, track = StructuredLight(), LevelTrack()
    restore(images[0], cal, track)
    reference = reference_workload()
    samples = []
    for k in range(runs * len(images)):
        t0 = time.perf_counter()
        restore(images[k % len(images)], cal, track)
        samples.append(time.perf_counter() - t0)
    counts = sorted({1, workers})
    return {
        "machine": machine(),
        "reference": reference,
        "sequence": str(folder),
        "frames_in_sequence": len(images),
        "latency": summarize(samples),
        "throughput": [throughput(folder, w, frames) for w in counts],
    }


def print_video(res: dict[str, Any]) -> None:
    """Human-readable report of :func:`bench_video`."""
    lat = res["latency"]
    print(
        f"latency (one process): median {lat['median_ms']:.1f} ms "
        f"({1e3 / lat['median_ms']:.1f} frames/s), IQR {lat['iqr_ms']:.1f} ms, "
        f"{lat['runs']} restorations of {res['frames_in_sequence']} frames, "
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
