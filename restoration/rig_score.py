"""A truth-free score for a view from a calibrated rig: its corners against the rig's own.

A rig whose camera v, water level and checkerboard placement are calibrated knows where the
board's inner corners appear when the water is still
(:func:`~restoration.metrics.predict_corners` through flat water). A restored view's corners,
found near those positions,
should lie on them; their spread about that map, less a common shift (the board's in-plane
placement is what a rig knows least well), is the paper's corner STD with the calibration in
place of the truth's corners. Unlike the free grid models of
:func:`restoration.video.grid_score`, which fit the map to each view and so absorb any
smooth warp of the whole image, it sees a view that is sharp but displaced, which is what
video-only methods give: they register the frames to their own temporal mean, whose geometry
a short sequence leaves off the flat-water view's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from restoration.metrics import (
    _camera_v,
    _window_valid,
    corner_offsets,
    corner_spread,
    corner_window_px,
    predict_corners,
    refine_corners,
)
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError

__all__ = ["RigGridScore", "rig_grid_score"]

RIG_MIN_CORNERS = 10
"""Fewest corners a :class:`RigGridScore` needs for a spread (as ``wai experiment compare``'s
corner STD)."""


@dataclass(frozen=True)
class RigGridScore:
    """The corners of one view against the calibrated rig's flat-water corners.

    Attributes
    ----------
    std_px : float
        RMS distance of the found corners from their flat-water positions after the common
        shift is removed, px of camera v; NaN on fewer than :data:`RIG_MIN_CORNERS` corners.
    shift_px : (2,) ndarray
        The common shift (x, y), px: the board's placement error, or the view's drift.
    corners_px : (K, 2) ndarray
        The corners found (x, y), px, in the order of the rig's board; NaN where lost.
    expected_px : (K, 2) ndarray
        Their flat-water positions from the rig; NaN outside the image or Snell's window.
    n_found : int
        Corners found (near their expected positions, in the restored part of the view).
    fraction : float
        ``n_found`` over the corners the rig expects in view.
    """

    std_px: float
    shift_px: NDArray[np.float64]
    corners_px: NDArray[np.float64]
    expected_px: NDArray[np.float64]
    n_found: int
    fraction: float


def rig_grid_score(
    image: ArrayLike, cfg: SystemConfig, valid: ArrayLike | None = None,
    win: int | None = None,
) -> RigGridScore:
    """Score a view of the rig's checkerboard against the rig's flat-water corners.

    Corners are refined (:func:`~restoration.metrics.refine_corners`) from their flat-water
    positions; a corner not found as a saddle within ``win`` px, near the border, or (with
    ``valid``) near a pixel the view left out is lost and counted, never scored.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array_like
        The view in camera v's pixels, on the [0, 1] scale (NaN counts as black).
    cfg : SystemConfig
        The rig: camera v, water (level, index), object plane and board.
    valid : (H, W) array_like of bool, optional
        Pixels the view holds (a restoration's mask).
    win : int, optional
        Half window of the corner search, px; by default
        :func:`~restoration.metrics.corner_window_px` of camera v.

    Returns
    -------
    RigGridScore

    Examples
    --------
    The flat-water prediction drawn as dots scores no board (dots are not saddles):

    >>> import numpy as np
    >>> from wai_core.config import load_config
    >>> cfg = load_config("scenes/paper.toml")
    >>> s = rig_grid_score(np.zeros((600, 800)), cfg)
    >>> s.n_found, bool(np.isnan(s.std_px))
    (0, True)
    """
    img = np.asarray(image)
    cam = _camera_v(cfg)
    if img.shape[:2] != (cam.height_px, cam.width_px):
        raise WaiInputError(f"view {img.shape[:2]} is not camera v's "
                            f"{cam.height_px} x {cam.width_px} pixels")
    win = corner_window_px(cam) if win is None else int(win)
    expected, in_view = predict_corners(cfg, None, margin_px=win + 1)
    found, ok = refine_corners(img, expected, win)
    if valid is not None:
        ok &= _window_valid(np.asarray(valid, bool), found, win)
    found[~ok] = np.nan
    spread = corner_spread(*corner_offsets(found, ok, expected, in_view))
    n = spread["n_used"]
    std = spread["std_px"] if n >= RIG_MIN_CORNERS else float("nan")
    return RigGridScore(std_px=float(std), shift_px=np.asarray(spread["mean_px"], float),
                        corners_px=found, expected_px=expected, n_found=n,
                        fraction=n / max(int(in_view.sum()), 1))
