"""A truth-free score for a view of a planar checkerboard: how far its corners are from a grid.

A pinhole camera maps a plane by a homography, so the inner corners of a flat checkerboard seen
with nothing between (or well restored) lie exactly on a homography of a regular grid. The
residual of the best such homography measures what distortion is left, with no ground truth
and no calibration; the corners' frame-to-frame motion measures how much the water moves them.
A camera under the water looking up at a board in air sees it through refraction even when
the water is still: ``model="flat-water"`` (:mod:`~restoration.video.gridscore`) fits that
smooth map instead, and :func:`grid_score` scores the part of a board a view shows.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from restoration.video.frames import to_grey_u8
from restoration.video.gridscore import FLAT_WATER_MIN_CORNERS, flat_water_residuals_px
from wai_core.errors import WaiInputError

__all__ = [
    "FLAT_WATER_TRIM",
    "GRID_MODELS",
    "CheckerScore",
    "GridScore",
    "checkerboard_score",
    "grid_residual_px",
    "grid_score",
    "stability_px",
    "track_corners",
]

DETECT_FLAGS = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
"""``cv2.findChessboardCornersSB`` flags: search exhaustively, refine corners accurately."""

DETECT_SEED = 0
"""OpenCV's random generator is seeded with this before every ``findChessboardCornersSB``
call: the detector draws from it, and on a distorted view the board it grows, hence its
score, can depend on the draw (``tests/restoration/test_grid_score.py``)."""

RING_CONTRAST = 0.15
"""A tracked corner is kept when the ring around it swings by at least this share of the grey
range (0-255) between its two dark and two light arcs."""

GRID_MODELS = ("homography", "flat-water")
"""The maps of a regular grid :func:`grid_residual_px` fits: a plane seen by a pinhole camera;
a plane in air seen by a camera under flat water (:mod:`~restoration.video.gridscore`)."""

FLAT_WATER_TRIM = 0.1
"""Share of the worst corners the flat-water score leaves out: where the board meets the
black band beyond Snell's window the detector takes the band for a dark square and misplaces
the corners along it."""

_RING_SAMPLES = 32
_MAX_STEP_RATIO = 1.8
"""Neighbouring steps along a detected row or column differ by less than this factor (more
near Snell's window's edge, where refraction squeezes the cells, than through the waves); a
grid that jumps a corner doubles one."""
_GRID_STARTS = ((4, 4), (6, 6), (5, 5), (3, 3), (8, 8))
"""Boards :func:`grid_score` asks the detector for in turn (it grows each to the largest
regular block it can follow), until one gives a grid of at least 4 x 4 corners that skips
none."""


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
    corners: ArrayLike,
    pattern: Sequence[int],
    used: ArrayLike | None = None,
    model: str = "homography",
    trim: float | None = None,
    n_water: float = 4.0 / 3.0,
) -> float:
    """RMS distance (px) of corners from the least-squares map of a regular grid.

    Parameters
    ----------
    corners : (cols * rows, 2) array_like
        Corners (x, y) in px, ``cols`` per row, rows in order; NaN rows (lost corners, as
        :func:`track_corners` leaves them) are left out.
    pattern : (cols, rows)
    used : (cols * rows,) array_like of bool, optional
        The corners to fit and score; all finite ones by default.
    model : {"homography", "flat-water"}
        ``"homography"``: a plane seen by a pinhole camera (at least 4 corners).
        ``"flat-water"``: a board in air seen from under flat water
        (:func:`~restoration.video.gridscore.flat_water_residuals_px`; square cells, at
        least :data:`~restoration.video.gridscore.FLAT_WATER_MIN_CORNERS` corners).
    trim : float in [0, 0.5], optional
        Share of the corners furthest from the model left out of the RMS (and, for flat
        water, out of a second fit); by default 0 for the homography,
        :data:`FLAT_WATER_TRIM` for flat water.
    n_water : float
        The water's refractive index (``"flat-water"`` only).

    Returns
    -------
    float
        0 for any view of a regular grid the model describes; grows with the distortion; NaN
        when too few corners are used.

    Examples
    --------
    >>> import numpy as np
    >>> j, i = np.mgrid[0:3, 0:4]
    >>> grid = np.c_[10 + 20 * i.ravel(), 5 + 20 * j.ravel()].astype(float)
    >>> round(grid_residual_px(grid, (4, 3)), 9)
    0.0
    """
    cols, rows = _check_pattern(pattern)
    if model not in GRID_MODELS:
        raise WaiInputError(f"model must be one of {', '.join(GRID_MODELS)}, not {model!r}")
    trim = (FLAT_WATER_TRIM if model == "flat-water" else 0.0) if trim is None else float(trim)
    if not 0.0 <= trim <= 0.5:
        raise WaiInputError(f"trim must lie in [0, 0.5], got {trim}")
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] != cols * rows:
        raise WaiInputError(f"{pts.shape[0]} corners do not fill a {cols}x{rows} pattern")
    mask = np.isfinite(pts).all(axis=1)
    if used is not None:
        mask &= np.asarray(used, bool).ravel()
    j, i = np.mgrid[0:rows, 0:cols]
    ideal = np.c_[i.ravel(), j.ravel()].astype(np.float64)[mask]
    if model == "flat-water":
        if np.count_nonzero(mask) < FLAT_WATER_MIN_CORNERS:
            return float("nan")
        dist = flat_water_residuals_px(pts[mask], ideal, n_water, trim)
    else:
        if np.count_nonzero(mask) < 4:
            return float("nan")
        hom, _ = cv2.findHomography(ideal, pts[mask], 0)
        if hom is None:
            return float("nan")
        fitted = cv2.perspectiveTransform(ideal[None], hom)[0]
        dist = np.linalg.norm(fitted - pts[mask], axis=1)
    kept = np.sort(dist)[: max(1, int(round(dist.size * (1.0 - trim))))]
    return float(np.sqrt(np.mean(kept**2)))


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
    cv2.setRNGSeed(DETECT_SEED)
    ok, found = cv2.findChessboardCornersSB(grey, (cols, rows), flags=DETECT_FLAGS)
    if ok and found is not None:
        corners = found.reshape(-1, 2).astype(np.float64)
        rms = grid_residual_px(corners, (cols, rows))
        return CheckerScore(True, 1.0, rms, corners, (cols, rows))
    return CheckerScore(False, 0.0, float("nan"), np.zeros((0, 2)), (cols, rows))


@dataclass(frozen=True)
class GridScore:
    """The corner-grid score of the part of a board that one view shows.

    Attributes
    ----------
    found : bool
        The detector found a block of at least 4 x 4 inner corners that skips none.
    pattern : tuple of int
        The found part's inner corners (cols, rows) in the detector's order (its rows may
        run down the image's columns); (0, 0) when not found.
    corners : (cols * rows, 2) ndarray of float64
        Its corners (x, y) in px, ``cols`` per row.
    used : (cols * rows,) ndarray of bool
        The corners scored: those whose neighbourhood the view restored.
    rms_px : float
        :func:`grid_residual_px` of the used corners under ``model``; NaN when not found or
        too few were used.
    fraction : float
        Corners used over the board's inner corners; NaN when the board was not given.
    model : str
        The grid map fitted (:data:`GRID_MODELS`).
    """

    found: bool
    pattern: tuple[int, int]
    corners: NDArray[np.float64]
    used: NDArray[np.bool_]
    rms_px: float
    fraction: float
    model: str


def grid_score(
    image: ArrayLike,
    board: Sequence[int] | None = None,
    valid: ArrayLike | None = None,
    model: str = "flat-water",
    trim: float | None = None,
    n_water: float = 4.0 / 3.0,
) -> GridScore:
    """Find a part of a checkerboard a view shows and score its corners' grid.

    For views that cut the board (it runs off the image, into Snell's window's edge, or into
    what a restoration left out): ``cv2.findChessboardCornersSBWithMeta`` with
    ``CALIB_CB_LARGER`` returns the largest regular block of corners it can follow from a
    small start. On a view cut into pieces it may join every other row or jump a corner;
    such a grid is refused (halfway between its neighbours lie corners, not edges; or one
    step is twice the next) and the next start tried.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array_like
        The view: float on the [0, 1] scale (NaN counts as black), or uint8.
    board : (cols, rows), optional
        The whole board's inner corners, for :attr:`GridScore.fraction`.
    valid : (H, W) array_like of bool, optional
        Pixels the view holds (a restoration's mask); the others are filled with the held
        pixels' mean grey (neither a dark nor a light square) and corners within 2 px of
        them are not scored.
    model, trim, n_water
        As :func:`grid_residual_px` (flat water by default: a camera under water looking up).

    Returns
    -------
    GridScore

    Examples
    --------
    A board larger than the view, seen straight on:

    >>> import numpy as np
    >>> y, x = np.mgrid[0:120, 0:160]
    >>> board = (((x + 7) // 20 + (y + 3) // 20) % 2).astype(np.float32)
    >>> s = grid_score(board, board=(12, 9), model="homography")
    >>> s.found, sorted(s.pattern), s.rms_px < 0.1, round(s.fraction, 3)
    (True, [5, 7], True, 0.324)
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = np.nan_to_num(img.astype(np.float32), nan=0.0)
    mask = None
    if valid is not None:
        mask = np.asarray(valid, bool)
        if mask.shape != img.shape[:2]:
            raise WaiInputError(f"valid mask {mask.shape} does not match the image {img.shape}")
        fill = img[mask].mean() if mask.any() else 0
        img = np.where(mask if img.ndim == 2 else mask[..., None], img, fill).astype(img.dtype)
    whole = float("nan") if board is None else float(np.prod(_check_pattern(board)))
    grey = _grey(img)
    for start in _GRID_STARTS:
        cv2.setRNGSeed(DETECT_SEED)
        ok, found, meta = cv2.findChessboardCornersSBWithMeta(
            grey, start, DETECT_FLAGS | cv2.CALIB_CB_LARGER
        )
        if not ok or found is None or meta is None:
            continue
        rows, cols = meta.shape[:2]
        corners = found.reshape(-1, 2).astype(np.float64)
        if not _skips_corners(grey, corners, (cols, rows)):
            break
    else:
        return GridScore(False, (0, 0), np.zeros((0, 2)), np.zeros(0, bool), float("nan"),
                         0.0 if board is not None else whole, model)
    used = np.ones(len(corners), bool)
    if mask is not None:
        inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8), borderValue=0)
        c = np.rint(corners).astype(int)
        inside = (c[:, 0] >= 0) & (c[:, 1] >= 0) & (c[:, 0] < mask.shape[1])
        inside &= c[:, 1] < mask.shape[0]
        used[inside] = inner[c[inside, 1], c[inside, 0]] > 0
        used[~inside] = False
    rms = grid_residual_px(corners, (cols, rows), used, model, trim, n_water)
    return GridScore(True, (cols, rows), corners, used, rms, float(used.sum() / whole), model)


def _skips_corners(grey: NDArray[np.uint8], corners: NDArray, pattern: tuple[int, int]) -> bool:
    """True when a detected grid steps over corners: on a view cut into pieces the detector
    may join every other row or column, or jump a corner in one. Halfway between two
    neighbours of a true grid lies an edge (no ring contrast), and a step along a row or
    column is close to the next (:data:`_MAX_STEP_RATIO`); a skipped corner breaks both."""
    cols, rows = pattern
    if min(cols, rows) < 4:
        return True
    grid = corners.reshape(rows, cols, 2)
    steps = [np.linalg.norm(np.diff(grid, axis=a), axis=2) for a in (1, 0)]
    with np.errstate(divide="ignore", invalid="ignore"):  # two corners in one place
        ratios = np.r_[(steps[0][:, 1:] / steps[0][:, :-1]).ravel(),
                       (steps[1][1:] / steps[1][:-1]).ravel()]
        stretch = np.maximum(ratios, 1.0 / ratios)
    if not np.all(np.isfinite(stretch)) or np.any(stretch > _MAX_STEP_RATIO):
        return True
    along = (grid[:, 1:] + grid[:, :-1]) / 2.0, (grid[1:] + grid[:-1]) / 2.0
    radius = max(2.0, float(min(np.median(st) for st in steps)) / 4.0)
    grey_f = grey.astype(np.float32)
    return any(
        float(np.median(_ring_contrast(grey_f, mid.reshape(-1, 2), radius)))
        >= RING_CONTRAST * 255.0
        for mid in along
    )


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
