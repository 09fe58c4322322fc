"""A sweep's command-line options (``--scheduler``, ``--workers``, ...) and the
:class:`SweepOptions` an experiment passes through to :func:`wai.sweep.run_sweep`."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any


def _count(minimum: int) -> Callable[[str], int]:
    """An argparse type: an int no smaller than ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, not {value}")
        return value

    return parse


def add_sweep_arguments(parser: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """Add the options of :func:`run_sweep` to an experiment's parser (as a group).

    Parameters
    ----------
    parser
        The experiment's parser (or subparser).

    Returns
    -------
    argparse._ArgumentGroup
        The group, to add more options to.
    """
    group = parser.add_argument_group("sweep", "where and how the sweep's points run")
    group.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="a running Dask scheduler, e.g. tcp://host:8786 (default: a local cluster)",
    )
    group.add_argument(
        "--workers",
        type=_count(0),
        default=None,
        metavar="N",
        help="local worker processes; 0 runs in this process without Dask (default: one per "
        "core, as memory allows)",
    )
    group.add_argument(
        "--threads-per-worker",
        type=_count(1),
        default=SweepOptions.threads_per_worker,
        metavar="N",
        help="threads of each local worker, and of its native libraries (default 1)",
    )
    group.add_argument(
        "--retry-errors", action="store_true", help="rerun the points whose row is an error"
    )
    group.add_argument("--no-progress", action="store_true", help="no progress bar")
    return group


@dataclass(frozen=True)
class SweepOptions:
    """Where and how a sweep's points run: the keyword arguments of :func:`run_sweep` that an
    experiment passes through (``scheduler``, ``workers``, ``threads_per_worker``,
    ``retry_errors``, ``progress``; see there)."""

    scheduler: str | None = None
    workers: int | None = None
    threads_per_worker: int = 1
    retry_errors: bool = False
    progress: bool = True

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> SweepOptions:
        """The options parsed from those that :func:`add_sweep_arguments` added."""
        return cls(args.scheduler, args.workers, args.threads_per_worker, args.retry_errors,
                   progress=not args.no_progress)

    def kwargs(self) -> dict[str, Any]:
        """The keyword arguments of :func:`run_sweep`."""
        return asdict(self)
