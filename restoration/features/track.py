"""Label a video frame's spots from the previous frames' labelled spots (tracking).

Each labelled spot of the previous frames is extrapolated to this frame (from its last one,
two or three positions) and its nearest detected spot takes its label when it is clearly the
nearest (:func:`track_spots`). Nodes next to the tracked ones (dots entering the view, or
rejected last frame) are then predicted from their tracked neighbours' displacements and
labelled the same way. The result is checked as region growing's labels are
(:func:`~restoration.features.match.match_distorted`): eq. 33's ordering, lit nodes, one
connected piece, and the lit/unlit evidence of the pattern's boundary and marker dots must not
prefer another lattice shift. A labelling is refused (None, and the caller matches the frame
in full) when it fails a check, finds too few of the previous frame's labels again, or when
the extrapolated spots are found more than a tenth of a spacing away (median): where spots
move by a good part of a spacing between frames, a spot's nearest prediction may be its
neighbour's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from restoration.features._lattice import _Lattice
from restoration.features._types import BoolArray, FloatArray, IntArray
from restoration.features.detect import Spots
from restoration.features.match import (
    MAX_LABEL_SHIFT,
    Matches,
    _Outline,
    labelled_features,
    match_distorted,
)
from restoration.features.ordering import (
    _anchor_shift,
    _braced_piece,
    _kept_order_violations,
    _SpotLookup,
)
from restoration.features.reference import ReferenceGrid
from wai_core.config import SystemConfig

__all__ = ["TRACK_FIRST", "TRACK_KEEP", "TRACK_MISS", "TrackedSpots", "features_tracked",
           "track_spots"]

TRACK_KEEP = 0.8
"""A tracked labelling must keep at least this fraction of the previous frame's labels."""

TRACK_FIRST = 0.9
"""Fewest of the previous frame's labels, as a fraction, that the predicted positions alone
must find again before the rest is labelled from their neighbours."""

TRACK_MISS = 0.1
"""Largest median distance, in spacings, between the predicted and the found spots for the
tracked labels to be trusted."""

TRACK_REACH = 0.35
"""Farthest a tracked spot may lie from its prediction, in units of the local spacing (the
region growing's acceptance radius)."""

TRACK_RATIO = 0.6
"""Largest ratio of the nearest to the second-nearest spot's distance from a prediction."""


@dataclass(frozen=True)
class TrackedSpots:
    """One frame's labelled spots, what the next frame's tracking starts from.

    Attributes
    ----------
    ij : (K, 2) ndarray of int
        Grid index of each spot.
    spot_px : (K, 2) ndarray
        Its centre in the wavy-water image, pixels.

    Examples
    --------
    >>> import numpy as np
    >>> TrackedSpots(np.zeros((0, 2), int), np.zeros((0, 2))).ij.shape
    (0, 2)
    """

    ij: IntArray
    spot_px: FloatArray

    @classmethod
    def of(cls, matches: Matches) -> TrackedSpots:
        """The labelled spots of ``matches``."""
        return cls(np.array(matches.ij, np.int64), np.array(matches.spot_px, float))


def _claim(
    nodes: IntArray, pred_px: FloatArray, spacing: FloatArray, lookup: _SpotLookup,
    usable: BoolArray, taken: BoolArray,
) -> tuple[IntArray, IntArray, IntArray]:
    """Nodes (of ``nodes``) whose prediction's nearest spot is clearly theirs: within
    :data:`TRACK_REACH` spacings, :data:`TRACK_RATIO` x nearer than the second, usable, not
    ``taken`` and claimed by no other node. Returns those nodes, their spots, and the nodes
    with no spot at all within half a spacing."""
    reach = TRACK_REACH * spacing[nodes]
    d1, idx, d2 = lookup.nearest(pred_px, np.maximum(reach / TRACK_RATIO, 0.5 * spacing[nodes]))
    ok = (d1 < reach) & (d1 < TRACK_RATIO * d2)
    ok[ok] &= usable[idx[ok]] & ~taken[idx[ok]]
    # A spot claimed by two nodes is neither's.
    claims = np.bincount(idx[ok], minlength=len(usable))
    ok[ok] &= claims[idx[ok]] == 1
    empty = nodes[~(d1 <= 0.5 * spacing[nodes])]
    return nodes[ok], idx[ok], empty


