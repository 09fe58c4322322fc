"""Sparse ``L D L^T`` factorisation of a pinned lattice Laplacian, compiled, for solves inside
compiled loops (:func:`restoration.refine._refine_kernel`).

The unknowns are ordered by nested dissection on their lattice indices (a lattice line
separates the two halves of a 4-connected lattice), which keeps the fill of ``L`` close to a
minimum-degree ordering's; the factorisation is Davis's up-looking LDL (elimination tree,
then one row of ``L`` at a time). Building it costs a small fraction of a SuperLU
factorisation with its ordering, and a solve reads the same few thousand entries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from restoration.integrate._common import Array, IntArray
from wai_core.errors import RestorationFailed

_LEAF = 8
"""Pieces of at most this many unknowns are not dissected further."""


@dataclass(frozen=True)
class LdlFactors:
    """``P A P^T = L D L^T`` of an SPD matrix ``A`` (m, m): ``L`` unit lower triangular by
    columns (CSC without its unit diagonal), ``D`` diagonal.

    Attributes
    ----------
    rank : (m,) ndarray of int
        Position of each unknown in the elimination order (``P``).
    l_ptr, l_idx, l_val : ndarray
        CSC arrays of ``L`` below its diagonal (rows in elimination order).
    diag : (m,) ndarray
        ``D``.
    """

    rank: IntArray
    l_ptr: IntArray
    l_idx: IntArray
    l_val: Array
    diag: Array

    @property
    def arrays(self) -> tuple:
        """The five arrays, in the order of :func:`ldl_solve`'s parameters."""
        return self.rank, self.l_ptr, self.l_idx, self.l_val, self.diag

    def solve(self, b: Array) -> Array:
        """``A^-1 b`` for ``b`` (m,)."""
        out = np.empty(b.size)
        ldl_solve(*self.arrays, np.ascontiguousarray(b, dtype=float), out)
        return out


def pinned_laplacian_ldl(
    lattice_ij: NDArray[np.int64], ea: IntArray, eb: IntArray, w: Array
) -> LdlFactors:
    """Factors of the weighted Laplacian of edges ``ea - eb`` (E,) with weights ``w`` (E,)
    on nodes ``0 .. m`` with lattice indices ``lattice_ij`` (m + 1, 2), node 0 pinned (its row
    and column removed): the matrix of :class:`~restoration.integrate.DifferenceGraph`, with
    unknown ``u`` for node ``u + 1``.

    Raises
    ------
    RestorationFailed
        When the matrix is not positive definite (a node not tied to node 0).
    """
    ij = np.ascontiguousarray(lattice_ij[1:], dtype=np.int64)
    m = ij.shape[0]
    rank = np.empty(m, np.int64)
    _dissect(ij, rank)
    ea = np.ascontiguousarray(ea, dtype=np.int64)
    eb = np.ascontiguousarray(eb, dtype=np.int64)
    w = np.ascontiguousarray(w, dtype=float)
    l_ptr = np.empty(m + 1, np.int64)
    col_ptr, col_idx, col_val, diag = _assemble_upper(ea, eb, w, rank, m)
    parent = np.empty(m, np.int64)
    _etree(col_ptr, col_idx, parent, l_ptr)
    l_idx = np.empty(l_ptr[m], np.int64)
    l_val = np.empty(l_ptr[m])
    if _numeric(col_ptr, col_idx, col_val, diag, parent, l_ptr, l_idx, l_val):
        raise RestorationFailed("integrate: the samples do not determine the surface "
                                "(singular fit)")
    return LdlFactors(rank, l_ptr, l_idx, l_val, diag)


@njit(cache=True, nogil=True)
def _dissect(ij, rank):  # pragma: no cover
    """Nested-dissection order of lattice nodes ``ij`` (m, 2): ``rank`` (m,) their positions.
    Each piece is split at the middle lattice line across its longer span; the line's nodes
    go last, after both halves."""
    m = ij.shape[0]
    order = np.arange(m)
    buf = np.empty(m, np.int64)
    stack = np.empty((2 * m + 2, 2), np.int64)
    stack[0, 0], stack[0, 1] = 0, m
    top = 1
    while top > 0:
        top -= 1
        lo, hi = stack[top, 0], stack[top, 1]
        if hi - lo <= _LEAF:
            continue
        mn0 = mx0 = ij[order[lo], 0]
        mn1 = mx1 = ij[order[lo], 1]
        for p in range(lo, hi):
            a, b = ij[order[p], 0], ij[order[p], 1]
            mn0, mx0, mn1, mx1 = min(mn0, a), max(mx0, a), min(mn1, b), max(mx1, b)
        axis = 0 if mx0 - mn0 >= mx1 - mn1 else 1
        mn, mx = (mn0, mx0) if axis == 0 else (mn1, mx1)
        if mx - mn < 2:
            continue
        cut = (mn + mx) // 2
        n_left = n_right = 0
        for p in range(lo, hi):
            if ij[order[p], axis] < cut:
                n_left += 1
            elif ij[order[p], axis] > cut:
                n_right += 1
        left, right, sep = lo, lo + n_left, lo + n_left + n_right
        for p in range(lo, hi):
            v = order[p]
            c = ij[v, axis]
            if c < cut:
                buf[left] = v
                left += 1
            elif c > cut:
                buf[right] = v
                right += 1
            else:
                buf[sep] = v
                sep += 1
        for p in range(lo, hi):
            order[p] = buf[p]
        stack[top, 0], stack[top, 1] = lo, lo + n_left
        stack[top + 1, 0], stack[top + 1, 1] = lo + n_left, lo + n_left + n_right
        top += 2
    for p in range(m):
        rank[order[p]] = p


