"""The paper's method, structured light, on one frame: features, surface, restored view.

Per frame (section 3 of Jian et al. 2022): the dots of the wavy-water pattern are matched to the
flat-water reference (:mod:`restoration.features`), their reflections give normals and the
normals a surface (:mod:`restoration.surface`), anchored in height by the slopes'
integrability (:mod:`restoration.anchor`), and the view is undistorted by reverse ray tracing
through that surface (:mod:`restoration.reverse_trace`). Reads only images and calibration.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from restoration.anchor import find_anchor, integration_residual_mm
from restoration.calibration import Calibration, LevelTrack
from restoration.consistency import Consistency, spot_consistency, unchecked_beside
from restoration.features import (
    Matches,
    ReferenceGrid,
    features_from_code,
    features_from_reference,
)
from restoration.features.match import MAX_LABEL_SHIFT
from restoration.features.track import TrackedSpots, features_tracked
from restoration.fit_level import fit_level
from restoration.frame_status import frame_status
from restoration.label_parts import misplaced_parts
from restoration.observations import Observations
from restoration.options import StructuredLightOptions, checked_options
from restoration.result import RestoreResult, Status
from restoration.reverse_trace import SplinePatches
from restoration.spot_bias import SpotBiasModel, spot_correction_px
from restoration.surface import COMPILED_INTEGRATORS, SurfaceEstimate, reconstruct
from restoration.tracking import SequenceState
from wai_core.config import SystemConfig
from wai_core.errors import RestorationFailed
from wai_core.parallel import run_beside
from wai_core.timings import Timings

__all__ = [
    "StructuredLight", "estimate_surface", "fit_to_spots", "match_features",
    "view_has_signal",
]

DARK_VIEW_CONTRAST = 1e-3
"""A view whose 1st-99th percentile spread (after the gain) is below this has no signal."""

SEARCH_INTEGRATOR = "fourth_order"
"""Integrator of the anchor search (see :func:`estimate_surface`), unless the options name
another lattice rule of :data:`~restoration.surface.COMPILED_INTEGRATORS`."""


def estimate_surface(
    obs: Observations,
    cal: Calibration,
    options: StructuredLightOptions,
    start_mm: float | None = None,
) -> SurfaceEstimate:
    """Surface from a frame's observations, anchored by the gauge's h0 or by integrability
    (searched from ``start_mm``, default h0).

    When the last refinement pass still moves the heights by more than
    ``options.converge_mm``, the fixed point had not converged (it contracts slowly when the
    diffuser is close to the water) and the whole estimate is made again with up to
    ``options.max_refine`` passes: an unconverged refinement biases the level search, and a
    wrong level gives a wrong shape (the depth-normal ambiguity). ``anchor.refine_passes``
    says how many passes the estimate allowed.

    Examples
    --------
    >>> import numpy as np
    >>> from restoration import Calibration, StructuredLightOptions
    >>> from restoration.structured_light import estimate_surface
    >>> from wai_core import load_system
    >>> from wai_core.geometry import intersect_plane_z
    >>> cal = Calibration(load_system("paper"))
    >>> ij = cal.cfg.rig.dot_ij[np.abs(cal.cfg.rig.dot_ij).max(axis=1) <= 6]
    >>> origin, dirs = cal.projector.pixel_rays(*cal.panel_px(ij).T)
    >>> # Flat water at h0: mirror the rays there and find their spots on the diffuser.
    >>> t = (cal.cfg.water.h0_mm - origin[2]) / dirs[:, 2]
    >>> q = origin + t[:, None] * dirs
    >>> spot, _ = intersect_plane_z(q, dirs * [1, 1, -1], cal.diffuser_z_mm)
    >>> cols, rows, _ = cal.camera_s.project(spot)
    >>> opts = StructuredLightOptions(anchor="gauge")
    >>> est = estimate_surface(cal.observe(ij, np.column_stack([cols, rows])), cal, opts)
    >>> bool(np.abs(est.points_mm[:, 2] - cal.cfg.water.h0_mm).max() < 1e-6)
    True
    """
    est = _estimate_surface(obs, cal, options, start_mm, options.n_refine)
    if (
        options.n_refine > 0
        and options.max_refine > options.n_refine
        and est.height_change_mm > options.converge_mm
    ):
        est = _estimate_surface(obs, cal, options, start_mm, options.max_refine)
        est.anchor.refine_passes = options.max_refine
    else:
        est.anchor.refine_passes = options.n_refine
    return est


def reconstruct_at(
    obs: Observations, anchor_mm: float, options: StructuredLightOptions, n_refine: int,
    integrator: str | None = None,
) -> SurfaceEstimate:
    """The surface of ``obs`` anchored at ``anchor_mm`` with ``options``' integration,
    gridding and refinement tolerance, ``n_refine`` passes at most (``integrator``: the
    options' unless given)."""
    return reconstruct(
        obs,
        anchor_mm,
        integrator=options.integrator if integrator is None else integrator,
        n_refine=n_refine,
        tol_mm=options.refine_tol_mm,
        grid_spacing_mm=options.grid_spacing_mm,
        gridder=options.gridder,
    )


def _estimate_surface(
    obs: Observations,
    cal: Calibration,
    options: StructuredLightOptions,
    start_mm: float | None,
    n_refine: int,
) -> SurfaceEstimate:
    """:func:`estimate_surface` with ``n_refine`` passes per reconstruction."""

    def rebuild(anchor_mm: float, integrator: str = options.integrator) -> SurfaceEstimate:
        return reconstruct_at(obs, anchor_mm, options, n_refine, integrator)

    # The level is a property of the data, not of the integrator: search it with a lattice
    # rule, whose fit error is the integrability residual itself (integrators that resample
    # onto a grid add their own resampling error to it): the fourth-order rule, or the
    # trapezoid when asked for (its systematic error biased the level; docs/results.md).
    search_with = (
        options.integrator if options.integrator in COMPILED_INTEGRATORS else SEARCH_INTEGRATOR
    )

    def probe(anchor_mm: float) -> SurfaceEstimate:
        # A search that strays below the diffuser has found no level: the frame's failure, not
        # a bad argument (reconstruct refuses such a level with this message).
        if not anchor_mm > cal.diffuser_z_mm:
            raise RestorationFailed(
                "reconstruct_surface: the water level h0 must lie above the diffuser"
            )
        return rebuild(anchor_mm, search_with)

    h0 = cal.cfg.water.h0_mm
    if options.anchor == "gauge":
        est = rebuild(h0)
        est.anchor.update(method="gauge", anchor_mm=h0)
        return est
    search = find_anchor(
        probe, h0 if start_mm is None else start_mm, options.anchor_step_mm, plans=obs.plans
    )
    info = {
        "searched_mm": search.anchor_mm,
        "sigma_mm": search.sigma_mm,
        "evaluations": search.evaluations,
    }
    if search.sigma_mm <= options.anchor_max_sigma_mm:
        est = search.estimate
        if options.integrator != search_with:
            est = rebuild(search.anchor_mm)
        est.anchor.update(method="integrability", anchor_mm=search.anchor_mm, **info)
    else:  # the slopes do not pin the level (calm water): trust the gauge, and say so
        est = rebuild(h0)
        est.anchor.update(method="gauge_fallback", anchor_mm=h0, **info)
    return est


# Most label shifts tried when the pattern leaves the labels ambiguous (each costs a surface).
MAX_REJECTION_ROUNDS = 2
"""Times a frame's surface is estimated again without the samples it did not reproduce at all
(:attr:`~restoration.consistency.Consistency.gross`); what is left after them marks the frame
``inconsistent``."""
SHARP_MINIMUM_RATIO = 1 / 3
"""The right labelling's integration residual sits far below every shifted one's (0.09 of the
runner-up's on the paper's seed 4); between two wrong ones a dot apart it changes 2-3x (0.43
on a U = 1.5 m/s frame whose labels lay 7 dots off). A best labelling at the edge of the shifts
tried whose residual is above this fraction of the runner-up's is not taken as pinned."""
MAX_SHIFT_CANDIDATES = 24
# A shifted labelling must keep this fraction of the features on lit dots to be considered.
MIN_SHIFT_KEEP = 0.8


def shifted(features: Matches, shift: NDArray, keep: NDArray) -> Matches:
    """``features`` relabelled ``ij + shift``, keeping the rows ``keep``."""
    di, dj = (int(v) for v in shift)
    counts = {**features.counts, "label_shift_di": di, "label_shift_dj": dj}
    return replace(
        features,
        ij=features.ij[keep] + shift,
        ref_px=features.ref_px[keep],
        spot_px=features.spot_px[keep],
        observed=features.observed[keep],
        counts=counts,
        alt_shifts=features.alt_shifts - shift,
    )


def shifted_surface(
    features: Matches, shift: NDArray, reference: ReferenceGrid, cal: Calibration,
    options: StructuredLightOptions,
) -> tuple[Matches, Observations, SurfaceEstimate] | None:
    """``features`` relabelled ``ij + shift`` (the rows that stay on lit dots), their
    observations and the surface estimated from them; None where fewer than
    :data:`MIN_SHIFT_KEEP` of them stay on lit dots or no surface can be estimated."""
    keep = reference.lit_at(features.ij + shift)
    if keep.sum() < MIN_SHIFT_KEEP * len(keep):
        return None
    candidate = shifted(features, shift, keep)
    obs = cal.observe(candidate.ij, candidate.spot_px, flat_referenced=options.flat_referenced)
    try:
        return candidate, obs, estimate_surface(obs, cal, options)
    except RestorationFailed:
        return None


def resolve_label_shift(
    features: Matches,
    surface: SurfaceEstimate,
    reference: ReferenceGrid,
    cal: Calibration,
    options: StructuredLightOptions,
) -> tuple[Matches, Observations | None, SurfaceEstimate]:
    """Among lattice shifts that the lit/unlit evidence cannot tell apart, keep the labelling
    whose slopes integrate best.

    A labelling shifted by whole dots pairs every spot with a neighbouring projector ray: the
    normals then describe no surface, and the integration residual grows (on the paper's rig
    by 2-3x per dot of shift). ``counts`` gains ``label_shift_candidates`` (tried),
    ``label_shift_di/dj`` (applied on top of the pattern's choice) and
    ``label_shift_at_edge`` (1 when the best lies at the edge of the shifts tried without a
    sharp minimum: :data:`SHARP_MINIMUM_RATIO`). Returns the chosen features, their
    observations (None when the pattern's own labelling won) and surface.
    """
    best = (integration_residual_mm(surface), features, None, surface)
    residuals = [best[0]]
    tried = 1
    for shift in features.alt_shifts[:MAX_SHIFT_CANDIDATES]:
        if not shift.any():
            continue
        built = shifted_surface(features, shift, reference, cal, options)
        if built is None:
            continue
        candidate, obs, est = built
        tried += 1
        residual = integration_residual_mm(est, obs.plans)
        residuals.append(residual)
        if residual < best[0]:
            best = (residual, candidate, obs, est)
    _, chosen, obs, est = best
    chosen.counts["label_shift_candidates"] = tried
    # The slopes integrating best at the edge of the shifts tried, and not far better than
    # at the runner-up: the residual is still falling there, and the best labelling may lie
    # beyond the shifts tried.
    total = (chosen.counts.get("anchor_di", 0) + chosen.counts.get("label_shift_di", 0),
             chosen.counts.get("anchor_dj", 0) + chosen.counts.get("label_shift_dj", 0))
    runner_up = sorted(residuals)[1] if len(residuals) > 1 else np.inf
    chosen.counts["label_shift_at_edge"] = int(
        obs is not None and max(abs(v) for v in total) >= MAX_LABEL_SHIFT
        and best[0] > SHARP_MINIMUM_RATIO * runner_up)
    return chosen, obs, est


def view_has_signal(view: NDArray, gain: float = 1.0) -> bool:
    """Whether the view ``view`` (H, W, 3) shows anything: the spread between the 1st and 99th
    percentiles of every 7th pixel of each 7th row, divided by the view's ``gain``, exceeds
    :data:`DARK_VIEW_CONTRAST`."""
    sample = np.asarray(view)[::7, ::7] / gain
    lo, hi = np.percentile(sample, [1.0, 99.0])
    return bool(hi - lo > DARK_VIEW_CONTRAST)


def fit_to_spots(surface: SurfaceEstimate, obs: Observations) -> SurfaceEstimate:
    """``surface`` refitted to its samples' spots through the exact model, its level included
    (:func:`restoration.fit_level.fit_level`); ``obs``: the surface's samples' observations,
    one per sample."""
    level = fit_level(surface.points_mm, surface.slopes, obs, surface.heightfield)
    fit = level.fit
    est = surface.refitted(
        fit.heightfield, fit.points_mm, fit.slopes, fit_ms=fit.timings_ms["total"]
    )
    est.anchor.update(
        fit_rms_mm=fit.rms_mm, fit_iterations=fit.iterations,
        fit_level_offset_mm=level.offset_mm, fit_level_sigma_mm=level.sigma_mm,
        fit_level_probes=len(level.offsets_mm),
        fit_level_probes_converged=int(level.converged.sum()),
        fit_level_kept_start=bool(level.kept_start), fit_level_reason=str(level.reason),
    )
    return est


def consistency_of(
    surface: SurfaceEstimate, spots_px: NDArray, cal: Calibration, reference: ReferenceGrid,
    patches: SplinePatches | None = None, rays: tuple[NDArray, NDArray] | None = None,
) -> Consistency:
    """The forward check of ``surface`` against its samples' spots (restoration.consistency),
    through the surface's spline table ``patches`` when it is built already, along its
    samples' projector ``rays`` (origins (3,) or (K, 3) mm, directions (K, 3)) when they are
    known (else from ``cal``)."""
    if rays is None:
        rays = cal.dot_rays(surface.ij)
    origin, dirs = rays
    return spot_consistency(
        surface.heightfield, surface.points_mm, origin, dirs, spots_px, cal.camera_s,
        cal.diffuser_z_mm, reference.median_spacing_px, patches=patches,
    )


class StructuredLight:
    """The paper's structured-light method, configured once and applied to frames.

    Parameters
    ----------
    options : StructuredLightOptions, optional
        Integrator, refinement, gridding, anchor and warp choices (default: the testbed's).

    Examples
    --------
    >>> from restoration import StructuredLight, StructuredLightOptions
    >>> method = StructuredLight(StructuredLightOptions(integrator="paper"))
    >>> method.name, method.options.integrator
    ('structured-light', 'paper')
    """

    name = "structured-light"
    calibration_type = Calibration
    options_type = StructuredLightOptions

    def __init__(self, options: StructuredLightOptions | None = None) -> None:
        self.options = checked_options(self.name, StructuredLightOptions, options)

    def __repr__(self) -> str:
        return f"StructuredLight({self.options!r})"

    def __call__(
        self,
        images: dict[str, NDArray],
        cal: Calibration,
        track: LevelTrack | None = None,
    ) -> RestoreResult:
        """Restore one frame.

        Parameters
        ----------
        images : dict of str to ndarray
            ``pattern`` and ``pattern_flat`` (camera s, (H, W) or (H, W, 3)) and ``view``
            (camera v, (H, W, 3)), linear values as read by :meth:`Calibration.load_images`.
        cal : Calibration
            The rig; its flat-water reference is prepared on the first call and kept.
        track : LevelTrack, optional
            A sequence's level: the search starts at the previous frame's level, and the
            track takes this frame's. A :class:`~restoration.tracking.SequenceState` also
            tracks the labels from the previous frames' spots and starts the warp solve at
            the previous frame's.

        Returns
        -------
        RestoreResult
            Status ``failed`` (with the reason, and no surface) when the frame gives no
            surface (:class:`~wai_core.errors.RestorationFailed`); otherwise the surface,
            the restored view and a truth-free status.

        Raises
        ------
        WaiInputError
            For bad input: a wrongly sized image, NaN or inf in one, a configuration whose
            geometry cannot work.
        """
        state = track if isinstance(track, SequenceState) else None
        start_mm = None if state is None else state.start_mm
        history = () if state is None else state.next_history()
        result = self._restore(images, cal, track, state, history)
        if state is not None and state.refuses(result):  # matched in full after all
            state.start_mm = start_mm
            result = self._restore(images, cal, track, state, ())
            result.features.counts["track_fallback"] = 1
        return result

    def _restore(
        self, images: dict[str, NDArray], cal: Calibration, track: LevelTrack | None,
        state: SequenceState | None, history: Sequence[TrackedSpots],
    ) -> RestoreResult:
        """:meth:`__call__` once, ``state`` the sequence's when ``track`` is one, the labels
        tracked from ``history`` where it holds any."""
        options = self.options
        timings = Timings()

        # The dark-view test reads only the view: on the helper while the pattern is detected.
        has_signal = run_beside(lambda: view_has_signal(images["view"], cal.view_gain))
        try:
            reference = cal.prepare(images["pattern_flat"])
            with timings("features"):
                features = match_features(images["pattern"], reference, cal.cfg, history)
            if state is not None and state.track:  # each frame says whether it was tracked
                features.counts.setdefault("tracked", 0)
                features.counts.setdefault("track_fallback", 0)
            with timings("surface"):
                obs = cal.observe(features.ij, features.spot_px,
                                  flat_referenced=options.flat_referenced)
                start = None if track is None else track.start_mm
                surface = estimate_surface(obs, cal, options, start)
                if len(features.alt_shifts) > 1:
                    features, shifted_obs, surface = resolve_label_shift(
                        features, surface, reference, cal, options
                    )
                    obs = obs if shifted_obs is None else shifted_obs
                surface.heightfield  # noqa: B018  (a patch too small to grid fails here)
            memo: dict[str, Any] = {}
            features, obs, surface = self._pin_labels(features, obs, surface, reference, cal,
                                                      images, memo, timings)
            if options.spot_bias_for(cal.cfg):
                with timings("surface"):
                    obs = self._observe_debiased(features, surface, cal, timings)
                    surface = estimate_surface(obs, cal, options, start)
            surface = self._level(obs, cal, surface, images, memo, timings)
            surface, view, check = self._view_and_check(images, cal, obs, surface, reference,
                                                        state, timings)

            def again(features: Matches, surface: SurfaceEstimate, rejected_xy: NDArray
                      ) -> tuple[Observations, SurfaceEstimate, Any, Consistency]:
                """The surface estimated, levelled and checked again from ``features``."""
                with timings("surface"):
                    obs = self._observe_debiased(features, surface, cal, timings)
                    surface = estimate_surface(obs, cal, options, start)
                surface = self._level(obs, cal, surface, images, memo, timings)
                return obs, *self._view_and_check(images, cal, obs, surface, reference, state,
                                                  timings, rejected_xy)

            rejected_xy = np.zeros((0, 2))
            for _ in range(MAX_REJECTION_ROUNDS):
                if not check.gross.any():
                    break
                # Samples the surface does not reproduce at all pull it off the water around
                # them: the surface is estimated again without them, and left unknown where
                # they were the nearest samples.
                drop = check.gross | unchecked_beside(surface.ij, check)
                features = without_samples(features, surface.ij[drop])
                rejected_xy = np.vstack([rejected_xy, check.xy_mm[drop]])
                obs, surface, view, check = again(features, surface, rejected_xy)
            with timings("surface"):
                drop = self._misplaced(features, cal)
            if drop.any():
                features = without_samples(features, features.ij[drop], "rejected_shifted_part")
                obs, surface, view, check = again(features, surface, rejected_xy)
        except RestorationFailed as exc:
            if state is not None:
                state.take(None, ok=False)
            return RestoreResult(self.name, Status.FAILED, str(exc))
        if track is not None:
            track.update(surface.anchor)
        timings.add("end_to_end", timings.total("features", "surface", "reverse_trace"))
        status, message = frame_status(
            features, reference, surface, check,
            has_signal(), options, cal.diffuser_mm_per_px,
        )
        if state is not None:
            state.take(features, ok=status == Status.OK, residual_px=check.median_px,
                       tried=bool(history))
        gain = (tuple(cal.spot_bias_gain(SpotBiasModel.of_scene(cal.cfg)))
                if options.spot_bias_for(cal.cfg) else None)
        return RestoreResult(
            self.name, status, message, features, surface, view, timings.to_dict(),
            features.counts, check, reference_rms_px=float(reference.rms_px),
            reference_spacing_px=reference.median_spacing_px, spot_bias_gain=gain,
        )

    def _observe_debiased(self, features: Matches, surface: SurfaceEstimate,
                          cal: Calibration, timings: Timings) -> Observations:
        """The features' observations; with ``spot_bias`` (as set, or on rough water), each
        spot less its bias on ``surface`` beyond flat water's
        (:func:`restoration.spot_bias.spot_correction_px`, timed as ``spot_bias``, a part of
        the surface's time)."""
        spots = features.spot_px
        if self.options.spot_bias_for(cal.cfg):
            with timings("spot_bias"):
                spots = spots - spot_correction_px(cal, features.ij, surface,
                                                   SpotBiasModel.of_scene(cal.cfg))
        return cal.observe(features.ij, spots, flat_referenced=self.options.flat_referenced)

    def _pin_labels(self, features: Matches, obs: Observations, surface: SurfaceEstimate,
                    reference: ReferenceGrid, cal: Calibration, images: dict[str, NDArray],
                    memo: dict[str, Any], timings: Timings
                    ) -> tuple[Matches, Observations, SurfaceEstimate]:
        """The labels, their observations and surface, pinned where something beyond the
        pattern can pin them: here nothing (a method that sees more overrides it,
        :class:`restoration.view_level.StructuredLightView`)."""
        return features, obs, surface

    def _misplaced(self, features: Matches, cal: Calibration) -> NDArray[np.bool_]:
        """The features in parts a neck joins whose labels a shift fits far better
        (:mod:`restoration.label_parts`; the parts tested counted in
        ``counts["shifted_parts_tested"]``)."""
        options = self.options
        reach = np.abs(cal.cfg.rig.dot_ij).max(axis=0)

        def residual_of(part: NDArray, shift: NDArray) -> float:
            ij = features.ij[part] + shift
            if np.any(np.abs(ij) > reach):  # a dot off the grid: no candidate
                return float("nan")
            obs = cal.observe(ij, features.spot_px[part], flat_referenced=options.flat_referenced)
            return integration_residual_mm(estimate_surface(obs, cal, options))

        drop, gains = misplaced_parts(features.ij, residual_of)
        if gains:
            features.counts["shifted_parts_tested"] = len(gains)
        return drop

    def _level(self, obs: Observations, cal: Calibration, surface: SurfaceEstimate,
               images: dict[str, NDArray], memo: dict[str, Any],
               timings: Timings) -> SurfaceEstimate:
        """The surface at its final level: as estimated here; a method that pins the level
        otherwise (:class:`restoration.view_level.StructuredLightView`) overrides it, ``memo``
        holding what it computes once a frame."""
        return surface

    def _view_and_check(
        self, images: dict[str, NDArray], cal: Calibration, obs: Observations,
        surface: SurfaceEstimate, reference: ReferenceGrid, state: SequenceState | None,
        timings: Timings, rejected_xy_mm: NDArray | None = None,
    ) -> tuple[SurfaceEstimate, Any, Consistency]:
        """The surface refitted to its spots (when the options say so) and left unknown near
        the samples rejected (``rejected_xy_mm`` (R, 2)), the view restored through it and the
        forward check of it; their times added to ``timings``."""
        options = self.options
        rows = obs.rows_of(surface.ij)
        spots = obs.spot_px[rows]
        with timings("surface"):
            if options.fit_spots:
                surface = fit_to_spots(surface, obs.take(rows))
            if rejected_xy_mm is not None:
                surface = surface.unknown_near(rejected_xy_mm)
            heightfield = surface.heightfield
        with timings("reverse_trace"):
            # The check and the view evaluate one spline table of the surface; the check runs
            # beside the view (it reads neither the view nor its results).
            patches = SplinePatches(heightfield)
            rays = (obs.origin_mm if obs.origin_mm.ndim == 1 else obs.origin_mm[rows],
                    obs.dirs[rows])
            checked = run_beside(
                lambda: _timed_check(surface, spots, cal, reference, patches, rays)
            )
            view = cal.restore_view(images["view"], heightfield, options.warp_step_px,
                                    gain=cal.view_gain, patches=patches,
                                    state=None if state is None else state.view_state)
            check, check_ms = checked()
        timings.add("consistency", check_ms)
        return surface, view, check


def without_samples(features: Matches, ij: NDArray,
                    count: str = "rejected_inconsistent") -> Matches:
    """``features`` without the samples whose grid indices are ``ij`` (K, 2), counted under
    ``count``: by default ``rejected_inconsistent``, spots the surface built from them did not
    reproduce at all."""
    drop = (features.ij[:, None, :] == np.asarray(ij)[None, :, :]).all(axis=2).any(axis=1)
    counts = {**features.counts, count: features.counts.get(count, 0) + int(drop.sum())}
    keep = ~drop
    return replace(features, ij=features.ij[keep], ref_px=features.ref_px[keep],
                   spot_px=features.spot_px[keep], observed=features.observed[keep],
                   counts=counts)


def match_features(
    pattern: NDArray, reference: ReferenceGrid, cfg: SystemConfig,
    history: Sequence[TrackedSpots] = (),
) -> Matches:
    """The wavy pattern's features, labelled with grid indices: the coded pattern decoded dot
    by dot, the plain one matched by ordering (:mod:`restoration.features`), or tracked from
    ``history``, a video's previous frames' labelled spots (most recent first)."""
    if cfg.pattern.code != "none":
        return features_from_code(pattern, reference, cfg)
    if history:
        return features_tracked(pattern, reference, cfg, history)
    return features_from_reference(pattern, reference, cfg)


def _timed_check(
    surface: SurfaceEstimate, spots_px: NDArray, cal: Calibration, reference: ReferenceGrid,
    patches: SplinePatches, rays: tuple[NDArray, NDArray],
) -> tuple[Consistency, float]:
    """:func:`consistency_of` and its wall time, ms (it runs on another thread)."""
    timings = Timings()
    with timings("check"):
        check = consistency_of(surface, spots_px, cal, reference, patches, rays)
    return check, timings.ms["check"]
