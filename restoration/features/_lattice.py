"""Lattice lookups shared by the flat-water reference and the wavy-water matching: the node
number of any grid index ``(i, j)`` and of each node's neighbours (:class:`_Lattice`), and the
neighbour tables built once with each
:class:`~restoration.features.reference.ReferenceGrid` (:class:`_LatticeTables`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from restoration.features._types import BoolArray, IntArray

_LATTICE_PAD = 2
_DIRS4 = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]])
_DIRS8 = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [1, -1], [-1, 1], [-1, -1]])
_DIRS4.setflags(write=False)
_DIRS8.setflags(write=False)


class _Lattice:
    """Dense lookup from grid index ``(i, j)`` to node number (-1 where absent)."""

    def __init__(self, ij: IntArray) -> None:
        self.ij = np.asarray(ij, dtype=np.int64)
        self.lo = self.ij.min(axis=0) - _LATTICE_PAD
        ni, nj = self.ij.max(axis=0) - self.lo + 1 + _LATTICE_PAD
        self.grid = np.full((nj, ni), -1, np.int64)
        self.grid[self.ij[:, 1] - self.lo[1], self.ij[:, 0] - self.lo[0]] = np.arange(len(ij))
        self._cache: dict[tuple[int, int], IntArray] = {}

    def neighbour(self, step: NDArray) -> IntArray:
        """Node number of each node's neighbour at ``(i, j) + step`` (|step| <= 2), or -1."""
        key = (int(step[0]), int(step[1]))
        if key not in self._cache:  # the growth asks for the same few steps every wave
            q = self.ij + np.asarray(key) - self.lo
            self._cache[key] = self.grid[q[:, 1], q[:, 0]]
        return self._cache[key]

    def lookup(self, ij: NDArray) -> IntArray:
        """Node number at any lattice indices (..., 2), -1 where there is none."""
        q = np.asarray(ij) - self.lo
        nj, ni = self.grid.shape
        ok = (q[..., 0] >= 0) & (q[..., 0] < ni) & (q[..., 1] >= 0) & (q[..., 1] < nj)
        q = np.where(ok[..., None], q, 0)
        return np.where(ok, self.grid[q[..., 1], q[..., 0]], -1)


@dataclass(frozen=True)
class _LatticeTables:
    """Neighbour tables of a reference lattice (built once with the :class:`ReferenceGrid`).

    Node numbers of neighbours, ``n`` (one past the last node) where there is none: ``back``
    (n + 1, 16) one step back along each of the 8 grid directions, then two steps, ``fwd``
    (n + 1, 16) the same forward, ``nbrs4`` (n, 4) and ``nbrs8`` (n, 8); the tables' last rows
    (node ``n``) point nowhere. ``lit_grid`` marks the lit dots on ``lat.grid``.
    """

    lat: _Lattice
    back: IntArray
    fwd: IntArray
    nbrs4: IntArray
    nbrs8: IntArray
    lit_grid: BoolArray

    @classmethod
    def of(cls, ij: IntArray, lit: BoolArray) -> _LatticeTables:
        lat = _Lattice(ij)
        n = len(lat.ij)

        def table(steps: NDArray, sentinel_row: bool = False) -> IntArray:
            t = np.stack([lat.neighbour(step) for step in steps], axis=1)
            t = np.where(t < 0, n, t)
            return np.vstack([t, np.full((1, len(steps)), n)]) if sentinel_row else t

        back = table(np.vstack([-_DIRS8, -2 * _DIRS8]), True)
        fwd = table(np.vstack([_DIRS8, 2 * _DIRS8]), True)
        lit_grid = np.zeros(lat.grid.shape, bool)
        q = lat.ij[np.asarray(lit, bool)] - lat.lo
        lit_grid[q[:, 1], q[:, 0]] = True
        return cls(lat, back, fwd, table(_DIRS4), table(_DIRS8), lit_grid)
