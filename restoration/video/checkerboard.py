"""A truth-free score for a view of a planar checkerboard: how far its corners are from a grid.

A pinhole camera maps a plane by a homography, so the inner corners of a flat checkerboard seen
through still water (or well restored) lie exactly on a homography of a regular grid. The
residual of the best such homography measures what distortion is left, with no ground truth
and no calibration; the corners' frame-to-frame motion measures how much the water moves them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from restoration.video.frames import to_grey_u8
from wai_core.errors import WaiInputError

__all__ = [
    "CheckerScore",
    "checkerboard_score",
    "grid_residual_px",
    "stability_px",
    "track_corners",
]

DETECT_FLAGS = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
"""``cv2.findChessboardCornersSB`` flags: search exhaustively, refine corners accurately."""

RING_CONTRAST = 0.15
"""A tracked corner is kept when the ring around it swings by at least this share of the grey
range (0-255) between its two dark and two light arcs."""

_RING_SAMPLES = 32


@dataclass(frozen=True)
class CheckerScore:
    """The corner-grid score of one image.

    Attributes
    ----------
    found : bool
        The detector found the full pattern of inner corners.
    fraction : float
        Corners found over corners expected: 1 or 0 (the detector finds all or none).
    rms_px : float
        RMS distance (px) of the corners from the best homography of a regular grid; NaN when
        nothing was found.
    corners : (M, 2) ndarray of float64
        The detected corners (x, y) in px, ``cols`` per row as the detector orders them;
        (0, 2) when not found.
    pattern : tuple of int
        The inner-corner pattern (cols, rows) that was looked for.
    """

    found: bool
    fraction: float
    rms_px: float
    corners: NDArray[np.float64]
    pattern: tuple[int, int]


def _check_pattern(pattern: Sequence[int]) -> tuple[int, int]:
    if len(pattern) != 2 or min(int(pattern[0]), int(pattern[1])) < 2:
        raise WaiInputError(f"pattern must be (cols, rows) of at least 2 each, got {pattern}")
    return int(pattern[0]), int(pattern[1])


def grid_residual_px(
    corners: ArrayLike, pattern: Sequence[int], used: ArrayLike | None = None
) -> float:
    """RMS distance (px) of corners from the least-squares homography of a regular grid.

    Parameters
    ----------
    corners : (cols * rows, 2) array_like
        Corners (x, y) in px, ``cols`` per row, rows in order; NaN rows (lost corners, as
        :func:`track_corners` leaves them) are left out.
    pattern : (cols, rows)
    used : (cols * rows,) array_like of bool, optional
        The corners to fit and score (at least 4); all finite ones by default.

    Returns
    -------
    float
        0 for any homography of a regular grid; grows with the distortion; NaN when fewer
        than 4 corners are used.

    Examples
    --------
    >>> import numpy as np
    >>> j, i = np.mgrid[0:3, 0:4]
    >>> grid = np.c_[10 + 20 * i.ravel(), 5 + 20 * j.ravel()].astype(float)
    >>> round(grid_residual_px(grid, (4, 3)), 9)
    0.0
    """
    cols, rows = _check_pattern(pattern)
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] != cols * rows:
        raise WaiInputError(f"{pts.shape[0]} corners do not fill a {cols}x{rows} pattern")
    mask = np.isfinite(pts).all(axis=1)
    if used is not None:
        mask &= np.asarray(used, bool).ravel()
    if np.count_nonzero(mask) < 4:
        return float("nan")
    j, i = np.mgrid[0:rows, 0:cols]
    ideal = np.c_[i.ravel(), j.ravel()].astype(np.float64)[mask]
    hom, _ = cv2.findHomography(ideal, pts[mask], 0)
    if hom is None:
        return float("nan")
    fitted = cv2.perspectiveTransform(ideal[None], hom)[0]
    return float(np.sqrt(np.mean(np.sum((fitted - pts[mask]) ** 2, axis=1))))


def _grey(image: ArrayLike) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise WaiInputError(f"image must be (H, W) or (H, W, 3), got {img.shape}")
    if img.dtype == np.uint8:
        return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return to_grey_u8(img)


def checkerboard_score(image: ArrayLike, pattern: Sequence[int]) -> CheckerScore:
    """Detect a checkerboard's inner corners and score their distance from a planar grid.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array_like
        The view: float on the [0, 1] scale, or uint8.
    pattern : (cols, rows)
        Inner corners per row and per column of the board.

    Returns
    -------
    CheckerScore
        ``found`` when the full pattern was detected (``cv2.findChessboardCornersSB``,
        exhaustive and accurate); otherwise ``fraction=0`` and NaN ``rms_px`` (the detector
        finds all corners or none; :func:`track_corners` follows a known board's corners
        through views it misses).

    Examples
    --------
    >>> import numpy as np
    >>> y, x = np.mgrid[0:120, 0:160]
    >>> board = np.where((x >= 20) & (x < 140) & (y >= 20) & (y < 100),
    ...                  ((x - 20) // 20 + (y - 20) // 20) % 2, 1).astype(np.float32)
    >>> s = checkerboard_score(board, (5, 3))
    >>> s.found, s.fraction, s.rms_px < 0.1
    (True, 1.0, True)
    """
    cols, rows = _check_pattern(pattern)
    grey = _grey(image)
    ok, found = cv2.findChessboardCornersSB(grey, (cols, rows), flags=DETECT_FLAGS)
    if ok and found is not None:
        corners = found.reshape(-1, 2).astype(np.float64)
        rms = grid_residual_px(corners, (cols, rows))
        return CheckerScore(True, 1.0, rms, corners, (cols, rows))
    return CheckerScore(False, 0.0, float("nan"), np.zeros((0, 2)), (cols, rows))


def _ring_contrast(grey: NDArray[np.float32], pts: NDArray, radius: float) -> NDArray:
    """For each point, how clearly the ring of ``radius`` px around it shows a checkerboard
    corner: the swing between the ring's opposite-quadrant means (dark, light, dark, light),
    taken at the ring's best rotation, on the 0-255 scale; 0 for anything else."""
    theta = 2.0 * np.pi * np.arange(_RING_SAMPLES) / _RING_SAMPLES
    xs = (pts[:, :1] + radius * np.cos(theta)).astype(np.float32)
    ys = (pts[:, 1:] + radius * np.sin(theta)).astype(np.float32)
    ring = cv2.remap(grey, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    quarter = _RING_SAMPLES // 4
    # A corner's ring alternates by quadrant: +1 -1 +1 -1 against its mean, at some rotation.
    sign = np.repeat([1.0, -1.0, 1.0, -1.0], quarter)
    centred = ring - ring.mean(axis=1, keepdims=True)
    best = np.zeros(len(pts))
    for shift in range(quarter * 2):
        best = np.maximum(best, np.abs(centred @ np.roll(sign, shift)) / (_RING_SAMPLES / 2))
    return best


def track_corners(
    frames: ArrayLike, seed: ArrayLike, pattern: Sequence[int]
) -> NDArray[np.float64]:
    """Follow a checkerboard's corners through frames the detector cannot read.

    Each corner of ``seed`` (the corners found in a restored view of the same board) is
    refined to the nearest saddle point of every frame (``cv2.cornerSubPix``, window a
    quarter of the grid spacing); a corner is kept where the refinement stayed inside its
    window and the ring around it still shows a corner (:data:`RING_CONTRAST`). Meant for
    sharp frames: a blurred view (the temporal mean) has no saddle to converge to.

    Parameters
    ----------
    frames : (N, H, W[, 3]) array_like
        Float frames on the [0, 1] scale, or uint8.
    seed : (cols * rows, 2) array_like
        Corners (x, y) in px, row by row.
    pattern : (cols, rows)

    Returns
    -------
    (N, cols * rows, 2) ndarray of float64
        Each frame's corners in the seed's order; NaN where a corner was lost.

    Examples
    --------
    >>> import numpy as np
    >>> y, x = np.mgrid[0:120, 0:160]
    >>> board = np.where((x >= 20) & (x < 140) & (y >= 20) & (y < 100),
    ...                  ((x - 20) // 20 + (y - 20) // 20) % 2, 1).astype(np.float32)
    >>> j, i = np.mgrid[0:3, 0:5]
    >>> corners = np.c_[39.5 + 20 * i.ravel(), 39.5 + 20 * j.ravel()]  # pixel edges
    >>> tracked = track_corners(board[None], corners + 2.0, (5, 3))
    >>> bool(np.abs(tracked[0] - corners).max() < 0.05)
    True
    """
    cols, rows = _check_pattern(pattern)
    pts = np.asarray(seed, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] != cols * rows:
        raise WaiInputError(f"seed holds {pts.shape[0]} corners, not {cols}x{rows}")
    grid = pts.reshape(rows, cols, 2)
    steps = np.r_[
        np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel(),
        np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel(),
    ]
    half = max(2, int(round(float(np.median(steps)) / 4)))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.01)
    stack = np.asarray(frames)
    out = np.full((stack.shape[0], pts.shape[0], 2), np.nan)
    for n, frame in enumerate(stack):
        grey = _grey(frame)
        start = pts.astype(np.float32).reshape(-1, 1, 2).copy()
        refined = cv2.cornerSubPix(grey, start, (half, half), (-1, -1), crit).reshape(-1, 2)
        h, w = grey.shape
        inside = (refined[:, 0] >= 0) & (refined[:, 0] <= w - 1)
        inside &= (refined[:, 1] >= 0) & (refined[:, 1] <= h - 1)
        near = np.abs(refined - pts).max(axis=1) < half
        contrast = _ring_contrast(grey.astype(np.float32), refined, float(half))
        ok = inside & near & (contrast >= RING_CONTRAST * 255.0)
        out[n, ok] = refined[ok]
    return out


def stability_px(corner_sets: Sequence[ArrayLike | None]) -> float:
    """Frame-to-frame RMS motion (px) of a checkerboard's corners over a sequence.

    Parameters
    ----------
    corner_sets : sequence of (M, 2) array_like or None
        Each frame's corners in a fixed order (:func:`track_corners`, or
        ``CheckerScore.corners`` of full detections); None or an empty array where the board
        was not found, NaN rows for lost corners. Consecutive frames of the same corner count
        are compared over the corners both hold; a pair whose order is reversed (the
        detector may start from the opposite corner) is compared in the matching order.

    Returns
    -------
    float
        RMS of the corners' displacements over all compared pairs, in px; NaN when no pair.

    Examples
    --------
    >>> import numpy as np
    >>> a = np.array([[0.0, 0.0], [10.0, 0.0]])
    >>> stability_px([a, a + [3.0, 4.0], None, a])
    5.0
    """
    sq = []
    for prev, cur in zip(corner_sets[:-1], corner_sets[1:], strict=True):
        if prev is None or cur is None:
            continue
        a = np.asarray(prev, dtype=np.float64).reshape(-1, 2)
        b = np.asarray(cur, dtype=np.float64).reshape(-1, 2)
        if a.shape[0] == 0 or a.shape != b.shape:
            continue
        forward = np.sum((b - a) ** 2, axis=1)
        backward = np.sum((b[::-1] - a) ** 2, axis=1)
        fwd, bwd = forward[np.isfinite(forward)], backward[np.isfinite(backward)]
        if fwd.size == 0:
            continue
        sq.append(fwd if bwd.size == 0 or fwd.mean() <= bwd.mean() else bwd)
    if not sq:
        return float("nan")
    return float(np.sqrt(np.mean(np.concatenate(sq))))
