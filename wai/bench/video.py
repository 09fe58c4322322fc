"""``wai bench video``: restoration latency and throughput over a rendered frame sequence.

A video restorer sees one frame after another. Latency is the time one process takes per frame
(what ``wai bench restore`` measures); throughput is how many frames per second the machine
restores when frames are spread over worker processes, one per core, each holding the
calibration (the flat-water reference is prepared once per worker, not per frame) and
restoring with one thread: the restoration's parallel kernels would otherwise run one thread
per core in every worker. Each restored frame travels to the parent as 8-bit RGB (what a
display or an encoder takes) as soon as it is done, through a slot of shared memory that the
parent frees once it has copied the frame out.

The sequence is rendered once into ``--out`` (default ``renders/bench_video``): consecutive
frames 1/30 s apart by default (``--fps``: the camera's frame rate), so the waves move as in a
real recording; where spots move a small part of a dot spacing between frames (~120 frames/s
and faster on the paper's rig) tracking can label them. It is played forth and back
(0, 1, .., n - 1, n - 2, .., 1, 0, 1, ..), so that every frame follows one of its neighbours in
time, and each worker restores a contiguous run of that order with its own
:class:`~restoration.tracking.SequenceState`: with tracking (``track=True``, ``--track``)
each frame's labels are tracked from the previous frames' spots and its warp solve starts at
the previous frame's; by default every frame is restored on its own. One period of the
order is also restored both ways and scored against the frames' truth: statuses and surface
RMSE with tracking and without.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path
from typing import Any

import numpy as np

from wai.bench.timing import check_runs, machine, reference_workload, summarize
from wai.threads import THREAD_VARIABLES, limit_native_threads, scoped_environ
from wai_core.errors import WaiInputError
from wai_core.sequence import DEFAULT_FPS

# Per worker process: the calibration and the frames' images, loaded by _init_worker.
_STATE: dict[str, Any] = {}


def sequence_folder(config: str, out: Path, n_frames: int, fps: float = DEFAULT_FPS) -> Path:
    """The sequence of ``n_frames`` frames at ``fps`` frames/s in ``out/sequence``, rendered
    once (by :func:`mitsuba_wai.sequence.render_sequence`, what ``wai render --frames`` runs;
    again when the frame count or rate differ)."""
    from mitsuba_wai import render_sequence
    from wai_core.sequence import is_sequence, read_sequence
    from wai_core.system import load_rig

    folder = out / "sequence"
    rec = read_sequence(folder) if is_sequence(folder) else None
    if rec is None or (len(rec.frames), rec.fps) != (n_frames, fps):
        render_sequence(load_rig(config), folder, n_frames, fps, progress=False)
    return folder


def played(index: int, n: int) -> int:
    """The frame shown at step ``index`` of a sequence of ``n`` frames played forth and back
    (0, 1, .., n - 1, n - 2, .., 1, 0, ..).

    Examples
    --------
    >>> [played(k, 3) for k in range(6)]
    [0, 1, 2, 1, 0, 1]
    """
    if n < 2:
        return 0
    k = index % (2 * n - 2)
    return k if k < n else 2 * n - 2 - k


def _init_worker(folder: str, track: bool) -> None:
    """Load the calibration and every frame's images (of a sequence, or the one frame of a
    render folder); prepare the reference; warm up."""
    from restoration import Calibration, StructuredLight, load_sequence
    from wai_core.sequence import is_sequence

    limit_native_threads(1)  # numba's pool too: the workers are the parallelism here
    if is_sequence(folder):
        cal, frames = load_sequence(folder)
    else:
        cal = Calibration.from_folder(folder)
        frames = [cal.load_images(folder)]
    restore = StructuredLight()
    restore(frames[0], cal)  # prepares the reference and warms every code path
    _STATE.update(cal=cal, frames=frames, restore=restore, track=track, state=None, last=None)


def _restore_frame(index: int, out: np.ndarray) -> tuple[float, int]:
    """Restore step ``index`` of the played order into ``out`` (H, W, 3) as 8-bit RGB; the
    worker's ms and whether its labels were tracked. A worker's state follows its own run of
    steps."""
    import cv2

    from restoration import SequenceState

    frames = _STATE["frames"]
    if _STATE["last"] is None or index != _STATE["last"] + 1:  # not the step after its last
        _STATE["state"] = SequenceState(track=_STATE["track"])
    _STATE["last"] = index
    t0 = time.perf_counter()
    res = _STATE["restore"](frames[played(index, len(frames))], _STATE["cal"], _STATE["state"])
    ms = 1e3 * (time.perf_counter() - t0)
    # One pass, rounded and saturated at 255 (the restored radiance is not negative).
    cv2.convertScaleAbs(res.view.image, dst=out, alpha=255.0)
    return ms, int(res.restored and res.features.counts.get("tracked", 0))


_SLOTS = 3
"""Restored frames a worker may hand over before the parent has taken the first."""


def _stream(k: int, folder: str, track: bool, steps: list[int], shm_name: str,
            shape: tuple[int, ...], free: Any, results: Any, go: Any) -> None:
    """Worker ``k``: restore ``steps`` in order, each into a free slot of its shared frames,
    and post ``(k, slot, ms, tracked)`` as each is done."""
    from multiprocessing.shared_memory import SharedMemory

    try:
        _init_worker(folder, track)
        shm = SharedMemory(shm_name)
        slots = np.ndarray((_SLOTS, *shape), np.uint8, buffer=shm.buf)
        _restore_frame(-2, slots[0])  # from step -2: no state follows on from it
        results.put(("ready", k))
        go.wait()
        for index in steps:
            slot = free.get()
            ms, tracked = _restore_frame(index, slots[slot])
            results.put((k, slot, ms, tracked))
        del slots
        shm.close()
    except BaseException as exc:  # the parent reports it and stops the other workers
        results.put(("failed", f"{type(exc).__name__}: {exc}"))


def throughput(folder: Path, workers: int, n_frames: int, shape: tuple[int, ...],
               track: bool = False) -> dict[str, Any]:
    """Frames per second over ``n_frames`` restorations spread over ``workers`` processes, each
    a contiguous run of the played order (of a sequence folder; of a render folder, its one
    frame again and again), the restored 8-bit frames ``shape`` (H, W, 3)
    streamed to this process as they are done (through shared memory: a slot each, freed
    once this process has copied the frame out, as a display would).

    Returns ``workers``, ``frames``, ``wall_s`` (from the start signal to the last frame
    copied out), ``fps`` (frames over the wall), ``worker_ms_median`` and ``worker_ms_total``
    (restoration time inside the workers, per frame and summed) and ``tracked`` (frames whose
    labels were tracked)."""
    from multiprocessing.shared_memory import SharedMemory

    run = -(-n_frames // workers)
    runs = [list(range(k * run, min((k + 1) * run, n_frames))) for k in range(workers)]
    nbytes = _SLOTS * int(np.prod(shape))
    # Spawned workers load OpenBLAS and numba's pool before any task: they must inherit one
    # thread each.
    ctx = mp.get_context("spawn")
    results, go = ctx.Queue(), ctx.Event()
    free = [ctx.Queue() for _ in range(workers)]
    shms = [SharedMemory(create=True, size=nbytes) for _ in range(workers)]
    procs = []
    try:
        with scoped_environ({name: "1" for name in THREAD_VARIABLES}):
            for k in range(workers):
                for slot in range(_SLOTS):
                    free[k].put(slot)
                procs.append(ctx.Process(
                    target=_stream, daemon=True,
                    args=(k, str(folder), track, runs[k], shms[k].name, shape, free[k], results,
                          go),
                ))
                procs[-1].start()
        for _ in range(workers):  # every worker warmed up
            _message(results, procs)
        slots = [np.ndarray((_SLOTS, *shape), np.uint8, buffer=shm.buf) for shm in shms]
        shown = np.empty(shape, np.uint8)
        done = []
        t0 = time.perf_counter()
        go.set()
        for _ in range(n_frames):
            k, slot, ms, tracked = _message(results, procs)
            np.copyto(shown, slots[k][slot])
            free[k].put(slot)
            done.append((ms, tracked))
        wall = time.perf_counter() - t0
        del slots
    finally:
        for proc in procs:
            proc.join(timeout=30)
            if proc.is_alive():
                proc.terminate()
        for shm in shms:
            shm.close()
            shm.unlink()
    return {
        "workers": workers,
        "frames": n_frames,
        "wall_s": wall,
        "fps": n_frames / wall,
        "worker_ms_median": float(np.median([ms for ms, _ in done])),
        "worker_ms_total": float(sum(ms for ms, _ in done)),
        "tracked": int(sum(t for _, t in done)),
    }


def _message(results: Any, procs: list[Any]) -> tuple:
    """The next message from the workers; RuntimeError when one failed or died."""
    import queue

    while True:
        try:
            msg = results.get(timeout=1.0)
        except queue.Empty:
            if any(p.exitcode not in (None, 0) for p in procs):
                raise RuntimeError("a video worker process died") from None
            continue
        if msg[0] == "failed":
            raise RuntimeError(f"a video worker failed: {msg[1]}")
        return msg


def accuracy(folder: Path, cal: Any, images: list[dict[str, Any]]) -> dict[str, Any]:
    """One period of the played order restored with tracking and without, each scored against
    its frame's truth: statuses, surface RMSE (mm) per step, and the largest difference."""
    from restoration import SequenceState, StructuredLight, Truth, score
    from wai_core.sequence import read_sequence

    dirs = read_sequence(folder).frame_dirs
    steps = [played(k, len(images)) for k in range(max(2 * len(images) - 2, 1))]
    truths = {k: Truth.from_folder(dirs[k], cal) for k in set(steps)}
    restore = StructuredLight()
    out: dict[str, Any] = {"frames": steps}
    for track in (True, False):
        state = SequenceState(track=track)
        statuses, rmse, tracked = [], [], []
        for k in steps:
            res = restore(images[k], cal, state)
            statuses.append(res.status.value)
            tracked.append(int(res.features.counts.get("tracked", 0)) if res.restored else 0)
            sc = score(res, cal.radiance(images[k]["view"]), cal, truths[k]) if (
                res.has_view and truths[k] is not None) else None
            rmse.append(None if sc is None or sc.surface is None else float(sc.rmse_mm))
        out["tracked" if track else "untracked"] = {
            "statuses": statuses, "rmse_mm": rmse, "tracked": tracked,
            "mean_rmse_mm": _mean(rmse),
        }
    a, b = out["tracked"]["rmse_mm"], out["untracked"]["rmse_mm"]
    diffs = [abs(x - y) for x, y in zip(a, b, strict=True) if x is not None and y is not None]
    out["max_rmse_difference_mm"] = max(diffs) if diffs else None
    out["statuses_equal"] = out["tracked"]["statuses"] == out["untracked"]["statuses"]
    return out


