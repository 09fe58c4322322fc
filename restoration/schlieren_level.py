"""Synthetic Schlieren with its level from the structured light on the same rig
(``--method schlieren-sl``).

Schlieren's slopes do not pin the level: at a wrong level they bend into another, nearly
integrable field, which the integration keeps (:mod:`restoration.schlieren`). At the gauge's
h0 that is what limits it: long waves raise or lower the whole patch camera v sees by
millimetres (3-31 mm on the frames of U = 1 m/s that miss 0.1 mm de-meaned, docs/results.md),
and its de-meaned error grows with that offset, from its 0.02 mm floor to 0.26 mm.

A rig with both systems knows the level from camera s's dots: the structured light's
surface, its level pinned by the slopes' integrability and by camera v's own view
(:class:`~restoration.view_level.StructuredLightView`), holds where its dots are clean and
keeps a level within a fraction of a millimetre where they blur (rough water), while
Schlieren's flow never looks at the pattern. This method runs that structured light first,
reconstructs Schlieren's surface at the gauge's level, moves the level to where the samples'
heights agree with the structured light's surface over the part of the patch both cover
(the median difference), and reconstructs it there (:func:`structured_light_level`).

Its status is Schlieren's (``sparse``, ``inconsistent``), then the two systems' agreement:
``inconsistent`` where Schlieren's heights and the structured light's surface, levelled, differ
by more than :data:`MAX_DIFFERENCE_MM` RMS over the part both cover; then the level's:
``uncertain_level`` where the structured light's level is (its standard error past its bound).

Where the structured light gives no level (a frame it failed or left ``sparse``, a flat
reference it refused, a surface covering less than :data:`MIN_SHARED` of Schlieren's samples)
its spots may still be in camera s's image: the level is searched where Schlieren's surface
sends the projector's dots onto them, no labels needed (:mod:`restoration.pattern_level`);
``uncertain_level`` where a level one dot spacing away fits nearly as well or the spots are
too blurred to place it. Only where that search finds nothing (or ``level_search_mm`` is 0)
is the level the gauge's, ``gauge_level``, as plain Schlieren's.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from restoration.calibration import LevelTrack
from restoration.features import detect_spots
from restoration.features.camera_s import pinhole_spots
from restoration.level import Anchor
from restoration.options import SchlierenOptions, StructuredLightOptions, checked_options
from restoration.pattern_level import (
    MAX_ALIAS_RATIO,
    MAX_RESIDUAL_FRACTION,
    PatternLevel,
    find_pattern_level,
)
from restoration.ray_surface import RaySurface
from restoration.result import RestoreResult, Status
from restoration.schlieren import LevelRule, Rebuild, restore_schlieren
from restoration.view_level import StructuredLightView, ViewLevelCalibration
from wai_core.errors import RestorationFailed

__all__ = ["MAX_DIFFERENCE_MM", "MIN_SHARED", "SchlierenLevelled", "pattern_anchor",
           "structured_light_level"]

MIN_SHARED = 0.25
"""The share of Schlieren's samples the structured light's surface must cover for its level to
be taken (the paper's rig at U = 1 m/s: 0.53-0.89)."""

MAX_DIFFERENCE_MM = 0.04
"""The RMS difference between Schlieren's heights and the structured light's surface over the
samples both cover, once levelled, past which the frame is ``inconsistent``: one of the two
shapes is wrong in a part. On the compare cases' rough frames (GGX alpha 0.01, 41 with a
level) right frames reach 0.038 mm and the four whose Schlieren shape is 0.115-0.367 mm off
0.046-0.126 mm; on smooth water 0.001-0.020 mm (docs/results.md)."""

LEVEL_STATUSES = (Status.OK, Status.UNCERTAIN_LEVEL)
"""The structured light's statuses whose level is taken (an uncertain one passes its verdict
on)."""


def pattern_anchor(found: PatternLevel) -> tuple[Anchor, tuple[Status, str] | None]:
    """The anchor of a level camera s's spots gave, and its verdict: None where it holds,
    ``uncertain_level`` where a level one dot spacing away fits nearly as well or the spots
    are too blurred to place it."""
    anchor = Anchor("pattern", found.level_mm, searched_mm=found.level_mm,
                    evaluations=found.evaluations, pattern_alias_ratio=found.alias_ratio,
                    pattern_matched_share=found.matched_share,
                    pattern_residual_px=found.residual_px)
    if not found.unique:
        return anchor, (Status.UNCERTAIN_LEVEL,
                        f"the level from camera s's spots is not unique: another level fits "
                        f"{found.alias_ratio:.2f} as well (more than {MAX_ALIAS_RATIO}), as one "
                        "a dot spacing away can")
    if not found.placed:
        return anchor, (Status.UNCERTAIN_LEVEL,
                        f"camera s's spots lie {found.residual_px:.2f} px (median) from where the "
                        f"surface sends the dots, more than {MAX_RESIDUAL_FRACTION:g} of their "
                        f"spacing: too blurred to place the level (rough water?)")
    return anchor, None


def structured_light_level(light: RestoreResult, gauge_mm: float,
                           search: Callable[[Rebuild], PatternLevel] | None = None
                           ) -> LevelRule:
    """The level rule (:data:`~restoration.schlieren.LevelRule`) that moves a Schlieren
    surface to the structured light's ``light`` (a frame's result): the samples' mean height
    shifted by the median of the structured light's heights less theirs where both are known.
    Where ``light`` gives no level: ``search``'s level (the surface's rebuild given, e.g.
    :func:`~restoration.pattern_level.find_pattern_level`; run once), else the gauge's
    ``gauge_mm`` with the verdict ``gauge_level``.

    Examples
    --------
    >>> import numpy as np
    >>> from restoration import RestoreResult, Status
    >>> rule = structured_light_level(RestoreResult("structured-light", Status.FAILED, "no"),
    ...                               150.0)
    >>> anchor, (status, _) = rule(None, None)
    >>> anchor.method, anchor.anchor_mm, str(status)
    ('gauge_fallback', 150.0, 'gauge_level')
    """
    searched: list[tuple[Anchor, tuple[Status, str] | None]] = []

    def gauge(why: str) -> tuple[Anchor, tuple[Status, str]]:
        return Anchor("gauge_fallback", float(gauge_mm)), (
            Status.GAUGE_LEVEL, f"{why}: the gauge's h0 was used")

    def fallback(why: str, rebuild: Rebuild | None) -> tuple[Anchor, tuple[Status, str] | None]:
        if search is None or rebuild is None:
            return gauge(why)
        if not searched:  # the rule is asked again at the level it gave
            try:
                searched.append(pattern_anchor(search(rebuild)))
            except RestorationFailed as exc:
                searched.append(gauge(f"{why}, and {exc}"))
        return searched[0]

    def rule(surface: RaySurface, rebuild: Rebuild | None = None
             ) -> tuple[Anchor, tuple[Status, str] | None]:
        if light.surface is None or light.status not in LEVEL_STATUSES:
            return fallback(f"the structured light gives no level ({light.status}"
                            + (f": {light.message}" if light.message else "") + ")", rebuild)
        points = surface.points_mm
        theirs = light.surface.heightfield.height(points[:, 0], points[:, 1])
        shared = np.isfinite(theirs)
        if shared.mean() < MIN_SHARED:
            return fallback(f"the structured light's surface covers {shared.mean():.0%} of the "
                            f"samples (less than {MIN_SHARED:.0%})", rebuild)
        difference = theirs[shared] - points[shared, 2]
        shift = float(np.median(difference))
        rms = float(np.sqrt(np.mean((difference - shift) ** 2)))
        own = light.surface.anchor
        anchor = Anchor("structured_light", float(np.mean(points[:, 2])) + shift,
                        searched_mm=own.anchor_mm, sigma_mm=own.sigma_mm,
                        source_difference_mm=rms)
        verdict = None
        if rms > MAX_DIFFERENCE_MM:
            verdict = (Status.INCONSISTENT,
                       f"the surface and the structured light's differ by {rms:.3f} mm RMS over "
                       f"the samples both cover, once levelled (more than {MAX_DIFFERENCE_MM} "
                       "mm): one of them is wrong in a part")
        elif light.status is Status.UNCERTAIN_LEVEL:
            verdict = (Status.UNCERTAIN_LEVEL,
                       f"the structured light's level, which the surface takes: {light.message}")
        return anchor, verdict

    return rule


class SchlierenLevelled:
    """Synthetic Schlieren at the structured light's level (module notes), configured once:
    Schlieren's options, and the structured light's (its level's source, pinned by the view).

    Examples
    --------
    >>> from restoration import SchlierenLevelled, SchlierenOptions
    >>> method = SchlierenLevelled(SchlierenOptions(sample_step_px=4))
    >>> method.name, method.options.sample_step_px
    ('schlieren-sl', 4)
    """

    name = "schlieren-sl"
    calibration_type = ViewLevelCalibration
    options_type = SchlierenOptions

    def __init__(self, options: SchlierenOptions | None = None,
                 light: StructuredLightOptions | None = None) -> None:
        self.options = checked_options(self.name, SchlierenOptions, options)
        self.light = StructuredLightView(light)

    def __repr__(self) -> str:
        return f"SchlierenLevelled({self.options!r})"

    def __call__(
        self,
        images: dict[str, NDArray],
        cal: ViewLevelCalibration,
        track: LevelTrack | None = None,
    ) -> RestoreResult:
        """Restore one frame (``pattern``, ``pattern_flat``, ``view``, ``view_flat``);
        ``track``: the structured light's (a sequence's level)."""
        return self.from_light(images, cal, self.light(images, cal, track))

    def from_light(self, images: dict[str, NDArray], cal: ViewLevelCalibration,
                   light: RestoreResult) -> RestoreResult:
        """:meth:`__call__` given the structured light's result on the frame, ``light``
        (:class:`~restoration.StructuredLightView`'s)."""
        h0_mm, search_mm = float(cal.cfg.water.h0_mm), float(self.options.level_search_mm)

        def search(rebuild: Rebuild) -> PatternLevel:
            cal.prepare(images["pattern_flat"])
            spots = pinhole_spots(detect_spots(images["pattern"],
                                               scales=cal.reference.spot_scales), cal.cfg)
            return find_pattern_level(rebuild, spots.centres_px, cal, h0_mm, search_mm)

        rule = structured_light_level(light, h0_mm, search if search_mm > 0 else None)
        result = restore_schlieren(images, cal, self.options, rule)
        result.method = self.name
        # The level's source is part of the method's time (a frame that stopped before its
        # surface has no other).
        level_ms = float((light.timings_ms or {}).get("end_to_end", 0.0))
        timings = result.timings_ms
        timings["level"] = level_ms
        timings["end_to_end"] = float(timings.get("end_to_end", 0.0)) + level_ms
        return result
