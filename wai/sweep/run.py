"""The sweep: the points the table lacks evaluated, their rows appended as they finish, and a
record of the run beside the table (:func:`run_sweep`)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from tqdm import tqdm

from wai.sweep.backend import open_backend
from wai.sweep.points import IN_PROCESS, Outcome, Point, Row, error_status, is_error, point_ids
from wai.sweep.table import SweepTable, typed_row, write_parquet
from wai_core.errors import WaiInputError
from wai_core.io import read_json, write_json


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
    with open_backend(*backend) as (runner, where), bar:
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
    workers: int | None = None,
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
        without Dask (for tests and debugging); None: :func:`wai.threads.default_workers`
        over ``threads_per_worker`` (one per core, as memory allows; a point is serial, so
        the cores are used by points side by side). Ignored with ``scheduler``.
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
    if workers is None:
        from wai.threads import default_workers

        workers = max(1, default_workers() // threads_per_worker)
    _check_mode(scheduler, workers, threads_per_worker)
    if table.suffix != ".csv":
        raise ValueError(f"the table must be a .csv file, not {table}")
    ids = point_ids(points, key)
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
        rows = {row["point_id"]: typed_row(row) for row in store.rows()}
        write_parquet(list(rows.values()), table.with_suffix(".parquet"))
    deaths = run.get("worker_deaths", 0)
    died = f"; {deaths} worker deaths, their points run again once" if deaths else ""
    _say(progress,
         f"{table}: ran {run['ran']} ({run['failed']} failed) in {run['wall_s']:.1f} s{died}")
    return [rows[pid] for pid in ids if pid in rows]

