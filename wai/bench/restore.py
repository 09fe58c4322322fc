"""``wai bench restore``: per-stage and end-to-end time of the restoration of one 800x600 frame.

The pipeline reports its own timings (:attr:`restoration.RestoreResult.timings_ms` and
those of its features, surface and view); :func:`stage_times` maps them to the report's stages.
That mapping is tolerant, since the restoration's keys change as it is optimised: a key it does
not know passes through under its dotted name (``features.<key>``, ``surface.<key>``,
``view.<key>``), a missing one drops the stages that need it, and a stage the pipeline does not
time itself is computed from the others and listed as ``derived``.
"""

from __future__ import annotations

import numbers
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from wai.bench.timing import (
    check_runs,
    machine,
    peak_rss_mib,
    print_stage_table,
    reference_workload,
    runtime,
    summarize,
    time_runs,
)
from wai_core.errors import WaiInputError

# Report name of each key of the pipeline's timing dicts, by source ("" is RestoreResult's own);
# None for aggregates the report rebuilds from their parts.
_KNOWN: dict[str, dict[str, str | None]] = {
    "": {"features": "features", "surface": "surface", "reverse_trace": "view", "end_to_end": None},
    "features": {"detect": "features.detect", "match": "features.match"},
    "surface": {
        "normals": "surface.normals",
        "integrate": "surface.integrate",
        "grid": "grid",
        "total": None,
    },
    "view": {
        "plan": "view.plan",
        "surface": "view.surface",
        "solve": "view.solve",
        "upsample": "view.upsample",
        "remap": "view.remap",
        "total": None,
    },
}

DERIVED: dict[str, tuple[tuple[str, ...], tuple[str, ...], str]] = {
    "normals": (
        ("surface.normals",),
        (),
        "surface.normals (normals of the final reconstruction; 0 when its passes run compiled, "
        "which count them in surface.integrate)",
    ),
    "integration": (
        ("surface",),
        ("normals",),
        "surface - normals (integration of every pass, plus the anchor search's other "
        "reconstructions)",
    ),
    "surface.anchor_search": (
        ("surface",),
        ("surface.normals", "surface.integrate"),
        "surface - its final reconstruction's parts (the anchor search's other reconstructions)",
    ),
    "reverse_trace": (
        ("view.plan", "view.surface", "view.solve"),
        (),
        "view.plan + view.surface + view.solve (ray-surface intersection and refraction solve)",
    ),
    "resampling": (
        ("view.upsample", "view.remap"),
        (),
        "view.upsample + view.remap (warp upsampled to pixels, image remapped)",
    ),
}
"""Stages computed from others: name -> (terms added, terms subtracted, meaning). A stage the
pipeline times itself is never overwritten."""

NOTES = {
    "end_to_end": "wall time of restore() on images in memory (loading not timed)",
    "surface": "the pipeline's surface stage: anchor search with its reconstructions",
    "grid": "heightfield gridding, timed when the view stage first reads the heightfield",
    "view": "the pipeline's reverse_trace stage: grid + reverse_trace + resampling",
    "consistency": "the forward check of the surface; runs beside the view (on a second thread "
    "when there is one), so the two overlap",
}

ORDER = (
    "features",
    "features.detect",
    "features.match",
    "surface",
    "normals",
    "integration",
    "surface.normals",
    "surface.integrate",
    "surface.anchor_search",
    "grid",
    "view",
    "reverse_trace",
    "resampling",
    "view.plan",
    "view.surface",
    "view.solve",
    "view.upsample",
    "view.remap",
)
"""Display order; unknown stages follow, then ``end_to_end``."""

CHART_HIDDEN = frozenset(
    {"view", "surface.normals", "surface.integrate", "surface.anchor_search"}
    | {n for n in ORDER if n.startswith("view.")}
)
"""Parts left out of ``bench.png`` (they are in the JSON and the table) to keep it readable."""


def _timings(obj: Any) -> dict[str, Any]:
    return dict(getattr(obj, "timings_ms", None) or {})


