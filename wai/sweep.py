"""Run a sweep of independent points on Dask and stream its rows into one CSV table.

A sweep is a list of points (dicts of parameters) and a top-level function ``fn(point) -> dict``
that returns one row of results. :func:`run_sweep` evaluates the points that the table does not
hold yet, on a local cluster of worker processes, on an existing Dask cluster, or in the calling
process, and appends each row to the table as soon as it is finished, so a killed sweep keeps
its rows and a rerun carries on where it stopped.

Next to ``table`` (``NAME.csv``) it writes ``NAME.parquet``, a copy of the table, and
``NAME.json``, a record of each run (where it ran, when, how many points ran, were skipped or
failed, how many workers died under them). A point whose worker process died runs once more;
a run stopped before its first row leaves the record as it was. ``docs/cluster.md`` describes
how to use it.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import fcntl
import functools
import hashlib
import importlib.util
import io
import json
import logging
import os
import re
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import IO, Any

from tqdm import tqdm

from wai.threads import THREAD_VARIABLES, limit_native_threads, scoped_environ, single_threaded
from wai_core.errors import WaiInputError
from wai_core.io import atomic_write_bytes, read_json, write_json

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
"""What the status of a point whose worker died says (after ``error: ``)."""


# What the table's text cells parse back into (repr() of Python floats, ints and bools).
_INT = re.compile(r"[+-]?\d+")
_FLOAT = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(inf|nan)")
_EXTRA = "\0extra"  # DictReader's key for cells beyond the header
_TEXT_COLUMNS = frozenset({"point_id", "status", "worker"})  # never parsed as numbers

Point = Mapping[str, Any]
Row = dict[str, Any]
Outcome = dict[str, Any]


# --- point ids -------------------------------------------------------------------------------


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


def _plain(value: Any) -> Any:
    """A numpy scalar (or 0-d array) as the Python scalar it holds; anything else as is."""
    return value.item() if getattr(value, "ndim", None) == 0 and hasattr(value, "item") else value


def _canonical(value: Any) -> Any:
    """Plain Python value for hashing: numpy scalars unwrapped, integral floats as ints."""
    value = _plain(value)
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def _point_ids(points: Sequence[Point], key: Sequence[str] | None) -> list[str]:
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


def _evaluate(fn: Callable[[dict], Mapping[str, Any]], point: Point) -> Outcome:
    """Call ``fn`` on a copy of ``point``; an exception becomes an error status, not a raise."""
    start = time.perf_counter()
    try:
        result = _checked_result(fn(dict(point)), point)
        status = OK
    except Exception as exc:  # any failure of fn is a result to report
        result, status = {}, error_status(exc)
    elapsed = round(time.perf_counter() - start, 4)
    return {"result": result, "status": status, "elapsed_s": elapsed, "worker": _worker_name()}


def _evaluate_on_worker(fn: Callable[[dict], Mapping[str, Any]], point: Point) -> Outcome:
    """:func:`_evaluate` in a Dask worker, with native thread pools sized to the worker."""
    from distributed import get_worker

    limit_native_threads(get_worker().state.nthreads)
    return _evaluate(fn, point)


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


# --- the table ---------------------------------------------------------------------------------


class SweepTable:
    """One CSV table of rows, appended a line at a time and rewritten atomically when it widens.

    Use it as a context manager: it holds an exclusive lock on the table (one sweep at a time
    writes it) and on entry drops a truncated last line that a killed run may have left.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.columns: list[str] = []
        self._out: IO[str] | None = None
        self._writer: csv.DictWriter | None = None
        self._lock: IO[str] | None = None

    def __enter__(self) -> SweepTable:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = _lock(self.path)
        try:
            self._drop_truncated_line()
            self.columns = self._header()
        except BaseException:
            self.__exit__()  # a table that is not a sweep's: no lock file left behind
            raise
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._close()
        if self._lock is not None:
            # Removed while still held (a sweep waiting for it opens a new one): nothing of the
            # lock survives the sweep.
            with contextlib.suppress(OSError):
                os.unlink(self._lock.name)
            self._lock.close()  # closing releases the flock
            self._lock = None

    def rows(self) -> list[dict[str, str]]:
        """All rows as text cells (a column a row lacks is ``""``)."""
        if not self.path.exists():
            return []
        with self.path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f, restkey=_EXTRA, restval=""))
        for line, row in enumerate(rows, start=2):
            if _EXTRA in row:
                raise WaiInputError(f"{self.path}:{line} has more cells than the header")
        return rows

    def append(self, row: Mapping[str, Any]) -> None:
        """Write one row and flush it; new columns first widen the whole table."""
        new = [name for name in row if name not in self.columns]
        if new:
            self._rewrite(_widened(self.columns, new), self.rows())
        if self._writer is None:
            self._open()
        assert self._writer is not None and self._out is not None
        self._writer.writerow({name: _cell(value) for name, value in row.items()})
        self._out.flush()  # a killed sweep keeps every finished row

    def drop(self, ids: set[str]) -> None:
        """Remove the rows of the points ``ids`` (to run them again)."""
        rows = self.rows()
        kept = [row for row in rows if row["point_id"] not in ids]
        if len(kept) < len(rows):
            self._rewrite(self.columns, kept)

    def _header(self) -> list[str]:
        if not self.path.exists() or self.path.stat().st_size == 0:
            return []
        with self.path.open(newline="", encoding="utf-8") as f:
            header = next(csv.reader(f), [])
        if "point_id" not in header or "status" not in header:
            raise WaiInputError(f"{self.path} is not a sweep table (no point_id/status column)")
        return header

    def _drop_truncated_line(self) -> None:
        """Cut a last line without its newline: a row that a killed run was writing."""
        if not self.path.exists():
            return
        data = self.path.read_bytes()
        if data and not data.endswith(b"\n"):
            atomic_write_bytes(self.path, data[: data.rfind(b"\n") + 1])
            print(f"{self.path}: dropped a truncated last line", file=sys.stderr)

    def _rewrite(self, columns: list[str], rows: list[dict[str, str]]) -> None:
        self._close()
        buf = io.StringIO()
        writer = csv.DictWriter(buf, columns, restval="", lineterminator="\n")
        writer.writeheader()
        writer.writerows({name: row.get(name, "") for name in columns} for row in rows)
        atomic_write_bytes(self.path, buf.getvalue().encode())
        self.columns = columns

    def _open(self) -> None:
        self._out = self.path.open("a", newline="", encoding="utf-8")
        self._writer = csv.DictWriter(self._out, self.columns, restval="", lineterminator="\n")

    def _close(self) -> None:
        if self._out is not None:
            self._out.close()
        self._out = self._writer = None


