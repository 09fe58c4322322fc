"""What the experiments share around their own work: the output folder, a sweep's points run
into its table, the command line a report quotes, and the report written and printed."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from wai.sweep import Point, Row, SweepOptions, run_sweep
from wai_core.io import atomic_write_bytes

__all__ = ["argv_command", "output_folder", "publish", "sweep_command", "sweep_rows"]


def output_folder(out: str | Path) -> Path:
    """The experiment's output folder, made if missing.

    Parameters
    ----------
    out : str or Path

    Returns
    -------
    Path
        ``out`` as a path.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return out


def sweep_rows(points: Iterable[Point], fn: Callable[[dict], Mapping[str, Any]], table: Path,
               sweep: SweepOptions | None, **kwargs: Any) -> list[Row]:
    """Run a sweep's ``points`` into ``table`` where and how ``sweep`` says.

    Parameters
    ----------
    points, fn, table
        As :func:`wai.sweep.run_sweep`.
    sweep : SweepOptions or None
        Where and how the points run; None: :class:`~wai.sweep.SweepOptions`' defaults.
    **kwargs
        Further keyword arguments of :func:`wai.sweep.run_sweep` (``key``).

    Returns
    -------
    list of dict
        The table's rows of these points (:func:`wai.sweep.run_sweep`).
    """
    sweep = SweepOptions() if sweep is None else sweep
    return run_sweep(points, fn, table, **kwargs, **sweep.kwargs())


def sweep_command(name: str, seeds: int, quick: bool) -> str:
    """The command line a sweep experiment's report quotes.

    Examples
    --------
    >>> sweep_command("budget", 20, True)
    'wai experiment budget --seeds 20 --quick'
    """
    return f"wai experiment {name} --seeds {seeds}" + (" --quick" if quick else "")


def argv_command(name: str) -> str:
    """``wai experiment NAME`` and this process's arguments after it, as a report quotes it."""
    return f"wai experiment {name} " + " ".join(sys.argv[3:])


def publish(path: Path, text: str) -> None:
    """Write the report ``text`` to ``path`` (atomically) and print it (the folder's page is
    :func:`wai.experiments.run_experiment`'s, once the experiment is done)."""
    atomic_write_bytes(path, text.encode())
    print(text)
