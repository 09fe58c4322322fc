"""The steps of coded decoding after the symbols (:mod:`restoration.features.decode`, steps 3, 5
and 6): the window votes, the growth into stretched patches (and the ordering labels that may
join it), and the checks that drop labels the lattice or the code contradicts."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from restoration.features._types import BoolArray, FloatArray, IntArray
from restoration.features.detect import Spots
from restoration.features.match import Matches
from restoration.features.reference import ReferenceGrid

# Opposite neighbour directions in _DIRS8 order ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1),
# (1, -1), (-1, 1), (-1, -1)).
_OPPOSITE = np.array([[0, 1], [2, 3], [4, 7], [5, 6]])
_OPPOSITE.setflags(write=False)


@numba.njit(cache=True)
def _votes(node: IntArray, disp: FloatArray, start: IntArray, nbrs8: IntArray,
           opposite: IntArray, tol1: FloatArray, tol2: FloatArray, jump: FloatArray) -> IntArray:
    """Neighbour votes (0..8) for each hypothesis (sorted by node; ``start`` (G + 1,) the first
    hypothesis of each node).

    A pair of opposite neighbours ``k + o``, ``k - o`` gives 2 votes when each has a hypothesis,
    within ``jump`` of this one's displacement, whose displacements are collinear with this
    one's: ``|d(k + o) + d(k - o) - 2 d(k)| < tol2`` (a second difference, blind to the local
    stretch and rotation of the pattern, which first differences are not). Otherwise each of the
    two gives 1 vote when it has a hypothesis within ``tol1`` of this one's displacement.
    Tolerances are per node, px (``tol1``, ``tol2``, ``jump`` (G,), squared)."""
    n_nodes = len(start) - 1
    out = np.zeros(len(node), np.int64)
    for a in range(len(node)):
        k = node[a]
        ax, ay = disp[a, 0], disp[a, 1]
        for q in range(opposite.shape[0]):
            kp, km = nbrs8[k, opposite[q, 0]], nbrs8[k, opposite[q, 1]]
            near_p = False
            near_m = False
            pair = False
            if kp < n_nodes:
                for b in range(start[kp], start[kp + 1]):
                    bx, by = disp[b, 0] - ax, disp[b, 1] - ay
                    r2 = bx * bx + by * by
                    if r2 < tol1[k]:
                        near_p = True
                    if pair or r2 >= jump[k] or km >= n_nodes:
                        continue
                    for c in range(start[km], start[km + 1]):
                        cx, cy = disp[c, 0] - ax, disp[c, 1] - ay
                        second = (bx + cx) ** 2 + (by + cy) ** 2
                        if second < tol2[k] and cx * cx + cy * cy < jump[k]:
                            pair = True
                            break
            if pair:
                out[a] += 2
                continue
            if km < n_nodes:
                for c in range(start[km], start[km + 1]):
                    cx, cy = disp[c, 0] - ax, disp[c, 1] - ay
                    if cx * cx + cy * cy < tol1[k]:
                        near_m = True
                        break
            out[a] += int(near_p) + int(near_m)
    return out


def _best_per_group(group: IntArray, score: IntArray, n: int) -> tuple[IntArray, IntArray]:
    """Per group id (0..n-1): the row with the highest score (-1 where the group is empty) and
    the runner-up's score (0 where there is none)."""
    if len(group) == 0:  # no row at all (e.g. no window decoded): every group is empty
        return np.full(n, -1, np.int64), np.zeros(n, np.int64)
    order = np.lexsort((-score, group))
    g_sorted = group[order]
    first = np.searchsorted(g_sorted, np.arange(n))
    count = np.bincount(group, minlength=n)
    best = np.where(count > 0, order[np.minimum(first, len(order) - 1)], -1)
    second_at = np.minimum(first + 1, len(order) - 1)
    second = np.where(count > 1, score[order[second_at]], 0)
    return best, second


def _lattice_check(
    nodes: IntArray, disp: FloatArray, n_nodes: int, tab: object, spacing: FloatArray
) -> tuple[IntArray, FloatArray]:
    """Per decoded dot: its decoded grid neighbours (of 8) and the distance, in local spacings,
    from its displacement to the one they predict (:func:`_predicted`; inf with fewer than two
    predictions)."""
    at = np.full((n_nodes + 1, 2), np.nan)
    at[nodes] = disp
    n_nbrs = np.sum(np.isfinite(at[tab.nbrs8[nodes], 0]), axis=1)
    pred, n_pred = _predicted(at, nodes, tab)
    err = np.linalg.norm(disp - pred, axis=1) / spacing[nodes]
    return n_nbrs, np.where((n_pred >= 2) & np.isfinite(err), err, np.inf)


