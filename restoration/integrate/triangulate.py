"""The Delaunay triangles of lattice samples that :func:`~restoration.integrate.to_heightfield`
blends, found on the lattice instead of by qhull.

The gridding keeps only Delaunay triangles whose corners lie at most ``max_step`` dots apart
along either lattice axis (:func:`~restoration.integrate.gridding.lattice_bridges`): all
three corners of such a triangle sit in one ``(max_step + 1)``-square block of lattice indices.
So every triple of samples in such a block is a candidate, and a candidate is a Delaunay
triangle when its circumcircle holds no sample (checked against every sample near it in the
plane, by a bucket grid, wherever the lattice maps to: folds included). In general position
that gives exactly qhull's triangles of small lattice span; four samples on one circle (ties
such as a regular lattice on flat water) make the Delaunay triangulation ambiguous, and the
caller falls back to qhull for the frame to keep its choice. The nearest-neighbour distances
(the gap filter's) come from the same bucket grid.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from restoration.integrate._common import _MAX_GRID_NODES, Array, IntArray

_TIE = 1e-9
"""An in-circle determinant within this fraction of its scale counts as a tie (cocircular)."""


def lattice_delaunay(
    xy: Array, lattice_ij: NDArray, max_step: int
) -> tuple[IntArray, Array] | None:
    """The Delaunay triangles of samples ``xy`` (K, 2) mm whose lattice indices
    ``lattice_ij`` (K, 2) lie at most ``max_step`` apart along each axis, and each sample's
    nearest-neighbour distance (mm).

    Returns
    -------
    simplices : (T, 3) ndarray of int
        The triangles, counter-clockwise.
    nearest : (K,) ndarray
        Distance from each sample to its nearest other sample, mm.

    None when the triangles cannot be told apart from qhull's choice: a tie (four samples on
    one circle), no triangle, or an index span too wide for a lookup table.
    """
    ij = np.asarray(lattice_ij, dtype=np.int64)
    lo = ij.min(axis=0)
    span = ij.max(axis=0) - lo + 1
    if span[0] * span[1] > _MAX_GRID_NODES or xy.shape[0] < 3:
        return None
    table = np.full((span[1], span[0]), -1, np.int64)
    table[ij[:, 1] - lo[1], ij[:, 0] - lo[0]] = np.arange(ij.shape[0])
    xy = np.ascontiguousarray(xy, dtype=float)
    # Buckets about one mean spacing wide: a few samples each.
    x0, y0 = xy.min(axis=0)
    extent = xy.max(axis=0) - xy.min(axis=0)
    h = max(math.sqrt(extent[0] * extent[1] / xy.shape[0]), float(extent.max()) / 1024, 1e-9)
    nb = np.floor(extent / h).astype(np.int64) + 1
    cell = (np.minimum(((xy[:, 0] - x0) / h).astype(np.int64), nb[0] - 1)
            + nb[0] * np.minimum(((xy[:, 1] - y0) / h).astype(np.int64), nb[1] - 1))
    order = np.argsort(cell, kind="stable")
    start = np.searchsorted(cell[order], np.arange(nb[0] * nb[1] + 1))
    out = np.empty((2 * xy.shape[0] + 8, 3), np.int64)  # a Delaunay triangulation's most
    nearest = np.empty(xy.shape[0])
    found = np.zeros(1, np.int64)
    for _ in range(2):  # a second pass only where more were found than fit
        code = _triangles_kernel(xy, table, int(max_step), x0, y0, h, nb[0], nb[1], order,
                                 start, out, found)
        if code:
            return None
        if found[0] <= out.shape[0]:
            break
        out = np.empty((found[0], 3), np.int64)
    if found[0] == 0:
        return None
    out = out[: found[0]]
    _nearest_kernel(xy, x0, y0, h, nb[0], nb[1], order, start, nearest)
    return out, nearest


@njit(cache=True, nogil=True, error_model="numpy")
def _in_circle(xy, a, b, c, d):  # pragma: no cover
    """In-circle determinant of ``d`` against counter-clockwise ``a, b, c`` (> 0: inside) and
    its scale."""
    adx, ady = xy[a, 0] - xy[d, 0], xy[a, 1] - xy[d, 1]
    bdx, bdy = xy[b, 0] - xy[d, 0], xy[b, 1] - xy[d, 1]
    cdx, cdy = xy[c, 0] - xy[d, 0], xy[c, 1] - xy[d, 1]
    al, bl, cl = adx * adx + ady * ady, bdx * bdx + bdy * bdy, cdx * cdx + cdy * cdy
    det = (adx * (bdy * cl - cdy * bl) - ady * (bdx * cl - cdx * bl)
           + al * (bdx * cdy - cdx * bdy))
    scale = (al + bl + cl) ** 2
    return det, scale


@njit(cache=True, nogil=True)
def _patterns(step):  # pragma: no cover
    """The corner triples of a block (codes ``dj * (step + 1) + di``), each with its smallest
    ``di`` and smallest ``dj`` 0 (so a triangle is met in one block only), and for each the
    block's other codes, those most inside the triple's circle on the lattice first (the
    samples likely to reject it)."""
    side = step + 1
    size = side * side
    n = 0
    pat = np.empty((size * size * size, 3), np.int64)
    for p in range(size):
        for q in range(p + 1, size):
            for r in range(q + 1, size):
                if min(p % side, min(q % side, r % side)) == 0 and min(
                        p // side, min(q // side, r // side)) == 0:
                    pat[n, 0], pat[n, 1], pat[n, 2] = p, q, r
                    n += 1
    pat = pat[:n].copy()
    tests = np.empty((n, size - 3), np.int64)
    power = np.empty(size - 3)
    for t in range(n):
        ax, ay = pat[t, 0] % side, pat[t, 0] // side
        bx, by = pat[t, 1] % side - ax, pat[t, 1] // side - ay
        cx, cy = pat[t, 2] % side - ax, pat[t, 2] // side - ay
        dd = 2.0 * (bx * cy - by * cx)
        if dd != 0:
            b2, c2 = bx * bx + by * by, cx * cx + cy * cy
            ux, uy = ax + (cy * b2 - by * c2) / dd, ay + (bx * c2 - cx * b2) / dd
            rad2 = (ux - ax) ** 2 + (uy - ay) ** 2
        else:  # collinear on the lattice: nearest the centroid first
            ux, uy, rad2 = ax + (bx + cx) / 3.0, ay + (by + cy) / 3.0, 0.0
        m = 0
        for k in range(size):
            if k != pat[t, 0] and k != pat[t, 1] and k != pat[t, 2]:
                tests[t, m] = k
                power[m] = (k % side - ux) ** 2 + (k // side - uy) ** 2 - rad2
                m += 1
        tests[t] = tests[t][np.argsort(power, kind="mergesort")]
    return pat, tests


@njit(cache=True, nogil=True, error_model="numpy")
def _triangles_kernel(xy, table, step, x0, y0, h, nbx, nby, order, start, out,
                      found):  # pragma: no cover
    """Write the empty-circle triangles into ``out`` (as many as fit) and their count into
    ``found[0]``; returns 1 on a tie, else 0. ``table`` (H, W) holds the sample at each
    lattice index from 0 (-1: none)."""
    height, width = table.shape
    side = step + 1
    pat, tests = _patterns(step)
    blk = np.empty(side * side, np.int64)
    n_found = 0
    for j0 in range(height):
        for i0 in range(width):
            for k in range(side * side):
                jj, ii = j0 + k // side, i0 + k % side
                blk[k] = table[jj, ii] if jj < height and ii < width else -1
            for t in range(pat.shape[0]):
                a, b, c = blk[pat[t, 0]], blk[pat[t, 1]], blk[pat[t, 2]]
                if a < 0 or b < 0 or c < 0:
                    continue
                e1x, e1y = xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1]
                e2x, e2y = xy[c, 0] - xy[a, 0], xy[c, 1] - xy[a, 1]
                det = e1x * e2y - e1y * e2x
                if abs(det) <= 1e-12 * (e1x**2 + e1y**2 + e2x**2 + e2y**2):
                    continue  # a flat sliver: the blend skips it
                if det < 0:
                    b, c = c, b
                inside = False
                for m in range(tests.shape[1]):  # the block's own samples reject most
                    d = blk[tests[t, m]]
                    if d >= 0:
                        v, scale = _in_circle(xy, a, b, c, d)
                        if v > _TIE * scale:
                            inside = True
                            break
                if inside:
                    continue
                tie = False
                # Circumcircle, then every sample in the buckets it touches.
                bx, by = xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1]
                cx, cy = xy[c, 0] - xy[a, 0], xy[c, 1] - xy[a, 1]
                dd = 2.0 * (bx * cy - by * cx)
                b2, c2 = bx * bx + by * by, cx * cx + cy * cy
                ux = xy[a, 0] + (cy * b2 - by * c2) / dd
                uy = xy[a, 1] + (bx * c2 - cx * b2) / dd
                rad = math.sqrt((ux - xy[a, 0]) ** 2 + (uy - xy[a, 1]) ** 2) * 1.001
                kx0 = max(int(math.floor((ux - rad - x0) / h)), 0)
                kx1 = min(int(math.floor((ux + rad - x0) / h)), nbx - 1)
                ky0 = max(int(math.floor((uy - rad - y0) / h)), 0)
                ky1 = min(int(math.floor((uy + rad - y0) / h)), nby - 1)
                for ky in range(ky0, ky1 + 1):
                    for kx in range(kx0, kx1 + 1):
                        cell = ky * nbx + kx
                        for r in range(start[cell], start[cell + 1]):
                            d = order[r]
                            if d == a or d == b or d == c:
                                continue
                            v, scale = _in_circle(xy, a, b, c, d)
                            if v > _TIE * scale:
                                inside = True
                                break
                            if v >= -_TIE * scale:
                                tie = True
                        if inside:
                            break
                    if inside:
                        break
                if inside:
                    continue
                if tie:
                    return 1
                if n_found < out.shape[0]:
                    out[n_found, 0], out[n_found, 1], out[n_found, 2] = a, b, c
                n_found += 1
    found[0] = n_found
    return 0


@njit(cache=True, nogil=True)
def _nearest_kernel(xy, x0, y0, h, nbx, nby, order, start, nearest):  # pragma: no cover
    """Distance from each sample to its nearest other one, ``nearest`` (K,) mm, by rings of
    buckets (as the triangles' edge lengths: ``sqrt(dx^2 + dy^2)``)."""
    for v in range(xy.shape[0]):
        kx = min(int((xy[v, 0] - x0) / h), nbx - 1)
        ky = min(int((xy[v, 1] - y0) / h), nby - 1)
        best = np.inf
        ring = 0
        while True:
            for jy in range(ky - ring, ky + ring + 1):
                if jy < 0 or jy >= nby:
                    continue
                for jx in range(kx - ring, kx + ring + 1):
                    if jx < 0 or jx >= nbx:
                        continue
                    if max(abs(jx - kx), abs(jy - ky)) != ring:
                        continue
                    k = jy * nbx + jx
                    for t in range(start[k], start[k + 1]):
                        d = order[t]
                        if d != v:
                            ex, ey = xy[v, 0] - xy[d, 0], xy[v, 1] - xy[d, 1]
                            best = min(best, math.sqrt(ex * ex + ey * ey))
            # Samples beyond this ring lie at least ring * h away.
            if best <= ring * h or (ring > nbx and ring > nby):
                break
            ring += 1
        nearest[v] = best
