"""Compiled (numba) kernels of the feature stage: the region growing of
:func:`restoration.features.match._grow` and the spatial lookup it needs.

The growing is a frontier loop of a few hundred small steps per frame; as NumPy it paid an
array pass per step and wave, compiled it touches only the nodes it changes. Arithmetic
follows the NumPy expressions term by term (sums in NumPy's pairwise order), so the labels
are the same.
"""

from __future__ import annotations

import math
from types import MappingProxyType

import numpy as np
from numba import njit

_JIT = MappingProxyType({"cache": True, "nogil": True, "error_model": "numpy"})


@njit(**_JIT)
def spot_cells(xy, cell):  # pragma: no cover
    """Bucket points ``xy`` (P, 2) px into square cells of side ``cell`` px.

    Returns ``(lo (2,), shape (2,) as (nx, ny), start (nx ny + 1,), order (P,))``: the points
    of cell ``(cx, cy)`` are ``order[start[c] : start[c + 1]]`` with ``c = cy nx + cx``.
    """
    p = xy.shape[0]
    lo = np.empty(2)
    hi = np.empty(2)
    for d in range(2):
        lo[d] = xy[0, d] if p else 0.0
        hi[d] = lo[d]
    for i in range(p):
        for d in range(2):
            lo[d] = min(lo[d], xy[i, d])
            hi[d] = max(hi[d], xy[i, d])
    nx = int((hi[0] - lo[0]) / cell) + 1
    ny = int((hi[1] - lo[1]) / cell) + 1
    shape = np.array([nx, ny])
    of = np.empty(p, np.int64)
    count = np.zeros(nx * ny + 1, np.int64)
    for i in range(p):
        cx = int((xy[i, 0] - lo[0]) / cell)
        cy = int((xy[i, 1] - lo[1]) / cell)
        of[i] = cy * nx + cx
        count[of[i] + 1] += 1
    start = np.cumsum(count)
    fill = start[:-1].copy()
    order = np.empty(p, np.int64)
    for i in range(p):
        order[fill[of[i]]] = i
        fill[of[i]] += 1
    return lo, shape, start, order


@njit(**_JIT)
def nearest_two(xy, lo, shape, start, order, cell, bound, x, y):  # pragma: no cover
    """Distances of the nearest and second-nearest of the points ``xy`` (bucketed by
    :func:`spot_cells` into cells of side ``cell``) to ``(x, y)`` closer than ``bound`` (inf
    where none), and the nearest's index (``P - 1`` where none, as :func:`grow` clips
    cKDTree's "none"). Distances as cKDTree computes them, ``sqrt(dx^2 + dy^2)``.

    Rings of cells around the point's are searched outwards until the next ring lies beyond
    the second distance found (or beyond ``bound``).
    """
    nx, ny = shape[0], shape[1]
    d1, d2, best = np.inf, np.inf, xy.shape[0] - 1
    if not (math.isfinite(x) and math.isfinite(y)):
        return d1, d2, best
    cx = int(math.floor((x - lo[0]) / cell))
    cy = int(math.floor((y - lo[1]) / cell))
    r = 0
    while True:
        # Ring r: the cells at Chebyshev distance r from (cx, cy), each once.
        for gy in range(max(cy - r, 0), min(cy + r, ny - 1) + 1):
            whole = gy == cy - r or gy == cy + r  # a top or bottom row of the ring
            for gx in range(max(cx - r, 0), min(cx + r, nx - 1) + 1):
                if not whole and gx != cx - r and gx != cx + r:
                    continue
                c = gy * nx + gx
                for k in range(start[c], start[c + 1]):
                    i = order[k]
                    dx, dy = xy[i, 0] - x, xy[i, 1] - y
                    d = math.sqrt(dx * dx + dy * dy)
                    if d >= bound:
                        continue
                    if d < d1 or (d == d1 and i < best):
                        d1, d2, best = d, d1, i
                    elif d < d2:
                        d2 = d
        # Points of ring r + 1 and beyond lie at least r cells away.
        reach = r * cell
        if reach >= d2 or reach >= bound:
            break
        if cx - r <= 0 and cy - r <= 0 and cx + r >= nx - 1 and cy + r >= ny - 1:
            break  # the ring covers the whole grid
        r += 1
    return d1, d2, best


