"""The level of a surface known up to its level, read off camera s's pattern without labels
(``schlieren-sl`` where the structured light gives none).

Synthetic Schlieren's slopes fix a surface's shape but not its level: at another level they
bend into another, nearly integrable shape (:mod:`restoration.schlieren`). Camera s's image
holds what pins it. Every projector dot reflects off the surface onto the diffuser, and where
its spot lands depends on the height the ray meets as well as on the slope there (on the
paper's rig about 1.7 px of the spot's shift per mm of level, mostly along the projector's
tilt). Where the structured light cannot label its spots (the caustics of capillary waves,
the merged spots of rough water, a flat reference it refuses) the spots are still in the
image: this search predicts every dot's spot from the surface rebuilt at a level and keeps
the level whose predictions land on detected spots. No spot needs a label; once the level is
found, the same predictions give labels where they are clear (:func:`dots_on_spots`, which
inverse rendering's fit from Schlieren's surface starts from).

Search
------
1. Coarse: a level every :data:`COARSE_STEP_MM` over the search range about the start (the
   gauge's h0), each surface rebuilt with few refinement passes; the score is the RMS of each
   predicted spot's distance to its nearest detected spot, capped at half the dot spacing.
2. Fine: from each of the :data:`CANDIDATES` lowest local minima, Gauss-Newton on the level.
   A dot whose prediction lies within :data:`MATCH_FRACTION` of the spacing of a detected spot
   (that spot less the dot's flat-water shift, the rough lobe's and the rig's bias the
   reference shows) gives a level step along its prediction's change with the level; the
   median step is taken until it falls below :data:`STEP_TOL_MM`.
3. The candidate with the lowest matched score (:attr:`PatternLevel.score`) is the level. A
   level one dot spacing away (about 6 mm on the paper's rig) can fit nearly as well, so the
   ratio of the best score to the runner-up's says whether the level is unique: past
   :data:`MAX_ALIAS_RATIO` it is ``uncertain_level``. So it is where the matched spots miss
   their predictions by more than :data:`MAX_RESIDUAL_FRACTION` of the spacing (median):
   spots that blurred (rough water's lobes lie along the projector's tilt, as the level's
   shift does) place the level a tenth of a millimetre or more off.

On the compare cases where the structured light is weak (U = 1 and 1.5 m/s, seeds 0 and 1,
8 frames each of GGX alpha 0.02, capillary cut-offs 5 and 6 omega_p and steep waves: 128
frames, 88 of them ones the structured light fails or leaves past 0.1 mm), at the level found
here 103 frames lie within 0.1 mm (ratios 0.001-0.704), 13 within 0.1-0.25 mm (0.45-0.90)
and 12 past 0.25 mm (0.77-1.0). The matched spots' median miss: 0.04-0.32 px on smooth
water, 0.68-1.34 px at alpha 0.02, whose levels lie up to 0.3 mm off (docs/results.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from restoration.calibration import Calibration
from restoration.consistency import predict_spots_px
from restoration.ray_surface import points_on_lines
from restoration.schlieren import Rebuild
from wai_core.errors import RestorationFailed
from wai_core.heightfield import Heightfield

__all__ = ["CANDIDATES", "COARSE_STEP_MM", "LABEL_RATIO", "LABEL_REACH", "MATCH_FRACTION",
           "MAX_ALIAS_RATIO", "MAX_RESIDUAL_FRACTION", "STEP_TOL_MM", "PatternLevel",
           "dot_crossings_mm", "dots_on_spots", "find_pattern_level", "predicted_spots_px"]

Array = NDArray[np.float64]

COARSE_STEP_MM = 1.0
"""Levels between the coarse search's probes, mm (the fine search's basin is about +-1.5 mm
wide on the paper's rig)."""
CANDIDATES = 3
"""Coarse local minima refined."""
MATCH_FRACTION = 0.15
"""A predicted spot is matched to the nearest detected spot within this fraction of the
median dot spacing."""
STEP_TOL_MM = 0.002
"""The Gauss-Newton steps stop once the median step falls below this, mm."""
MAX_STEPS = 6
"""Most Gauss-Newton steps per candidate."""
MAX_STEP_MM = 0.5
"""Largest Gauss-Newton step, mm (the matched spots lose their match past about a spacing's
0.15 of shift)."""
MIN_CHANGE_PX_PER_MM = 0.5
"""Dots whose spot moves less than this with the level do not weigh it, px per mm."""
DERIVATIVE_MM = 0.05
"""The level step of the finite difference that gives each spot's change with the level, mm."""
MAX_ALIAS_RATIO = 0.7
"""The best level's score over the runner-up's past which the level is ``uncertain_level``:
on the compare cases (module notes) frames within 0.1 mm 0.001-0.704, past 0.25 mm 0.77-1.0."""
MAX_RESIDUAL_FRACTION = 0.04
"""The matched spots' median miss, as a fraction of the median dot spacing, past which the
level is ``uncertain_level``: on the paper's rig (13 px spacing) 0.52 px, between smooth
water's 0.04-0.32 px and rough water's (alpha 0.02) 0.68-1.34 px."""
LABEL_REACH = 0.25
"""A dot takes the label of the detected spot nearest its prediction within this fraction of
the median dot spacing (:func:`dots_on_spots`)."""
LABEL_RATIO = 0.6
"""... and only when that spot is this much nearer than the second nearest (the tracking's
rule, :data:`restoration.features.track.TRACK_RATIO`)."""


