"""Score a restoration against truth, when truth exists (the only place the truth is read).

Distorted and restored views are scored on the same pixels: where the restoration produced a
value and the truth view sees the object. The fraction of the view that was restored is reported
beside the scores, so a method cannot look good by restoring little. A user's own captures have
no truth: :meth:`Truth.from_folder` then returns None and the restoration stands unscored.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from restoration.calibration import RigCalibration
from restoration.metrics import (
    angular_px,
    corner_spread,
    image_metrics,
    score_corners,
    surface_errors,
)
from restoration.result import RestoreResult
from wai_core.heightfield import Heightfield, load_heightfield
from wai_core.images import locate_image, read_image

__all__ = ["OBJECT_MIN_LEVEL", "Scores", "Truth", "score", "surface_profile"]

OBJECT_MIN_LEVEL = 0.01
"""Truth pixels darker than this (after the gain) show no object: TIR or beyond the board."""


@dataclass
class Truth:
    """What a frame really was: the true surface and the view through flat water.

    Attributes
    ----------
    surface : Heightfield or None
        Absolute heights, mm, lab frame (``heightfield.npz``).
    view : (H, W, 3) ndarray or None
        The view through flat water at h0, divided by the gain (``view_truth.exr``), in
        camera v's ideal pinhole.
    recorded : (H, W) ndarray of bool or None
        Where :attr:`view` holds the camera's data: a real lens's image resampled into its
        pinhole has none past the sensor's edge
        (:attr:`~restoration.undistort.PinholeRemap.seen`); None: everywhere.
    """

    surface: Heightfield | None = None
    view: NDArray | None = None
    recorded: NDArray | None = None

    @classmethod
    def from_folder(cls, folder: str | Path, cal: RigCalibration) -> Truth | None:
        """The truth files of a render folder, or None when it has neither (a capture)."""
        folder = Path(folder)
        surface_file = folder / "heightfield.npz"
        surface = load_heightfield(surface_file) if surface_file.is_file() else None
        view_file = locate_image(folder, "view_truth")
        view = None
        if view_file is not None:
            view = cal.to_pinhole("view_truth", read_image(view_file)) / cal.view_gain
        if surface is None and view is None:
            return None
        return cls(surface, view, cal.recorded("view_truth"))


@dataclass
class Scores:
    """Every score of one restoration against its truth (eq. 44-47, Fig. 15).

    Surface scores are None without a true surface; view scores are None without a true view;
    corner scores need both. Arrays (:attr:`error_map_mm`, :attr:`corner_points_px`) are kept
    for figures and left out of :meth:`to_dict`.

    Attributes
    ----------
    surface : dict or None
        ``rmse_mm``, ``rmse_demeaned_mm``, ``max_abs_mm``, ``mean_offset_mm``, ``n_points``.
    distorted, restored : dict or None
        ``mse``, ``psnr_db``, ``ssim`` (and pixel counts) of the views against the truth.
    corner_std_distorted_px, corner_std_restored_px : float or None
        The paper's corner STD on the corners found in truth, distorted and restored views,
        in camera v's own pixels.
    corner_std_restored_px800 : float or None
        ``corner_std_restored_px`` in pixels of the paper's 800 x 600 camera v (the same angle:
        :func:`restoration.metrics.angular_px`, ``x 800 / width`` at its sensor width), so
        that cameras of different resolutions compare.
    corners_common : int
        How many corners that is.
    corners : dict
        Per-image corner statistics.
    view_pixels_with_object : int
    view_restored_fraction : float
        Of the truth's object pixels, the fraction restored.
    error_map_mm : (m, n) ndarray or None
        Estimated minus true height on the estimate's grid, mm.
    corner_points_px : dict of str to (C, 2) ndarray
        Corner positions per image, px (NaN where not found).
    """

    surface: dict[str, float] | None = None
    distorted: dict[str, float] | None = None
    restored: dict[str, float] | None = None
    corner_std_distorted_px: float | None = None
    corner_std_restored_px: float | None = None
    corner_std_restored_px800: float | None = None
    corners_common: int = 0
    corners: dict[str, Any] = field(default_factory=dict)
    view_pixels_with_object: int = 0
    view_restored_fraction: float | None = None
    error_map_mm: NDArray | None = field(default=None, repr=False)
    corner_points_px: dict[str, NDArray] = field(default_factory=dict, repr=False)

    @property
    def rmse_mm(self) -> float | None:
        """Surface RMSE (eq. 44), mm."""
        return None if self.surface is None else self.surface["rmse_mm"]

    def to_dict(self) -> dict[str, Any]:
        """The scores as plain values, with ``metrics.json``'s names (``wai_rmse_mm``, ...)."""
        out: dict[str, Any] = {}
        if self.surface is not None:
            s = self.surface
            out.update(
                wai_rmse_mm=s["rmse_mm"],
                wai_rmse_demeaned_mm=s["rmse_demeaned_mm"],
                wai_max_abs_mm=s["max_abs_mm"],
                wai_mean_offset_mm=s["mean_offset_mm"],
                wai_points=s["n_points"],
            )
        if self.restored is not None:
            out.update(
                distorted=self.distorted,
                restored=self.restored,
                view_pixels_with_object=self.view_pixels_with_object,
                view_restored_fraction=self.view_restored_fraction,
            )
        if self.corners:
            out.update(
                corner_std_distorted_px=self.corner_std_distorted_px,
                corner_std_restored_px=self.corner_std_restored_px,
                corner_std_restored_px800=self.corner_std_restored_px800,
                corners_common=self.corners_common,
                corners=self.corners,
            )
        return out