def _lock(path: Path) -> IO[str]:
    """Hold an exclusive lock beside ``path``: two sweeps writing one table would lose rows.

    The holder removes the lock file when it is done (:meth:`SweepTable.__exit__`), so a lock
    taken on a file that is no longer at its path (removed meanwhile) is taken again afresh.
    """
    name = path.with_name(f".{path.name}.lock")
    while True:
        lock = name.open("w")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.close()
            raise WaiInputError(f"another sweep is writing {path}") from None
        try:
            if os.stat(name).st_ino == os.fstat(lock.fileno()).st_ino:
                return lock
        except FileNotFoundError:
            pass
        lock.close()  # its holder removed it as we opened it: another round


def _widened(columns: list[str], new: list[str]) -> list[str]:
    """``columns`` plus ``new``, keeping the bookkeeping columns last."""
    body = [name for name in [*columns, *new] if name not in BOOKKEEPING]
    return body + list(BOOKKEEPING)


def _cell(value: Any) -> str:
    """Text of one cell, on one line (a row is a line, which makes truncation easy to spot)."""
    value = _plain(value)
    return "" if value is None else " ".join(str(value).splitlines())


def parse_cell(text: str) -> Any:
    """A table cell back as a Python value: ``""`` is None; bools, ints and floats as such."""
    if text == "":
        return None
    if text in ("True", "False"):
        return text == "True"
    if _INT.fullmatch(text):
        return int(text)
    if _FLOAT.fullmatch(text):
        return float(text)
    return text


