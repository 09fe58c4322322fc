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

__all__ = ["CheckerScore", "checkerboard_score", "grid_residual_px", "stability_px"]

DETECT_FLAGS = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
"""``cv2.findChessboardCornersSB`` flags: search exhaustively, refine corners accurately."""


@dataclass(frozen=True)
class CheckerScore:
    """The corner-grid score of one image.

    Attributes
    ----------
    found : bool
        The detector found the full pattern of inner corners.
    fraction : float
        Corners found over corners expected: 1 or 0 from the detector (it finds all or
        none); the share of refined seed corners when the score was seeded.
    rms_px : float
        RMS distance (px) of the corners from the best homography of a regular grid; NaN when
        not found.
    corners : (M, 2) ndarray of float64
        The detected corners (x, y) in px, row by row as the detector orders them (the
        converged seed corners, in the seed's order, when seeded); (0, 2) when not found.
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
        Corners (x, y) in px, ``cols`` per row, rows in order.
    pattern : (cols, rows)
    used : (cols * rows,) array_like of bool, optional
        The corners to fit and score (at least 4); all by default.

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
    mask = np.ones(len(pts), bool) if used is None else np.asarray(used, bool).ravel()
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


def _refine_seed(
    grey: NDArray[np.uint8], seed: NDArray[np.float64], pattern: tuple[int, int]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Corners refined from ``seed`` to the image's nearest saddle points, and which of them
    converged within the search window (a quarter of the grid spacing)."""
    cols, rows = pattern
    grid = seed.reshape(rows, cols, 2)
    spacing = np.median(
        np.r_[
            np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel(),
            np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel(),
        ]
    )
    half = max(2, int(round(spacing / 4)))
    pts = seed.astype(np.float32).reshape(-1, 1, 2).copy()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.01)
    refined = cv2.cornerSubPix(grey, pts, (half, half), (-1, -1), crit).reshape(-1, 2)
    h, w = grey.shape
    moved = np.abs(refined - seed).max(axis=1)
    inside = (refined[:, 0] >= 0) & (refined[:, 0] <= w - 1) & (refined[:, 1] >= 0)
    ok = (moved < half) & inside & (refined[:, 1] <= h - 1)
    return refined.astype(np.float64), ok


def checkerboard_score(
    image: ArrayLike, pattern: Sequence[int], seed: ArrayLike | None = None
) -> CheckerScore:
    """Detect a checkerboard's inner corners and score their distance from a planar grid.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array_like
        The view: float on the [0, 1] scale, or uint8.
    pattern : (cols, rows)
        Inner corners per row and per column of the board.
    seed : (cols * rows, 2) array_like, optional
        Corners found in another view of the same board (e.g. a restored image). When the
        detector misses the pattern here, each seed corner is refined to this image's nearest
        saddle point (``cv2.cornerSubPix``, window a quarter of the grid spacing) instead, and
        the corners that converged are scored: a comparable score for views too distorted or
        blurred for the detector.

    Returns
    -------
    CheckerScore
        When the full pattern is not found (``cv2.findChessboardCornersSB``, exhaustive and
        accurate) and no seed is given: ``found=False``, ``fraction=0``, NaN ``rms_px``.
        With a seed: ``found=False``, ``fraction`` the share of the seed's corners that
        converged, ``rms_px`` over those.

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
    if seed is None:
        return CheckerScore(False, 0.0, float("nan"), np.zeros((0, 2)), (cols, rows))
    seed_pts = np.asarray(seed, dtype=np.float64).reshape(-1, 2)
    if seed_pts.shape[0] != cols * rows:
        raise WaiInputError(f"seed holds {seed_pts.shape[0]} corners, not {cols}x{rows}")
    corners, used = _refine_seed(grey, seed_pts, (cols, rows))
    rms = grid_residual_px(corners, (cols, rows), used)
    fraction = float(np.mean(used))
    return CheckerScore(False, fraction, rms, corners[used], (cols, rows))


def stability_px(corner_sets: Sequence[ArrayLike | None]) -> float:
    """Frame-to-frame RMS motion (px) of a checkerboard's corners over a sequence.

    Parameters
    ----------
    corner_sets : sequence of (M, 2) array_like or None
        Each frame's corners in detector order (``CheckerScore.corners``); None or an empty
        array where the board was not found. Only consecutive frames that both hold the same
        number of corners are compared; a pair whose order is reversed (the detector may
        start from the opposite corner) is compared in the matching order.

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
        sq.append(forward if forward.sum() <= backward.sum() else backward)
    if not sq:
        return float("nan")
    return float(np.sqrt(np.mean(np.concatenate(sq))))