def stage_times(result: Any) -> tuple[dict[str, float], list[str]]:
    """Report stages (ms) of one :class:`~restoration.RestoreResult`, derived included.

    Parameters
    ----------
    result : RestoreResult
        Anything with ``timings_ms`` and ``features``/``surface``/``view`` holding their own
        ``timings_ms``; missing parts are skipped.

    Returns
    -------
    times : dict of str to float
        Milliseconds per stage, without ``end_to_end`` (the caller times the whole call).
    derived : list of str
        The stages of ``times`` computed by :data:`DERIVED` rather than read.
    """
    sources = {
        "": _timings(result),
        "features": _timings(getattr(result, "features", None)),
        "surface": _timings(getattr(result, "surface", None)),
        "view": _timings(getattr(result, "view", None)),
    }
    out: dict[str, float] = {}
    for source, timings in sources.items():
        known = _KNOWN[source]
        for key, ms in timings.items():
            name = known[key] if key in known else (f"{source}.{key}" if source else key)
            if name is not None and isinstance(ms, numbers.Real) and not isinstance(ms, bool):
                out[name] = float(ms)
    derived = []
    for name, (plus, minus, _) in DERIVED.items():
        if name not in out and all(t in out for t in plus + minus):
            out[name] = sum(out[t] for t in plus) - sum(out[t] for t in minus)
            derived.append(name)
    return out, derived


def ordered(names: list[str]) -> list[str]:
    """``names`` in display order: :data:`ORDER`, then unknown ones, then ``end_to_end``."""
    rest = [n for n in names if n not in ORDER and n != "end_to_end"]
    tail = ["end_to_end"] if "end_to_end" in names else []
    return [n for n in ORDER if n in names] + rest + tail


def peak_traced_mib(fn: Callable[[], Any]) -> float:
    """Peak of the Python and NumPy allocations made during ``fn()``, MiB (tracemalloc).

    Counted above what was allocated when ``fn`` started. Native allocations of other
    libraries (OpenCV, BLAS workspaces) are not traced.
    """
    was_tracing = tracemalloc.is_tracing()
    if was_tracing:
        tracemalloc.reset_peak()
    else:
        tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        if not was_tracing:
            tracemalloc.stop()
    return (peak - base) / 2**20


MITSUBA_TUTORIAL_ITERATION_MS = 37.6
"""Time of one Adam iteration of Mitsuba 3's caustic-design tutorial (a 512 x 512 heightmap
through ``ptracer``) on a GPU, ms: the reference a fit to the pattern image is set against."""


def _render_dir(render_dir: str | Path | None, config: str | Path, variant: str) -> Path:
    """``render_dir``, or ``renders/bench`` (rendered from ``config`` unless already there)."""
    if render_dir is not None:
        return Path(render_dir)
    render_dir = Path("renders/bench")
    if not (render_dir / "scene.json").is_file():
        from mitsuba_wai import render_folder, select_variant
        from wai_core.system import load_rig

        # The variant asked for, before render_folder takes "auto": a process cannot switch.
        select_variant(variant)
        render_folder(load_rig(config), render_dir, progress=False)
    return render_dir


