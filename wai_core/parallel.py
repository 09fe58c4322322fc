"""The threads one frame's work shares its compiled kernels between.

Compiled kernels split their work into chunks (:func:`run_chunks`), and independent stages run
side by side (:func:`run_beside`); the restoration's stages use both. Results never depend on
the thread count (``tests/restoration/test_kernels.py`` compares 1 and 2 threads).
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import numba

T = TypeVar("T")
def restore_threads() -> int:
    """Threads one frame's restoration runs on: numba's thread count in the calling thread
    (``numba.set_num_threads``, or ``NUMBA_NUM_THREADS``: one per core by default; worker
    processes that restore frames side by side set 1)."""
    return numba.get_num_threads()


# The helper threads of run_chunks, one per core but one (started on first use). In a forked
# child they are gone, and its frames then run every chunk on the calling thread.
_HELPERS = ThreadPoolExecutor(max((os.cpu_count() or 1) - 1, 1), thread_name_prefix="restore")


def run_chunks(kernel: Callable[..., Any], n_chunks: int, *args: Any) -> None:
    """Call ``kernel(k, n_chunks, *args)`` for every chunk ``k < n_chunks``, shared between
    this thread and up to ``restore_threads() - 1`` helpers.

    ``kernel`` is a compiled kernel that releases the GIL (``nogil``) and writes chunk ``k``'s
    share of its outputs only, so the result does not depend on which thread ran which chunk,
    nor on how many did. Each thread takes the next chunk when it is free, and the calling
    thread waits only for chunks already under way: a helper that the system does not schedule
    (the machine busy with other processes) costs at most one chunk, where a fork-join
    parallel loop (numba's ``prange``) waits for every thread at its start and end, which under
    load took 5-10x the serial time.
    """
    helpers = min(restore_threads(), n_chunks) - 1
    if helpers <= 0:
        for k in range(n_chunks):
            kernel(k, n_chunks, *args)
        return
    taken = itertools.count()  # next() is atomic: each chunk goes to one thread

    def work() -> None:
        for k in taken:
            if k >= n_chunks:
                return
            kernel(k, n_chunks, *args)

    futures = [_HELPERS.submit(work) for _ in range(helpers)]
    try:
        work()
    finally:
        for future in futures:
            if not future.cancel():  # not cancelled: under way, finishing its last chunk
                future.result()


def run_beside(task: Callable[[], T]) -> Callable[[], T]:
    """Start ``task`` on a helper thread while this one goes on; returns the call that gives
    its result.

    ``task`` must not depend on what this thread does meanwhile (it reads and makes its own
    data), so its result is the same wherever it runs. With one thread, or when no helper has
    taken it up by the time its result is asked for, it runs on the calling thread then.
    """
    if restore_threads() < 2:
        return task
    future = _HELPERS.submit(task)

    def result() -> T:
        return task() if future.cancel() else future.result()

    return result
