"""Wavy-water correspondence: label the distorted pattern's spots with grid indices
(:func:`match_distorted`, which returns :class:`Matches`) by region growing over the reference
lattice from a confident seed, re-evaluating per wave only the nodes whose matched neighbours
changed; drop matches that break eq. 33's ordering (:func:`order_violations`), merged blobs and
doubly claimed spots; and anchor the labels, which ordering fixes only up to a whole-lattice
shift, on the pattern's visible boundary or its unlit marker dots. Also the per-frame step,
detection plus matching against a prepared reference (:func:`features_from_reference`), and all
steps from the two images (:func:`find_features`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.features._kernels import grow, seed_scores
from restoration.features._lattice import _LatticeTables
from restoration.features._outline import _Outline, _outline_px, _visible_outline
from restoration.features._types import BoolArray, FloatArray, IntArray
from restoration.features.camera_s import pinhole_spots
from restoration.features.detect import Spots, detect_spots
from restoration.features.ordering import (
    _AMBIGUOUS,
    _BORDER,
    _MERGED,
    _NONE,
    _ORDER,
    _UNLIT,
    _absent_nodes,
    _anchor_shift,
    _braced_piece,
    _Growth,
    _kept_order_violations,
    _relabel,
    _SpotLookup,
)
from restoration.features.reference import (
    ReferenceGrid,
    flag_diffuser_edge,
    prepare_reference,
)
from wai_core.config import SystemConfig
from wai_core.errors import RestorationFailed, WaiInputError
from wai_core.timings import Timings


@dataclass(frozen=True)
class Matches:
    """Correspondence between grid dots, their flat-water spot and their wavy-water spot.

    Attributes
    ----------
    ij : (K, 2) ndarray of int
        Grid index of each kept match.
    ref_px : (K, 2) ndarray
        Flat-water spot centre (detected, or predicted where ``observed`` is False), pixels.
    spot_px : (K, 2) ndarray
        Wavy-water spot centre, pixels.
    observed : (K,) ndarray of bool
        The dot's spot was also seen on flat water.
    counts : dict of str to int
        ``detected``: spots in the wavy image. ``reference``: dots seen on flat water.
        ``matched``: kept matches, of which ``matched_unobserved`` are dots not seen on flat water.
        Lattice nodes dropped: ``rejected_order`` (break eq. 33 with a grid neighbour),
        ``rejected_merged`` (their spot is a merged blob), ``rejected_ambiguous`` (two candidate
        spots, a spot claimed by two nodes, or no closed loop of matches through the node
        to check its label), ``rejected_border`` (spot cut by the image or
        diffuser edge, or saturated), ``rejected_unlit`` (matched to a node that is not a lit dot);
        after the surface, ``rejected_inconsistent`` (spots the surface built with them did not
        reproduce at all: :func:`restoration.structured_light.without_samples`).
        ``unmatched_reference``: dots seen on flat water but lost in the wavy image.
        ``unassigned_spots``: detected spots given to no dot. ``anchor_di``, ``anchor_dj``:
        lattice shift applied to the proximity labelling; ``anchor_candidates``: how many shifts
        fit the evidence equally well (1: the labelling is pinned by the pattern's visible
        boundary; more: it is only the one nearest to flat water). ``labels_ambiguous``: 1 when
        ``anchor_candidates > 1``, i.e. the labels may be shifted by whole grid steps; the
        pipeline reports it (with all counts, as ``feature_counts``).
    timings_ms : dict of str to float
        Wall time per step, ms: ``detect`` and ``match`` from :func:`features_from_reference`,
        plus ``reference`` and ``total`` from :func:`find_features`.
    alt_shifts : (C, 2) ndarray of int
        Lattice shifts, relative to ``ij``, that fit the lit/unlit evidence as well as the one
        applied (``[0, 0]`` included); more than one row when ``labels_ambiguous``. A caller
        with more evidence (:func:`restoration.pipeline.restore` uses the integrability of the
        slopes) may relabel ``ij + shift``.
    """

    ij: IntArray
    ref_px: FloatArray
    spot_px: FloatArray
    observed: BoolArray
    counts: dict[str, int]
    timings_ms: dict[str, float] = field(default_factory=dict)
    alt_shifts: IntArray = field(default_factory=lambda: np.zeros((1, 2), np.int64))

    def __len__(self) -> int:
        return int(self.ij.shape[0])


MAX_LABEL_SHIFT = 6
"""Largest whole-lattice shift of the labels the anchoring tries, dots (each way)."""

STRETCHED_MAX_LABEL_SHIFT = 2 * MAX_LABEL_SHIFT
"""Largest whole-lattice shift tried when anchoring labels grown by the lines' own steps (a
lattice stretched or squeezed far from flat water's spacing: its seed's nearest spot may be a
dot many spacings away), dots (each way)."""

# A growth that matches fewer than this fraction of the flat-water dots is tried once more from
# another seed (see match_distorted), and while the largest piece is under REGROW_PATCH of
# them (a patch grown from a seed in the confused part of the image), from further seeds, up to
# REGROW_SEEDS growths in all.
REGROW_BELOW = 0.5
REGROW_PATCH = 0.2
REGROW_SEEDS = 5


def _det2(m: FloatArray) -> FloatArray:
    """Determinants of 2 x 2 matrices (N, 2, 2)."""
    return m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]


def _choose_seed(
    tab: _LatticeTables,
    base_px: FloatArray,
    ref: ReferenceGrid,
    spots: Spots,
    lookup: _SpotLookup,
    accept: float,
    ratio: float,
    exclude: BoolArray | None = None,
) -> int:
    """Node whose nearest spot is most confidently its own, in a calm part of the image (and
    not ``exclude``, (G,) bool, if given).

    Among observed nodes whose nearest spot is close, unambiguous and usable, and so are those
    of at least 6 of their 8 neighbours (or as many as any node has), the score adds (in units
    of the local spacing) the largest displacement difference to a neighbour and the node's own
    displacement, plus the change of spot size from flat water (``|log|`` of the area ratio:
    near a caustic, focusing shrinks or swells spots and the displacement field is at its least
    smooth), plus a small pull towards the middle of the pattern.
    """
    n, spacing = len(base_px), ref.spacing_px
    obs = np.flatnonzero(ref.observed)  # only an observed node can be the seed or support it
    d1, i1, d2 = lookup.nearest(base_px[obs])
    good = (d1 < accept * spacing[obs]) & (d1 < ratio * d2) & ~spots.suspicious[i1]
    if exclude is not None:
        good &= ~exclude[obs]
    if not good.any():
        return -1
    ok = np.zeros(n + 1, bool)  # entry n: "no neighbour"
    ok[obs] = good
    disp = np.zeros((n + 1, 2))
    disp[obs] = lookup.xy[i1] - base_px[obs]
    cand = obs[good]
    spot = i1[good]
    with np.errstate(divide="ignore", invalid="ignore"):
        size = np.abs(0.5 * np.log(_det2(spots.cov_px2[spot]) / _det2(ref.cov_px2[cand])))
    size = np.where(np.isfinite(size), size, 0.0)
    cols = base_px[obs].T.copy()  # (2, K): NumPy reduces a long axis fastest
    centre = np.median(cols, axis=1)
    extent = (cols.max(axis=1) - cols.min(axis=1)).max() + 1.0
    # Per candidate (compiled): the largest displacement difference to an ok neighbour, its
    # own displacement and its distance from the middle, and the ok neighbours.
    score, n_ok = seed_scores(
        cand, tab.nbrs8, ok, disp, np.ascontiguousarray(base_px, float), centre, float(extent),
        np.ascontiguousarray(spacing, float), size,
    )
    score = np.where(n_ok >= min(6, int(n_ok.max())), score, np.inf)
    best = int(np.argmin(score))
    return int(cand[best]) if np.isfinite(score[best]) else -1


def _grow(
    tab: _LatticeTables,
    base_px: FloatArray,
    spacing: FloatArray,
    spots: Spots,
    lookup: _SpotLookup,
    seed: tuple[int, int],
    visible: _Outline,
    accept: float,
    ratio: float,
    max_step_ratio: float = 1.7,
    ray_steps: bool = False,
) -> _Growth:
    """Region growing over the lattice from ``seed = (node, spot)``, best-supported nodes first.

    Each wave predicts the frontier nodes' spots from their matched 8-neighbours (linear
    extrapolation along the grid line through two matched nodes where possible, else the
    neighbour's own displacement; averaged over directions) and finds the nearest spot; it is
    acceptable if within ``accept`` x spacing, at most ``ratio`` x as far as the second nearest,
    usable, claimed by no other node, and keeps the spacing along every grid line through matched
    neighbours within ``max_step_ratio`` either way (else it skips or doubles a spot). A wave
    accepts only the best tier present: nodes with at least 3 matched 8-neighbours and a
    clear-cut nearest spot, then with at least 2, then any, so the region fills in (interpolating)
    before it reaches out (extrapolating). Nodes not accepted stay on the frontier, unless
    predicted more than two spacings outside ``visible``; growth stops when a wave accepts
    nothing.

    A node's prediction and the tests on it change only when a node one or two steps back along
    one of its grid lines is accepted, so each wave re-evaluates just those nodes (compiled:
    :func:`restoration.features._kernels.grow`).
    """
    n = len(base_px)
    radius = accept * spacing
    # Beyond reach / (0.5 ratio) a second spot changes no test on a node whose nearest spot is
    # within reach (and on any other the tests do not matter): the search stops there.
    bound = float(radius.max()) / (0.5 * ratio) if n and ratio > 0 else np.inf
    # The visible outline as half-planes: a point is m px inside edge k where
    # xy . normal[k] - offset[k] = m.
    offset = np.einsum("mk,mk->m", visible.poly, visible.normal)
    match, claim, reason, pred, tried = grow(
        np.vstack([base_px, np.zeros((1, 2))]), lookup.xy,
        ~spots.suspicious, spots.merged, radius, -2.0 * spacing, tab.back, tab.fwd, tab.nbrs4,
        np.ascontiguousarray(visible.normal), offset, float(ratio), float(max_step_ratio),
        bound, lookup.cells, int(seed[0]), int(seed[1]), ray_steps,
    )
    return _Growth(match, reason, claim, pred, tried)


def _drop_double_claims(g: _Growth) -> None:
    """A spot within reach of a node that failed is claimed twice: trust neither claim."""
    failed = (g.match < 0) & (g.claim >= 0)
    holder = np.full(len(g.match), -1, np.int64)
    matched = np.flatnonzero(g.match >= 0)
    owner = np.full(int(max(g.match.max(), g.claim.max())) + 1, -1, np.int64)
    owner[g.match[matched]] = matched
    holder[failed] = owner[g.claim[failed]]
    held = holder[holder >= 0]
    g.match[held] = -1
    g.reason[held] = _AMBIGUOUS


def match_distorted(
    ref: ReferenceGrid,
    spots: Spots,
    *,
    accept: float = 0.35,
    ratio: float = 0.6,
    order_margin_px: float | None = None,
    visible_px: FloatArray | None = None,
    prior_px: FloatArray | None = None,
    anchor: bool = True,
    max_shift: int = MAX_LABEL_SHIFT,
) -> Matches:
    """Label the wavy-water spots with grid indices (robust ordering-based correspondence).

    1. Region growing over the lattice (:func:`_grow`) from the node whose nearest spot is most
       confidently its own (close to the flat-water position, or to ``prior_px``). A growth
       that matches under :data:`REGROW_BELOW` of the dots is tried again from a seed clear of
       it, and while the largest piece is a patch (:data:`REGROW_PATCH`) from further seeds
       clear of every piece and seed before (:data:`REGROW_SEEDS` growths in all), then
       across the lattice's lines by the first spot along each step (a lattice stretched or
       squeezed far from flat water's spacing, where one step at that spacing falls between
       spots: ``counts['regrown']`` 1 or 2); the largest piece is kept.
    2. Spots claimed by two nodes are dropped, then pairs that break eq. 33
       (:func:`order_violations`). Of what is left, the corners of the largest piece of whole
       lattice squares are kept, with the pieces joined to it by two links or more: a label
       is checked only around closed loops of matches, and a chain, a column one dot wide or
       a patch hanging off the rest by one link can be labelled a dot off unseen
       (:func:`~restoration.features.ordering._braced_piece`).
    3. Anchoring: growing fixes labels only up to a whole-lattice shift when spots move by more
       than half a spacing. The shift is chosen so that matched nodes are lit dots and in-view
       nodes seen empty are not (:func:`_anchor_shift`), and applied to all labels.
       ``counts['anchor_candidates']`` says whether it was unique. Shifts of up to
       ``max_shift`` dots are tried, :data:`STRETCHED_MAX_LABEL_SHIFT` after a growth along
       the lines' steps.

    Parameters
    ----------
    ref : ReferenceGrid
        Flat-water lattice (:func:`match_reference`).
    spots : Spots
        Spots detected in the wavy-water image.
    accept : float
        Acceptance radius, in units of the local spot spacing.
    ratio : float
        Largest allowed ratio of nearest to second-nearest spot distance.
    order_margin_px : float, optional
        ``dp / 2`` of eq. 33, pixels; default 0.5 px at the tuned spot size, scaled with the
        reference's calibrated one (:attr:`ReferenceGrid.pixel_scale`): a spot's position
        uncertainty grows with its size in pixels.
    visible_px : (M, 2) ndarray, optional
        Convex outline where a spot would be seen (diffuser within the image), pixels; default:
        the convex hull of the flat-water spots.
    prior_px : (G, 2) ndarray, optional
        Expected wavy-water position of each lattice node (e.g. from a previous frame), pixels;
        NaN where unknown. Default: the flat-water positions.
    anchor : bool
        Look for a lattice shift (step 3); off, the labelling nearest to flat water is kept.
    max_shift : int
        Largest lattice shift tried when anchoring, nodes.

    Returns
    -------
    Matches
    """
    n_obs = int(ref.observed.sum())
    counts = {
        "detected": len(spots), "reference": n_obs, "matched": 0, "matched_unobserved": 0,
        "rejected_order": 0, "rejected_merged": 0, "rejected_ambiguous": 0,
        "rejected_border": 0, "rejected_unlit": 0, "unmatched_reference": n_obs,
        "unassigned_spots": len(spots), "anchor_di": 0, "anchor_dj": 0, "anchor_candidates": 0,
        "labels_ambiguous": 0,
    }
    empty = Matches(
        np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool), counts
    )
    if n_obs == 0 or len(spots) == 0:
        return empty
    tab = ref.tables
    base = ref.ref_px
    if prior_px is not None:
        prior = np.asarray(prior_px, dtype=float)
        base = np.where(np.isfinite(prior), prior, base)
    lookup = _SpotLookup(spots.centres_px)
    if visible_px is None:
        hull = cv2.convexHull(ref.ref_px[ref.observed].astype(np.float32))[:, 0]
    else:
        hull = visible_px
    visible = _Outline.of(hull)

    def grow_from(exclude: BoolArray | None, ray_steps: bool = False
                  ) -> tuple[_Growth | None, int]:
        seed = _choose_seed(tab, base, ref, spots, lookup, accept, ratio, exclude)
        if seed < 0:
            return None, seed
        seed_spot = int(lookup.nearest(base[seed])[1][0])
        g = _grow(
            tab, base, ref.spacing_px, spots, lookup, (seed, seed_spot), visible, accept, ratio,
            ray_steps=ray_steps,
        )
        _drop_double_claims(g)
        return g, seed

    g, seed = grow_from(None)
    if g is None:
        return empty
    counts["regrown"] = 0
    # A fold of the pattern (a caustic) stops the growing, and a seed in the confused part of
    # the image grows only a patch: grow again from seeds clear of every piece and seed so
    # far, whose spots no piece has taken (a node beside a piece, seeded on the piece's own
    # spots, grows the piece again labelled a dot off), and keep the largest piece.
    cleared = np.zeros(len(ref.ij) + 1, bool)  # entry G: "no neighbour"
    taken = np.zeros(len(spots), bool)
    last = g
    for k in range(REGROW_SEEDS - 1):
        if np.sum(g.match >= 0) >= (REGROW_BELOW if k == 0 else REGROW_PATCH) * n_obs:
            break
        if k == 0:
            nearest_spot = lookup.nearest(base)[1]
        grown = np.flatnonzero(last.match >= 0)
        cleared[grown] = cleared[seed] = True
        cleared[tab.nbrs8[grown]] = cleared[tab.nbrs8[seed]] = True
        taken[last.match[grown]] = True
        cleared[:-1] |= taken[nearest_spot]
        last, seed = grow_from(cleared[:-1])
        if last is None:
            break
        if np.sum(last.match >= 0) > np.sum(g.match >= 0):
            g, counts["regrown"] = last, 1
    if np.sum(g.match >= 0) < REGROW_BELOW * n_obs:
        # Still small: the lattice may be stretched or squeezed past a step at flat water's
        # spacing (a strong lens of the waves, denser dots behind a port); grow across its
        # lines by the first spot along each step.
        other, _ = grow_from(None, ray_steps=True)
        if other is not None and np.sum(other.match >= 0) > np.sum(g.match >= 0):
            g, counts["regrown"] = other, 2

    shift, tied = np.zeros(2, np.int64), np.zeros((1, 2), np.int64)
    if anchor:
        absent, seen_lit = _absent_nodes(tab, g, lookup, ref.spacing_px, visible, spots.flux)
        reach = max(max_shift, STRETCHED_MAX_LABEL_SHIFT) if counts["regrown"] == 2 \
            else max_shift
        shift, tied = _anchor_shift(tab, seen_lit, absent, reach)
    n_tied = len(tied)
    match, reason, n_off = _relabel(tab.lat, g.match, g.reason, shift)
    counts.update(
        anchor_di=int(shift[0]), anchor_dj=int(shift[1]), anchor_candidates=n_tied,
        labels_ambiguous=int(n_tied > 1),
    )

    kept = np.flatnonzero(match >= 0)
    spot_px = spots.centres_px[match[kept]]
    bad = _kept_order_violations(ref, tab, kept, spot_px, lookup, order_margin_px)
    reason[kept[bad]] = _ORDER
    unlit = ~ref.lit[kept] & ~bad
    reason[kept[unlit]] = _UNLIT
    kept = kept[~bad & ~unlit]
    # Labels are checked only around closed loops of matches: keep the pieces of whole lattice
    # squares that such loops join.
    main = _braced_piece(tab.lat, kept)
    reason[kept[~main]] = _AMBIGUOUS
    kept = kept[main]
    lost = np.ones(len(ref.ij), bool)
    lost[kept] = False
    why = reason[lost & ref.lit]  # virtual and unlit nodes are nobody's loss
    counts.update(
        matched=int(len(kept)),
        matched_unobserved=int(np.sum(~ref.observed[kept])),
        rejected_order=int(np.sum(why == _ORDER)),
        rejected_merged=int(np.sum(why == _MERGED)),
        rejected_ambiguous=int(np.sum(why == _AMBIGUOUS)),
        rejected_border=int(np.sum(why == _BORDER)),
        rejected_unlit=int(np.sum(reason == _UNLIT)) + n_off,
        unmatched_reference=int(np.sum(lost & ref.observed & (reason == _NONE))),
        unassigned_spots=int(len(spots) - len(kept)),
    )
    return Matches(
        ref.ij[kept], ref.ref_px[kept], spots.centres_px[match[kept]], ref.observed[kept], counts,
        alt_shifts=tied - shift,
    )


def find_features(
    pattern_img: NDArray,
    pattern_flat_img: NDArray,
    cfg: SystemConfig,
    *,
    lit: BoolArray | None = None,
    min_features: int = 16,
) -> Matches:
    """Detect, predict and match: grid index, flat and wavy spot centre of every usable dot.

    Parameters
    ----------
    pattern_img : (h, w) or (h, w, 3) ndarray
        Camera-s image of the pattern over the wavy water (linear intensity).
    pattern_flat_img : (h, w) or (h, w, 3) ndarray
        The same over flat water (the reference).
    cfg : SystemConfig
        System calibration; camera s must be ``w x h`` pixels.
    lit : (K,) ndarray of bool, optional
        Dots the projector lit, in :func:`~wai_core.pattern.dot_grid` order (default: those the
        renderer lights, :func:`wai_core.layout.lit_dots`).
    min_features : int
        Fewest kept matches accepted.

    Returns
    -------
    Matches
        With ``timings_ms`` for ``detect`` and ``match`` (:func:`features_from_reference`),
        ``reference`` (the flat frame's grid) and ``total``.

    Raises
    ------
    WaiInputError
        On bad images (shape, NaN).
    RestorationFailed
        On fewer than ``min_features`` matches (or features on flat water).
    """
    cam = cfg.camera_s
    for name, img in (("pattern", pattern_img), ("flat pattern", pattern_flat_img)):
        if np.shape(img)[:2] != (cam.height_px, cam.width_px):
            raise WaiInputError(
                f"{name} image is {np.shape(img)[:2]}, camera s is {cam.height_px}x{cam.width_px}"
            )
    timings = Timings()
    with timings("total"):
        with timings("reference"):
            if not np.isfinite(pattern_img).all():
                raise WaiInputError("pattern image holds NaN or inf")
            ref = prepare_reference(pattern_flat_img, cfg, lit=lit, min_features=min_features)
        matches = features_from_reference(pattern_img, ref, cfg, min_features=min_features)
    matches.timings_ms.update(timings.ms)
    return matches


def detect_frame(pattern_img: NDArray, ref: ReferenceGrid, cfg: SystemConfig) -> Spots:
    """The spots of one wavy frame (sized as camera s, checked), at the reference's spot scale,
    those cut by the diffuser's edge flagged: what either matcher starts from."""
    cam = cfg.camera_s
    if np.shape(pattern_img)[:2] != (cam.height_px, cam.width_px):
        raise WaiInputError(
            f"pattern image is {np.shape(pattern_img)[:2]}, camera s is "
            f"{cam.height_px}x{cam.width_px}"
        )
    outline = _outline_px(cfg) if ref.outline_px is None else ref.outline_px
    spots = pinhole_spots(detect_spots(pattern_img, scales=ref.spot_scales), cfg)
    return flag_diffuser_edge(spots, outline)


def visible_outline(ref: ReferenceGrid, cfg: SystemConfig) -> FloatArray:
    """Where camera s can see a spot (M, 2), pixels: the reference's
    (:attr:`ReferenceGrid.visible_px`), or from ``cfg`` for a grid built without one."""
    return _visible_outline(cfg) if ref.visible_px is None else ref.visible_px


def features_from_reference(
    pattern_img: NDArray, ref: ReferenceGrid, cfg: SystemConfig, *, min_features: int = 16,
) -> Matches:
    """Detect the spots of one wavy frame and match them to a prepared reference grid
    (:func:`restoration.features.track.features_tracked` labels them from a video's previous
    frames first).

    Raises
    ------
    WaiInputError
        On a bad image (shape, NaN).
    RestorationFailed
        On fewer than ``min_features`` matches.
    """
    return labelled_features(
        pattern_img, ref, cfg,
        lambda wavy, visible: match_distorted(ref, wavy, visible_px=visible), min_features,
    )


def labelled_features(
    pattern_img: NDArray, ref: ReferenceGrid, cfg: SystemConfig,
    label: Callable[[Spots, FloatArray], Matches], min_features: int,
) -> Matches:
    """The frame's spots detected, then labelled by ``label(spots, visible_px)``, both timed;
    :class:`RestorationFailed` on fewer than ``min_features`` labels."""
    timings = Timings()
    with timings("detect"):
        wavy = detect_frame(pattern_img, ref, cfg)
    with timings("match"):
        matches = label(wavy, visible_outline(ref, cfg))
    if len(matches) < min_features:
        raise RestorationFailed(f"too few features matched: {len(matches)} (need {min_features})")
    matches.timings_ms.update(timings.ms)
    return matches