def _predicted(at: FloatArray, nodes: IntArray, tab: object) -> tuple[FloatArray, IntArray]:
    """Displacement (K, 2) of ``nodes`` predicted from their decoded grid neighbours (``at``
    (G + 1, 2), NaN where not decoded): the median of the midpoints of decoded opposite pairs
    and of the straight-line extrapolations from two decoded dots in a row; and how many
    predictions there were."""
    one = at[tab.nbrs8[nodes]]  # (K, 8, 2)
    two = at[tab.fwd[nodes, 8:16]]  # two steps along the same directions
    mid = 0.5 * (one[:, _OPPOSITE[:, 0]] + one[:, _OPPOSITE[:, 1]])  # (K, 4, 2)
    line = 2.0 * one - two  # (K, 8, 2)
    preds = np.concatenate([mid, line], axis=1)
    n = np.sum(np.isfinite(preds[..., 0]), axis=1)
    # The median of the n finite ones, which sorting puts first (np.nanmedian's value, several
    # times faster on these short rows); all-NaN rows stay NaN.
    srt = np.sort(preds, axis=1)
    lo = np.broadcast_to((np.maximum(n - 1, 0) // 2)[:, None, None], (len(n), 1, 2))
    hi = np.broadcast_to((n // 2)[:, None, None], (len(n), 1, 2))
    med = 0.5 * (np.take_along_axis(srt, lo, axis=1) + np.take_along_axis(srt, hi, axis=1))
    return med[:, 0], n


def _grow_decoded(
    node: IntArray, spot: IntArray, disp: FloatArray, take: IntArray, n_nodes: int,
    n_spots: int, tab: object, spacing: FloatArray, tol: float, min_predictions: int = 2,
    max_waves: int = 64,
) -> IntArray:
    """Extend the decoded hypotheses ``take`` into their grid neighbours, wave by wave: a dot
    takes the hypothesis (of its own symbol) nearest to the displacement its decoded neighbours
    predict (:func:`_predicted`, from at least ``min_predictions``) when it lies within ``tol``
    local spacings, the dot's next hypothesis lies farther than ``tol`` and twice as far, and
    its spot is still free. Returns the grown ``take``."""
    take = np.asarray(take, np.int64)
    for _ in range(max_waves):
        at = np.full((n_nodes + 1, 2), np.nan)
        at[node[take]] = disp[take]
        used_node = np.zeros(n_nodes + 1, bool)
        used_node[node[take]] = True
        used_spot = np.zeros(n_spots, bool)
        used_spot[spot[take]] = True
        free = ~used_node[node] & ~used_spot[spot]
        # Only hypotheses of nodes next to a decoded dot.
        free &= used_node[tab.nbrs8[node]].any(axis=1)
        cand = np.flatnonzero(free)
        if len(cand) == 0:
            break
        pred, n_pred = _predicted(at, node[cand], tab)
        err = np.linalg.norm(disp[cand] - pred, axis=1) / spacing[node[cand]]
        err = np.where((n_pred >= min_predictions) & np.isfinite(err), err, np.inf)
        rank = -np.round(np.minimum(err, 1e3) * 1e6).astype(np.int64)
        best, _ = _best_per_group(node[cand], rank, n_nodes)
        has = np.flatnonzero(best >= 0)
        b = best[has]
        # Runner-up error of each node's hypotheses.
        err2 = np.where(np.isin(np.arange(len(cand)), b), np.inf, err)
        second = np.full(n_nodes, np.inf)
        np.minimum.at(second, node[cand], err2)
        ok = (err[b] < tol) & (second[node[cand[b]]] > np.maximum(2.0 * err[b], tol))
        new = cand[b[ok]]
        # A spot chosen by two dots goes to neither.
        count = np.bincount(spot[new], minlength=n_spots)
        new = new[count[spot[new]] == 1]
        if len(new) == 0:
            break
        take = np.concatenate([take, new])
    return take


def _ordering_pairs(
    ordering: Matches, ref: ReferenceGrid, spots: Spots, node_ok: NDArray, spot_ok: NDArray,
    codes: IntArray, sym: IntArray,
) -> tuple[IntArray, IntArray]:
    """The ordering matcher's labels as (node, spot) pairs, where the spot shows the dot's
    symbol and both are usable (``node_ok``, ``spot_ok``): the hypotheses it adds.

    Where the plain grid leaves the labelling's lattice shift open (``ordering.alt_shifts``:
    the lit/unlit evidence fits several), the symbols settle it: the labels of the right shift
    show their dots' symbols (all but the misread), those of any other shift about 1 in 4
    (chance). The shift whose labels agree most is applied ([0, 0] on a tie)."""
    dist, p = cKDTree(spots.centres_px).query(ordering.spot_px)
    shifts = np.asarray(ordering.alt_shifts, np.int64).reshape(-1, 2)
    shifts = np.concatenate([np.zeros((1, 2), np.int64), shifts[np.any(shifts != 0, axis=1)]])
    k = ref.tables.lat.lookup(ordering.ij[None, :, :] + shifts[:, None, :])  # (C, N)
    ok = (k >= 0) & (dist < 1e-6)[None, :] & spot_ok[p][None, :]
    ok &= node_ok[np.maximum(k, 0)]
    agree = ok & (codes[np.maximum(k, 0)] == sym[p][None, :])
    best = int(np.argmax(agree.sum(axis=1)))  # the first (no shift) on a tie
    return k[best, agree[best]].astype(np.int64), p[agree[best]].astype(np.int64)


def _from_ordering(
    hyp: IntArray, node: IntArray, spot: IntArray, take: IntArray, n_nodes: int, n_spots: int,
) -> IntArray:
    """Of the ordering matcher's hypotheses ``hyp`` (indices into ``node``, ``spot``), those
    whose spot and dot no label in ``take`` holds."""
    free_node = np.ones(n_nodes, bool)
    free_node[node[take]] = False
    free_spot = np.ones(n_spots, bool)
    free_spot[spot[take]] = False
    return hyp[free_node[node[hyp]] & free_spot[spot[hyp]]]


@dataclass(frozen=True)
class _Window:
    """What :func:`_contradicted` reads of a frame: the flat-water spots (G, 2) and local
    spacings (G,), px, and the code (G,) of the lattice; the wavy spots' centres (P, 2), their
    symbols (P,) and whether those can be read (P,: clear, bright, not suspicious); the
    tolerance, local spacings, and the fewest disagreeing symbols that drop a label."""

    ref_px: FloatArray
    spacing: FloatArray
    codes: IntArray
    centres_px: FloatArray
    sym: IntArray
    readable: BoolArray
    tol: float
    min_mismatch: int


_RAY_REACH = 1.5
"""How far along the ray to where the labelling puts a neighbour :func:`_contradicted` looks
for its spot, in multiples of that distance: a squeezed neighbour lies nearer, a stretched
one farther, and the neighbour after it twice as far."""

_RAY_CANDIDATES = 12
"""Spots nearest to a ray's middle that :func:`_contradicted` considers."""


def _contradicted(
    take: IntArray, node: IntArray, spot: IntArray, disp: FloatArray, tab: object, win: _Window
) -> BoolArray:
    """Per label of ``take``: whether its 3 x 3 window contradicts it where the window's dots
    were not decoded.

    The labelling puts each undecoded lit grid neighbour of a label where the displacement its
    decoded neighbours predict (:func:`_predicted`; the label's own with fewer than two) takes
    it. When that lies within ``win.tol`` local spacings of the label's own spot, the lattice
    puts two dots on one spot, as in a fold's overlap where the labelling one dot over fits
    the displacements as well (the lattice check passes both): the label is ambiguous.
    Otherwise the neighbour's spot is the first spot along the ray from the label's spot to
    there (within ``win.tol`` spacings of the ray, up to :data:`_RAY_REACH` times as far): a fold
    squeezes the neighbour towards the label, so the spot nearest to the predicted place may
    be the next dot's. A readable spot that no label holds shows the code's symbol for the
    neighbour or another; a held spot, a speck or a mixed colour is no evidence. The spots
    around a label shifted by whole dots show their own dots' window, which differs from the
    label's in at least :data:`~wai_core.pattern.CODE_MIN_DISTANCE` of 9 symbols; its decoded
    neighbours show the label's by construction, so the differences lie where the window was
    not decoded.

    A label is contradicted when ambiguous, or when at least ``win.min_mismatch`` of its
    neighbours' spots show another symbol than the code's and they outnumber those that show
    the code's.
    """
    if len(take) == 0:
        return np.zeros(0, bool)
    n_nodes = len(win.codes)
    k = node[take]
    at = np.full((n_nodes + 1, 2), np.nan)
    at[k] = disp[take]
    nb = tab.nbrs8[k]  # (K, 8), n_nodes where there is none
    nbc = np.minimum(nb, n_nodes - 1)
    open_ = (nb < n_nodes) & np.isnan(at[nb, 0]) & (win.codes[nbc] >= 0)
    # Each undecoded neighbour once: most border several labels.
    uniq, inv = np.unique(np.where(open_, nbc, 0), return_inverse=True)
    pred_u, n_u = _predicted(at, uniq, tab)
    inv = inv.reshape(nb.shape)
    n_pred = np.where(open_, n_u[inv], 0)
    pred = np.where((n_pred >= 2)[..., None], pred_u[inv], disp[take][:, None, :])
    own = win.centres_px[spot[take]]
    ray = win.ref_px[nbc] + pred - own[:, None, :]  # (K, 8, 2)
    width = win.tol * win.spacing[nbc]
    length2 = np.sum(ray**2, axis=2)
    length2 = np.where(np.isfinite(length2), length2, 0.0)
    twice = open_ & (n_pred >= 2) & (length2 < width**2) & np.isfinite(ray[..., 0])
    # The first spot along each ray; spots that labels hold block it without evidence.
    held = np.zeros(len(win.centres_px), bool)
    held[spot[take]] = True
    cand = np.flatnonzero(win.readable | held)
    lab, o = np.nonzero(open_ & ~twice & (length2 > 0))  # the rays to follow, (M,)
    if len(lab) == 0:
        return twice.any(axis=1)
    r, r2, origin = ray[lab, o], length2[lab, o], own[lab]
    _, q = cKDTree(win.centres_px[cand]).query(
        origin + 0.5 * _RAY_REACH * r, k=min(_RAY_CANDIDATES, len(cand))
    )
    q = cand[np.reshape(q, (len(lab), -1))]  # (M, C)
    rel = win.centres_px[q] - origin[:, None, :]
    t = np.sum(rel * r[:, None, :], axis=2) / r2[:, None]
    off = np.linalg.norm(rel - t[..., None] * r[:, None, :], axis=2)
    on_ray = ((t > 0) & (t <= _RAY_REACH) & (off < width[lab, o][:, None])
              & (q != spot[take][lab][:, None]))
    first = q[np.arange(len(lab)), np.argmin(np.where(on_ray, t, np.inf), axis=1)]
    found = on_ray.any(axis=1) & win.readable[first] & ~held[first]
    same = win.sym[first] == win.codes[nbc[lab, o]]
    agree = np.bincount(lab[found & same], minlength=len(take))
    disagree = np.bincount(lab[found & ~same], minlength=len(take))
    return twice.any(axis=1) | ((disagree >= win.min_mismatch) & (disagree > agree))


def _consistent(
    take: IntArray, node: IntArray, spot: IntArray, disp: FloatArray, n_nodes: int,
    tab: object, spacing: FloatArray, min_consistent: int, tol_grow: float,
    win: _Window | None = None,
) -> tuple[IntArray, IntArray]:
    """The lattice check: the labels ``take`` that the labels decoded around them confirm
    (each neighbour's window overlaps its own): the displacement their decoded neighbours
    predict (leaving each out) lies within ``2 tol_grow`` of its own, from at least
    ``min_consistent`` of them; repeated while it drops any (at most 8 times). Then (``win``)
    the code must not contradict them where their windows were not decoded
    (:func:`_contradicted`): the labels it drops change their neighbours' windows and lattice,
    so both checks are repeated while it drops any (at most 8 times). Returns the labels kept
    and those the code contradicted."""
    dropped = [np.zeros(0, np.int64)]
    for _ in range(8):
        for _ in range(8):
            cons, resid = _lattice_check(node[take], disp[take], n_nodes, tab, spacing)
            ok = (cons >= min_consistent) & (resid < 2.0 * tol_grow)
            if ok.all():
                break
            take = take[ok]
        if win is None:
            break
        bad = _contradicted(take, node, spot, disp, tab, win)
        if not bad.any():
            break
        dropped.append(take[bad])
        take = take[~bad]
    return take, np.concatenate(dropped)
