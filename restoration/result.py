"""What one restoration of one frame produced: a status, and the surface and view when it ran.

Statuses (:class:`Status`, a string enum: ``Status.OK == "ok"``) are decided from the images
and the calibration alone (no truth), so a user restoring their own captures reads the same
verdict as a sweep does:

``ok``
    the frame was restored and nothing truth-free says it is wrong;
``bad_reference``
    the flat-water reference is not flat water for this rig: its spots lie further from the
    calibrated flat-water positions than :data:`REFERENCE_RMS_FRACTION` of their spacing (the
    pattern images swapped, the rig moved since it was calibrated, or spots too blurred to
    place: rough water, a defocused projector);
``sparse``
    the flat-water reference shows fewer than :data:`SPARSE_FRACTION` of the features the
    calibration puts in view (a lost pattern, swapped reference and frame), or fewer than that
    were matched (waves past the correspondence limit) and nothing in the pattern pins their
    labels: a small patch labelled by ordering alone may be shifted by whole dots and still
    integrate, so it cannot be trusted. A small patch whose labels are pinned (decoded by the
    coded pattern, a unique lattice anchor at the pattern's edge or markers, or, with
    ``structured-light-view``, camera v's lines of sight, which labels a dot off send
    millimetres astray) is judged by the checks below like any other;
``inconsistent``
    the surface does not reproduce the detected spots through the exact geometric model
    (:mod:`restoration.consistency`): its level or shape cannot be right;
``gauge_level``
    the slopes did not pin the level, so the gauge's h0 was used (the structured light on calm
    water: the shape is fine, the level is the gauge's; synthetic Schlieren, whose slopes
    never pin it, on every frame its checks pass: its shape bends with the level's error);
``uncertain_level``
    the slopes pin the level, but loosely: its standard error (the spread of the level found
    from interleaved sets of the samples) exceeds the method's bound
    (``StructuredLightOptions.level_max_sigma_px``, in camera s's pixels on the diffuser); the
    shape is the data's, the level may be off by several times that error (rough water biases
    it: docs/results.md);
``dark_view``
    the view image holds no signal (lens cap, wrong file): nothing to restore;
``view_mismatch``
    the restored view does not show what the rig sees through flat water
    (:mod:`restoration.view_check`): it disagrees with a flat-water view (``view_flat``) or,
    in a sequence, with the other frames' restored views (a still object stays still); the
    view is of another moment or camera, or turned;
``ambiguous_input``
    the folder holds two files of one image (``pattern.exr`` and ``pattern.png``) with
    different content; the first of :data:`~wai_core.images.IMAGE_SUFFIXES` was used;
``failed``
    the data cannot support a surface (too few features, samples that fix no surface):
    the method caught :class:`~wai_core.errors.RestorationFailed`, whose text is the
    ``message``. Bad input (a wrong shape, NaN, an unknown option) is no status: it raises
    :class:`~wai_core.errors.WaiInputError`;
``no_sun``, ``sun_out_of_view``, ``too_few_spots``
    Alterman's sensor had no usable sunlight (it then returns no surface).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from restoration.consistency import Consistency
    from restoration.features import Matches
    from restoration.level import Anchor
    from restoration.reverse_trace import Restoration
    from restoration.view_check import ViewMatch
    from wai_core.heightfield import Heightfield

__all__ = [
    "REFERENCE_RMS_FRACTION", "SPARSE_FRACTION", "STATUSES", "RestoreResult", "RestoredView",
    "Status",
]


class Status(enum.StrEnum):
    """A frame's truth-free verdict (see the module notes); each member is its string value.

    Examples
    --------
    >>> from restoration import Status
    >>> Status.OK == "ok", str(Status.GAUGE_LEVEL), f"{Status.FAILED}"
    (True, 'gauge_level', 'failed')
    >>> Status("sparse") is Status.SPARSE
    True
    """

    OK = "ok"
    BAD_REFERENCE = "bad_reference"
    SPARSE = "sparse"
    INCONSISTENT = "inconsistent"
    GAUGE_LEVEL = "gauge_level"
    DARK_VIEW = "dark_view"
    VIEW_MISMATCH = "view_mismatch"
    AMBIGUOUS_INPUT = "ambiguous_input"
    FAILED = "failed"
    NO_SUN = "no_sun"
    SUN_OUT_OF_VIEW = "sun_out_of_view"
    TOO_FEW_SPOTS = "too_few_spots"
    UNCERTAIN_LEVEL = "uncertain_level"


STATUSES = tuple(s.value for s in Status)
"""Every status's string, in :class:`Status` order."""
SPARSE_FRACTION = 0.25
"""Fewer dots seen in the flat reference, or fewer matches with unpinned labels, than this
fraction of the features in view make a frame ``sparse``."""
REFERENCE_RMS_FRACTION = 0.15
"""A flat-water reference whose detected spots lie further (RMS) than this fraction of the spot
spacing from the calibrated flat-water prediction makes a frame ``bad_reference``. A flat-water
render of the paper's rig lies 0.02 spacings from it; the wavy pattern taken for the reference
0.3 (a proximity match cannot exceed about 0.5)."""


