"""Coded-pattern correspondence: label the wavy-water spots by their colour code, with no
ordering assumption (``[pattern] code = "colour"``; :func:`decode_distorted`, which returns the
same :class:`~restoration.features.match.Matches` as the ordering matcher).

Every dot carries one of four blue-green symbols (its green fraction ``G / (G + B)``,
:data:`wai_core.pattern.CODE_LEVELS`) and every two 3 x 3 windows of the grid within
:data:`~wai_core.pattern.CODE_REACH` dots differ in at least
:data:`~wai_core.pattern.CODE_MIN_DISTANCE` symbols (:func:`wai_core.pattern.code_array`).
Per frame:

1. **Symbols.** Each detected spot's green fraction is read from the Gaussian-smoothed G and B
   channels at its centre; four level centres are refined on the frame itself (1-D k-means
   from the nominal levels: a camera's channel crosstalk or the water's colour shifts them
   alike) and the spot takes the nearest, with a confidence (1 at a level, 0 half-way to the
   next); spots under :data:`MIN_SYMBOL_CONFIDENCE` (two colours mixed: overlapping spots)
   abstain. Specks, spots under :data:`MIN_DOT_FLUX` of a typical spot's flux (Monte Carlo
   fireflies, stray light), vote in step 3 but take no label: in a bright spot's skirt a speck
   shows that spot's colour, and as its label it would put the dot 7-19 px off its spot.
2. **Candidates.** Every lit dot of the spot's symbol whose flat-water spot lies within
   ``reach`` spacings: a hypothesis "spot p is dot k", i.e. a displacement ``d = x_p - r_k``.
3. **Window votes.** A hypothesis is voted for by each of the dot's 8 grid neighbours that has
   a hypothesis of its own with nearly the same displacement (within ``tol`` of the local
   spacing; a pair of opposite neighbours whose displacements are collinear with it within
   ``tol_second`` also counts, for both): the neighbour's spot is where this labelling puts it
   and shows the symbol the code puts there. The true label collects up to 8 votes; a label
   shifted by any offset within reach agrees with the true window on at most 6 of 9 dots (the
   code's distance), so it collects at most 5 on a smooth patch. Nothing assumes that
   neighbouring spots keep their order: only that a dot and most of its neighbours move alike.
4. **Decision.** A spot takes its best-voted label when the votes reach ``min_votes`` and beat
   the runner-up by ``min_margin``; a dot claimed by two spots goes to the better-voted one
   (neither on a tie).
5. **Growth.** Where the pattern is stretched, a dot's displacement differs from its
   neighbours' by more than ``tol``: wave by wave, an undecoded dot next to decoded ones takes
   the hypothesis of its own symbol nearest to the displacement they predict (midpoints of
   opposite pairs, straight-line extrapolations), within ``tol_grow`` spacings and clear of
   its next hypothesis. The symbol makes each step 4x less ambiguous than the plain grid's.
   Before growing, the ordering matcher's labels may join (``ordering``; what
   :func:`features_from_code` does): only where the spot shows the label's symbol and the
   spot and dot are still free, and judged by step 6 like any other. They join also beyond
   ``reach`` (a long wave's tilt moves whole patches 6-12 spacings at U = 1 m/s, where no
   window can be decoded), and where the plain grid leaves the labelling's lattice shift open
   the shift whose labels show their dots' symbols is applied. Past eq. 35's bound the
   ordering labels are often shifted: a shifted label shows the wrong symbol 3 times in 4,
   and the few that survive disagree with the decoded neighbours, so step 6 drops them.
   Steps 5 and 6 run twice: a wrong window label that step 6 drops frees the spot or dot
   of a right ordering label, which the second round lets join.
6. **Redundancy.** The decoded labels must form a consistent lattice: a label stays only while
   at least ``min_consistent`` grid neighbours were decoded and the displacement they predict
   (leaving it out) lies within ``2 tol_grow`` of its own; the others are counted
   (``rejected_inconsistent``) and dropped. The lattice alone passes a patch decoded one dot
   or more off where the pattern is folded (columns squeezed together, a neighbour's spot
   moved a whole dot), as its displacements vary more smoothly there than the true ones; the
   code does not. The labelling puts each undecoded neighbour of a label somewhere: when that
   is the label's own spot (two dots on one spot), or when at least ``min_mismatch`` of the
   spots met first on the way there (a fold squeezes a neighbour towards the label) show
   another symbol than the code's, and more than show the code's, the label is dropped
   (``rejected_window``) and both checks repeat. Last, pieces detached from the largest one
   are dropped.

Per-dot confidence (:class:`Decoded`): the votes over 8, the margin over the runner-up, the
symbol confidence, and the consistent neighbours.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from restoration.errors import RestorationFailed
from restoration.features._types import BoolArray, FloatArray, IntArray
from restoration.features.detect import Spots, _typical_flux
from restoration.features.match import (
    Matches,
    _largest_component,
    detect_frame,
    match_distorted,
    visible_outline,
)
from restoration.features.reference import ReferenceGrid
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.pattern import CODE_LEVELS, dot_codes
from wai_core.timings import Timings

__all__ = [
    "MIN_SYMBOL_CONFIDENCE",
    "Decoded",
    "decode_distorted",
    "features_from_code",
    "node_symbols",
    "spot_symbols",
]

MIN_SYMBOL_CONFIDENCE = 0.4
"""A spot whose green fraction lies farther than 0.6 of the half-gap from its level (two
colours mixed) casts and receives no vote."""

MIN_DOT_FLUX = 0.03
"""A spot with less than this share of a typical spot's flux (the detector's flux-weighted
median) is a speck, not a dot's spot: it votes but takes no label. On the paper's rig 2 of
about 9200 dots' spots lie under it, and the Monte Carlo specks that the detector keeps (about
220 a frame) carry 0.005-0.02."""


@dataclass(frozen=True)
class Decoded:
    """A decoded frame: the matches and each kept dot's confidence.

    Attributes
    ----------
    matches : Matches
        As :func:`~restoration.features.match.match_distorted` gives them; ``counts`` adds
        ``decode_candidates`` (hypotheses), ``decoded`` (labels taken before the lattice
        check), ``rejected_symbol`` (spots whose colour read as a mix), ``rejected_faint``
        (specks: spots under :data:`MIN_DOT_FLUX` of a typical spot's flux, which vote but take
        no label), ``rejected_weak``
        (best label under ``min_votes``), ``ordering_beyond_reach`` (ordering labels added as
        hypotheses beyond ``reach``), ``rejected_ambiguous`` (runner-up within
        ``min_margin``, or a dot claimed by two spots), ``rejected_inconsistent`` (dropped by
        the lattice check: the wrong decodes the redundancy caught), ``rejected_window``
        (consistent with the lattice but contradicted by the symbols of their windows'
        undecoded dots, or sharing their spot with one), ``rejected_detached``
        (decoded, but off the largest 4-connected piece, which alone the surface can level),
        ``rejected_border``
        (spots cut by the image or diffuser edge, merged or saturated).
    votes : (K,) ndarray of int
        Neighbour windows (of 8) that voted for each kept label.
    margin : (K,) ndarray of int
        Votes over the spot's runner-up label.
    symbol_confidence : (K,) ndarray
        Confidence of the spot's colour symbol, 0..1.
    consistent : (K,) ndarray of int
        Grid neighbours decoded independently with the same displacement.
    green_fraction : (P,) ndarray
        Measured ``G / (G + B)`` of every detected spot (NaN where dark).
    levels : (4,) ndarray
        The symbol levels refined on this frame.
    """

    matches: Matches
    votes: IntArray
    margin: IntArray
    symbol_confidence: FloatArray
    consistent: IntArray
    green_fraction: FloatArray
    levels: FloatArray

    @property
    def confidence(self) -> FloatArray:
        """Per kept dot, 0..1: the share of its 8 neighbour windows that voted for it, times
        its symbol's confidence."""
        return self.votes / 8.0 * self.symbol_confidence


