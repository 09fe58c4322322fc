"""Score a restoration against the render folder's truth (the only place the truth is read).

Distorted and restored views are scored on the same pixels: where the restoration produced a
value and the truth view sees the object. The fraction of the view that was restored is reported
beside the scores, so a method cannot look good by restoring little.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from restoration.metrics import corner_spread, image_metrics, score_corners, surface_errors
from restoration.pipeline import Calibration, RestoreResult
from wai_core.heightfield import Heightfield, load_heightfield
from wai_core.io import read_exr

# Truth pixels darker than this (after the n^2 gain) show no object: TIR or beyond the board.
OBJECT_MIN_LEVEL = 0.01


def load_truth(render_dir: str | Path, cal: Calibration) -> tuple[Heightfield, NDArray]:
    """The true surface and the true view (divided by the radiance gain, so in [0, 1])."""
    render_dir = Path(render_dir)
    surface = load_heightfield(render_dir / "heightfield.npz")
    view = read_exr(render_dir / "view_truth.exr") / cal.view_gain
    return surface, view


def score(
    result: RestoreResult,
    distorted_view: NDArray,
    cal: Calibration,
    true_surface: Heightfield,
    true_view: NDArray,
) -> dict[str, Any]:
    """All scores of one restoration (``metrics.json`` without the timings).

    Parameters
    ----------
    result : RestoreResult
    distorted_view : (H, W, 3) ndarray
        ``view.exr`` divided by the radiance gain.
    cal : Calibration
    true_surface : Heightfield
    true_view : (H, W, 3) ndarray
        ``view_truth.exr`` divided by the radiance gain.
    """
    surf = surface_errors(result.surface.heightfield, true_surface)
    seen = true_view.mean(axis=2) > OBJECT_MIN_LEVEL
    mask = result.view.valid & seen
    corners = score_corners(
        cal.cfg,
        true_view,
        distorted_view,
        result.view.image,
        true_surface,
        restored_valid=result.view.valid,
    )
    # The paper's STD pair on the same corners: those found in the truth, distorted and restored.
    pts = corners["points_px"]
    common = np.all([np.isfinite(p[:, 0]) for p in pts.values()], axis=0)
    same = {v: corner_spread(pts[v] - pts["truth"], common) for v in ("distorted", "restored")}
    counts = result.features.counts
    return {
        "wai_rmse_mm": surf["rmse_mm"],
        "wai_rmse_demeaned_mm": surf["rmse_demeaned_mm"],
        "wai_max_abs_mm": surf["max_abs_mm"],
        "wai_mean_offset_mm": surf["mean_offset_mm"],
        "wai_points": surf["n_points"],
        "corner_std_distorted_px": same["distorted"]["std_px"],
        "corner_std_restored_px": same["restored"]["std_px"],
        "corners_common": int(common.sum()),
        "corners": {k: v for k, v in corners.items() if k != "points_px"},
        "distorted": image_metrics(distorted_view, true_view, mask),
        "restored": image_metrics(result.view.image, true_view, mask),
        "view_pixels_with_object": int(seen.sum()),
        "view_restored_fraction": float(mask.sum() / max(seen.sum(), 1)),
        "view_status_counts": result.view.counts,
        "features_detected": int(counts.get("detected", 0)),
        "features_used": int(len(result.surface.ij)),
        "features_rejected": int(
            sum(v for k, v in counts.items() if k.startswith("rejected_"))
        ),
        "feature_counts": counts,
        "refine_iterations": int(result.surface.iterations),
        "anchor": result.surface.anchor,
        "_error_map": surf["error_map_mm"],
        "_corner_points": corners["points_px"],
    }


def load_and_score(render_dir: str | Path, result: RestoreResult, cal: Calibration,
                   distorted_view: NDArray) -> dict[str, Any]:
    """Read the truth of ``render_dir`` and :func:`score` against it."""
    surface, view = load_truth(render_dir, cal)
    return score(result, distorted_view, cal, surface, view)


def surface_profile(
    est: Heightfield, truth: Heightfield, y_mm: float = 0.0
) -> tuple[NDArray, NDArray, NDArray]:
    """Heights along ``y = y_mm`` of the estimate and the truth (the paper's Fig. 11f), mm."""
    x = est.x
    y = np.full_like(x, y_mm)
    return x, est.height(x, y), truth.height(x, y)