def bench_restore(config: str | Path, runs: int, render_dir: str | Path | None = None,
                  variant: str = "auto", workers: int | None = None,
                  method: str = "structured-light") -> dict[str, Any]:
    """Time a method (default :class:`restoration.StructuredLight`) on a render folder
    (rendered if not given).

    Loading the images is not timed (a camera delivers them in memory); everything from the
    pattern image to the restored view is. A warm-up run (which also prepares the flat-water
    reference) is reported apart; one more run, untimed, measures allocations.

    Parameters
    ----------
    config : str or Path
        The scene rendered into ``renders/bench`` when ``render_dir`` is None and that folder
        holds no render.
    runs : int
        Measured runs, after one warm-up.
    render_dir : str, Path or None
        The render folder to restore; None: ``renders/bench``.
    variant : str
        Mitsuba variant of that render, when it is made.
    workers : int or None
        Worker processes that then restore the frame side by side, ``max(runs, 10)`` each, for
        the machine's throughput (:func:`wai.bench.video.throughput`, the structured light's);
        1: none; None: :func:`wai.threads.default_workers` (another method: none). One
        frame's restoration is serial: its stages are milliseconds each and depend on each
        other, so a machine's cores are used by frames in parallel.
    method : str
        The method timed: a name of :func:`restoration.method_names` or ``module:Class``.

    Returns
    -------
    dict
        ``end_to_end_ms`` and ``stages_ms``: medians, ms, as printed before (``stages_ms`` keeps
        the pipeline's own keys, so there ``reverse_trace`` is the whole view stage);
        ``stages``: summaries under the report's stage names (see :func:`stage_times`), each
        with its ``share`` of the end-to-end median,
        ``derived`` and ``notes`` on them; ``warmup_ms``, ``peak_rss_mib`` and
        ``tracemalloc_peak_mib``; ``reference``: the reference workload timed in the same run
        and ``end_to_end_per_reference``, the end-to-end median in units of it; ``parallel``:
        :func:`~wai.bench.video.throughput`'s figures, None with one worker; ``method``; and
        for a fit to the pattern image, ``image_fit``: its loss evaluations and ms per
        evaluation in its descents (medians over the runs) and its ``backend``, beside
        :data:`MITSUBA_TUTORIAL_ITERATION_MS`.
    """
    from restoration import StructuredLight, get_method

    check_runs(runs)
    try:
        restore = get_method(method)
    except WaiInputError as exc:
        raise WaiInputError(f"--method: {exc}") from None
    own = restore.name == StructuredLight.name
    if workers is None:
        from wai.threads import default_workers

        workers = default_workers() if own else 1
    if workers < 1:
        raise WaiInputError(f"--workers must be at least 1, got {workers}")
    if workers > 1 and not own:
        raise WaiInputError(f"--workers {workers}: frames in parallel are timed for "
                            f"structured-light only, not {restore.name} (give --workers 1)")
    render_dir = _render_dir(render_dir, config, variant)
    cal = restore.calibration_type.from_folder(render_dir)
    images = cal.load_images(render_dir)
    options = restore.options
    fits: dict[str, list[float]] = {}
    backends: set[str] = set()
    reference = reference_workload()
    raw: dict[str, list[float]] = {}
    stages: dict[str, list[float]] = {}
    derived: list[str] = []

    def run(i: int) -> None:
        res = restore(images, cal)
        if i < 0:  # the warm-up's figures are not kept
            return
        anchor = getattr(getattr(res, "surface", None), "anchor", None)
        if getattr(anchor, "image_fit_ms_per_evaluation", None) is not None:
            fits.setdefault("evaluations", []).append(float(anchor.image_fit_evaluations))
            fits.setdefault("ms_per_evaluation", []).append(
                float(anchor.image_fit_ms_per_evaluation))
            backends.add(str(anchor.image_fit_backend))
        for name, ms in _raw_timings(res).items():
            raw.setdefault(name, []).append(ms)
        times, made = stage_times(res)
        derived.extend(n for n in made if n not in derived)
        for name, ms in times.items():
            stages.setdefault(name, []).append(ms)

    warm, samples = time_runs(run, runs)
    stages["end_to_end"] = [s * 1e3 for s in samples]
    summaries = {n: summarize([ms / 1e3 for ms in stages[n]]) for n in ordered(list(stages))}
    e2e = summaries["end_to_end"]
    for summary in summaries.values():  # the stage's budget: its share of the frame
        summary["share"] = summary["median_ms"] / e2e["median_ms"]
    return {
        "render_dir": str(render_dir),
        "method": restore.name,
        "image_fit": ({k: float(np.median(v)) for k, v in fits.items()}
                      | {"tutorial_iteration_ms": MITSUBA_TUTORIAL_ITERATION_MS,
                         "backend": ", ".join(sorted(backends))}
                      if fits else None),
        "machine": machine(),
        "runtime": runtime(),
        "options": options.to_dict(),
        "warmup_ms": warm * 1e3,
        "end_to_end_ms": e2e["median_ms"],
        "end_to_end": e2e,
        "fps": 1e3 / e2e["median_ms"],
        "reference": reference,
        "end_to_end_per_reference": e2e["median_ms"] / reference["median_ms"],
        "stages_ms": {k: float(np.median(v)) for k, v in raw.items()},
        "stages": summaries,
        "derived": derived,
        "notes": {
            **{k: v for k, v in NOTES.items() if k in summaries},
            **{k: DERIVED[k][2] for k in derived},
        },
        "peak_rss_mib": peak_rss_mib(),  # before the traced run: tracemalloc costs memory too
        "tracemalloc_peak_mib": peak_traced_mib(lambda: restore(images, cal)),
        "parallel": _parallel(render_dir, workers, runs, images["view"].shape),
    }


