"""``wai bench``: wall-time benchmarks that print figures (median and spread of several runs).

Dr.Jit and numba compile kernels on first use, so every benchmark runs one warm-up that is
reported apart from the measured runs, and times a reference workload in the same run
(:mod:`wai.bench.timing`). ``wai bench`` (``all``, :mod:`wai.bench.report`) times every stage,
rendering and restoration, and writes ``bench.json`` and ``bench.png``; ``render``
(:mod:`wai.bench.render`) and ``restore`` (:mod:`wai.bench.restore`) print their part only;
``accuracy`` (:mod:`wai.bench.accuracy`) scores seeds with an error budget; ``surfaces``
(:mod:`wai.bench.surfaces`) restores analytic surfaces; ``inputs`` (:mod:`wai.bench.inputs`)
restores wrong inputs and reports their statuses; ``video``
(:mod:`wai.bench.video`) measures latency and throughput over a sequence.
"""

from __future__ import annotations

import json
from pathlib import Path

from wai_core.errors import WaiInputError

__all__ = ["DEFAULT_OUT", "run_bench"]

DEFAULT_OUT = {
    "all": Path("renders/bench"),
    "accuracy": Path("renders/bench_accuracy"),
    "video": Path("renders/bench_video"),
    "surfaces": Path("renders/bench_surfaces"),
    "inputs": Path("renders/bench_inputs"),
}
"""Output folder of the benchmarks that write files, when ``--out`` is not given."""


def run_bench(what: str | None, *, config: str | Path, out: str | Path | None, runs: int,
              as_json: bool, variant: str, render_dir: str | Path | None, seeds: int,
              wind: float | None, surface: str | None, camera: str | None, spp: int | None,
              phi: float, workers: int, frames: int, sequence: int) -> None:
    """Run ``wai bench WHAT`` and print the figures (or one JSON object).

    Parameters
    ----------
    what : str or None
        ``all`` (None too), ``render``, ``restore``, ``accuracy``, ``surfaces``, ``inputs`` or
        ``video``.
    config, out, runs
        The scene, the output folder (None: :data:`DEFAULT_OUT`'s) and the measured runs.
    as_json : bool
        Print one JSON object instead of the report.
    variant, render_dir
        ``all``, ``render``, ``restore``: see :func:`wai.bench.restore.bench_restore`.
    seeds, wind, surface, camera, spp
        ``accuracy``: see :func:`wai.bench.accuracy.run_accuracy`.
    phi
        ``surfaces``: see :func:`wai.bench.surfaces.bench_surfaces`.
    workers, frames, sequence
        ``video``: see :func:`wai.bench.video.bench_video`.
    """
    what = what or "all"
    if what != "accuracy" and runs < 1:
        raise WaiInputError(f"--runs must be at least 1, got {runs}")
    if out is None and what in DEFAULT_OUT:
        out = DEFAULT_OUT[what]
    paths: list[Path] = []
    if what == "all":
        from wai.bench.report import bench_all, print_report, write_report

        res = bench_all(config, runs, render_dir, variant)
        paths = write_report(res, out)
        printer = print_report
    elif what == "render":
        from wai.bench.render import bench_render, print_render

        res = bench_render(config, runs, variant)
        printer = print_render
    elif what == "accuracy":
        from wai.bench.accuracy import print_accuracy, run_accuracy

        res = run_accuracy(config, out, seeds, wind, surface, camera, spp)
        printer = print_accuracy
    elif what == "surfaces":
        from wai.bench.surfaces import bench_surfaces, print_surfaces

        res = bench_surfaces(config, out, phi)
        printer = print_surfaces
    elif what == "inputs":
        from wai.bench.inputs import bench_inputs, print_inputs

        res = bench_inputs(config, Path(out))
        printer = print_inputs
    elif what == "video":
        from wai.bench.video import bench_video, print_video

        res = bench_video(config, out, runs, workers, frames, sequence)
        printer = print_video
    else:
        from wai.bench.restore import bench_restore, print_restore

        res = bench_restore(config, runs, render_dir, variant)
        printer = print_restore
    if as_json:
        print(json.dumps(res))
        return
    printer(res)
    for path in paths:
        print(f"wrote {path}")