@njit(cache=True, nogil=True)
def _assemble_upper(ea, eb, w, rank, m):  # pragma: no cover
    """The pinned Laplacian in elimination order: its strictly upper entries by columns
    (CSC, column ``k`` holding rows ``< k``) and its diagonal."""
    diag = np.zeros(m)
    count = np.zeros(m + 1, np.int64)
    for e in range(ea.size):
        a, b = ea[e] - 1, eb[e] - 1
        if a >= 0:
            diag[rank[a]] += w[e]
        if b >= 0:
            diag[rank[b]] += w[e]
        if a >= 0 and b >= 0:
            count[max(rank[a], rank[b]) + 1] += 1
    for k in range(m):
        count[k + 1] += count[k]
    ptr = count.copy()
    fill = count[:m].copy()
    idx = np.empty(ptr[m], np.int64)
    val = np.empty(ptr[m])
    for e in range(ea.size):
        a, b = ea[e] - 1, eb[e] - 1
        if a >= 0 and b >= 0:
            ra, rb = rank[a], rank[b]
            col = max(ra, rb)
            idx[fill[col]] = min(ra, rb)
            val[fill[col]] = -w[e]
            fill[col] += 1
    return ptr, idx, val, diag


@njit(cache=True, nogil=True)
def _etree(ptr, idx, parent, l_ptr):  # pragma: no cover
    """Elimination tree ``parent`` (m,) and the column pointers ``l_ptr`` (m + 1,) of ``L``
    (ldl_symbolic)."""
    m = parent.size
    flag = np.empty(m, np.int64)
    lnz = np.zeros(m, np.int64)
    for k in range(m):
        parent[k] = -1
        flag[k] = k
        for p in range(ptr[k], ptr[k + 1]):
            i = idx[p]
            while flag[i] != k:
                if parent[i] == -1:
                    parent[i] = k
                lnz[i] += 1
                flag[i] = k
                i = parent[i]
    l_ptr[0] = 0
    for k in range(m):
        l_ptr[k + 1] = l_ptr[k] + lnz[k]


@njit(cache=True, nogil=True, error_model="numpy")
def _numeric(ptr, idx, val, diag, parent, l_ptr, l_idx, l_val):  # pragma: no cover
    """Rows of ``L`` one at a time (ldl_numeric); ``diag`` (m,) enters as ``A``'s diagonal and
    leaves as ``D``. Returns 1 when a pivot is not positive, else 0."""
    m = diag.size
    y = np.zeros(m)
    flag = np.empty(m, np.int64)
    pattern = np.empty(m, np.int64)
    lnz = np.zeros(m, np.int64)
    for k in range(m):
        top = m
        flag[k] = k
        for p in range(ptr[k], ptr[k + 1]):
            i = idx[p]
            y[i] += val[p]
            length = 0
            while flag[i] != k:
                pattern[length] = i
                length += 1
                flag[i] = k
                i = parent[i]
            while length > 0:
                top -= 1
                length -= 1
                pattern[top] = pattern[length]
        d = diag[k]
        for t in range(top, m):
            i = pattern[t]
            yi = y[i]
            y[i] = 0.0
            end = l_ptr[i] + lnz[i]
            for p in range(l_ptr[i], end):
                y[l_idx[p]] -= l_val[p] * yi
            l_ki = yi / diag[i]
            d -= l_ki * yi
            l_idx[end] = k
            l_val[end] = l_ki
            lnz[i] += 1
        if not d > 0.0:
            return 1
        diag[k] = d
    return 0


@njit(cache=True, nogil=True)
def ldl_solve(rank, l_ptr, l_idx, l_val, diag, b, out):  # pragma: no cover
    """``out`` (m,) = ``A^-1 b`` from the factors of :class:`LdlFactors`; ``b`` (m,) is left
    unchanged."""
    m = b.size
    y = np.empty(m)
    for u in range(m):
        y[rank[u]] = b[u]
    for j in range(m):  # L y' = y by columns
        yj = y[j]
        for p in range(l_ptr[j], l_ptr[j + 1]):
            y[l_idx[p]] -= l_val[p] * yj
    for j in range(m):
        y[j] /= diag[j]
    for j in range(m - 1, -1, -1):  # L^T z = y'
        s = y[j]
        for p in range(l_ptr[j], l_ptr[j + 1]):
            s -= l_val[p] * y[l_idx[p]]
        y[j] = s
    for u in range(m):
        out[u] = y[rank[u]]