@njit(**_JIT)
def first_along(xy, lo, shape, start, order, cell, ox, oy, vx, vy, lam_lo, lam_hi,
                perp_max):  # pragma: no cover
    """The first of the points ``xy`` (bucketed by :func:`spot_cells`) along the ray
    ``o + lam v`` with ``lam_lo <= lam <= lam_hi``, at most ``perp_max`` px off it: its index
    (-1: none), its ``lam``, and the next point's ``lam`` (inf: none)."""
    nx, ny = shape[0], shape[1]
    vv = vx * vx + vy * vy
    best, lam1, lam2 = -1, np.inf, np.inf
    if not vv > 0.0:
        return best, lam1, lam2
    norm = math.sqrt(vv)
    xa, xb = ox + lam_lo * vx, ox + lam_hi * vx
    ya, yb = oy + lam_lo * vy, oy + lam_hi * vy
    gx0 = max(int(math.floor((min(xa, xb) - perp_max - lo[0]) / cell)), 0)
    gx1 = min(int(math.floor((max(xa, xb) + perp_max - lo[0]) / cell)), nx - 1)
    gy0 = max(int(math.floor((min(ya, yb) - perp_max - lo[1]) / cell)), 0)
    gy1 = min(int(math.floor((max(ya, yb) + perp_max - lo[1]) / cell)), ny - 1)
    for gy in range(gy0, gy1 + 1):
        for gx in range(gx0, gx1 + 1):
            c = gy * nx + gx
            for k in range(start[c], start[c + 1]):
                i = order[k]
                dx, dy = xy[i, 0] - ox, xy[i, 1] - oy
                lam = (dx * vx + dy * vy) / vv
                if lam < lam_lo or lam > lam_hi or abs(dx * vy - dy * vx) / norm > perp_max:
                    continue
                if lam < lam1 or (lam == lam1 and i < best):
                    best, lam1, lam2 = i, lam, lam1
                elif lam < lam2:
                    lam2 = lam
    return best, lam1, lam2


@njit(**_JIT)
def nearest_each(xy, lo, shape, start, order, cell, bound, pts):  # pragma: no cover
    """:func:`nearest_two` for each point of ``pts`` (Q, 2) px, with its own ``bound`` (Q,)
    px. Returns the nearest distances ``d1`` (Q,), the second-nearest ``d2`` (Q,) and the
    nearest's index ``idx`` (Q,) (inf, inf and ``P - 1`` where none)."""
    q = pts.shape[0]
    d1 = np.empty(q)
    d2 = np.empty(q)
    idx = np.empty(q, np.int64)
    for k in range(q):
        d1[k], d2[k], idx[k] = nearest_two(
            xy, lo, shape, start, order, cell, bound[k], pts[k, 0], pts[k, 1]
        )
    return d1, d2, idx


@njit(**_JIT)
def order_pairs(a, b, ref_px, spot_px, margin, xy, lo, shape, start, order, cell,
                bad):  # pragma: no cover
    """Mark both ends of each neighbour pair ``(a[k], b[k])`` that breaks eq. 33 in ``bad``;
    see :func:`restoration.features.ordering.order_violations` for the tests. ``xy`` (P, 2) are
    the detected spots, bucketed by :func:`spot_cells` (``lo, shape, start, order, cell``);
    P = 0: no skipped-spot test. Arithmetic as the NumPy expressions, term by term."""
    for k in range(a.size):
        i, j = a[k], b[k]
        ux, uy = ref_px[j, 0] - ref_px[i, 0], ref_px[j, 1] - ref_px[i, 1]
        norm = math.sqrt(ux * ux + uy * uy)
        ux, uy = ux / norm, uy / norm
        dx, dy = spot_px[j, 0] - spot_px[i, 0], spot_px[j, 1] - spot_px[i, 1]
        viol = dx * ux + dy * uy <= margin
        if not viol and xy.shape[0] > 0:
            reach = 0.3 * math.sqrt(dx * dx + dy * dy)
            mx = 0.5 * (spot_px[i, 0] + spot_px[j, 0])
            my = 0.5 * (spot_px[i, 1] + spot_px[j, 1])
            d1 = nearest_two(xy, lo, shape, start, order, cell, reach, mx, my)[0]
            viol = d1 < reach
        if viol:
            bad[i] = True
            bad[j] = True


@njit(**_JIT)
def seed_scores(cand, nbrs8, ok, disp, base, centre, extent, spacing, size):  # pragma: no cover
    """The seed score of each candidate node ``cand`` (C,) and how many of its 8-neighbours
    (``nbrs8`` (n, 8), ``n`` for none) are ``ok`` (n + 1,); see
    :func:`restoration.features.match._choose_seed`. ``disp`` (n + 1, 2) px: each node's
    displacement to its nearest spot; ``base`` (n, 2) px, ``centre`` (2,) px and ``extent`` px:
    where the nodes are, the pattern's middle and its size; ``spacing`` (n,) px; ``size``
    (C,): the spot-size term. Arithmetic as the NumPy expressions, term by term."""
    score = np.empty(cand.size)
    n_ok = np.zeros(cand.size, np.int64)
    for q in range(cand.size):
        i = cand[q]
        worst = 0.0
        for k in range(8):
            j = nbrs8[i, k]
            dx, dy = disp[i, 0] - disp[j, 0], disp[i, 1] - disp[j, 1]
            d = math.sqrt(dx * dx + dy * dy) if ok[j] else 0.0
            if d > worst or math.isnan(d):
                worst = d
            n_ok[q] += ok[j]
        own = math.sqrt(disp[i, 0] * disp[i, 0] + disp[i, 1] * disp[i, 1])
        rx, ry = base[i, 0] - centre[0], base[i, 1] - centre[1]
        reach = math.sqrt(rx * rx + ry * ry) / extent
        score[q] = (worst + own) / spacing[i] + size[q] + 0.1 * reach
    return score, n_ok