def _parallel(folder: Path, workers: int, runs: int, shape: tuple[int, ...]
              ) -> dict[str, Any] | None:
    """The frame restored ``max(runs, 10)`` times in each of ``workers`` processes side by side."""
    if workers < 2:
        return None
    from wai.bench.video import throughput

    return throughput(folder, workers, workers * max(runs, 10), shape)


def _raw_timings(res: Any) -> dict[str, float]:
    """The pipeline's timings under the keys ``wai bench restore`` has always printed."""
    out = dict(_timings(res))
    parts = {"features": "features", "surface": "surface", "reverse_trace": "view"}
    for prefix, part in parts.items():
        out.update({f"{prefix}.{k}": v for k, v in _timings(getattr(res, part, None)).items()})
    return out


def print_restore(res: dict[str, Any]) -> None:
    """Human-readable report of :func:`bench_restore`."""
    e = res["end_to_end"]
    rt = res["runtime"]
    print(
        f"restore {res['render_dir']} ({res.get('method', 'structured-light')}): end to end "
        f"median {e['median_ms']:.1f} ms "
        f"({res['fps']:.1f} frames/s; min {e['min_ms']:.1f}, max {e['max_ms']:.1f}, "
        f"{e['runs']} runs, {res['machine']['cores']} cores, "
        f"{rt.get('opencv_threads')} OpenCV threads, {rt.get('numba_threads')} restoration "
        f"threads; warm-up {res['warmup_ms']:.0f} ms)"
    )
    ref = res["reference"]
    print(
        f"reference workload ({ref['workload']}) in the same run: median {ref['median_ms']:.1f} "
        f"ms; end to end = {res['end_to_end_per_reference']:.2f} x reference"
    )
    print_stage_table(res["stages"], res["derived"], res["notes"], e["runs"])
    print(
        f"peak RSS {res['peak_rss_mib']:.0f} MiB; Python/NumPy allocations in one restoration "
        f"peak at {res['tracemalloc_peak_mib']:.1f} MiB (tracemalloc)"
    )
    fit = res.get("image_fit")
    if fit:
        print(
            f"fit to the pattern image ({fit['backend']}): {fit['evaluations']:.0f} loss "
            f"evaluations, {fit['ms_per_evaluation']:.1f} ms each in its descents (the model's "
            f"image and its gradient; median over the runs) against "
            f"{fit['tutorial_iteration_ms']} ms a GPU iteration of Mitsuba's caustic-design "
            "tutorial"
        )
    par = res.get("parallel")
    if par:
        print(
            f"frames in parallel: {par['workers']} worker processes, one thread each, "
            f"{par['fps']:.1f} frames/s ({par['frames']} frames in {par['wall_s']:.2f} s; "
            f"{par['worker_ms_median']:.1f} ms per frame inside a worker)"
        )
    else:
        print("frames in parallel: not measured (one worker)")
