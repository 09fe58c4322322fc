"""What integrating one sample set needs beyond its values, built once per set.

A frame's level search and refinement passes integrate the same samples tens of times, with
the same grid indices and weights: the edges, the difference graph and its factorisation
depend on those alone. :class:`IntegrationPlans` keeps them for as long as its owner lives
(one frame's :class:`~restoration.observations.Observations`); a call given none builds
its own.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

__all__ = ["IntegrationPlans"]

T = TypeVar("T")


class IntegrationPlans:
    """Structures built from grid indices (edges, graphs, factorisations), each built once.

    Keys are the kind of structure, the grid indices' values and whatever else it depends on;
    values are never written after they are built (callers treat them as read-only).

    Examples
    --------
    >>> import numpy as np
    >>> from restoration.integrate import IntegrationPlans
    >>> plans = IntegrationPlans()
    >>> ij = np.array([[0, 0], [1, 0], [0, 1]])
    >>> calls = []
    >>> def build():
    ...     calls.append(1)
    ...     return len(ij)
    >>> plans.get("count", ij, build), plans.get("count", ij, build), len(calls)
    (3, 3, 1)
    """

    def __init__(self) -> None:
        self._built: dict[tuple, Any] = {}

    def get(
        self, kind: str, ij: NDArray, build: Callable[[], T], *extra: Hashable
    ) -> T:
        """The structure ``kind`` of grid indices ``ij`` (and ``extra``), built by ``build()``
        the first time it is asked for."""
        ij = np.asarray(ij)
        key = (kind, ij.shape, ij.dtype.str, ij.tobytes(), *extra)
        found = self._built.get(key)
        if found is None:
            found = self._built[key] = build()
        return found

    def __len__(self) -> int:
        return len(self._built)


def plan_of(
    plans: IntegrationPlans | None, kind: str, ij: NDArray, build: Callable[[], T],
    *extra: Hashable,
) -> T:
    """``plans.get(kind, ij, build, *extra)``, or ``build()`` when there are no plans."""
    return build() if plans is None else plans.get(kind, ij, build, *extra)
