"""The structured light's truth-free verdict on a restored frame (:func:`frame_status`; the
statuses: :mod:`restoration.result`)."""

from __future__ import annotations

from restoration.consistency import TAIL_FACTOR, TAIL_NEIGHBOURS, Consistency
from restoration.features import Matches, ReferenceGrid
from restoration.features.match import MAX_LABEL_SHIFT
from restoration.options import StructuredLightOptions
from restoration.result import REFERENCE_RMS_FRACTION, SPARSE_FRACTION, Status
from restoration.surface import SurfaceEstimate

__all__ = ["SEARCHED_LEVELS", "VIEW_MAX_RESIDUAL_PX", "VIEW_MAX_TAIL_PX",
           "VIEW_LEVEL_MAX_RESIDUAL_PX", "frame_status", "unpinned_patch"]

SEARCHED_LEVELS = ("integrability", "view")
"""Anchor methods whose level was searched, with a standard error that makes a frame
``uncertain_level`` past the bound."""
VIEW_MAX_RESIDUAL_PX = 0.6
"""Where camera v's view weighed the level (:mod:`restoration.view_level`): the median miss
of its lines of sight through the surface against the flow's object points, flat-water px,
past which the surface is wrong. Right surfaces leave 0.02-0.07 px on smooth water and
0.17-0.34 px at GGX alpha 0.01 (the flow's own error, the view blurred too); labels shifted
by whole dots, 1.1-5.0 px (docs/results.md, "The level from the view")."""
VIEW_MAX_TAIL_PX = 1.0
"""The same for the misses' 90th percentile, over the samples where the flow is trusted
(synthetic Schlieren's edge margin inside the object's texture): a surface wrong in a part.
Right surfaces leave 0.07-0.16 px smooth and 0.34-0.59 px rough; a real rig's frame holding
wrong labels, 1.6 px (docs/results.md, "The view's tail is read where the flow is
trusted")."""
VIEW_LEVEL_MAX_RESIDUAL_PX = 0.35
"""Where camera v's view set the level: the median miss of its lines of sight past which that
level is not trusted, flat-water px. The miss grows with the water's micro-roughness (the
view blurred): right surfaces leave 0.02-0.06 px smooth and up to 0.34 px at GGX alpha 0.01
(175 frames), 0.30-0.78 px at alpha 0.02 (29). There the view's level follows the structured
light's shape, which the blurred spots bias: of the 12 stored frames past this bound that the
other checks call `ok`, 11 lay 0.06-0.26 mm off in level with standard errors of
0.002-0.014 mm that do not see it (docs/results.md, "The view's level follows the spots, not
the flow, at alpha 0.02 too")."""


def unpinned_patch(features: Matches, reference: ReferenceGrid) -> bool:
    """Whether ``features`` are a small patch (under :data:`SPARSE_FRACTION` of the dots in
    view) whose labels only the ordering gave: shifted by whole dots, its slopes would
    integrate nearly as well (docs/results.md, "Knowing when a frame is wrong"), so only labels
    that something pins (the pattern decoded, a unique lattice anchor, camera v's view) make it
    trustworthy."""
    in_view = max(int(reference.counts.get("predicted_in_view", 0)), 1)
    return bool(len(features) < SPARSE_FRACTION * in_view
                and features.counts.get("labels_ambiguous", 1))


