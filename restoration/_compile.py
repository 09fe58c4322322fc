"""Whether the restoration's compiled kernels are cached yet (the first run compiles them).

Every kernel is compiled by numba with ``cache=True``: the first restoration after an install
compiles them (35 s on an idle two-core machine, minutes on a loaded one) and writes them
beside the modules (or to numba's user-wide cache where the install is read-only, or
``NUMBA_CACHE_DIR``); later processes load them in a fraction of a second.
:func:`kernels_cached` lets a command say so before it starts; :func:`kernel_activity` tells
a timing whether it included compiling or loading kernels.
"""

from __future__ import annotations

import contextlib
import importlib
import os
from collections.abc import Iterator

__all__ = ["COMPILE_NOTICE", "KernelActivity", "kernel_activity", "kernels_cached"]

COMPILE_NOTICE = (
    "compiling the restoration's kernels once (about 35 s on 2 idle cores, longer when they are "
    "busy; cached for later runs)"
)

# Modules whose kernels a structured-light frame runs: one cached kernel of each must exist.
_KERNEL_MODULES = (
    "restoration.features._kernels",
    "restoration.features._spot_kernels",
    "restoration.integrate.lattice",
    "restoration.reverse_trace._kernels",
    "restoration.anchor",
    "restoration.refine",
)


def _index_exists(dispatcher: object) -> bool | None:
    """Whether numba's cache index of ``dispatcher`` exists (None: not a cached kernel)."""
    cache = getattr(dispatcher, "_cache", None)
    index = getattr(getattr(cache, "_cache_file", None), "_index_path", None)
    return None if index is None else os.path.exists(index)


def kernels_cached() -> bool:
    """True when every kernel module has a cached kernel on disk (or the check cannot tell:
    no notice is better than a wrong one).

    Examples
    --------
    >>> isinstance(kernels_cached(), bool)
    True
    """
    try:
        for name in _KERNEL_MODULES:
            module = importlib.import_module(name)
            found = [_index_exists(v) for v in vars(module).values()]
            found = [f for f in found if f is not None]
            if found and not any(found):
                return False
    except Exception:  # numba's cache internals moved: stay quiet
        return True
    return True


class KernelActivity:
    """What numba did during a :func:`kernel_activity` block, in any thread of the process.

    Attributes
    ----------
    loads : int
        Times numba took its compiler lock: a kernel called with new argument types, compiled
        or loaded from the cache. A call of a kernel already loaded takes none.
    compiles : int
        Kernels compiled (not found in the cache), nested ones included.
    """

    def __init__(self) -> None:
        self.loads = 0
        self.compiles = 0

    @property
    def warm(self) -> bool:
        """Whether the block ran only kernels already loaded in this process."""
        return self.loads == 0 and self.compiles == 0


@contextlib.contextmanager
def kernel_activity() -> Iterator[KernelActivity]:
    """Count numba's kernel loads and compiles while the block runs.

    A timing taken in the block measures warm code only if ``activity.warm`` after it; the
    first call of each kernel in a process loads it from the cache (hundreds of ms for a
    frame's kernels) or compiles it (seconds).

    Examples
    --------
    >>> with kernel_activity() as activity:
    ...     pass
    >>> activity.warm
    True
    """
    from numba.core import event

    activity = KernelActivity()

    class _Count(event.Listener):
        def __init__(self, field: str) -> None:
            self.field = field

        def on_start(self, ev: event.Event) -> None:
            setattr(activity, self.field, getattr(activity, self.field) + 1)

        def on_end(self, ev: event.Event) -> None:
            pass

    with (event.install_listener("numba:compiler_lock", _Count("loads")),
          event.install_listener("numba:compile", _Count("compiles"))):
        yield activity
