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

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from restoration.features._decode_steps import (
    _OPPOSITE,
    _best_per_group,
    _consistent,
    _from_ordering,
    _grow_decoded,
    _lattice_check,
    _ordering_pairs,
    _votes,
    _Window,
)
from restoration.features._segments import _typical_flux
from restoration.features._types import FloatArray, IntArray
from restoration.features.detect import Spots
from restoration.features.match import Matches, detect_frame, match_distorted, visible_outline
from restoration.features.ordering import _largest_component
from restoration.features.reference import ReferenceGrid
from restoration.features.symbols import (
    MIN_DOT_FLUX,
    node_symbols,
    spot_symbols,
)
from wai_core.config import SystemConfig
from wai_core.errors import RestorationFailed
from wai_core.timings import Timings

__all__ = ["Decoded", "decode_distorted", "features_from_code"]


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
    sigma = ref.detect_sigma_px
    sym, sym_conf, green, levels = spot_symbols(
        image, spots.in_image_px, 1.5 if sigma is None else sigma
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
