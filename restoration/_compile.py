"""Whether the restoration's compiled kernels are cached yet (the first run compiles them).

Every kernel is compiled by numba with ``cache=True``: the first restoration after an install
compiles them (30-60 s on two cores) and writes them beside the modules (or to numba's
user-wide cache where the install is read-only, or ``NUMBA_CACHE_DIR``); later processes load
them in a fraction of a second. :func:`kernels_cached` lets a command say so before it starts.
"""

from __future__ import annotations

import importlib
import os

__all__ = ["COMPILE_NOTICE", "kernels_cached"]

COMPILE_NOTICE = (
    "compiling the restoration's kernels once (30-60 s on 2 cores; cached for later runs)"
)

# Modules whose kernels a structured-light frame runs: one cached kernel of each must exist.
_KERNEL_MODULES = (
    "restoration.features._kernels",
    "restoration.integrate.lattice",
    "restoration.reverse_trace._kernels",
    "restoration.anchor",
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