@dataclass(frozen=True)
class PatternLevel:
    """The level :func:`find_pattern_level` found.

    Attributes
    ----------
    level_mm : float
        The samples' mean height at the level, mm.
    score : float
        Mean of each predicted spot's squared distance to its nearest detected spot, capped at
        the match radius, over the radius squared (0 for a perfect match, 1 for none).
    runner_up : float
        The same at the next best candidate (1.0 when there was none).
    matched_share : float
        Share of the predicted spots that were matched.
    residual_px : float
        Median distance of the matched spots, px.
    spacing_px : float
        The flat reference's median dot spacing, px.
    evaluations : int
        Surfaces rebuilt.

    Examples
    --------
    >>> from restoration import PatternLevel
    >>> found = PatternLevel(148.6, 0.3, 0.6, 0.5, 0.2, spacing_px=13.0, evaluations=70)
    >>> found.alias_ratio, found.unique, found.placed
    (0.5, True, True)
    """

    level_mm: float
    score: float
    runner_up: float
    matched_share: float
    residual_px: float
    spacing_px: float
    evaluations: int

    @property
    def alias_ratio(self) -> float:
        """``score / runner_up``: near 1 when a level one dot spacing away fits as well."""
        return float(self.score / self.runner_up) if self.runner_up > 0 else 1.0

    @property
    def unique(self) -> bool:
        """Whether the alias ratio is within :data:`MAX_ALIAS_RATIO`."""
        return self.alias_ratio <= MAX_ALIAS_RATIO

    @property
    def placed(self) -> bool:
        """Whether the matched spots' median miss is within :data:`MAX_RESIDUAL_FRACTION` of
        the spacing."""
        return bool(self.residual_px <= MAX_RESIDUAL_FRACTION * self.spacing_px)


def dot_crossings_mm(level_mm: float, cal: Calibration) -> tuple[Array, Array, Array]:
    """Every projector dot's ray, in the order of the rig's dots: origins (G, 3) mm,
    directions (G, 3), and where each crosses the plane ``z = level_mm`` (G, 3) mm."""
    origin, dirs = cal.cfg.rig.dot_rays
    origin = np.broadcast_to(np.asarray(origin, float), dirs.shape)
    return origin, dirs, points_on_lines(origin, dirs, level_mm)


