"""A sweep's points: their stable ids, and one point evaluated into an outcome (the row's
results and bookkeeping), in this process or on a Dask worker."""

from __future__ import annotations

import hashlib
import json
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from wai.threads import limit_native_threads

# Columns that run_sweep adds to every row, in this order, after the point and result fields.
BOOKKEEPING = ("point_id", "status", "elapsed_s", "worker")
OK = "ok"
IN_PROCESS = "in-process"
MAX_MESSAGE = 400  # characters of an error message kept in a row's status
WORKER_LOSSES = frozenset({"KilledWorker", "CommClosedError", "FutureCancelledError"})
"""Exceptions of a point whose worker process died (not of the point's own code)."""
WORKER_RETRIES = 1
"""Times the sweep runs a point again after the worker running it died."""
WORKER_DIED = "worker died"
"""What the status of a point whose worker died says (after ``error:``)."""

Point = Mapping[str, Any]
"""A sweep's point: its parameters by name."""
Row = dict[str, Any]
"""A row of a sweep's table: the point's parameters and its outcome."""
Outcome = dict[str, Any]
"""What evaluating a point gives: values by name."""


def point_id(point: Point, key: Sequence[str] | None = None) -> str:
    """Return the stable id of a point: a 12-digit hash of its key fields as canonical JSON.

    Parameters
    ----------
    point
        The point's parameters; values should be scalars (str, int, float, bool, None).
    key
        The fields that identify the point (default: all of them). Their order does not matter.

    Returns
    -------
    str
        12 hexadecimal digits. Integral floats hash like ints, so ``3.0`` and ``3`` are one point.
    """
    names = sorted(point) if key is None else sorted(key)
    missing = [name for name in names if name not in point]
    if missing:
        raise ValueError(f"point {dict(point)} lacks the key fields {missing}")
    fields = {name: _canonical(point[name]) for name in names}
    text = json.dumps(fields, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def plain(value: Any) -> Any:
    """A numpy scalar (or 0-d array) as the Python scalar it holds; anything else as is."""
    return value.item() if getattr(value, "ndim", None) == 0 and hasattr(value, "item") else value


def _canonical(value: Any) -> Any:
    """Plain Python value for hashing: numpy scalars unwrapped, integral floats as ints."""
    value = plain(value)
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def point_ids(points: Sequence[Point], key: Sequence[str] | None) -> list[str]:
    """Ids of all points; a field named like a bookkeeping column or a repeated id is an error."""
    for point in points:
        clash = [name for name in point if name in BOOKKEEPING]
        if clash:
            raise ValueError(f"point fields {clash} are reserved for run_sweep's own columns")
    ids = [point_id(point, key) for point in points]
    seen: dict[str, int] = {}
    for i, pid in enumerate(ids):
        if pid in seen:
            raise ValueError(
                f"points {seen[pid]} and {i} have the same key fields: {dict(points[i])}"
            )
        seen[pid] = i
    return ids


# --- evaluating one point (runs on a worker) --------------------------------------------------


def evaluate(fn: Callable[[dict], Mapping[str, Any]], point: Point) -> Outcome:
    """Call ``fn`` on a copy of ``point``; an exception becomes an error status, not a raise."""
    start = time.perf_counter()
    try:
        result = _checked_result(fn(dict(point)), point)
        status = OK
    except Exception as exc:  # any failure of fn is a result to report
        result, status = {}, error_status(exc)
    elapsed = round(time.perf_counter() - start, 4)
    return {"result": result, "status": status, "elapsed_s": elapsed, "worker": _worker_name()}


def evaluate_on_worker(fn: Callable[[dict], Mapping[str, Any]], point: Point) -> Outcome:
    """:func:`evaluate` in a Dask worker, with native thread pools sized to the worker."""
    from distributed import get_worker

    limit_native_threads(get_worker().state.nthreads)
    return evaluate(fn, point)


def _checked_result(result: Any, point: Point) -> dict[str, Any]:
    """``fn``'s result as a dict whose keys are new column names."""
    if not isinstance(result, Mapping):
        raise TypeError(f"fn returned {type(result).__name__}, not a dict")
    bad = [k for k in result if not isinstance(k, str) or k in point or k in BOOKKEEPING]
    if bad:
        raise ValueError(f"result keys {bad} are not new column names")
    return dict(result)


def error_status(exc: BaseException) -> str:
    """One-line status of a failed point: ``error: <ExceptionType>: <message>``.

    Messages longer than :data:`MAX_MESSAGE` characters are cut (Dask's serialisation errors
    carry whole tracebacks).
    """
    message = " ".join(str(exc).split())
    if len(message) > MAX_MESSAGE:
        message = message[: MAX_MESSAGE - 3] + "..."
    name = type(exc).__name__
    return f"error: {name}: {message}" if message else f"error: {name}"


def is_error(status: str | None) -> bool:
    """Whether a row's status records a failure."""
    return bool(status) and status.startswith("error")


def _worker_name() -> str:
    """The Dask worker's address, or ``in-process`` outside a worker."""
    distributed = sys.modules.get("distributed")  # not imported: certainly not in a worker
    if distributed is None:
        return IN_PROCESS
    try:
        return distributed.get_worker().address
    except ValueError:
        return IN_PROCESS