def frame_status(
    features: Matches, reference: ReferenceGrid, surface: SurfaceEstimate, check: Consistency,
    view_ok: bool, options: StructuredLightOptions, diffuser_mm_per_px: float,
) -> tuple[Status, str]:
    """The truth-free verdict on a restored frame (see :mod:`restoration.result`);
    ``diffuser_mm_per_px``: the scale of camera s on the diffuser, mm
    (:attr:`Calibration.diffuser_mm_per_px`), that of the level's bound."""
    in_view = max(int(reference.counts.get("predicted_in_view", 0)), 1)
    seen = int(reference.counts.get("observed", 0))
    spacing = reference.median_spacing_px
    if reference.rms_px > REFERENCE_RMS_FRACTION * spacing:
        return Status.BAD_REFERENCE, (
            f"pattern_flat is not flat water for this rig: its {seen} spots lie "
            f"{reference.rms_px:.2f} px (RMS, {reference.rms_px / spacing:.0%} of their "
            "spacing) from the calibrated flat-water positions: pattern and pattern_flat "
            "swapped, the rig moved since calibration, or spots too blurred to place (rough "
            "water, a defocused projector)?"
        )
    if seen < SPARSE_FRACTION * in_view:
        return Status.SPARSE, (
            f"the flat-water reference shows only {seen} of the {in_view} dots in view"
        )
    if unpinned_patch(features, reference):
        return Status.SPARSE, (
            f"only {len(features)} of the {in_view} dots in view were matched, and nothing in "
            "the pattern pins their labels (they may be shifted by whole dots)"
        )
    if features.counts.get("label_shift_at_edge"):
        return Status.SPARSE, (
            "nothing in the pattern pins the labels, and the slopes integrate best at the "
            f"edge of the shifts tried ({MAX_LABEL_SHIFT} dots): they may be shifted further"
        )
    if not check.consistent:
        return Status.INCONSISTENT, (
            f"the surface misses the detected spots by {check.median_px:.2f} px (median; "
            f"threshold {check.threshold_px:.2f} px)"
        )
    if check.gross.any():
        return Status.INCONSISTENT, (
            f"the surface misses {check.where_gross()} by more than {check.gross_px:.1f} px "
            "(a fifth of the dot spacing): it is wrong there"
        )
    if not check.tail_consistent:
        return Status.INCONSISTENT, (
            f"the surface misses the spots of a part of it: a twentieth of the detected spots "
            f"and their {TAIL_NEIGHBOURS} nearest are missed by {check.local_p95_px:.2f} px or "
            f"more (median of each neighbourhood, 95th percentile; more than {TAIL_FACTOR:g}x "
            f"the threshold {check.threshold_px:.2f} px): it is wrong in a part"
        )
    view_px, view_p90 = surface.anchor.view_residual_px, surface.anchor.view_residual_p90_px
    if view_px is not None and view_px > VIEW_MAX_RESIDUAL_PX:
        return Status.INCONSISTENT, (
            f"camera v's lines of sight through the surface miss the object points the flow "
            f"gives them by {view_px:.2f} px (median; more than {VIEW_MAX_RESIDUAL_PX:g} px): "
            "it is wrong"
        )
    if view_p90 is not None and view_p90 > VIEW_MAX_TAIL_PX:
        return Status.INCONSISTENT, (
            f"a tenth of camera v's lines of sight through the surface miss the object points "
            f"the flow gives them by {view_p90:.2f} px or more (more than {VIEW_MAX_TAIL_PX:g} "
            "px): it is wrong in a part"
        )
    if not view_ok:
        return Status.DARK_VIEW, "the view image holds no signal (all pixels alike)"
    if options.anchor == "integrability" and surface.anchor.method == "gauge_fallback":
        return Status.GAUGE_LEVEL, "the slopes do not pin the level: the gauge's h0 was used"
    sigma = surface.anchor.sigma_mm
    bound_mm = options.level_max_sigma_px * diffuser_mm_per_px
    if (options.anchor == "integrability" and surface.anchor.method in SEARCHED_LEVELS
            and sigma is not None and sigma > bound_mm):
        return Status.UNCERTAIN_LEVEL, (
            f"the level's standard error is {sigma:.3f} mm (more than {bound_mm:.3f} mm, "
            f"{options.level_max_sigma_px:g} px of camera s): the shape is the data's, the "
            "level may be off by several times that"
        )
    if (surface.anchor.method == "view" and view_px is not None
            and view_px > VIEW_LEVEL_MAX_RESIDUAL_PX):
        return Status.UNCERTAIN_LEVEL, (
            f"camera v's lines of sight miss by {view_px:.2f} px (median; more than "
            f"{VIEW_LEVEL_MAX_RESIDUAL_PX:g} px): on water this rough the level the view gives "
            "follows the blurred spots' bias and may be off by tenths of a millimetre"
        )
    return Status.OK, ""