def predicted_spots_px(heightfield: Heightfield, level_mm: float, cal: Calibration) -> Array:
    """Every projector dot's spot (G, 2) in camera s's pinhole px, reflected by
    ``heightfield`` (absolute heights, mm; each dot's ray started where it crosses
    ``level_mm``), in the order of the rig's dots; NaN where its ray misses the surface.
    Flat water's shift is not added
    (:meth:`~restoration.features.ReferenceGrid.flat_shift_at`)."""
    origin, dirs, crossing = dot_crossings_mm(level_mm, cal)
    return predict_spots_px(heightfield, origin, dirs, crossing, cal.camera_s,
                            cal.diffuser_z_mm)


def dots_on_spots(predicted_px: Array, spots_px: Array, spacing_px: float
                  ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Labels for detected spots from predictions: each dot whose predicted spot has one
    detected spot clearly nearest (within :data:`LABEL_REACH` of ``spacing_px``, and
    :data:`LABEL_RATIO` times nearer than the next) that no other dot claims.

    Parameters
    ----------
    predicted_px : (G, 2) ndarray
        Each dot's predicted spot, px (NaN: none).
    spots_px : (N, 2) ndarray
        The detected spots, px.
    spacing_px : float
        The dots' median spacing in the image, px.

    Returns
    -------
    dots, spots : (K,) ndarray of int
        The dots labelled (indices into ``predicted_px``) and their spots (into ``spots_px``).

    Examples
    --------
    >>> import numpy as np
    >>> predicted = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [np.nan, np.nan]])
    >>> spots = np.array([[10.5, 0.2], [0.4, 0.0], [25.0, 0.0]])
    >>> dots, found = dots_on_spots(predicted, spots, spacing_px=10.0)
    >>> dots.tolist(), found.tolist()
    ([0, 1], [1, 0])
    """
    spots_px = np.asarray(spots_px, float).reshape(-1, 2)
    dots = np.flatnonzero(np.isfinite(predicted_px).all(axis=1))
    if len(spots_px) < 2 or not len(dots):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    distance, nearest = cKDTree(spots_px).query(predicted_px[dots], k=2)
    ok = (distance[:, 0] < LABEL_REACH * spacing_px) & (
        distance[:, 0] < LABEL_RATIO * distance[:, 1])
    claims = np.bincount(nearest[ok, 0], minlength=len(spots_px))
    ok[ok] &= claims[nearest[ok, 0]] == 1
    return dots[ok].astype(np.int64), nearest[ok, 0].astype(np.int64)


class _Spots:
    """The detected spots (pinhole px) and every dot's predicted spot on a surface."""

    def __init__(self, spots_px: Array, cal: Calibration, rebuild: Rebuild) -> None:
        if cal.reference is None:
            raise RestorationFailed("the pattern's level needs the flat-water reference")
        self.tree = cKDTree(spots_px)
        self.spots_px = spots_px
        self.spacing_px = float(cal.reference.median_spacing_px)
        self.radius_px = MATCH_FRACTION * self.spacing_px
        self.shift_px = cal.reference.flat_shift_at(cal.cfg.rig.dot_ij)
        self.cal, self.rebuild, self.evaluations = cal, rebuild, 0

    def predict(self, level_mm: float, coarse: bool) -> Array:
        """Every dot's spot (G, 2) px from the surface at ``level_mm``; NaN off it."""
        surface = self.rebuild(level_mm, coarse)
        self.evaluations += 1
        return predicted_spots_px(surface.heightfield, level_mm, self.cal)

    def coarse_score(self, level_mm: float) -> float:
        px = self.predict(level_mm, True)
        distance = self.tree.query(px[np.isfinite(px).all(axis=1)])[0]
        cap = self.spacing_px / 2
        return float(np.sqrt(np.mean(np.minimum(distance, cap) ** 2))) if distance.size else cap

    def refine(self, level_mm: float) -> tuple[float, float, float, float]:
        """Gauss-Newton from ``level_mm``: the level, its score, matched share and residual."""
        for _ in range(MAX_STEPS):
            px = self.predict(level_mm, False)
            change = (self.predict(level_mm + DERIVATIVE_MM, False) - px) / DERIVATIVE_MM
            dots = np.flatnonzero(np.isfinite(px).all(axis=1) & np.isfinite(change).all(axis=1))
            distance, nearest = self.tree.query(px[dots])
            matched = distance < self.radius_px
            dots, nearest = dots[matched], nearest[matched]
            miss = self.spots_px[nearest] - self.shift_px[dots] - px[dots]
            slope = change[dots]
            weight = (slope ** 2).sum(axis=1)
            use = weight > MIN_CHANGE_PX_PER_MM ** 2
            if not use.any():
                break
            step = float(np.median((miss[use] * slope[use]).sum(axis=1) / weight[use]))
            level_mm += float(np.clip(step, -MAX_STEP_MM, MAX_STEP_MM))
            if abs(step) < STEP_TOL_MM:
                break
        px = self.predict(level_mm, False)
        distance = self.tree.query(px[np.isfinite(px).all(axis=1)])[0]
        if distance.size == 0:
            return level_mm, 1.0, 0.0, float("nan")
        matched = distance < self.radius_px
        score = float(np.mean(np.minimum(distance, self.radius_px) ** 2) / self.radius_px ** 2)
        residual = float(np.median(distance[matched])) if matched.any() else float("nan")
        return level_mm, score, float(matched.mean()), residual


