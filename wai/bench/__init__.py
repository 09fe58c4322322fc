"""``wai bench NAME``: wall-time benchmarks that print figures (median and spread of several runs).

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
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["DEFAULT_OUT", "show"]

DEFAULT_OUT = {
    "all": Path("renders/bench"),
    "accuracy": Path("renders/bench_accuracy"),
    "video": Path("renders/bench_video"),
    "surfaces": Path("renders/bench_surfaces"),
    "inputs": Path("renders/bench_inputs"),
    "sizes": Path("renders/bench_sizes"),
}
"""Output folder of the benchmarks that write files, when ``--out`` is not given."""


def show(result: dict[str, Any], printer: Callable[[dict[str, Any]], None], *, as_json: bool,
         written: Sequence[Path] = ()) -> None:
    """Print a benchmark's ``result``: one JSON object, or ``printer``'s report and the files
    the benchmark ``written``."""
    if as_json:
        print(json.dumps(result))
        return
    printer(result)
    for path in written:
        print(f"wrote {path}")