def _typed(row: Mapping[str, str]) -> Row:
    return {k: v if k in _TEXT_COLUMNS else parse_cell(v) for k, v in row.items()}


def read_table(path: str | Path) -> list[Row]:
    """Read a sweep table with its cells parsed (see :func:`parse_cell`).

    Parameters
    ----------
    path
        The CSV table that :func:`run_sweep` wrote.

    Returns
    -------
    list of dict
        One dict per row, every column present (None where a row has no value).
    """
    path = Path(path)
    if not path.is_file():
        raise WaiInputError(f"table not found: {path}")
    with path.open(newline="", encoding="utf-8") as f:
        return [_typed(row) for row in csv.DictReader(f, restval="")]


# --- where the points run -------------------------------------------------------------------

Runner = Callable[[list[tuple[str, Point]], Callable], Iterator[tuple[str, Point, Outcome]]]


def _run_in_process(
    todo: list[tuple[str, Point]], fn: Callable
) -> Iterator[tuple[str, Point, Outcome]]:
    """Evaluate the points one after another in this process, on one thread as a worker of
    the default local cluster has (so timings compare across ``--workers``)."""
    with single_threaded():
        for pid, point in todo:
            yield pid, point, _evaluate(fn, point)


def _run_on_dask(
    client: Any, todo: list[tuple[str, Point]], fn: Callable
) -> Iterator[tuple[str, Point, Outcome]]:
    """Submit every point and yield the outcomes in the order they finish.

    A point whose worker died (:data:`WORKER_LOSSES`) is submitted again, :data:`WORKER_RETRIES`
    times; its outcome counts the deaths (``deaths``), and its status says ``worker died``
    when every run of it lost its worker.
    """
    from distributed import as_completed

    def submit(point: Point) -> Any:
        # pure=False: a point rerun (retry_errors, a retry) must run again, not reuse a result
        return client.submit(_evaluate_on_worker, fn, point, pure=False)

    futures = {submit(p): (pid, p, 0, 0) for pid, p in todo}
    pending = as_completed(list(futures))
    for future in pending:
        pid, point, retries, deaths = futures.pop(future)
        try:
            outcome = {**future.result(), "deaths": deaths}
        except Exception as exc:  # the worker died, a result did not pickle, ...
            if type(exc).__name__ not in WORKER_LOSSES:
                outcome = {"result": {}, "status": error_status(exc), "elapsed_s": None,
                           "worker": "", "deaths": deaths}
            else:
                # KilledWorker comes after the scheduler's own tries (an existing cluster's
                # allowed-failures; none on the sweep's local cluster)
                deaths += getattr(exc, "allowed_failures", 0) + 1
                if retries < WORKER_RETRIES:
                    future.release()
                    retry = submit(point)
                    futures[retry] = (pid, point, retries + 1, deaths)
                    pending.add(retry)
                    continue
                outcome = {"result": {}, "status": _death_status(exc, deaths),
                           "elapsed_s": None, "worker": "", "deaths": deaths}
        future.release()
        yield pid, point, outcome


def _death_status(exc: BaseException, tries: int) -> str:
    """Status of a point whose worker died on each of its ``tries``:
    ``error: worker died (2 tries): tcp://... died running it``."""
    last = getattr(getattr(exc, "last_worker", None), "address", None)
    why = f"{last} died running it" if last else error_status(exc).removeprefix("error: ")
    times = "1 try" if tries == 1 else f"{tries} tries"
    return f"error: {WORKER_DIED} ({times}): {why}"[:MAX_MESSAGE]