def spot_symbols(
    image: NDArray, centres_px: FloatArray, sigma_px: float, levels: FloatArray | None = None
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray]:
    """Colour symbol of each spot from its green fraction ``G / (G + B)``.

    Parameters
    ----------
    image : (H, W, 3) ndarray
        Camera-s image, linear RGB.
    centres_px : (P, 2) ndarray
        Spot centres ``(col, row)``, pixels.
    sigma_px : float
        Spot standard deviation, pixels: the smoothing of the channels before sampling.
    levels : (L,) ndarray, optional
        Starting level centres (default :data:`~wai_core.pattern.CODE_LEVELS`), refined by
        three 1-D k-means steps on the spots whose colour is clear.

    Returns
    -------
    symbol : (P,) ndarray of int
        Index of the nearest level, -1 where the confidence is under
        :data:`MIN_SYMBOL_CONFIDENCE` or the spot is dark.
    confidence : (P,) ndarray
        ``1 - |g - level| / half-gap``, clipped to 0..1.
    green : (P,) ndarray
        The green fraction g (NaN where G + B is not positive).
    levels : (L,) ndarray
        The refined level centres.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] < 3:
        raise WaiInputError(
            "the coded pattern needs an RGB pattern image (H, W, 3), got shape "
            f"{np.shape(image)}"
        )
    s = max(float(sigma_px), 0.5)
    g_img = cv2.GaussianBlur(np.ascontiguousarray(img[..., 1], np.float32), (0, 0), s)
    b_img = cv2.GaussianBlur(np.ascontiguousarray(img[..., 2], np.float32), (0, 0), s)
    c = np.asarray(centres_px, np.float32).reshape(-1, 2)
    gs = cv2.remap(g_img, c[:, :1], c[:, 1:], cv2.INTER_LINEAR)[:, 0].astype(np.float64)
    bs = cv2.remap(b_img, c[:, :1], c[:, 1:], cv2.INTER_LINEAR)[:, 0].astype(np.float64)
    total = gs + bs
    green = np.where(total > 0, gs / np.where(total > 0, total, 1.0), np.nan)
    lev = np.asarray(CODE_LEVELS if levels is None else levels, np.float64).copy()
    finite = np.isfinite(green)

    def assign(lv: FloatArray) -> tuple[IntArray, FloatArray]:
        dist = np.abs(np.where(finite, green, -10.0)[:, None] - lv[None, :])
        sym = np.argmin(dist, axis=1)
        # Half the gap to the neighbouring level on the side the value lies.
        gaps = np.diff(lv)
        half = 0.5 * np.concatenate([[gaps[0]], np.minimum(gaps[:-1], gaps[1:]), [gaps[-1]]])
        conf = np.clip(1.0 - dist[np.arange(len(sym)), sym] / half[sym], 0.0, 1.0)
        return sym, np.where(finite, conf, 0.0)

    for _ in range(3):  # k-means on the clear spots; a level without any keeps its place
        sym, conf = assign(lev)
        clear = conf > 0.5
        sums = np.bincount(sym[clear], green[clear], len(lev))
        n = np.bincount(sym[clear], minlength=len(lev))
        lev = np.where(n > 0, sums / np.maximum(n, 1), lev)
    sym, conf = assign(lev)
    sym = np.where(conf >= MIN_SYMBOL_CONFIDENCE, sym, -1)
    return sym.astype(np.int64), conf, green, lev


def node_symbols(ref: ReferenceGrid, cfg: SystemConfig) -> IntArray:
    """Code symbol (G,) of every node of the reference lattice; -1 for virtual and unlit
    nodes (no spot can show their symbol)."""
    projector = cfg.rig.projector
    ij = cfg.rig.dot_ij
    codes = dot_codes(cfg.pattern, projector).astype(np.int64)
    lo = ij.min(axis=0)
    side = ij.max(axis=0) - lo + 1
    grid = np.full((side[1], side[0]), -1, np.int64)
    grid[ij[:, 1] - lo[1], ij[:, 0] - lo[0]] = codes
    q = ref.ij - lo
    inside = (q >= 0).all(axis=1) & (q[:, 0] < side[0]) & (q[:, 1] < side[1])
    out = np.full(len(ref.ij), -1, np.int64)
    out[inside] = grid[q[inside, 1], q[inside, 0]]
    return np.where(ref.lit, out, -1)


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


def decode_distorted(
    ref: ReferenceGrid,
    spots: Spots,
    image: NDArray,
    cfg: SystemConfig,
    *,
    reach: float = 6.0,
    tol: float = 0.4,
    tol_second: float = 0.25,
    max_jump: float = 0.5,
    min_votes: int = 5,
    min_margin: int = 2,
    min_consistent: int = 3,
    tol_grow: float = 0.3,
    min_flux: float = MIN_DOT_FLUX,
    tol_window: float = 0.35,
    min_mismatch: int = 2,
    ordering: Matches | None = None,
) -> Decoded:
    """Label the wavy-water spots by the pattern's colour code (see the module notes).

    Parameters
    ----------
    ref : ReferenceGrid
        Flat-water lattice (:func:`~restoration.features.reference.prepare_reference`).
    spots : Spots
        Spots detected in the wavy-water image.
    image : (H, W, 3) ndarray
        The wavy-water camera-s image (linear RGB) the spots came from.
    cfg : SystemConfig
        The rig; ``cfg.pattern`` gives the code.
    reach : float
        Largest displacement from flat water considered, in local spacings.
    tol : float
        Largest displacement difference between a dot and a neighbour voting alone, in local
        spacings.
    tol_second : float
        Largest second difference of the displacements of a dot and a voting pair of opposite
        neighbours, in local spacings.
    max_jump : float
        Largest displacement difference between a dot and a voting pair's members, spacings.
    min_votes, min_margin : int
        Fewest neighbour votes for a label, and fewest over the runner-up.
    min_consistent : int
        Fewest neighbours decoded with the same displacement for a label to stay.
    tol_grow : float
        Largest distance of a grown label's displacement from its neighbours' prediction,
        local spacings.
    min_flux : float
        Least flux of a labelled spot, as a share of a typical spot's (:data:`MIN_DOT_FLUX`).
    tol_window : float
        The window check's tolerance, local spacings: a label whose undecoded neighbour the
        labelling puts this near its own spot is ambiguous, and a spot this far from the ray
        to where it puts the neighbour is not the neighbour's (:func:`_contradicted`).
    min_mismatch : int
        Fewest spots of a label's undecoded neighbours showing another symbol than the code's
        that drop it (when they also outnumber those that agree): 2, so that one misread
        symbol (about 1 spot in 500 of the paper's rig) does not drop the 8 labels around it.
    ordering : Matches, optional
        The ordering matcher's labels of the same spots: those whose spot shows the code's
        symbol for the label, and whose spot and dot no decoded label holds, join the decoded
        ones before the growth; the lattice check then judges all alike. Where ordering holds
        (below eq. 35's bound) it labels the steep patches that the window votes miss, and the
        spots moved beyond ``reach``. Of its ``alt_shifts``, the one whose labels show their
        dots' symbols is applied.

    Returns
    -------
    Decoded
    """
    n_nodes = len(ref.ij)
    sym, sym_conf, green, levels = spot_symbols(
        image, spots.centres_px, ref.spot_sigma_px if np.isfinite(ref.spot_sigma_px) else 1.5
    )
    codes = node_symbols(ref, cfg)
    tab = ref.tables
    usable = ~spots.suspicious
    # Specks (Monte Carlo fireflies, stray light: ~1 % of a dot's flux) often sit in a bright
    # spot's skirt and show its colour: as a label they put the dot 7-19 px off its spot.
    bright = spots.flux >= min_flux * _typical_flux(spots.flux)
    counts = {
        "detected": len(spots), "reference": int(ref.observed.sum()), "matched": 0,
        "matched_unobserved": 0, "decode_candidates": 0, "decoded": 0,
        "rejected_symbol": int(np.sum(usable & (sym < 0))),
        "rejected_faint": int(np.sum(usable & (sym >= 0) & ~bright)), "rejected_weak": 0,
        "rejected_ambiguous": 0, "rejected_inconsistent": 0,
        "rejected_border": int(np.sum(~usable)), "unassigned_spots": len(spots),
        "anchor_candidates": 1, "labels_ambiguous": 0,
    }
    spacing = np.where(np.isfinite(ref.spacing_px), ref.spacing_px, np.nanmedian(ref.spacing_px))
    tols = ((tol * spacing) ** 2, (tol_second * spacing) ** 2, (max_jump * spacing) ** 2)
    radius = reach * float(np.nanmedian(spacing))
    # Hypotheses: (spot, node) pairs of the same symbol within the reach, all symbols at once
    # (a symbol offset far larger than the image keeps symbols apart in one tree).
    far = 1e6
    node_ok = (codes >= 0) & np.isfinite(ref.ref_px).all(axis=1)
    spot_ok = usable & (sym >= 0)
    n_id, s_id = np.flatnonzero(node_ok), np.flatnonzero(spot_ok)
    empty = Decoded(
        Matches(np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros((0, 2)),
                np.zeros(0, bool), counts),
        np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64),
        green, levels,
    )
    if len(n_id) == 0 or len(s_id) == 0:
        return empty
    tree_n = cKDTree(ref.ref_px[n_id] + far * codes[n_id, None])
    tree_s = cKDTree(spots.centres_px[s_id] + far * sym[s_id, None])
    pairs = tree_n.sparse_distance_matrix(tree_s, radius, output_type="ndarray")
    node = n_id[pairs["i"].astype(np.int64)]
    spot = s_id[pairs["j"].astype(np.int64)]
    order = np.argsort(node, kind="stable")
    node, spot = node[order], spot[order]
    disp = spots.centres_px[spot] - ref.ref_px[node]
    start = np.searchsorted(node, np.arange(n_nodes + 1))
    votes = _votes(node, np.ascontiguousarray(disp), start, tab.nbrs8, _OPPOSITE, *tols)
    # A speck votes (beside a dot's spot it shows that dot's symbol about where the dot is) but
    # takes no label: its centre is not the dot's.
    dot_like = bright[spot]
    node, spot, disp, votes = node[dot_like], spot[dot_like], disp[dot_like], votes[dot_like]
    spot_ok &= bright
    counts["decode_candidates"] = len(node)
    # The ordering labels farther than the reach from flat water (a long wave's tilt moves
    # whole patches 6-12 spacings at U = 1 m/s) join as hypotheses of their own: beyond the
    # reach no window can be compared with its rivals, so they neither vote nor are voted for,
    # and only the join, the symbol and the lattice check admit them.
    hyp_ord = np.zeros(0, np.int64)
    if ordering is not None and len(ordering):
        k_ord, p_ord = _ordering_pairs(ordering, ref, spots, node_ok, spot_ok, codes, sym)
        keys = node * len(spots) + spot
        want = k_ord * len(spots) + p_ord
        srt = np.argsort(keys)
        at = np.minimum(np.searchsorted(keys, want, sorter=srt), max(len(keys) - 1, 0))
        found = (keys[srt[at]] == want) if len(keys) else np.zeros(len(want), bool)
        hyp_ord = np.concatenate([srt[at[found]], len(node) + np.arange(int(np.sum(~found)))])
        node = np.concatenate([node, k_ord[~found]])
        spot = np.concatenate([spot, p_ord[~found]])
        disp = spots.centres_px[spot] - ref.ref_px[node]
        votes = np.concatenate([votes, np.zeros(int(np.sum(~found)), np.int64)])
    counts["ordering_beyond_reach"] = len(node) - counts["decode_candidates"]
    if len(node) == 0:
        return empty

    # Per spot: the best-voted label, if clear of the runner-up.
    best, second = _best_per_group(spot, votes, len(spots))
    has = best >= 0
    b = best[has]
    weak = votes[b] < min_votes
    unclear = ~weak & (votes[b] - second[has] < min_margin)
    counts["rejected_weak"] = int(weak.sum())
    take = b[~weak & ~unclear]
    # A dot claimed by two spots: the better-voted one, neither on a tie.
    claim_best, claim_second = _best_per_group(node[take], votes[take], n_nodes)
    owner = claim_best[node[take]]
    tied = votes[take] <= claim_second[node[take]]
    keep = (owner == np.arange(len(take))) & ~tied
    counts["rejected_ambiguous"] = int(unclear.sum() + np.sum(~keep))
    take = take[keep]
    counts["decoded_windows"] = len(take)
    # Join, grow, check; twice: a wrong window label the check drops may have held the spot or
    # the dot of a right ordering label, which the second round lets join.
    ever = np.zeros(len(node), bool)
    contradicted = np.zeros(len(node), bool)
    win = _Window(ref.ref_px, spacing, codes, spots.centres_px, sym, spot_ok, tol_window,
                  min_mismatch)
    joined = 0
    for round_ in range(2):
        new = _from_ordering(hyp_ord, node, spot, take, n_nodes, len(spots))
        if round_ and not len(new):
            break
        joined += len(new)
        take = np.concatenate([take, new])
        take = _grow_decoded(node, spot, disp, take, n_nodes, len(spots), tab, spacing, tol_grow)
        ever[take] = True
        take, dropped = _consistent(take, node, spot, disp, n_nodes, tab, spacing,
                                    min_consistent, tol_grow, win)
        contradicted[dropped] = True
    contradicted[take] = False
    counts["from_ordering"] = joined
    counts["decoded"] = int(ever.sum())
    counts["rejected_window"] = int(contradicted.sum())
    counts["rejected_inconsistent"] = counts["decoded"] - len(take) - counts["rejected_window"]
    # The surface integrates slopes along the lattice: pieces that touch no other decoded dot
    # have no height relative to the rest (their labels are right, their level is not known).
    main = _largest_component(tab.lat, node[take])
    counts["rejected_detached"] = int(np.sum(~main))
    take = take[main]
    cons, _ = _lattice_check(node[take], disp[take], n_nodes, tab, spacing)
    k, p = node[take], spot[take]
    counts.update(
        matched=len(take), matched_unobserved=int(np.sum(~ref.observed[k])),
        unassigned_spots=len(spots) - len(take),
    )
    margin = votes[take] - second[p]
    matches = Matches(ref.ij[k], ref.ref_px[k], spots.centres_px[p], ref.observed[k], counts)
    return Decoded(matches, votes[take], margin, sym_conf[p], cons, green, levels)


def features_from_code(
    pattern_img: NDArray, ref: ReferenceGrid, cfg: SystemConfig, *, min_features: int = 16
) -> Matches:
    """Detect the spots of one wavy frame and decode them (the coded pattern's counterpart of
    :func:`~restoration.features.match.features_from_reference`).

    Raises
    ------
    WaiInputError
        On a wrongly sized or grey image.
    RestorationFailed
        On fewer than ``min_features`` decoded dots.
    """
    timings = Timings()
    with timings("detect"):
        wavy = detect_frame(pattern_img, ref, cfg)
    with timings("match"):
        ordering = match_distorted(ref, wavy, visible_px=visible_outline(ref, cfg))
        matches = decode_distorted(ref, wavy, pattern_img, cfg, ordering=ordering).matches
    if len(matches) < min_features:
        raise RestorationFailed(f"too few features decoded: {len(matches)} (need {min_features})")
    matches.timings_ms.update(timings.ms)
    return matches
