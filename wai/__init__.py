"""Command line and experiments of the wavy-water testbed.

The ``wai`` command (:func:`main`), the experiments behind ``wai experiment`` (:data:`EXPERIMENTS`,
:func:`run_experiment`); sweeps on Dask are :mod:`wai.sweep`, datasets :mod:`wai.dataset`.
The names load on first use, so ``import wai`` stays light.

Examples
--------
>>> import wai
>>> "budget" in wai.EXPERIMENTS
True
"""

from __future__ import annotations

import importlib
from typing import Any

_HOMES = {
    "main": "wai.cli",
    "EXPERIMENTS": "wai.experiments",
    "Experiment": "wai.experiments",
    "describe": "wai.experiments",
    "run_experiment": "wai.experiments",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    if name in _HOMES:
        return getattr(importlib.import_module(_HOMES[name]), name)
    raise AttributeError(f"module 'wai' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
