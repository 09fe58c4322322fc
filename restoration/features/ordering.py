"""The ordering matcher's checks and its anchoring (:func:`restoration.features.match_distorted`,
steps 2 and 3): pairs of matched spots that break eq. 33's order with a grid neighbour, and the
whole-lattice shift that best explains where spots are and are not."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from restoration.features._kernels import nearest_each, order_pairs, spot_cells
from restoration.features._lattice import _DIRS4, _Lattice, _LatticeTables
from restoration.features._outline import _Outline
from restoration.features._types import BoolArray, FloatArray, IntArray
from restoration.features.reference import (
    ReferenceGrid,
)

# Why a lattice node was not matched (the last reason seen while it was on the frontier).
_NONE, _MERGED, _BORDER, _AMBIGUOUS, _ORDER, _UNLIT = range(6)


@dataclass(frozen=True)
class _Growth:
    """State of a region growing, per node: its spot (-1: none), why not, the last spot within
    reach (-1: none), the last predicted position, and whether it was ever tried."""

    match: IntArray
    reason: NDArray[np.int8]
    claim: IntArray
    pred_px: FloatArray
    tried: BoolArray


class _SpotLookup:
    """The detected spots bucketed into cells of about one spot each (compiled:
    :func:`restoration.features._kernels.spot_cells`), for nearest-spot queries; the region
    growing searches the same cells."""

    def __init__(self, xy: FloatArray) -> None:
        self.xy = np.ascontiguousarray(xy, float)
        cell = _lookup_cell(self.xy)
        self.cells = (*spot_cells(self.xy, cell), cell)

    def nearest(
        self, pts: FloatArray, bound: float | FloatArray = np.inf
    ) -> tuple[FloatArray, IntArray, FloatArray]:
        """Distance (Q,) px and index (Q,) of the nearest spot to each of ``pts`` (Q, 2) px,
        and the distance of the second nearest (Q,) px, counting only spots closer than
        ``bound`` px (one for all, or (Q,)); inf where none (the index is then ``P - 1``)."""
        pts = np.ascontiguousarray(np.reshape(pts, (-1, 2)), float)
        bounds = np.broadcast_to(np.asarray(bound, float), len(pts)).copy()
        lo, shape, start, order, cell = self.cells
        d1, d2, idx = nearest_each(self.xy, lo, shape, start, order, cell, bounds, pts)
        return d1, idx, d2


def _lookup_cell(xy: FloatArray) -> float:
    """Cell size of the growing's spot lookup, px: about one spot per cell of their bounding
    box (any size gives the same answers; this one visits the fewest cells and points)."""
    cols = np.asarray(xy).T.copy()  # (2, P): NumPy reduces a long axis fastest
    extent = cols.max(axis=1) - cols.min(axis=1) if len(xy) else np.ones(2)
    return float(max(np.sqrt(max(extent[0] * extent[1], 1.0) / max(len(xy), 1)), 1.0))


def order_violations(
    ij: IntArray,
    ref_px: FloatArray,
    spot_px: FloatArray,
    margin_px: float = 0.5,
    all_spots_px: FloatArray | None = None,
) -> BoolArray:
    """Matches that break eq. 33 with a grid neighbour along a row or a column.

    For grid neighbours ``k`` and ``k+1`` (``i`` or ``j`` + 1, both matched), the flat-water image
    direction ``u = (ref_{k+1} - ref_k) / |.|`` orders the spots; eq. 33 requires
    ``(s_{k+1} - s_k) . u > dp/2``. If ``all_spots_px`` is given, the pair is also wrong when
    another detected spot lies between them (within 0.6 x half their distance of the midpoint):
    a spot has been skipped, so the two labels cannot both be right. Both ends of a bad pair are
    flagged.

    Parameters
    ----------
    ij : (K, 2) ndarray of int
        Grid indices of the matches.
    ref_px, spot_px : (K, 2) ndarray
        Flat-water and wavy-water spot centres, pixels.
    margin_px : float
        ``dp / 2``: half the spot-position uncertainty, pixels.
    all_spots_px : (P, 2) ndarray, optional
        Every detected spot in the wavy image, pixels.

    Returns
    -------
    (K,) ndarray of bool
    """
    bad = np.zeros(len(ij), bool)
    if len(ij) == 0:
        return bad
    lat = _Lattice(ij)
    pairs = [(np.flatnonzero(nb >= 0), nb[nb >= 0]) for nb in map(lat.neighbour, _DIRS4[[0, 2]])]
    has = all_spots_px is not None and len(all_spots_px) > 0
    lookup = _SpotLookup(all_spots_px) if has else None
    return _order_violations(pairs, ref_px, spot_px, margin_px, lookup)


def _kept_order_violations(
    ref: ReferenceGrid, tab: _LatticeTables, kept: IntArray, spot_px: FloatArray,
    lookup: _SpotLookup | None, order_margin_px: float | None,
) -> BoolArray:
    """Which of the labelled nodes ``kept`` (their spots ``spot_px``) break eq. 33's order
    with a labelled grid neighbour (i + 1 or j + 1); the margin half the reference's pixel
    scale unless ``order_margin_px`` is given."""
    # Positions in ``kept``; the tables name a missing neighbour len(ref.ij): -1 here.
    where = np.full(len(ref.ij) + 1, -1)
    where[kept] = np.arange(len(kept))
    pairs = []
    for step in (0, 2):  # _DIRS4: (1, 0), (0, 1)
        nb = where[tab.nbrs4[kept, step]]
        pairs.append((np.flatnonzero(nb >= 0), nb[nb >= 0]))
    margin = 0.5 * ref.pixel_scale if order_margin_px is None else order_margin_px
    return _order_violations(pairs, ref.ref_px[kept], spot_px, margin, lookup)


def _order_violations(
    pairs: list[tuple[IntArray, IntArray]],
    ref_px: FloatArray,
    spot_px: FloatArray,
    margin_px: float,
    lookup: _SpotLookup | None,
) -> BoolArray:
    """:func:`order_violations` given the neighbour pairs ``(a, b)`` along rows and along
    columns, and the detected spots bucketed for lookup (or None)."""
    bad = np.zeros(len(spot_px), bool)
    if lookup is None:
        lookup = _SpotLookup(np.zeros((0, 2)))
    lo, shape, start, order, cell = lookup.cells
    for a, b in pairs:
        order_pairs(
            np.ascontiguousarray(a), np.ascontiguousarray(b), np.ascontiguousarray(ref_px, float),
            np.ascontiguousarray(spot_px, float), float(margin_px), lookup.xy, lo, shape, start,
            order, cell, bad,
        )
    return bad


def _anchor_shift(
    tab: _LatticeTables, matched: BoolArray, absent: BoolArray, max_shift: int
) -> tuple[IntArray, IntArray]:
    """Lattice shift that best explains where spots are and are not, and all shifts that tie
    with it (C, 2), best first.

    A shift ``d`` relabels node ``ij`` as ``ij + d``. Its cost counts the contradictions: each
    matched node that would not be a lit dot (weight 3: a spot where no dot shines), and each
    node seen empty (``absent``: nothing there although it is in view) that would be a lit dot.
    Near the pattern's visible boundary or its unlit marker dots only the right shift is free of
    contradictions; elsewhere all shifts tie, and the unshifted labelling is kept.

    The counts for all shifts at once are cross-correlations, on the lattice grid, of the lit
    dots with the matched and with the absent nodes.
    """
    s = max_shift
    lit = np.pad(tab.lit_grid, s).astype(np.float32)  # nothing is lit off the lattice

    def lit_at(nodes: BoolArray) -> FloatArray:  # (2s + 1, 2s + 1) indexed [dj, di]
        grid = np.zeros(tab.lat.grid.shape, np.float32)
        q = tab.lat.ij[nodes] - tab.lat.lo
        grid[q[:, 1], q[:, 0]] = 1.0
        return np.rint(cv2.matchTemplate(lit, grid, cv2.TM_CCORR))

    cost = 3 * (matched.sum() - lit_at(matched)) + lit_at(absent)
    cost = cost.T.ravel().astype(np.int64)  # shift (di, dj), di slowest
    r = np.arange(-s, s + 1)
    shifts = np.stack(np.meshgrid(r, r, indexing="ij"), axis=-1).reshape(-1, 2)
    best = cost.min()
    tied = np.flatnonzero(cost <= best + 3 + best // 4)
    # Among ties, the labelling nearest to flat water first (the unshifted one if it ties).
    tied = tied[np.lexsort((np.abs(shifts[tied]).sum(axis=1), cost[tied]))]
    zero = (shifts[tied] == 0).all(axis=1)
    pick = tied[np.flatnonzero(zero)[0]] if zero.any() else tied[
        np.argmin(np.abs(shifts[tied]).sum(axis=1))
    ]
    return shifts[pick].astype(np.int64), shifts[tied].astype(np.int64)


DIM_FLUX = 0.1
"""A spot whose flux is under this fraction of its matched neighbours' (their median) is no
sign of a lit dot in the anchoring: it is light scattered into a dark node's place (by rough
water or a caustic's skirt). At GGX alpha 0.01 the faint spots the growth finds at unlit marker
dots carry 1-4 % of their neighbours' flux, lit dots' own spots over half (1st percentile)."""


def _neighbour_flux(tab: _LatticeTables, match: IntArray, flux: FloatArray) -> FloatArray:
    """Median flux of each node's matched 8-neighbours' spots (n,); NaN where fewer than two
    are matched."""
    spot_flux = np.full(len(match) + 1, np.nan)
    spot_flux[:-1][match >= 0] = flux[match[match >= 0]]
    around = np.sort(spot_flux[tab.nbrs8], axis=1)  # NaN last
    k = np.sum(np.isfinite(around), axis=1)
    rows = np.arange(len(around))
    lo, hi = around[rows, np.maximum((k - 1) // 2, 0)], around[rows, np.maximum(k // 2, 0)]
    return np.where(k >= 2, 0.5 * (lo + hi), np.nan)


def _absent_nodes(
    tab: _LatticeTables, g: _Growth, lookup: _SpotLookup, spacing: FloatArray,
    visible: _Outline, flux: FloatArray,
) -> tuple[BoolArray, BoolArray]:
    """The anchoring's evidence: nodes seen empty, and nodes seen lit (n,) each.

    Seen empty: unmatched, predicted from at least two matched neighbours to a place well
    inside the visible area where no spot lies within half a spacing, or only a dim one
    (:data:`DIM_FLUX`); and matched nodes whose spot is dim. Seen lit: the other matched
    nodes."""
    matched = g.match >= 0
    around = _neighbour_flux(tab, g.match, flux)
    dim = np.zeros(len(matched), bool)
    dim[matched] = flux[g.match[matched]] < DIM_FLUX * around[matched]  # NaN: not dim
    cand = g.tried & ~matched & (np.append(matched, False)[tab.nbrs8].sum(axis=1) >= 2)
    idx = np.flatnonzero(cand)
    idx = idx[visible.inside(g.pred_px[idx], spacing[idx])]
    dist, spot, _ = lookup.nearest(g.pred_px[idx], 0.5 * spacing[idx] + 1.0)
    near = dist <= 0.5 * spacing[idx]
    faint = np.zeros(len(idx), bool)
    faint[near] = flux[spot[near]] < DIM_FLUX * around[idx[near]]
    cand[:] = False
    cand[idx[~near | faint]] = True
    return cand | dim, matched & ~dim


def _occupied(lat: _Lattice, nodes: IntArray) -> tuple[IntArray, BoolArray]:
    """The nodes' places ``(col, row)`` (K, 2) on ``lat.grid``, and the grid's mask of them."""
    q = lat.ij[nodes] - lat.lo
    occupied = np.zeros(lat.grid.shape, bool)
    occupied[q[:, 1], q[:, 0]] = True
    return q, occupied


def _largest_component(lat: _Lattice, nodes: IntArray) -> BoolArray:
    """Which of ``nodes`` belong to their largest 4-connected piece of the lattice."""
    if len(nodes) == 0:
        return np.zeros(0, bool)
    q, occupied = _occupied(lat, nodes)
    labels, _ = ndimage.label(occupied)
    lab = labels[q[:, 1], q[:, 0]]
    return lab == np.argmax(np.bincount(lab)[1:]) + 1


JOIN_LINKS = 2
"""Lattice links that join a piece of whole squares to the checked ones: two close a loop
through the join, along which the slopes must integrate; one closes none."""


def _braced_piece(lat: _Lattice, nodes: IntArray) -> BoolArray:
    """Which of ``nodes`` have their labels checked by closed loops of matches: the corners of
    the largest piece of whole lattice squares (all four corners among ``nodes``; squares
    joined where they share a side), and of every other such piece joined to those by at
    least :data:`JOIN_LINKS` links.

    Ordering labels a spot relative to its neighbours, so only a closed loop of matches can
    contradict a label a whole dot off: a chain hanging off the rest, a column one dot wide or
    a patch joined by a single link can carry such labels unseen, and the surface through them
    reproduces their spots. Where there are no squares at all, the largest 4-connected piece
    (:func:`_largest_component`).
    """
    if len(nodes) == 0:
        return np.zeros(0, bool)
    q, occupied = _occupied(lat, nodes)
    # square (r, c) has corners (r, c), (r + 1, c), (r, c + 1), (r + 1, c + 1)
    square = occupied[:-1, :-1] & occupied[1:, :-1] & occupied[:-1, 1:] & occupied[1:, 1:]
    labels, n = ndimage.label(square)
    if n == 0:
        return _largest_component(lat, nodes)
    size = np.bincount(labels.ravel(), minlength=n + 1)
    size[0] = 0
    piece = np.zeros(lat.grid.shape, np.int64)  # each node's largest piece, 0: none
    for dr in (0, 1):
        for dc in (0, 1):
            corner = piece[dr : dr + labels.shape[0], dc : dc + labels.shape[1]]
            np.copyto(corner, labels, where=size[labels] > size[corner])
    links = np.zeros((n + 1, n + 1), np.int64)
    for a, b in ((piece[:-1], piece[1:]), (piece[:, :-1], piece[:, 1:])):
        across = (a > 0) & (b > 0) & (a != b)
        np.add.at(links, (a[across], b[across]), 1)
    links += links.T
    kept = np.zeros(n + 1, bool)
    kept[np.argmax(size)] = True
    while True:
        joined = ~kept & (links[:, kept].sum(axis=1) >= JOIN_LINKS)
        if not joined.any():
            break
        kept |= joined
    kept[0] = False
    return kept[piece[q[:, 1], q[:, 0]]]


def _relabel(
    lat: _Lattice, match: IntArray, reason: NDArray[np.int8], shift: IntArray
) -> tuple[IntArray, NDArray[np.int8], int]:
    """Move every node's result to node ``ij + shift``; also count matches shifted off the
    lattice."""
    if not shift.any():
        return match.copy(), reason.copy(), 0
    dest = lat.lookup(lat.ij + shift)
    ok = dest >= 0
    new_match = np.full_like(match, -1)
    new_reason = np.full_like(reason, _NONE)
    new_match[dest[ok]] = match[ok]
    new_reason[dest[ok]] = reason[ok]
    return new_match, new_reason, int(np.sum((match >= 0) & ~ok))