def _neighbour_prediction(
    nbrs8: IntArray, match: IntArray, base_px: FloatArray, spot_px: FloatArray, nodes: IntArray,
    use: BoolArray | None = None,
) -> tuple[FloatArray, IntArray]:
    """Predicted positions (N, 2) px of ``nodes``: their ``base_px`` moved by the mean
    displacement from ``base_px`` of their matched 8-neighbours (those of ``use``, (G,), when
    given); and how many such neighbours each has."""
    m = match >= 0 if use is None else (match >= 0) & use
    nb = nbrs8[nodes]  # (N, 8), n where there is none
    has = np.append(m, False)[nb]
    disp = np.zeros((len(match) + 1, 2))
    on = np.flatnonzero(m)
    disp[on] = spot_px[match[on]] - base_px[on]
    count = has.sum(axis=1)
    mean = (disp[nb] * has[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    return base_px[nodes] + mean, count


# Extrapolation weights of the last one, two or three positions (most recent first): where
# the spot was, moving on at its last velocity, and with its last acceleration too.
_EXTRAPOLATE = ((1.0,), (2.0, -1.0), (3.0, -3.0, 1.0))


MAX_STEP_RATIO = 1.7
"""Largest ratio between consecutive steps along a grid line (the region growing's): a
larger one skips or doubles a spot."""


def _steady_steps(
    back: IntArray, match: IntArray, spot_px: FloatArray, nodes: IntArray, idx: IntArray
) -> BoolArray:
    """Which claims (node ``nodes[k]`` takes spot ``idx[k]``) keep, along every grid line
    through two labelled nodes behind it, the step to them within :data:`MAX_STEP_RATIO` of
    the step between them either way."""
    n = len(match)
    pos = np.full((n + 1, 2), np.nan)
    on = np.flatnonzero(match >= 0)
    pos[on] = spot_px[match[on]]
    one, two = pos[back[nodes, :8]], pos[back[nodes, 8:]]  # (K, 8, 2)
    here = spot_px[idx][:, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.linalg.norm(here - one, axis=2) / np.linalg.norm(one - two, axis=2)
    wild = (ratio > MAX_STEP_RATIO) | (ratio < 1.0 / MAX_STEP_RATIO)  # NaN: no such line
    return ~wild.any(axis=1)


def _predicted(lat: _Lattice, n: int, history: Sequence[TrackedSpots]) -> FloatArray:
    """Where each of the ``n`` lattice nodes' spot should be now (G, 2) px, NaN where unknown:
    extrapolated from the most recent frames of ``history`` (most recent first, at most
    three) that all saw it (a spot every frame saw moves on with its last acceleration)."""
    past = np.full((len(history), n, 2), np.nan)
    for k, spots in enumerate(history):
        node = lat.lookup(spots.ij)
        past[k, node[node >= 0]] = spots.spot_px[node >= 0]
    seen = np.isfinite(past[..., 0])
    # How many of the most recent frames in a row saw each node.
    depth = np.cumprod(seen, axis=0).sum(axis=0)
    pred = np.full((n, 2), np.nan)
    for d, weights in enumerate(_EXTRAPOLATE[: len(history)], start=1):
        on = depth == d if d < len(history) else depth >= d
        pred[on] = np.tensordot(np.asarray(weights), past[:d, on], axes=1)
    return pred


def track_spots(
    ref: ReferenceGrid,
    spots: Spots,
    history: Sequence[TrackedSpots],
    visible_px: FloatArray,
    *,
    order_margin_px: float | None = None,
    max_shift: int = MAX_LABEL_SHIFT,
    rounds: int = 2,
) -> Matches | None:
    """Label ``spots`` from the previous frame's labelled spots, or None where that fails.

    Parameters
    ----------
    ref : ReferenceGrid
        The flat-water lattice.
    spots : Spots
        This frame's detected spots.
    history : sequence of TrackedSpots
        The labelled spots of the previous frames, the most recent first (up to three are
        used): each spot is predicted by extrapolating its last positions.
    visible_px : (M, 2) ndarray
        Convex outline where a spot can be seen, pixels.
    order_margin_px : float, optional
        ``dp / 2`` of eq. 33, pixels (default as :func:`match_distorted`'s).
    max_shift : int
        Largest lattice shift the anchoring check compares with, nodes.
    rounds : int
        Rounds of labelling the unlabelled neighbours of labelled nodes.

    Returns
    -------
    Matches or None
        As :func:`match_distorted` gives, ``counts['tracked']`` 1 (``alt_shifts`` the shifts
        the lit/unlit evidence cannot tell from the tracked labels, which then are
        ``labels_ambiguous`` as full matching's would be); None when the tracked labels break
        a check, another lattice shift fits the pattern's evidence better, or fewer than
        :data:`TRACK_KEEP` of the previous labels survive.

    Examples
    --------
    >>> import numpy as np
    >>> from restoration import Calibration
    >>> from restoration.features.match import detect_frame, visible_outline
    >>> from wai_core import load_system
    >>> from wai_core.io import read_exr
    >>> cal = Calibration(load_system("paper"))                       # doctest: +SKIP
    >>> ref = cal.prepare(read_exr("seq/pattern_flat.exr"))            # doctest: +SKIP
    >>> spots = detect_frame(read_exr("seq/frame001/pattern.exr"), ref, cal.cfg)  # doctest: +SKIP
    >>> tracked = track_spots(ref, spots, TrackedSpots.of(previous_matches),
    ...                       visible_outline(ref, cal.cfg))          # doctest: +SKIP
    """
    tab = ref.tables
    n = len(ref.ij)
    if not history or len(history[0].ij) == 0 or len(spots) == 0:
        return None
    n_previous = len(history[0].ij)
    lookup = _SpotLookup(spots.centres_px)
    usable = ~spots.suspicious
    taken = np.zeros(len(spots), bool)
    match = np.full(n, -1, np.int64)
    spacing = ref.spacing_px
    pred = _predicted(tab.lat, n, history[:len(_EXTRAPOLATE)])
    known = np.isfinite(pred[:, 0])
    nodes, idx, _ = _claim(np.flatnonzero(known), pred[known], spacing, lookup, usable, taken)
    # Where spots move by a good part of a spacing between frames, the extrapolation misses by
    # a part of one too, and a spot's nearest prediction may be its neighbour's: a small
    # typical miss is what makes the nearest spot's label trustworthy.
    miss = np.linalg.norm(spots.centres_px[idx] - pred[nodes], axis=1) / spacing[nodes]
    if len(nodes) == 0 or np.median(miss) > TRACK_MISS:
        return None
    match[nodes] = idx
    taken[idx] = True
    n_first = len(nodes)
    if n_first < TRACK_FIRST * n_previous:  # the prediction is lost: match in full
        return None

    # The rest from their labelled neighbours: a previous spot moved as its neighbours moved
    # from their predictions, a new one as they moved from flat water.
    base = np.where(known[:, None], pred, ref.ref_px)
    outline = _Outline.of(visible_px)
    absent = np.zeros(n, bool)
    for _ in range(rounds):
        frontier = np.zeros(n + 1, bool)
        frontier[tab.nbrs8[match >= 0]] = True
        frontier[:n] &= match < 0
        cand = np.flatnonzero(frontier[:n])
        at = np.empty((len(cand), 2))
        count = np.zeros(len(cand), np.int64)
        mine = known[cand]
        at[mine], count[mine] = _neighbour_prediction(
            tab.nbrs8, match, base, spots.centres_px, cand[mine], known)
        at[~mine], count[~mine] = _neighbour_prediction(
            tab.nbrs8, match, ref.ref_px, spots.centres_px, cand[~mine])
        # As the region growing: a node predicted more than two spacings outside the visible
        # outline is given up; one seen empty counts against a shift only well inside it.
        near = (count >= 2) & outline.inside(at, -2.0 * spacing[cand])
        cand, at = cand[near], at[near]
        # An unlit node has no spot of its own (its nearest is a neighbour's): it is never
        # claimed, but seen empty it is evidence for the labelling's shift.
        lit = ref.lit[cand]
        nodes, idx, empty = _claim(cand[lit], at[lit], spacing, lookup, usable, taken)
        dark = _claim(cand[~lit], at[~lit], spacing, lookup, usable, np.ones_like(taken))[2]
        empty = np.concatenate([empty, dark])
        inside = np.zeros(n, bool)
        inside[cand[outline.inside(at, spacing[cand])]] = True
        absent[:] = False
        absent[empty] = inside[empty]
        steady = _steady_steps(tab.back, match, spots.centres_px, nodes, idx)
        nodes, idx = nodes[steady], idx[steady]
        if len(nodes) == 0:
            break
        match[nodes] = idx
        taken[idx] = True

    kept = np.flatnonzero(match >= 0)
    spot_px = spots.centres_px[match[kept]]
    bad = _kept_order_violations(ref, tab, kept, spot_px, lookup, order_margin_px)
    unlit = ~ref.lit[kept]
    # Tracked labels are the previous frame's, which broke no order and sat on lit dots: a
    # tracked spot that now does is a wrong label, not a dropped one.
    if unlit.sum() > 0.02 * len(kept) or bad.sum() > 0.1 * len(kept):
        return None
    kept = kept[~bad & ~unlit]
    kept = kept[_braced_piece(tab.lat, kept)]
    if len(kept) < TRACK_KEEP * n_previous:
        return None
    matched = np.zeros(n, bool)
    matched[kept] = True
    shift, tied = _anchor_shift(tab, matched, absent & ~matched, max_shift)
    if not (tied == 0).all(axis=1).any():  # the pattern's evidence says the labels moved
        return None
    n_obs = int(ref.observed.sum())
    lost = np.ones(n, bool)
    lost[kept] = False
    counts = {
        "detected": len(spots), "reference": n_obs, "matched": int(len(kept)),
        "matched_unobserved": int(np.sum(~ref.observed[kept])),
        "rejected_order": int(bad.sum()), "rejected_merged": 0, "rejected_ambiguous": 0,
        "rejected_border": 0, "rejected_unlit": int(unlit.sum()),
        "unmatched_reference": int(np.sum(lost & ref.observed)),
        "unassigned_spots": int(len(spots) - len(kept)), "anchor_di": 0, "anchor_dj": 0,
        "anchor_candidates": int(len(tied)), "labels_ambiguous": int(len(tied) > 1),
        "tracked": 1, "tracked_first_pass": int(n_first),
    }
    return Matches(
        ref.ij[kept], ref.ref_px[kept], spots.centres_px[match[kept]], ref.observed[kept],
        counts, alt_shifts=np.asarray(tied, np.int64),
    )


def features_tracked(
    pattern_img: NDArray, ref: ReferenceGrid, cfg: SystemConfig,
    history: Sequence[TrackedSpots], *, min_features: int = 16,
) -> Matches:
    """:func:`~restoration.features.match.features_from_reference` with the spots labelled
    by tracking ``history`` (a video's previous frames' labelled spots, most recent first)
    and matched in full only where tracking's labels fail its checks.

    ``counts['tracked']`` is 1 for a tracked frame, 0 for a matched one, and
    ``counts['track_fallback']`` 1 where tracking was tried and refused.

    Raises
    ------
    RestorationFailed
        On fewer than ``min_features`` matches.
    """
    def label(wavy: Spots, visible: FloatArray) -> Matches:
        matches = track_spots(ref, wavy, history, visible) if history else None
        if matches is None:
            matches = match_distorted(ref, wavy, visible_px=visible)
            matches.counts.update(tracked=0, track_fallback=int(bool(history)))
        else:
            matches.counts["track_fallback"] = 0
        return matches

    return labelled_features(pattern_img, ref, cfg, label, min_features)