@contextlib.contextmanager
def _dask_client(scheduler: str | None, workers: int, threads_per_worker: int) -> Iterator[Any]:
    """A Client of the cluster at ``scheduler``, or of a local cluster started for the block."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ModuleNotFoundError as exc:  # a dependency, but an environment may lack it
        raise WaiInputError(
            f"--workers/--scheduler run on Dask, which is not installed ({exc}): "
            "pip install 'dask[distributed]', or --workers 0 to run in this process"
        ) from None

    if scheduler is not None:
        with Client(scheduler) as client:
            yield client
        return
    # Workers import numpy (and with it OpenBLAS) before any task runs: the thread counts must
    # be in the environment they are spawned with. Nannies copy these variables over dask's
    # defaults because they are set in os.environ.
    env = {name: str(threads_per_worker) for name in THREAD_VARIABLES}
    settings = {
        # The sweep, not the scheduler, runs again a point whose worker died, and says so
        # (WORKER_RETRIES): no silent retries, and a worker holds only the tasks it runs, so
        # a death counts against those alone (not against tasks queued behind them).
        "distributed.scheduler.allowed-failures": 0,
        "distributed.scheduler.worker-saturation": 1.0,
        # Dask's 64 KiB trim threshold hands every freed array back to the system: a frame's
        # restoration then page-faults its arrays in anew each time (5000 faults against 140)
        # and ran 1.3-1.5x slower in a worker than in this process, skewing sweep timings.
        "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
        # Nor does a worker sample its threads' stacks every 10 ms (for a dashboard the sweep
        # does not start): the samples take the GIL from the point being timed.
        "distributed.worker.profile.enabled": False,
    }
    with scoped_environ(env), dask.config.set(settings):
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=threads_per_worker,
            processes=True,
            dashboard_address=None,  # needs bokeh, which is not a dependency
            # the scheduler's HTTP endpoints would otherwise claim port 8787, and warn when
            # another cluster (a concurrent sweep) holds it
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
            silence_logs=logging.ERROR,  # start/stop chatter; errors still show
        )
    with cluster, Client(cluster) as client:
        yield client


@contextlib.contextmanager
def _backend(
    scheduler: str | None, workers: int, threads_per_worker: int
) -> Iterator[tuple[Runner, dict[str, Any]]]:
    """Yield a runner of points and a description of where it runs (for the metadata)."""
    if scheduler is None and workers == 0:
        where = {"scheduler": IN_PROCESS, "workers": 0, "threads_per_worker": 1, "threads": 1}
        yield _run_in_process, where
        return
    with _dask_client(scheduler, workers, threads_per_worker) as client:
        nthreads = client.nthreads()
        per_worker = set(nthreads.values())
        where = {
            "scheduler": scheduler or "local",
            "workers": len(nthreads),
            "threads_per_worker": per_worker.pop() if len(per_worker) == 1 else None,
            "threads": sum(nthreads.values()),
        }
        yield functools.partial(_run_on_dask, client), where


# --- the sweep ---------------------------------------------------------------------------------


@dataclass
class _Plan:
    """Which points run and how many the table already holds."""

    todo: list[tuple[str, Point]]
    skipped: int = 0
    skipped_errors: int = 0
    retried: set[str] = field(default_factory=set)


def _plan(
    ids: list[str], points: Sequence[Point], done: Mapping[str, str], retry_errors: bool
) -> _Plan:
    """Split the points into those to run and those whose row (status ``done``) is kept."""
    plan = _Plan(todo=[])
    for pid, point in zip(ids, points, strict=True):
        status = done.get(pid)
        if status is None:
            plan.todo.append((pid, point))
        elif is_error(status) and retry_errors:
            plan.todo.append((pid, point))
            plan.retried.add(pid)
        else:
            plan.skipped += 1
            plan.skipped_errors += is_error(status)
    return plan


def _row(pid: str, point: Point, outcome: Outcome) -> Row:
    """A table row: point fields, result fields, then the bookkeeping columns."""
    return {
        **point,
        **outcome["result"],
        "point_id": pid,
        "status": outcome["status"],
        "elapsed_s": outcome["elapsed_s"],
        "worker": outcome["worker"],
    }


def _check_mode(scheduler: str | None, workers: int, threads_per_worker: int) -> None:
    if workers < 0:
        raise WaiInputError(f"workers must be >= 0 (0 runs in this process), not {workers}")
    if threads_per_worker < 1:
        raise WaiInputError(f"threads_per_worker must be >= 1, not {threads_per_worker}")
    if scheduler is not None and workers == 0:
        raise WaiInputError("workers=0 runs in this process; it cannot go with a scheduler")


def _now() -> str:
    return datetime.now().astimezone().isoformat(timespec="seconds")


def write_parquet(rows: Sequence[Mapping[str, Any]], path: str | Path) -> bool:
    """Write rows as a Parquet file atomically, if pyarrow is installed.

    A column whose values pyarrow cannot put in one type (say ints and strings) is stored as
    strings. Returns whether the file was written.
    """
    if importlib.util.find_spec("pyarrow") is None:
        return False
    import pyarrow as pa
    import pyarrow.parquet as pq

    names = list(dict.fromkeys(name for row in rows for name in row))
    columns = {}
    for name in names:
        values = [row.get(name) for row in rows]
        try:
            columns[name] = pa.array(values)
        except (pa.ArrowInvalid, pa.ArrowTypeError):
            columns[name] = pa.array([None if v is None else str(v) for v in values])
    sink = pa.BufferOutputStream()
    pq.write_table(pa.table(columns), sink)
    atomic_write_bytes(path, sink.getvalue().to_pybytes())
    return True


def _record_run(path: Path, run: Mapping[str, Any]) -> None:
    """Append one run's metadata to the sweep's JSON record (rewritten atomically)."""
    try:
        record = read_json(path) if path.exists() else {}
    except WaiInputError:
        record = {}  # an unreadable record must not stop the sweep; it starts afresh
    runs = record.get("runs", []) if isinstance(record, dict) else []
    write_json(path, {"table": path.with_suffix(".csv").name, "runs": [*runs, dict(run)]})


def _say(enabled: bool, message: str) -> None:
    if enabled:
        print(message, file=sys.stderr)


def _announce(enabled: bool, table: Path, plan: _Plan) -> None:
    """Say how many points the table already holds and how many will run."""
    held = f"{plan.skipped} already in the table"
    if plan.skipped_errors:
        held += f" ({plan.skipped_errors} as errors, rerun with retry_errors/--retry-errors)"
    _say(enabled, f"{table}: {held}, {len(plan.todo)} to run")


def _execute(
    todo: list[tuple[str, Point]],
    fn: Callable[[dict], Mapping[str, Any]],
    store: SweepTable,
    run: dict[str, Any],
    progress: bool,
    backend: tuple[str | None, int, int],
) -> None:
    """Run the points and append their rows; ``run`` counts them as they finish."""
    run.update(ran=0, failed=0, worker_deaths=0)
    if not todo:
        return  # no cluster to start
    bar = tqdm(total=len(todo), desc=store.path.name, unit="point", disable=not progress)
    with _backend(*backend) as (runner, where), bar:
        run.update(where)
        for pid, point, outcome in runner(todo, fn):
            store.append(_row(pid, point, outcome))
            run["ran"] += 1
            run["worker_deaths"] += outcome.get("deaths", 0)
            if is_error(outcome["status"]):
                run["failed"] += 1
                bar.set_postfix(failed=run["failed"], refresh=False)
            bar.update()


def run_sweep(
    points: Iterable[Point],
    fn: Callable[[dict], Mapping[str, Any]],
    table: str | Path,
    *,
    scheduler: str | None = None,
    workers: int = 2,
    threads_per_worker: int = 1,
    progress: bool = True,
    key: Sequence[str] | None = None,
    retry_errors: bool = False,
) -> list[Row]:
    """Evaluate ``fn`` on every point that ``table`` lacks and append its rows to the table.

    Parameters
    ----------
    points
        The sweep: dicts of scalar parameters. Their ids (see :func:`point_id`) must differ.
    fn
        A top-level (picklable) function of one point returning a dict of results, whose keys
        must not repeat the point's fields. If it raises, the row records the error in
        ``status`` and the sweep goes on. If the worker process running it dies, the point runs
        once more; when that worker dies too its status is ``error: worker died ...``.
    table
        The CSV table (``*.csv``). It gains one row per finished point, flushed at once; a
        rerun skips the points it holds. ``*.parquet`` (a copy of the table, at the end) and
        ``*.json`` (a record of every run) go next to it.
    scheduler
        Address of a running Dask scheduler (``tcp://host:8786``); None starts a local cluster
        for the call.
    workers
        Worker processes of the local cluster; 0 runs the points one by one in this process,
        without Dask (for tests and debugging). Ignored with ``scheduler``.
    threads_per_worker
        Dask threads of each local worker; the native thread pools (OpenBLAS, OpenMP, Dr.Jit,
        OpenCV) of each worker are sized to it too. On an existing cluster, each worker's own
        thread count sizes them.
    progress
        Show a progress bar and a line on what is skipped and what failed.
    key
        The fields that identify a point (default: all of them).
    retry_errors
        Run again the points whose row records an error (by default they are skipped).

    Returns
    -------
    list of dict
        The table's rows of these points, in the order of ``points``, cells parsed back into
        Python values (see :func:`read_table`); a point an interrupt left unfinished has none.
    """
    points = list(points)
    table = Path(table)
    _check_mode(scheduler, workers, threads_per_worker)
    if table.suffix != ".csv":
        raise ValueError(f"the table must be a .csv file, not {table}")
    ids = _point_ids(points, key)
    start = time.perf_counter()
    run: dict[str, Any] = {
        "scheduler": scheduler or ("local" if workers else IN_PROCESS),
        "workers": workers,
        "threads_per_worker": threads_per_worker,
        "threads": workers * threads_per_worker or 1,
        "key": None if key is None else list(key),
        "started": _now(),
    }
    with SweepTable(table) as store:
        done = {row["point_id"]: row["status"] for row in store.rows()}
        plan = _plan(ids, points, done, retry_errors)
        store.drop(plan.retried)
        run.update(points=len(points), skipped=plan.skipped, to_run=len(plan.todo))
        _announce(progress, table, plan)
        try:
            backend = (scheduler, workers, threads_per_worker)
            _execute(plan.todo, fn, store, run, progress, backend)
            run["outcome"] = "complete"
        except BaseException as exc:
            run["outcome"] = f"stopped: {error_status(exc)}"
            raise
        finally:
            run.update(finished=_now(), wall_s=round(time.perf_counter() - start, 3))
            # A run stopped before any row (the cluster did not start, ...) leaves no record:
            # the record describes the table's rows.
            if run["outcome"] == "complete" or run.get("ran"):
                _record_run(table.with_suffix(".json"), run)
        rows = {row["point_id"]: _typed(row) for row in store.rows()}
        write_parquet(list(rows.values()), table.with_suffix(".parquet"))
    deaths = run.get("worker_deaths", 0)
    died = f"; {deaths} worker deaths, their points run again once" if deaths else ""
    _say(progress,
         f"{table}: ran {run['ran']} ({run['failed']} failed) in {run['wall_s']:.1f} s{died}")
    return [rows[pid] for pid in ids if pid in rows]


# --- command line ----------------------------------------------------------------------------


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
        default=SweepOptions.workers,
        metavar="N",
        help="local worker processes; 0 runs in this process without Dask (default 2)",
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
    workers: int = 2
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