# Why a lattice node was not matched (as restoration.features.match).
_NONE, _MERGED, _BORDER, _AMBIGUOUS = 0, 1, 2, 3


@njit(**_JIT)
def grow(base, spot_xy, usable, merged, radius, margin, back, fwd, nbrs4, normal, offset,
         ratio, max_step_ratio, bound, cells, seed_node, seed_spot,
         ray_steps=False):  # pragma: no cover
    """Region growing over the lattice from ``(seed_node, seed_spot)``; see
    :func:`restoration.features.match._grow` for the rules.

    Parameters
    ----------
    base : (n + 1, 2) ndarray
        Expected spot of each node, px; row ``n`` (no neighbour) is zero.
    spot_xy : (P, 2) ndarray
        Detected spots, px.
    usable, merged : (P,) ndarray of bool
        Spots that may be matched; merged blobs.
    radius, margin : (n,) ndarray
        Acceptance radius and how far inside the visible outline a prediction must stay
        (negative: outside), px.
    back, fwd : (n + 1, 16) ndarray of int
        One then two steps back (forward) along the 8 grid directions; ``n`` for none.
    nbrs4 : (n, 4) ndarray of int
        4-neighbours; ``n`` for none.
    normal, offset : (M, 2), (M,) ndarray
        The visible outline as half-planes: ``xy . normal[k] - offset[k]`` px inside edge k.
    ratio, max_step_ratio, bound : float
        Nearest to second-nearest ratio, largest spacing change along a grid line, and the
        search radius of the spot lookup, px.
    cells : tuple
        The spots bucketed by :func:`spot_cells`: ``(lo, shape, start, order, cell)``.
    seed_node, seed_spot : int
        The first match.
    ray_steps : bool
        A node on no grid line through two matched nodes is predicted at the first spot along
        the grid step from a matched 4-neighbour's spot (0.4 to 2.5 reference steps out,
        within its acceptance radius of the line, the next spot at least 1.5 times as far),
        in the lowest tier: a lattice stretched or squeezed far from flat water's spacing
        then grows across its lines, where one step at the reference spacing falls between
        spots.

    Returns
    -------
    match, claim : (n,) ndarray of int
        Matched spot (-1: none); last spot within reach (-1: none).
    reason : (n,) ndarray of int8
        Why not matched (``_NONE`` .. ``_AMBIGUOUS``).
    pred : (n, 2) ndarray
        Last predicted position, px.
    tried : (n,) ndarray of bool
        Evaluated at least once.
    """
    n, n_spots = radius.size, spot_xy.shape[0]
    lo, shape, start, order, cell = cells
    match = np.full(n, -1, np.int64)
    matched = np.zeros(n + 1, np.bool_)
    blocked = np.zeros(n + 1, np.bool_)
    blocked[n] = True
    dirty = np.zeros(n + 1, np.bool_)
    disp = np.zeros((n + 1, 2))
    pos = base.copy()
    free = np.ones(n_spots, np.bool_)
    pred = base[:n].copy()
    last_spot = np.full(n, -1, np.int64)
    last_near = np.zeros(n, np.bool_)
    last_nc = np.zeros(n, np.bool_)
    last_tier = np.zeros(n, np.int64)
    claims = np.zeros(n_spots, np.int64)
    acc = np.empty(n, np.int64)
    acc_spot = np.empty(n, np.int64)
    front = np.empty(n, np.int64)
    t = np.empty((8, 2))
    in_front = np.zeros(n + 1, np.bool_)
    n_front = 0
    acc[0], acc_spot[0], n_acc = seed_node, seed_spot, 1
    while True:
        for a in range(n_acc):
            node, s = acc[a], acc_spot[a]
            match[node] = s
            free[s] = False
            for d in range(2):
                moved = spot_xy[s, d] - base[node, d]
                disp[node, d] = moved
                pos[node, d] = base[node, d] + moved
            matched[node] = True
            blocked[node] = True
            for k in range(16):
                dirty[fwd[node, k]] = True
        # The frontier (unblocked 4-neighbours of matched nodes), kept from wave to wave: its
        # blocked nodes leave it, the accepted nodes' neighbours join it. No wave's outcome
        # depends on the frontier's order.
        kept = 0
        for f in range(n_front):
            node = front[f]
            if blocked[node]:
                in_front[node] = False
            else:
                front[kept] = node
                kept += 1
        n_front = kept
        for a in range(n_acc):
            for k in range(4):
                nb = nbrs4[acc[a], k]
                if not blocked[nb] and not in_front[nb]:
                    in_front[nb] = True
                    front[n_front] = nb
                    n_front += 1
        if n_front == 0:
            break
        for f in range(n_front):
            node = front[f]
            if not dirty[node]:
                continue
            dirty[node] = False
            # Prediction: per direction, the line through two matched nodes, else one's own
            # displacement; summed in NumPy's pairwise order, then averaged.
            support = 0
            for k in range(8):
                b1, b2 = back[node, k], back[node, 8 + k]
                if matched[b1]:
                    support += 1
                for d in range(2):
                    if matched[b1] and matched[b2]:
                        t[k, d] = 2.0 * disp[b1, d] - disp[b2, d]
                    else:
                        t[k, d] = disp[b1, d]
            s_div = float(max(support, 1))
            for d in range(2):
                total = ((t[0, d] + t[4, d]) + (t[1, d] + t[5, d])) + (
                    (t[2, d] + t[6, d]) + (t[3, d] + t[7, d])
                )
                pred[node, d] = total / s_div + base[node, d]
            rayed = False
            if ray_steps and support > 0:
                lines = 0
                for k in range(8):
                    lines += matched[back[node, k]] and matched[back[node, 8 + k]]
                for k in range(4 if lines == 0 else 0):
                    b1 = back[node, k]
                    if not matched[b1]:
                        continue
                    hit, lam1, lam2 = first_along(
                        spot_xy, lo, shape, start, order, cell, pos[b1, 0], pos[b1, 1],
                        base[node, 0] - base[b1, 0], base[node, 1] - base[b1, 1], 0.4, 2.5,
                        radius[node])
                    if hit >= 0 and lam2 >= 1.5 * lam1:
                        pred[node, 0], pred[node, 1] = spot_xy[hit, 0], spot_xy[hit, 1]
                        rayed = True
                    break
            x, y = pred[node, 0], pred[node, 1]
            inside = np.inf
            for m in range(offset.size):
                inside = min(inside, x * normal[m, 0] + y * normal[m, 1] - offset[m])
            far = inside < margin[node]
            if far:
                blocked[node] = True
            d1, d2, s = nearest_two(spot_xy, lo, shape, start, order, cell, bound, x, y)
            near = d1 < radius[node]
            nc = near and d1 < ratio * d2
            # A spot that skips or doubles the spacing along a grid line is no match.
            jump = False
            for k in range(8):
                b1, b2 = back[node, k], back[node, 8 + k]
                if not (matched[b1] and matched[b2]):
                    continue
                now = math.hypot(spot_xy[s, 0] - pos[b1, 0], spot_xy[s, 1] - pos[b1, 1])
                before = math.hypot(pos[b1, 0] - pos[b2, 0], pos[b1, 1] - pos[b2, 1])
                if now > max_step_ratio * before or max_step_ratio * now < before:
                    jump = True
            ok = nc and usable[s] and not far and not jump
            tier = 1 if rayed else (
                1 + (support >= 2) + ((support >= 3) and (d1 < 0.5 * ratio * d2)))
            last_spot[node], last_near[node], last_nc[node] = s, near, nc
            last_tier[node] = tier if ok else 0
        # Acceptance: a spot is taken once, and not by two nodes in one wave; only the best
        # tier present.
        for f in range(n_front):
            node = front[f]
            s = last_spot[node]
            if last_nc[node] and free[s]:
                claims[s] += 1
        best = 0
        for f in range(n_front):
            node = front[f]
            s = last_spot[node]
            if last_nc[node] and free[s] and claims[s] == 1:
                best = max(best, last_tier[node])
        n_acc = 0
        for f in range(n_front):
            node = front[f]
            s = last_spot[node]
            if last_nc[node] and free[s]:
                if best > 0 and claims[s] == 1 and last_tier[node] == best:
                    acc[n_acc], acc_spot[n_acc] = node, s
                    n_acc += 1
        for f in range(n_front):
            s = last_spot[front[f]]
            if s >= 0:
                claims[s] = 0
        if best == 0:
            break

    reason = np.empty(n, np.int8)
    claim = np.full(n, -1, np.int64)
    tried = last_spot >= 0
    for node in range(n):
        s = max(last_spot[node], 0)
        if not tried[node] or not last_near[node]:
            reason[node] = _NONE
        elif merged[s]:
            reason[node] = _MERGED
        elif not usable[s]:
            reason[node] = _BORDER
        else:
            reason[node] = _AMBIGUOUS
        if tried[node] and last_near[node]:
            claim[node] = last_spot[node]
    return match, claim, reason, pred, tried
