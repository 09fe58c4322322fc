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

import argparse
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


def run_bench(args: argparse.Namespace) -> None:
    """Dispatch ``wai bench [WHAT]`` and print the figures (or one JSON object)."""
    what = args.what or "all"
    if what != "accuracy" and args.runs < 1:
        raise WaiInputError(f"--runs must be at least 1, got {args.runs}")
    if getattr(args, "out", None) is None and what in DEFAULT_OUT:
        args.out = DEFAULT_OUT[what]
    paths: list[Path] = []
    if what == "all":
        from wai.bench.report import bench_all, print_report, write_report

        res = bench_all(args)
        paths = write_report(res, args.out)
        printer = print_report
    elif what == "render":
        from wai.bench.render import bench_render, print_render

        res = bench_render(args)
        printer = print_render
    elif what == "accuracy":
        from wai.bench.accuracy import print_accuracy, run_accuracy

        res = run_accuracy(args)
        printer = print_accuracy
    elif what == "surfaces":
        from wai.bench.surfaces import bench_surfaces, print_surfaces

        res = bench_surfaces(args)
        printer = print_surfaces
    elif what == "inputs":
        from wai.bench.inputs import bench_inputs, print_inputs

        res = bench_inputs(args.config, Path(args.out))
        printer = print_inputs
    elif what == "video":
        from wai.bench.video import bench_video, print_video

        res = bench_video(args)
        printer = print_video
    else:
        from wai.bench.restore import bench_restore, print_restore

        res = bench_restore(args)
        printer = print_restore
    if args.json:
        print(json.dumps(res))
        return
    printer(res)
    for path in paths:
        print(f"wrote {path}")
