"""Who renders a dataset's frames: this process, spawned worker processes or a Dask cluster.

Whichever renders them, the frames come back in order, to be written by the process that runs
:func:`wai.dataset.write_dataset`.
"""

from __future__ import annotations

import functools
import itertools
import multiprocessing
import os
from collections import deque
from collections.abc import Iterator, Sequence
from typing import Any

from wai.dataset.maker import FrameMaker
from wai.dataset.records import FramePacker, PackedFrame
from wai.dataset.spec import DatasetSpec
from wai.threads import limit_native_threads
from wai_core.errors import WaiInputError

__all__ = ["frame_resources", "make_frames", "size_pools"]


# A worker process's FrameMaker and FramePacker of each spec (its scenes stay loaded between
# frames, the flat-water chunks compressed once).
_MAKERS: dict[DatasetSpec, tuple[FrameMaker, FramePacker]] = {}


def _make_cached(spec: DatasetSpec, index: int, host_threads: dict[str, int] | None = None
                 ) -> PackedFrame:
    """Frame ``index`` of ``spec``, made and compressed by this process's FrameMaker of it;
    on a Dask worker, with the native pools sized to the cores over the cluster's threads on
    its host."""
    if host_threads is not None:
        from distributed import get_worker
        from distributed.comm import get_address_host

        host = get_address_host(get_worker().address)
        size_pools(max(1, (os.cpu_count() or 1) // host_threads.get(host, 1)))
    if spec not in _MAKERS:
        _MAKERS[spec] = FrameMaker(spec), FramePacker()
    maker, packer = _MAKERS[spec]
    return packer.pack(maker.make(index))


@functools.cache
def size_pools(threads: int) -> None:
    """Size a worker's native thread pools to ``threads`` (:func:`wai.threads.
    limit_native_threads`), Dr.Jit's to one more: a frame's truth is traced on the renderer's
    device from a second thread while the frame renders (:meth:`FrameMaker.make`), and on the
    CPU both kernels then run side by side rather than one after the other (48-120 frames on
    2 cores, two workers: 4.1-4.25 frames/s against 3.7-3.9 with one Dr.Jit thread each)."""
    limit_native_threads(threads)
    import drjit

    drjit.set_thread_count(threads + 1)


def frame_resources(workers: Sequence[dict[str, Any]]) -> dict[str, int] | None:
    """What each frame asks of a Dask worker: one ``GPU`` where any worker offers that
    resource (one worker process per GPU, started with ``--resources GPU=1``: the frames then
    go to those workers only, one at a time each), else nothing.

    Examples
    --------
    >>> frame_resources([{"resources": {"GPU": 1}}, {"resources": {}}])
    {'GPU': 1}
    >>> frame_resources([{"resources": {}}]) is None
    True
    """
    return {"GPU": 1} if any(w.get("resources", {}).get("GPU") for w in workers) else None


def _frames_on_dask(client: Any, spec: DatasetSpec, indices: Sequence[int]
                    ) -> Iterator[PackedFrame]:
    """The frames ``indices`` in order, rendered by the workers of ``client``'s cluster
    (those with a GPU where there are any: :func:`frame_resources`); a window of twice the
    workers' threads is in flight (the rest waits, not the memory)."""
    with client:
        workers = list(client.scheduler_info()["workers"].values())
        resources = frame_resources(workers)
        if resources is not None:
            workers = [w for w in workers if w.get("resources", {}).get("GPU")]
        info = [(w["host"], w["nthreads"]) for w in workers]
        hosts = {h: sum(n for k, n in info if k == h) for h, _ in info}
        window, todo = max(2, 2 * sum(hosts.values())), iter(indices)

        def submit(i: int) -> Any:
            return client.submit(_make_cached, spec, i, hosts, pure=False, resources=resources)

        pending = deque(submit(i) for i in itertools.islice(todo, window))
        while pending:
            rec = pending.popleft().result()
            for i in itertools.islice(todo, 1):
                pending.append(submit(i))
            yield rec


def _dask_client(scheduler: str) -> Any:
    try:
        from distributed import Client
        return Client(scheduler, timeout=30)
    except ModuleNotFoundError as exc:
        raise WaiInputError(f"--scheduler needs Dask's distributed ({exc})") from None
    except (OSError, TimeoutError, ValueError) as exc:
        raise WaiInputError(f"--scheduler {scheduler}: no Dask scheduler there ({exc})") from None


def _frames_in_pool(spec: DatasetSpec, indices: Sequence[int], n: int) -> Iterator[PackedFrame]:
    threads = max(1, (os.cpu_count() or 1) // n)
    with multiprocessing.get_context("spawn").Pool(n, size_pools, (threads,)) as pool:
        yield from pool.imap(functools.partial(_make_cached, spec), indices)


def make_frames(spec: DatasetSpec, indices: Sequence[int], workers: int,
                scheduler: str | None, maker: FrameMaker | None
                ) -> tuple[Iterator[PackedFrame], str]:
    """The frames ``indices`` in order, compressed for the store, rendered here (``workers``
    <= 1, by ``maker``), in ``workers`` spawned processes or on the Dask cluster at
    ``scheduler``; who, in words."""
    if scheduler is not None:
        threads = (client := _dask_client(scheduler)).nthreads()
        return (_frames_on_dask(client, spec, indices),
                f"Dask {scheduler}: {len(threads)} workers, {sum(threads.values())} threads")
    if workers <= 1:
        maker, packer = maker or FrameMaker(spec), FramePacker()
        return (packer.pack(maker.make(i)) for i in indices), "this process"
    return _frames_in_pool(spec, indices, workers), f"{workers} worker processes"

