"""The native thread pools of a process (OpenBLAS, OpenMP, numba, OpenCV, Dr.Jit): sized for
a sweep's workers, or held at one thread while a sweep runs points in the calling process."""

from __future__ import annotations

import contextlib
import functools
import importlib
import importlib.util
import os
import sys
from collections.abc import Iterator, Mapping

__all__ = ["THREAD_VARIABLES", "WORKER_MEMORY_GIB", "default_workers", "limit_native_threads",
           "scoped_environ", "single_threaded"]

WORKER_MEMORY_GIB = 1.5
"""Memory a worker process restoring or rendering paper-sized frames may take, GiB (a render
worker's peak is about 1 GiB at 800 x 600): what :func:`default_workers` leaves each one."""

# Native thread pools that read their size from the environment when they are loaded.
THREAD_VARIABLES = (
    "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS",
)


def default_workers() -> int:
    """Worker processes for frames in parallel: one per core this process may run on, no more
    than the available memory holds at :data:`WORKER_MEMORY_GIB` each, at least one.

    One frame's restoration is serial (a chain of millisecond stages, each too small to split
    across cores with gain), so a machine's cores are used by frames side by side.

    Examples
    --------
    >>> default_workers() >= 1
    True
    """
    import psutil

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    by_memory = int(psutil.virtual_memory().available / (WORKER_MEMORY_GIB * 2**30))
    return max(1, min(cores or 1, by_memory))


@functools.cache
def limit_native_threads(threads: int) -> None:
    """Size the native thread pools of this (worker) process to ``threads``, once.

    OpenBLAS and OpenMP read the environment when loaded, which in a local cluster's workers is
    before any task (see :func:`scoped_environ`); setting it here covers libraries loaded
    later. Dr.Jit (Mitsuba's LLVM backend), OpenCV and numba otherwise start one thread per core
    in every worker.
    """
    # numba refuses a NUMBA_NUM_THREADS that changes once its threads are up (it rereads the
    # environment when it compiles): its pool is sized by set_num_threads below instead.
    numba_up = "numba" in sys.modules
    os.environ.update({name: str(threads) for name in THREAD_VARIABLES
                       if not (numba_up and name == "NUMBA_NUM_THREADS")})
    if importlib.util.find_spec("drjit") is not None:
        import drjit

        drjit.set_thread_count(threads)
    if importlib.util.find_spec("cv2") is not None:
        import cv2

        cv2.setNumThreads(threads)
    if importlib.util.find_spec("numba") is not None:  # the restoration's chunked kernels
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


@contextlib.contextmanager
def single_threaded() -> Iterator[None]:
    """Numba's, OpenCV's, Dr.Jit's and the BLAS/OpenMP thread pools at one thread for the
    block, then as they were (this process goes on after the sweep)."""
    import cv2
    import numba
    from threadpoolctl import threadpool_limits

    saved_numba, saved_cv = numba.get_num_threads(), cv2.getNumThreads()
    # Loaded now if present: a sweep's renders would load it inside the block, at full width.
    drjit = importlib.import_module("drjit") if importlib.util.find_spec("drjit") else None
    saved_dr = drjit.thread_count() if drjit is not None else None
    numba.set_num_threads(1)
    cv2.setNumThreads(1)
    if drjit is not None:
        drjit.set_thread_count(1)
    try:
        # OpenBLAS and OpenMP, loaded with numpy at full width here, sit at one thread in a
        # local worker (its environment at spawn): same in the timings of both
        with threadpool_limits(1):
            yield
    finally:
        numba.set_num_threads(saved_numba)
        cv2.setNumThreads(saved_cv)
        if drjit is not None:
            drjit.set_thread_count(saved_dr)


@contextlib.contextmanager
def scoped_environ(values: Mapping[str, str]) -> Iterator[None]:
    """Set environment variables for the block (spawned workers inherit them), then restore."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