def find_pattern_level(rebuild: Rebuild, spots_px: Array, cal: Calibration, start_mm: float,
                       search_mm: float) -> PatternLevel:
    """The level at which the surface ``rebuild`` gives sends the projector's dots onto the
    detected spots ``spots_px`` (N, 2, camera s's pinhole px), searched over ``start_mm`` +-
    ``search_mm`` (module notes).

    Parameters
    ----------
    rebuild : callable
        ``rebuild(level_mm, coarse)``: the surface with its samples' mean height at
        ``level_mm``, mm (:data:`~restoration.schlieren.Rebuild`).
    spots_px : (N, 2) ndarray
        The wavy pattern's detected spot centres, camera s's pinhole px.
    cal : Calibration
        The rig (its dots, camera s, the diffuser) and its prepared flat-water reference.
    start_mm, search_mm : float
        The search's centre and half-width, mm.

    Returns
    -------
    PatternLevel

    Raises
    ------
    RestorationFailed
        Without a flat-water reference, or when no level matches a spot.

    Examples
    --------
    >>> from restoration.pattern_level import find_pattern_level  # doctest: +SKIP
    >>> found = find_pattern_level(rebuild, spots_px, cal, 150.0, 20.0)  # doctest: +SKIP
    >>> round(found.level_mm, 2), found.unique  # doctest: +SKIP
    (148.61, True)
    """
    spots = _Spots(np.asarray(spots_px, float).reshape(-1, 2), cal, rebuild)
    n = int(round(search_mm / COARSE_STEP_MM))
    levels = start_mm + COARSE_STEP_MM * np.arange(-n, n + 1)
    scores = np.array([spots.coarse_score(float(h)) for h in levels])
    padded = np.concatenate([[np.inf], scores, [np.inf]])
    minima = np.flatnonzero((scores <= padded[:-2]) & (scores <= padded[2:]))
    minima = minima[np.argsort(scores[minima], kind="stable")][:CANDIDATES]
    found = sorted((spots.refine(float(levels[i])) for i in minima), key=lambda c: c[1])
    if not found or not found[0][2] > 0:
        raise RestorationFailed("no level sends the projector's dots onto the pattern's spots")
    level, score, share, residual = found[0]
    runner_up = found[1][1] if len(found) > 1 else 1.0
    return PatternLevel(float(level), score, float(runner_up), share, residual,
                        spots.spacing_px, spots.evaluations)
