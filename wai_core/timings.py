"""A stopwatch for named steps: ``with timings("features"): ...`` records wall times in ms."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Timings"]


class Timings:
    """Wall times of named steps, milliseconds; a step timed twice adds up.

    Examples
    --------
    >>> from wai_core.timings import Timings
    >>> timings = Timings()
    >>> with timings("features"):
    ...     _ = sum(range(1000))
    >>> list(timings.ms), timings.ms["features"] >= 0.0
    (['features'], True)
    >>> timings.add("end_to_end", 2.5); timings.ms["end_to_end"]
    2.5
    """

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        """Time the ``with`` block as step ``name`` (recorded even when it raises)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, 1e3 * (time.perf_counter() - start))

    def add(self, name: str, ms: float) -> None:
        """Add ``ms`` milliseconds to step ``name``."""
        self.ms[name] = self.ms.get(name, 0.0) + float(ms)

    def total(self, *names: str) -> float:
        """Sum of the named steps (all steps when none are named), ms."""
        return sum(self.ms.get(n, 0.0) for n in names) if names else sum(self.ms.values())

    def to_dict(self) -> dict[str, float]:
        """The steps' times as a plain dict, ms (what ``metrics.json`` records)."""
        return dict(self.ms)

    def __repr__(self) -> str:
        steps = ", ".join(f"{k}={v:.2f}" for k, v in self.ms.items())
        return f"Timings({steps})"
