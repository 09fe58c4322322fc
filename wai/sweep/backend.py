"""Where a sweep's points run: one after another in this process, or on a Dask cluster (a
local one started for the sweep, or one already running), a point whose worker died run again."""

from __future__ import annotations

import contextlib
import functools
import logging
from collections.abc import Callable, Iterator
from typing import Any

from wai.sweep.points import (
    IN_PROCESS,
    MAX_MESSAGE,
    WORKER_DIED,
    WORKER_LOSSES,
    WORKER_RETRIES,
    Outcome,
    Point,
    error_status,
    evaluate,
    evaluate_on_worker,
)
from wai.threads import THREAD_VARIABLES, scoped_environ, single_threaded
from wai_core.errors import WaiInputError

Runner = Callable[[list[tuple[str, Point]], Callable], Iterator[tuple[str, Point, Outcome]]]


def _run_in_process(
    todo: list[tuple[str, Point]], fn: Callable
) -> Iterator[tuple[str, Point, Outcome]]:
    """Evaluate the points one after another in this process, on one thread as a worker of
    the default local cluster has (so timings compare across ``--workers``)."""
    with single_threaded():
        for pid, point in todo:
            yield pid, point, evaluate(fn, point)


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
        return client.submit(evaluate_on_worker, fn, point, pure=False)

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
def open_backend(
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

