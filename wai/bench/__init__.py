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

__all__ = ["DEFAULT_OUT", "parse_pair", "show"]

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


def parse_pair(text: str, option: str, form: str, minimum: int, unit: str) -> tuple[int, int]:
    """Two whole numbers written ``AxB`` (``1600x1200``, ``8x6``), each at least ``minimum``.

    Parameters
    ----------
    text : str
        The option's value.
    option : str
        The option, as the error names it (``--camera``).
    form : str
        What the value should look like, in the error (``WIDTHxHEIGHT in pixels``).
    minimum : int
        The least of each number.
    unit : str
        What the numbers count, in the error (``pixels``).

    Returns
    -------
    (int, int)

    Raises
    ------
    WaiInputError
        One line naming ``option``: not two whole numbers, or one under ``minimum``.

    Examples
    --------
    >>> parse_pair("8x6", "--board", "COLSxROWS inner corners", 2, "inner corners")
    (8, 6)
    """
    from wai_core.errors import WaiInputError

    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise WaiInputError(f"{option} must be {form}, not {text!r}") from None
    if a < minimum or b < minimum:
        raise WaiInputError(f"{option} {text}: at least {minimum} x {minimum} {unit}")
    return a, b