@dataclass(frozen=True)
class RestoredView:
    """A restored view of a method that gives no warp of its own (one restoring from images
    alone, a method of one's own): what :class:`RestoreResult` and the scores read.

    Attributes
    ----------
    image : (H, W, 3) ndarray
        The restored view, in the flat-water view's geometry, radiance (the view divided by
        the calibration's gain); 0 where not valid.
    valid : (H, W) ndarray of bool
        True where the pixel was restored.
    counts : dict of str to int
        Pixels per cause, if the method counts them (``ok`` and its own names).
    timings_ms : dict of str to float
        The method's own stage times, ms.

    Examples
    --------
    >>> import numpy as np
    >>> view = RestoredView(np.zeros((4, 5, 3)), np.ones((4, 5), bool))
    >>> RestoreResult("mine", view=view).has_view, RestoreResult("mine", view=view).restored
    (True, False)
    """

    image: NDArray
    valid: NDArray[np.bool_]
    counts: dict[str, int] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)


class SurfaceSamples(Protocol):
    """What a method's surface offers the result, the scores and the reports (the structured
    light's :class:`~restoration.surface.SurfaceEstimate` and the sun sensor's
    :class:`~restoration.ray_surface.RaySurface` of Alterman and Schlieren alike)."""

    heightfield: Heightfield
    ij: NDArray[np.int64]
    points_mm: NDArray[np.float64]
    slopes: NDArray[np.float64]
    iterations: int
    timings_ms: dict[str, float]
    anchor: Anchor