def score(
    result: RestoreResult, distorted_view: NDArray, cal: RigCalibration, truth: Truth
) -> Scores:
    """All scores of one restoration that its truth allows.

    Parameters
    ----------
    result : RestoreResult
        A restoration with a view (``result.has_view``); its surface is scored when it has
        one.
    distorted_view : (H, W, 3) ndarray
        The view image divided by the calibration's gain.
    cal : RigCalibration
    truth : Truth

    Returns
    -------
    Scores

    Raises
    ------
    ValueError
        When ``result`` holds no restoration (its status says why).
    """
    if not result.has_view:
        raise ValueError(f"nothing to score: the frame's status is {result.status.value!r}")
    out = Scores()
    if truth.surface is not None and result.surface is not None:
        surf = surface_errors(result.surface.heightfield, truth.surface)
        out.surface = {
            k: surf[k]
            for k in ("rmse_mm", "rmse_demeaned_mm", "max_abs_mm", "mean_offset_mm", "n_points")
        }
        out.error_map_mm = surf["error_map_mm"]
    if truth.view is not None:
        seen = truth.view.mean(axis=2) > OBJECT_MIN_LEVEL
        if truth.recorded is not None:
            seen &= truth.recorded
        mask = result.view.valid & seen
        if mask.any():  # a view restored nowhere on the object has no image scores
            out.distorted = image_metrics(distorted_view, truth.view, mask)
            out.restored = image_metrics(result.view.image, truth.view, mask)
        out.view_pixels_with_object = int(seen.sum())
        out.view_restored_fraction = float(mask.sum() / max(seen.sum(), 1))
    if truth.view is not None and truth.surface is not None:
        corners = score_corners(
            cal.cfg, truth.view, distorted_view, result.view.image, truth.surface,
            restored_valid=result.view.valid,
        )
        # The paper's STD pair on the same corners: found in the truth, distorted and restored.
        pts = corners["points_px"]
        common = np.all([np.isfinite(p[:, 0]) for p in pts.values()], axis=0)
        same = {v: corner_spread(pts[v] - pts["truth"], common) for v in ("distorted", "restored")}
        out.corner_std_distorted_px = same["distorted"]["std_px"]
        out.corner_std_restored_px = same["restored"]["std_px"]
        out.corner_std_restored_px800 = angular_px(
            out.corner_std_restored_px, cal.cfg.rig.camera_v
        )
        out.corners_common = int(common.sum())
        out.corners = {k: v for k, v in corners.items() if k != "points_px"}
        out.corner_points_px = pts
    return out


def surface_profile(
    est: Heightfield, truth: Heightfield, y_mm: float = 0.0
) -> tuple[NDArray, NDArray, NDArray]:
    """Heights along ``y = y_mm`` of the estimate and the truth (the paper's Fig. 11f), mm."""
    x = est.x
    y = np.full_like(x, y_mm)
    return x, est.height(x, y), truth.height(x, y)