def _mean(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def _stage_times(res: Any) -> dict[str, float]:
    """A restoration's stages (ms) and, prefixed, the features' and the view's own steps."""
    parts = {**res.timings_ms}
    if res.restored:
        parts.update({f"features.{k}": v for k, v in res.features.timings_ms.items()})
        parts.update({f"view.{k}": v for k, v in res.view.timings_ms.items()})
    return {key: float(ms) for key, ms in parts.items()}


def _stage_medians(timings: list[dict[str, float]]) -> dict[str, float]:
    """Median ms of each stage over restorations (:func:`_stage_times` of each)."""
    table: dict[str, list[float]] = {}
    for parts in timings:
        for key, ms in parts.items():
            table.setdefault(key, []).append(ms)
    return {key: float(np.median(v)) for key, v in table.items()}


def bench_video(config: str | Path, out: str | Path | None, runs: int, workers: int | None,
                frames: int, sequence: int, *, track: bool = False,
                fps: float = DEFAULT_FPS) -> dict[str, Any]:
    """Latency (one process) and throughput for 1 .. ``workers`` worker processes, with
    tracking or without, and the accuracy both ways (:func:`accuracy`).

    Parameters
    ----------
    config : str or Path
        The scene: a packaged name or a TOML file.
    out : str, Path or None
        The folder of the rendered sequence; None: ``renders/bench_video``.
    runs : int
        Measured passes over the sequence for the latency.
    workers : int or None
        The most worker processes (throughput is measured for 1 and ``workers``); None:
        :func:`wai.threads.default_workers`.
    frames : int
        Frames restored per worker count.
    sequence : int
        Distinct frames rendered.
    track : bool
        Each frame reuses the previous ones (:class:`~restoration.tracking.SequenceState`).
    fps : float
        Frame rate of the rendered sequence, frames/s (the camera's).
    """
    check_runs(runs)
    if workers is None:
        from wai.threads import default_workers

        workers = default_workers()
    if not (np.isfinite(fps) and fps > 0):
        raise WaiInputError(f"--fps must be a positive frame rate, got {fps}")
    for name, value in (("workers", workers), ("frames", frames), ("sequence", sequence)):
        if value < 1:
            raise WaiInputError(f"--{name} must be at least 1, got {value}")
    out = Path(out or "renders/bench_video")
    folder = sequence_folder(config, out, sequence, fps)
    from restoration import SequenceState, StructuredLight, load_sequence

    cal, images = load_sequence(folder)
    restore, state = StructuredLight(), SequenceState(track=track)
    restore(images[0], cal)  # prepares the reference and warms every code path
    reference = reference_workload()
    samples, timings = [], []
    for k in range(runs * max(2 * len(images) - 2, 1)):
        t0 = time.perf_counter()
        res = restore(images[played(k, len(images))], cal, state)
        samples.append(time.perf_counter() - t0)
        # Only the timings are kept: a video restorer shows each frame and lets it go (kept,
        # every frame's new image would cost the next one fresh memory, ~6 us a page here).
        timings.append(_stage_times(res))
    counts = sorted({1, workers})
    return {
        "machine": machine(),
        "reference": reference,
        "sequence": str(folder),
        "frames_in_sequence": len(images),
        "fps_rendered": float(fps),
        "tracking": track,
        "latency": summarize(samples),
        "latency_tracked": state.tracked,
        "latency_fallbacks": state.fallbacks,
        "latency_skipped": state.skipped,
        "stages_ms": _stage_medians(timings),
        "throughput": [throughput(folder, w, frames, images[0]["view"].shape, track)
                       for w in counts],
        "accuracy": accuracy(folder, cal, images),
    }


def print_video(res: dict[str, Any]) -> None:
    """Human-readable report of :func:`bench_video`."""
    lat = res["latency"]
    print(
        f"latency (one process): median {lat['median_ms']:.1f} ms "
        f"({1e3 / lat['median_ms']:.1f} frames/s), IQR {lat['iqr_ms']:.1f} ms, "
        f"{lat['runs']} restorations of {res['frames_in_sequence']} frames at "
        f"{res['fps_rendered']:g} frames/s, {res['machine']['cores']} cores"
    )
    ref = res["reference"]
    print(
        f"reference workload ({ref['workload']}) in the same run: median {ref['median_ms']:.1f} "
        f"ms; latency = {lat['median_ms'] / ref['median_ms']:.2f} x reference"
    )
    if res["tracking"]:
        print(f"with tracking (--track): labels tracked on {res['latency_tracked']} of "
              f"{lat['runs']} frames ({res['latency_fallbacks']} matched in full after tracking "
              f"failed its checks, {res['latency_skipped']} without trying after failures)")
    else:
        print("every frame matched in full (--track: labels tracked from the previous frames)")
    stages = res["stages_ms"]
    print("stages (median ms): " + ", ".join(
        f"{k} {stages[k]:.1f}" for k in ("features.detect", "features.match", "surface",
                                         "view.solve", "view.remap", "reverse_trace",
                                         "consistency") if k in stages))
    for t in res["throughput"]:
        print(
            f"throughput, {t['workers']} worker(s): {t['fps']:.1f} frames/s "
            f"({t['frames']} frames in {t['wall_s']:.2f} s; {t['worker_ms_median']:.1f} ms "
            f"per frame inside a worker" + (f"; {t['tracked']} tracked)" if res["tracking"]
                                              else ")")
        )
    acc = res["accuracy"]
    on, off = acc["tracked"], acc["untracked"]
    print(
        f"accuracy over {len(acc['frames'])} frames: mean surface RMSE "
        f"{_mm(on['mean_rmse_mm'])} with tracking ({sum(on['tracked'])} tracked), "
        f"{_mm(off['mean_rmse_mm'])} without; largest per-frame difference "
        f"{_mm(acc['max_rmse_difference_mm'])}; statuses "
        f"{'the same' if acc['statuses_equal'] else 'DIFFER'}"
    )


def _mm(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.4f} mm"