@dataclass
class RestoreResult:
    """One frame restored (or the status saying why not), from images and calibration only.

    Attributes
    ----------
    method : str
        ``structured-light`` or ``alterman``.
    status : Status
        The verdict (see the module notes); a string given here is converted.
    message : str
        Why, in words, when the status is not ``ok``.
    features : Matches or None
        Matched features (grid index, flat-water and wavy spot centres in px, counts).
    surface : SurfaceSamples or None
        The reconstructed surface (``.heightfield``: absolute heights, mm, lab frame, NaN where
        not reconstructed) and its samples.
    view : Restoration or None
        The restored view (``.image`` (H, W, 3) in the flat-water view's geometry, ``.valid``).
    timings_ms : dict of str to float
        ``features``, ``surface``, ``reverse_trace`` and ``end_to_end`` wall times, ms.
    counts : dict of str to int
        The features' counts (detected, matched, rejections by cause).
    consistency : Consistency or None
        The forward check of the surface against the spots (structured light).
    view_match : ViewMatch or None
        The restored view against a flat-water view or the sequence's other frames
        (:mod:`restoration.view_check`), when either was available.
    warnings : list of str
        What the input's folder said that the status reflects (e.g. two differing files of
        one image).
    reference_rms_px : float or None
        The flat-water reference's residual: its detected spots against where the
        calibration puts them, RMS px (structured light; the check of a rig, docs/rig.md).
    reference_spacing_px : float or None
        The reference's median dot spacing, px (the residual's scale).
    spot_bias_gain : (float, float) or None
        Where the spots were corrected for their bias (structured light's ``spot_bias``): the
        share of the modelled bias taken off, along x and y
        (:meth:`restoration.Calibration.spot_bias_gain`).
    """

    method: str
    status: Status = Status.OK
    message: str = ""
    features: Matches | None = None
    surface: SurfaceSamples | None = None
    view: Restoration | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    consistency: Consistency | None = None
    view_match: ViewMatch | None = None
    warnings: list[str] = field(default_factory=list)
    reference_rms_px: float | None = None
    reference_spacing_px: float | None = None
    spot_bias_gain: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self.status = Status(self.status)

    @property
    def ok(self) -> bool:
        """True when the status is ``ok``."""
        return self.status == Status.OK

    def flag(self, status: Status, message: str) -> None:
        """Mark a frame that a later check found wrong: an ``ok`` frame takes ``status``; a
        frame already flagged keeps its status and gains ``message``."""
        if self.status == Status.OK:
            self.status, self.message = Status(status), message
        elif message not in self.message:
            self.message = f"{self.message}; {message}" if self.message else message

    @property
    def restored(self) -> bool:
        """True when a surface and a restored view exist (whatever the status says of them)."""
        return self.surface is not None and self.view is not None

    @property
    def has_view(self) -> bool:
        """True when a restored view exists, with or without a surface (a method that
        restores from images alone gives none)."""
        return self.view is not None

    def summary(self) -> dict[str, Any]:
        """The truth-free figures of the frame, as plain values (``metrics.json``)."""
        out: dict[str, Any] = {
            "method": self.method,
            "status": self.status.value,
            "message": self.message,
            "feature_counts": dict(self.counts),
            "features_detected": int(self.counts.get("detected", 0)),
            "features_rejected": int(
                sum(v for k, v in self.counts.items() if k.startswith("rejected_"))
            ),
        }
        if self.surface is not None:
            out.update(
                features_used=int(len(self.surface.ij)),
                refine_iterations=int(self.surface.iterations),
                anchor=self.surface.anchor.to_dict(),
            )
        if self.view is not None:
            valid = self.view.valid
            out.update(
                view_status_counts=self.view.counts,
                view_valid_fraction=float(np.mean(valid)) if valid.size else 0.0,
            )
        if self.consistency is not None:
            out["consistency"] = self.consistency.summary()
        if self.view_match is not None:
            out["view_match"] = self.view_match.summary()
        if self.reference_rms_px is not None:
            out["flat_reference"] = {
                "rms_px": float(self.reference_rms_px),
                "spacing_px": float(self.reference_spacing_px or np.nan),
                "rms_of_spacing": float(self.reference_rms_px / (self.reference_spacing_px
                                                                 or np.nan)),
            }
            if self.spot_bias_gain is not None:
                out["flat_reference"]["spot_bias_gain"] = [float(g) for g in self.spot_bias_gain]
        if self.warnings:
            out["warnings"] = list(self.warnings)
        if self.timings_ms:
            out["timings_ms"] = self.timings_ms_all()
        return out

    def timings_ms_all(self) -> dict[str, Any]:
        """Stage timings with each stage's own steps, ms."""
        out: dict[str, Any] = dict(self.timings_ms)
        for key, part in (
            ("features_steps", self.features),
            ("surface_steps", self.surface),
            ("reverse_trace_steps", self.view),
        ):
            if part is not None:
                out[key] = part.timings_ms
        return out
