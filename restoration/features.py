"""Pattern features on camera s and their correspondence with the projector's dot grid.

The paper (Jian et al. 2022, section 3.2.1) needs, for every projected dot ``k``, its spot ``s_k`` on
the diffuser in the wavy image and the dot's grid index, so that the projector ray ``v_k^p`` is
known. Section 4.2 (eq. 33) states when this correspondence can be made by ordering alone:
neighbouring spots must keep their order with a margin, ``s_k + dp/2 < s_{k+1}``. This module

1. detects the spots (:func:`detect_spots`) with sub-pixel centres,
2. predicts where each dot lands for flat water from calibration only (:func:`predict_flat_spots`),
3. labels the flat-water spots with grid indices (:func:`match_reference`),
4. labels the wavy-water spots by region growing over the grid from a confident seed, then drops
   matches that break eq. 33's ordering, merged blobs and doubly claimed spots
   (:func:`match_distorted`),

and :func:`find_features` runs the four steps. Pixel coordinates are continuous ``(col, row)`` with
integer values at pixel centres (see :mod:`wai_core.geometry`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.geometry import intersect_plane_z, reflect
from wai_core.pattern import dot_grid

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_LATTICE_PAD = 2
_DIRS4 = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]])
_DIRS8 = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [1, -1], [-1, 1], [-1, -1]])


# ----------------------------------------------------------------------------------------------
# Results
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Spots:
    """Spots detected in one camera-s image.

    Attributes
    ----------
    centres_px : (P, 2) ndarray
        Sub-pixel centres ``(col, row)``, pixels (integer = pixel centre).
    flux : (P,) ndarray
        Background-subtracted intensity summed over the spot's segment (image units x pixels).
    peak : (P,) ndarray
        Peak of the smoothed, background-subtracted image in the segment (image units).
    area_px : (P,) ndarray of int
        Pixels in the spot's segment.
    cov_px2 : (P, 2, 2) ndarray
        Estimated spot covariance (second moments of the spot profile), pixels^2.
    merged : (P,) ndarray of bool
        Segment much larger than its neighbours': probably two or more dots run together.
    border : (P,) ndarray of bool
        Segment touches the image border (the centre is biased towards the inside).
    saturated : (P,) ndarray of bool
        Peak at or above the saturation level given to :func:`detect_spots`.
    """

    centres_px: FloatArray
    flux: FloatArray
    peak: FloatArray
    area_px: IntArray
    cov_px2: FloatArray
    merged: BoolArray
    border: BoolArray
    saturated: BoolArray

    def __len__(self) -> int:
        return int(self.centres_px.shape[0])

    @property
    def suspicious(self) -> BoolArray:
        """True for spots whose centre should not be trusted (merged, border or saturated)."""
        return self.merged | self.border | self.saturated


@dataclass(frozen=True)
class ReferenceGrid:
    """Flat-water spots labelled with their dot's grid index.

    Attributes
    ----------
    ij : (K, 2) ndarray of int
        Grid index ``(i, j)`` of each dot (see :func:`wai_core.pattern.dot_grid`).
    ref_px : (K, 2) ndarray
        Detected flat-water spot centre, pixels.
    pred_px : (K, 2) ndarray
        Calibration-only prediction of that centre (:func:`predict_flat_spots`), pixels.
    spacing_px : (K,) ndarray
        Local spot spacing: distance to the nearest grid neighbour in the image, pixels.
    unmatched_ij : (M, 2) ndarray of int
        In-view predicted dots for which no flat-water spot was found.
    counts : dict of str to int
        ``predicted_in_view``, ``matched``, ``unmatched_predicted``, ``unassigned_spots``.
    rms_px : float
        RMS distance between ``ref_px`` and ``pred_px``, pixels (calibration consistency).
    """

    ij: IntArray
    ref_px: FloatArray
    pred_px: FloatArray
    spacing_px: FloatArray
    unmatched_ij: IntArray
    counts: dict[str, int]
    rms_px: float


@dataclass(frozen=True)
class Matches:
    """Correspondence between grid dots, their flat-water spot and their wavy-water spot.

    Attributes
    ----------
    ij : (K, 2) ndarray of int
        Grid index of each kept match.
    ref_px : (K, 2) ndarray
        Flat-water spot centre, pixels.
    spot_px : (K, 2) ndarray
        Wavy-water spot centre, pixels.
    counts : dict of str to int
        ``detected`` spots in the wavy image; the reference dots split into ``matched`` (kept),
        ``rejected_order`` (break eq. 33 with a grid neighbour), ``rejected_merged`` (their spot is a
        merged blob), ``rejected_ambiguous`` (two candidate spots, or a spot claimed by two dots),
        ``rejected_border`` (their spot is cut by the border or saturated) and
        ``unmatched_reference`` (no spot found: lost in the wavy image); plus ``reference`` (their
        total) and ``unassigned_spots`` (detected spots matched to no dot).
    timings_ms : dict of str to float
        Wall time per step, ms (filled by :func:`find_features`).
    """

    ij: IntArray
    ref_px: FloatArray
    spot_px: FloatArray
    counts: dict[str, int]
    timings_ms: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.ij.shape[0])


# ----------------------------------------------------------------------------------------------
# 1. Spot detection
# ----------------------------------------------------------------------------------------------


def _luminance(image: NDArray) -> NDArray[np.float32]:
    """Sum of the colour channels as float32 (h, w); rejects bad shapes and non-finite values."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (1, 3, 4):
        img = img[..., :3].sum(axis=2, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 8:
        raise WaiInputError(f"pattern image must be (h, w) or (h, w, 3), got shape {image.shape}")
    if not np.issubdtype(img.dtype, np.number):
        raise WaiInputError(f"pattern image must be numeric, got {img.dtype}")
    img = img.astype(np.float32)
    if not np.isfinite(img).all():
        raise WaiInputError("pattern image contains NaN or infinite values")
    return img


def _background(smooth: NDArray[np.float32], size_px: int) -> NDArray[np.float32]:
    """Slowly varying background: local minimum over a window wider than a spot, then averaged."""
    kernel = np.ones((size_px, size_px), np.uint8)
    low = cv2.erode(smooth, kernel, borderType=cv2.BORDER_REPLICATE)
    return cv2.blur(low, (size_px, size_px), borderType=cv2.BORDER_REPLICATE)


def _noise_sigma(lum: NDArray[np.float32], smooth: NDArray[np.float32], smooth_px: float) -> float:
    """Noise standard deviation of the smoothed image (image units).

    Taken from the high-pass residual ``lum - smooth``, whose MAD is set by the dark background
    even when dots fill much of the image, and scaled by what the Gaussian does to white noise.
    """
    g = cv2.getGaussianKernel(2 * int(np.ceil(4 * smooth_px)) + 1, smooth_px).ravel()
    g2 = float(np.sum(g**2)) ** 2  # sum of the squared 2-D kernel
    g0 = float(g.max()) ** 2  # its centre weight
    sub = (lum[::3, ::3] - smooth[::3, ::3]).ravel()  # every 9th pixel is plenty
    mad = 1.4826 * float(np.median(np.abs(sub - np.median(sub))))
    return mad * float(np.sqrt(g2 / (1.0 - 2.0 * g0 + g2)))


def _weighted_moments(
    lab: IntArray, rows: IntArray, cols: IntArray, w: FloatArray, n: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-label total, mean (n, 2) and covariance (n, 2, 2) of pixels with weights ``w``."""
    tot = np.bincount(lab, w, n)
    safe = np.where(tot > 0, tot, 1.0)
    mx = np.bincount(lab, w * cols, n) / safe
    my = np.bincount(lab, w * rows, n) / safe
    dx, dy = cols - mx[lab], rows - my[lab]
    cov = np.empty((n, 2, 2))
    cov[:, 0, 0] = np.bincount(lab, w * dx * dx, n) / safe
    cov[:, 1, 1] = np.bincount(lab, w * dy * dy, n) / safe
    cov[:, 0, 1] = cov[:, 1, 0] = np.bincount(lab, w * dx * dy, n) / safe
    return tot, np.stack([mx, my], axis=1), cov


@dataclass(frozen=True)
class _Segments:
    """Per-label statistics of the segmented image (index 0 is the background)."""

    tot: FloatArray  # smoothed intensity summed over the segment
    mean: FloatArray  # (n, 2) smoothed-intensity centroid, px
    cov: FloatArray  # (n, 2, 2) smoothed-intensity second moments, px^2
    peak: FloatArray  # peak of the smoothed image
    flux: FloatArray  # raw intensity summed over the segment


def _segment_stats(
    labels: NDArray[np.int32], n: int, smooth: NDArray[np.float32], raw: NDArray[np.float32]
) -> _Segments:
    """Moments of every segment at once: ``bincount`` over the segmented pixels, no segment loop."""
    rows, cols = np.nonzero(labels)
    lab = labels[rows, cols]
    s = smooth[rows, cols].astype(np.float64)
    r = raw[rows, cols].astype(np.float64)
    tot, mean, cov = _weighted_moments(lab, rows, cols, np.clip(s, 0.0, None), n)
    peak = np.full(n, -np.inf)
    np.maximum.at(peak, lab, s)
    return _Segments(tot, mean, cov, peak, np.bincount(lab, r, n))


def _windowed_centroids(
    img: NDArray[np.float32],
    labels: NDArray[np.int32],
    keep_label: IntArray,
    own: IntArray,
    start: FloatArray,
    cov: FloatArray,
    half_px: int,
    n_iter: int,
) -> FloatArray:
    """Gaussian-windowed centroids (SExtractor's ``XWIN``) of spots sharing one window size.

    For a Gaussian spot of covariance C, a Gaussian window of the same C centred at ``x_n`` weights
    the spot into a Gaussian centred half-way to the true centre, so ``x_{n+1} = x_n + 2 (m - x_n)``
    (``m`` the weighted mean) converges in one step and stays unbiased for any symmetric profile;
    a wrong C only slows convergence. Pixels of *other* kept segments are masked so a much brighter
    neighbour cannot pull the centre.
    """
    off = np.arange(-half_px, half_px + 1)
    base = np.rint(start).astype(np.int64)
    h, w = img.shape
    cols = base[:, 0, None, None] + off[None, None, :]
    rows = base[:, 1, None, None] + off[None, :, None]
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    rc, cc = np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)
    lab = keep_label[labels[rc, cc]]
    keep = inside & ((lab == 0) | (lab == own[:, None, None]))
    vals = np.where(keep, img[rc, cc], np.float32(0.0))
    inv = np.linalg.inv(cov).astype(np.float32)
    a, b, c = inv[:, 0, 0, None], inv[:, 0, 1, None, None], inv[:, 1, 1, None]
    offf = off.astype(np.float32)[None, :]
    x = start.copy()
    for _ in range(n_iter):
        dx = offf - (x[:, 0] - base[:, 0]).astype(np.float32)[:, None]  # (n, w)
        dy = offf - (x[:, 1] - base[:, 1]).astype(np.float32)[:, None]
        q = (a * dx * dx)[:, None, :] + (c * dy * dy)[:, :, None]
        q += 2.0 * b * dy[:, :, None] * dx[:, None, :]
        wv = vals * np.exp(-0.5 * q)
        col_sum = wv.sum(axis=1)  # (n, w) over rows
        row_sum = wv.sum(axis=2)
        tot = col_sum.sum(axis=1).astype(np.float64)
        mx = np.einsum("nw,nw->n", col_sum, dx).astype(np.float64)
        my = np.einsum("nw,nw->n", row_sum, dy).astype(np.float64)
        ok = tot > 0
        step = 2.0 * np.stack([mx, my], axis=1) / np.where(ok, tot, 1.0)[:, None]
        # A step longer than a pixel means noise dominates the window: do not wander off.
        x += np.where(ok[:, None], np.clip(step, -1.0, 1.0), 0.0)
    return x


def _refine_centres(
    img: NDArray[np.float32],
    labels: NDArray[np.int32],
    keep_label: IntArray,
    own: IntArray,
    start: FloatArray,
    cov: FloatArray,
    n_iter: int = 3,
) -> FloatArray:
    """Windowed centroids for all spots, batched by window size (a loop over a few sizes).

    The window reaches 2.5 sigma + 1 px: beyond it the spot times the window is below 0.2 %.
    """
    sigma_max = np.sqrt(np.linalg.eigvalsh(cov)[:, 1])
    half = np.clip(np.ceil(2.5 * sigma_max + 1.0), 3, 24).astype(int)
    half = 3 * np.ceil(half / 3).astype(int)  # a handful of window sizes
    out = start.copy()
    for h_px in np.unique(half):
        sel = half == h_px
        out[sel] = _windowed_centroids(
            img, labels, keep_label, own[sel], start[sel], cov[sel], h_px, n_iter
        )
    return out


def _segment(
    smooth: NDArray[np.float32], radius_px: int, rel_level: float, floor: float
) -> tuple[int, NDArray[np.int32], NDArray[np.int32]]:
    """Label pixels above ``rel_level`` x their local maximum (and above ``floor``).

    The max filter's radius is under half the spot spacing, so a pixel is compared with its own
    dot's peak: a dim dot next to a bright one is segmented like the bright one.
    """
    size = 2 * radius_px + 1
    local_max = cv2.dilate(smooth, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
    mask = (smooth > rel_level * local_max) & (smooth > floor)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return n, labels, stats


def _spot_covariance(cov_seg: FloatArray) -> FloatArray:
    """Spot covariance (n, 2, 2) for the centroid window, from the segments' second moments.

    The segment (cut at a fraction of the smoothed peak) holds about 0.55 of the variance of a
    large spot and, because the smoothing widens a small one, about 0.85 of a small one's; the
    window needs only a rough width (a wrong one just slows convergence), so the moments are used
    as they are, with eigenvalues kept above (0.3 px)^2.
    """
    evals, evecs = np.linalg.eigh(cov_seg)
    evals = np.clip(evals, 0.3**2, None)
    return np.einsum("nij,nj,nkj->nik", evecs, evals, evecs)


def _local_ratio(values: FloatArray, centres: FloatArray, k: int = 8) -> FloatArray:
    """Each value divided by the median of its ``k`` nearest spots' values."""
    n = values.shape[0]
    if n < 3:
        return np.ones(n)
    kk = min(k, n - 1)
    _, idx = cKDTree(centres).query(centres, k=kk + 1)
    return values / np.median(values[idx[:, 1:]], axis=1)


def detect_spots(
    image: NDArray,
    *,
    smooth_px: float = 1.0,
    local_radius_px: int = 3,
    rel_level: float = 0.25,
    snr_min: float = 6.0,
    rel_floor: float = 1e-3,
    min_area_px: int = 3,
    merge_factor: float = 1.5,
    background_px: int = 25,
    saturation: float | None = None,
) -> Spots:
    """Detect the pattern's spots and measure their sub-pixel centres.

    A pixel belongs to a spot when the smoothed, background-subtracted image exceeds
    ``rel_level`` x its own local maximum (a max filter of radius ``local_radius_px``), so a dot
    100x dimmer than its neighbour is segmented as well as a bright one: the window is smaller
    than the spot spacing, hence a pixel is compared with its own dot's peak. Segments whose peak
    is not significant (below ``snr_min`` x noise or ``rel_floor`` x the bright-spot level) are
    dropped. Each centre starts at the segment's intensity centroid and is refined by a
    Gaussian-windowed centroid of the raw image (unbiased for symmetric spots, near-optimal in
    noise).

    Parameters
    ----------
    image : (h, w) or (h, w, 3) array_like
        Linear intensity (the channels are summed).
    smooth_px : float
        Standard deviation of the Gaussian that suppresses pixel noise before segmentation, px.
    local_radius_px : int
        Radius of the local maximum filter, px; keep it under half the smallest spot spacing.
    rel_level : float
        Segment level relative to the local maximum (0-1).
    snr_min : float
        Minimum peak over the background noise (robust standard deviation of the smoothed image).
    rel_floor : float
        Minimum peak relative to the bright-spot level (99.9th percentile of the image).
    min_area_px : int
        Smallest segment kept, pixels.
    merge_factor : float
        A spot is flagged ``merged`` when its equivalent area ``sqrt(det(cov))`` exceeds this
        multiple of its 8 nearest neighbours' median (two equal dots ``d`` apart give
        ``sqrt(1 + d^2 / 4 sigma^2)``; 1.5 flags pairs more than 2.2 sigma apart).
    background_px : int
        Window of the background estimate, px; wider than a spot's short axis.
    saturation : float, optional
        Level at or above which the raw peak is flagged ``saturated`` (None: float images never
        saturate).

    Returns
    -------
    Spots
        Possibly empty.

    Raises
    ------
    WaiInputError
        On a wrong shape or non-finite values.
    """
    lum = _luminance(image)
    smooth = cv2.GaussianBlur(lum, (0, 0), smooth_px, borderType=cv2.BORDER_REFLECT)
    noise = _noise_sigma(lum, smooth, smooth_px)
    bg = _background(smooth, background_px)
    smooth -= bg
    raw = lum - bg
    bright = float(np.percentile(smooth[::3, ::3], 99.9))  # level of the bright spots
    tiny = 1e-6 * max(float(smooth.max()), 1e-30)  # keeps a noiseless zero background out
    n, labels, stats = _segment(
        smooth, local_radius_px, rel_level, max(2.0 * noise, 0.2 * rel_floor * bright, tiny)
    )
    seg = _segment_stats(labels, n, smooth, raw)
    area = stats[:, cv2.CC_STAT_AREA]
    good = (
        (seg.peak > max(snr_min * noise, rel_floor * bright, tiny))
        & (area >= min_area_px)
        & (seg.tot > 0)
    )
    good[0] = False  # label 0 is the background
    idx = np.flatnonzero(good)
    keep_label = np.where(good, np.arange(n), 0)  # rejected segments count as background
    cov = _spot_covariance(seg.cov[idx])
    centres = _refine_centres(raw, labels, keep_label, idx, seg.mean[idx], cov)

    x, y, wd, ht = (stats[idx, k] for k in range(4))
    h, w = raw.shape
    border = (x == 0) | (y == 0) | (x + wd == w) | (y + ht == h)
    # Merging is judged on the segment's own moments (truncation and smoothing cancel in ratios).
    eq_area = np.sqrt(np.clip(np.linalg.det(seg.cov[idx]), 0.0, None))
    merged = _local_ratio(eq_area, centres) > merge_factor
    saturated = np.zeros(idx.size, bool)
    if saturation is not None:
        saturated = np.bincount(labels[lum >= saturation], minlength=n)[idx] > 0
    return Spots(
        centres_px=centres,
        flux=seg.flux[idx],
        peak=seg.peak[idx],
        area_px=area[idx].astype(np.int64),
        cov_px2=cov,
        merged=merged,
        border=border,
        saturated=saturated,
    )


# ----------------------------------------------------------------------------------------------
# 2. Calibration-only prediction for flat water
# ----------------------------------------------------------------------------------------------


def predict_flat_spots(
    cfg: SystemConfig, margin_px: float = 0.0
) -> tuple[IntArray, FloatArray, FloatArray, BoolArray]:
    """Where every dot of the grid lands in camera s when the water is flat.

    Projector ray through the dot's panel position -> plane ``z = h0`` -> mirror reflection about
    ``(0, 0, 1)`` -> diffuser plane ``z = z_h`` -> camera s. Panel -> camera s is then a plane
    projective map (a homography), so grid lines stay straight.

    Parameters
    ----------
    cfg : SystemConfig
        The system (projector, pattern, water level, diffuser height, camera s).
    margin_px : float
        Keep spots at least this far inside the image, pixels.

    Returns
    -------
    ij : (K, 2) ndarray of int
        Grid index of every dot (:func:`wai_core.pattern.dot_grid`).
    panel_px : (K, 2) ndarray
        Dot centre on the projector panel, panel pixels.
    spot_px : (K, 2) ndarray
        Predicted spot centre in camera s, pixels (NaN where the ray misses).
    in_view : (K,) ndarray of bool
        The ray goes up, hits the modelled water patch, comes down to the diffuser and the spot is
        in front of and inside camera s.
    """
    projector = cfg.projector.camera()
    cam = cfg.camera_s.camera()
    ij, panel = dot_grid(cfg.pattern, projector)
    origin, dirs = projector.pixel_rays(panel[:, 0], panel[:, 1])
    hit, _ = intersect_plane_z(origin, dirs, cfg.water.h0_mm)
    down = reflect(dirs, np.array([0.0, 0.0, 1.0]))
    spot, _ = intersect_plane_z(hit, down, cfg.diffuser.z_mm)
    cols, rows, in_front = cam.project(spot)
    spot_px = np.stack([cols, rows], axis=1)
    (x0, x1), (y0, y1) = cfg.water.extent_x_mm, cfg.water.extent_y_mm
    with np.errstate(invalid="ignore"):
        on_water = (hit[:, 0] >= x0) & (hit[:, 0] <= x1) & (hit[:, 1] >= y0) & (hit[:, 1] <= y1)
        in_view = (
            (dirs[:, 2] > 0)
            & on_water
            & np.isfinite(spot_px).all(axis=1)
            & in_front
            & cam.in_image(cols, rows, margin_px)
        )
    return ij.astype(np.int64), panel, spot_px, in_view


# ----------------------------------------------------------------------------------------------
# Lattice helpers: node index of the grid neighbour (i + di, j + dj)
# ----------------------------------------------------------------------------------------------


class _Lattice:
    """Dense lookup from grid index ``(i, j)`` to node number (-1 where absent)."""

    def __init__(self, ij: IntArray) -> None:
        self.ij = np.asarray(ij, dtype=np.int64)
        self.lo = self.ij.min(axis=0) - _LATTICE_PAD
        ni, nj = self.ij.max(axis=0) - self.lo + 1 + _LATTICE_PAD
        self.grid = np.full((nj, ni), -1, np.int64)
        self.grid[self.ij[:, 1] - self.lo[1], self.ij[:, 0] - self.lo[0]] = np.arange(len(ij))

    def neighbour(self, step: NDArray) -> IntArray:
        """Node number of each node's neighbour at ``(i, j) + step`` (|step| <= 2), or -1."""
        q = self.ij + np.asarray(step) - self.lo
        return self.grid[q[:, 1], q[:, 0]]


def _local_spacing(ij: IntArray, px: FloatArray) -> FloatArray:
    """Distance in the image from each node to its nearest present 4-neighbour, pixels."""
    lat = _Lattice(ij)
    dist = np.full((len(ij), 4), np.inf)
    for n, step in enumerate(_DIRS4):
        nb = lat.neighbour(step)
        ok = nb >= 0
        dist[ok, n] = np.linalg.norm(px[nb[ok]] - px[ok], axis=1)
    out = dist.min(axis=1)
    finite = np.isfinite(out)
    fallback = float(np.median(out[finite])) if finite.any() else 1.0
    return np.where(finite, out, fallback)


def _mutual_nearest(
    a: FloatArray, b: FloatArray, radius: FloatArray
) -> tuple[IntArray, IntArray]:
    """Pairs (ia, ib) that are each other's nearest neighbour and closer than ``radius[ia]``."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d_ab, nn_ab = cKDTree(b).query(a)
    _, nn_ba = cKDTree(a).query(b)
    ia = np.flatnonzero((nn_ba[nn_ab] == np.arange(len(a))) & (d_ab < radius))
    return ia, nn_ab[ia]


# ----------------------------------------------------------------------------------------------
# 3. Flat-water reference
# ----------------------------------------------------------------------------------------------


def match_reference(
    ref_spots: Spots,
    predicted: tuple[IntArray, FloatArray, FloatArray, BoolArray],
    *,
    tol: float = 0.35,
) -> ReferenceGrid:
    """Label the flat-water spots with grid indices by proximity to the prediction.

    A first mutual-nearest pass (radius 0.5 spacing) fits a homography from predicted to detected
    centres (RANSAC): predicted and detected spots both lie on the diffuser plane, so a small
    calibration error in camera s is a plane projective map. The final pass pairs mutual nearest
    neighbours closer than ``tol`` x the local spacing, so each dot and each spot is used once.

    Parameters
    ----------
    ref_spots : Spots
        Spots detected in the flat-water image; suspicious ones are not used.
    predicted : tuple
        The output of :func:`predict_flat_spots`.
    tol : float
        Acceptance radius, in units of the local spot spacing.

    Returns
    -------
    ReferenceGrid
    """
    ij_all, _, pred_all, in_view = predicted
    finite = np.isfinite(pred_all).all(axis=1)
    spacing_all = np.full(len(ij_all), np.nan)
    spacing_all[finite] = _local_spacing(ij_all[finite], pred_all[finite])
    ij, pred, spacing = ij_all[in_view], pred_all[in_view], spacing_all[in_view]
    keep = ~ref_spots.suspicious
    det = ref_spots.centres_px[keep]

    pa, pb = _mutual_nearest(pred, det, 0.5 * spacing)
    moved = pred
    if len(pa) >= 8:
        hom, _ = cv2.findHomography(
            pred[pa], det[pb], cv2.RANSAC, max(0.5, 0.05 * float(np.median(spacing)))
        )
        if hom is not None:
            moved = cv2.perspectiveTransform(pred[None].astype(np.float64), hom)[0]
    pa, pb = _mutual_nearest(moved, det, tol * spacing)
    unmatched = np.ones(len(ij), bool)
    unmatched[pa] = False
    ref_px = det[pb]
    rms = float(np.sqrt(np.mean(np.sum((ref_px - pred[pa]) ** 2, axis=1)))) if len(pa) else 0.0
    counts = {
        "predicted_in_view": int(len(ij)),
        "matched": int(len(pa)),
        "unmatched_predicted": int(unmatched.sum()),
        "unassigned_spots": int(len(ref_spots) - len(pa)),
    }
    return ReferenceGrid(ij[pa], ref_px, pred[pa], spacing[pa], ij[unmatched], counts, rms)


# ----------------------------------------------------------------------------------------------
# 4. Wavy-water correspondence: region growing + ordering check (eq. 33)
# ----------------------------------------------------------------------------------------------


def _nearest_two(tree: cKDTree, pts: FloatArray) -> tuple[FloatArray, IntArray, FloatArray]:
    """Distance and index of the nearest spot, and distance of the second nearest (inf if none)."""
    k = min(2, tree.n)
    d, idx = tree.query(pts, k=k)
    d, idx = d.reshape(len(pts), k), idx.reshape(len(pts), k)
    d2 = d[:, 1] if k == 2 else np.full(len(pts), np.inf)
    return d[:, 0], idx[:, 0], d2


def _choose_seed(
    lat: _Lattice, ref_px: FloatArray, spacing: FloatArray, tree: cKDTree, usable: BoolArray,
    accept: float, ratio: float,
) -> int:
    """Node whose nearest spot is close, unambiguous and displaced like its 4 neighbours'.

    Score = (largest displacement difference to the neighbours + own displacement) / spacing,
    plus a small pull towards the middle of the pattern, where the spots are best seen.
    """
    d1, i1, d2 = _nearest_two(tree, ref_px)
    disp = tree.data[i1] - ref_px
    ok = (d1 < accept * spacing) & (d1 < ratio * d2) & usable[i1]
    worst = np.zeros(len(ref_px))
    n_ok = np.zeros(len(ref_px), int)
    for step in _DIRS4:
        nb = lat.neighbour(step)
        has = (nb >= 0) & ok[np.maximum(nb, 0)]
        diff = np.linalg.norm(disp - disp[np.maximum(nb, 0)], axis=1)
        worst = np.where(has, np.maximum(worst, diff), worst)
        n_ok += has
    centre = np.median(ref_px, axis=0)
    reach = np.linalg.norm(ref_px - centre, axis=1) / (np.ptp(ref_px, axis=0).max() + 1e-9)
    score = (worst + np.linalg.norm(disp, axis=1)) / spacing + 0.1 * reach
    score = np.where(ok & (n_ok >= min(3, int(n_ok.max(initial=0)))), score, np.inf)
    best = int(np.argmin(score)) if len(score) else -1
    return best if best >= 0 and np.isfinite(score[best]) else -1


def _predict_displacement(
    lat: _Lattice, disp: FloatArray, matched: BoolArray, nodes: IntArray
) -> FloatArray:
    """Displacement of ``nodes`` from their matched 8-neighbours: linear extrapolation along the
    line through two matched nodes where possible, else the neighbour's own displacement."""
    total = np.zeros((len(nodes), 2))
    count = np.zeros(len(nodes))
    for step in _DIRS8:
        n1 = lat.neighbour(-step)[nodes]
        n2 = lat.neighbour(-2 * step)[nodes]
        has1 = (n1 >= 0) & matched[np.maximum(n1, 0)]
        has2 = has1 & (n2 >= 0) & matched[np.maximum(n2, 0)]
        d1 = disp[np.maximum(n1, 0)]
        pred = np.where(has2[:, None], 2.0 * d1 - disp[np.maximum(n2, 0)], d1)
        total += np.where(has1[:, None], pred, 0.0)
        count += has1
    return total / np.maximum(count, 1)[:, None]


def order_violations(
    ij: IntArray, ref_px: FloatArray, spot_px: FloatArray, margin_px: float = 0.5
) -> BoolArray:
    """Matches that break eq. 33 with a grid neighbour along a row or a column.

    For grid neighbours ``k`` and ``k+1`` (``i`` or ``j`` + 1, both matched), the flat-water image
    direction ``u = (ref_{k+1} - ref_k) / |.|`` orders the spots; eq. 33 requires
    ``(s_{k+1} - s_k) . u > dp/2``. Both ends of a violating pair are flagged.

    Parameters
    ----------
    ij : (K, 2) ndarray of int
        Grid indices of the matches.
    ref_px, spot_px : (K, 2) ndarray
        Flat-water and wavy-water spot centres, pixels.
    margin_px : float
        ``dp / 2``: half the spot-position uncertainty, pixels.

    Returns
    -------
    (K,) ndarray of bool
    """
    bad = np.zeros(len(ij), bool)
    if len(ij) == 0:
        return bad
    lat = _Lattice(ij)
    for step in ([1, 0], [0, 1]):
        nb = lat.neighbour(step)
        a = np.flatnonzero(nb >= 0)
        b = nb[a]
        u = ref_px[b] - ref_px[a]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        gap = np.sum((spot_px[b] - spot_px[a]) * u, axis=1)
        viol = gap <= margin_px
        bad[a[viol]] = True
        bad[b[viol]] = True
    return bad


def match_distorted(
    ref: ReferenceGrid | tuple[IntArray, FloatArray],
    spots: Spots,
    *,
    accept: float = 0.35,
    ratio: float = 0.7,
    order_margin_px: float = 0.5,
) -> Matches:
    """Label the wavy-water spots with grid indices (robust ordering-based correspondence).

    Region growing over the ``(i, j)`` lattice from a confident seed: each wave predicts the
    frontier nodes' spots as reference position + displacement extrapolated from matched
    neighbours (the displacement field is smooth), and accepts the nearest spot if it lies within
    ``accept`` x the local spacing, is at most ``ratio`` x as far as the second nearest, is not
    flagged and is claimed by no other node. Nodes that fail stay on the frontier and are tried
    again with more matched neighbours. Afterwards, a spot that a failed node also claims is
    dropped, and pairs that break eq. 33 (:func:`order_violations`) are dropped.

    Parameters
    ----------
    ref : ReferenceGrid or (ij, ref_px)
        Flat-water reference: grid indices (K, 2) and spot centres (K, 2), pixels.
    spots : Spots
        Spots detected in the wavy-water image.
    accept : float
        Acceptance radius, in units of the local spot spacing.
    ratio : float
        Largest allowed ratio of nearest to second-nearest spot distance.
    order_margin_px : float
        ``dp / 2`` of eq. 33, pixels.

    Returns
    -------
    Matches
    """
    if isinstance(ref, ReferenceGrid):
        ij, ref_px, spacing = ref.ij, ref.ref_px, ref.spacing_px
    else:
        ij, ref_px = (np.asarray(a) for a in ref)
        spacing = _local_spacing(ij, ref_px) if len(ij) else np.zeros(0)
    n_ref = len(ij)
    counts = {
        "detected": len(spots), "reference": n_ref, "matched": 0, "rejected_order": 0,
        "rejected_merged": 0, "rejected_ambiguous": 0, "rejected_border": 0,
        "unmatched_reference": n_ref, "unassigned_spots": len(spots),
    }
    empty = Matches(np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros((0, 2)), counts)
    if n_ref == 0 or len(spots) == 0:
        return empty
    lat = _Lattice(ij)
    tree = cKDTree(spots.centres_px)
    usable = ~spots.suspicious
    seed = _choose_seed(lat, ref_px, spacing, tree, usable, accept, ratio)
    if seed < 0:
        return empty

    owner = np.full(len(spots), -1, np.int64)  # node that holds each spot
    match = np.full(n_ref, -1, np.int64)  # spot held by each node
    reason = np.zeros(n_ref, np.int8)  # last failure: 0 none, 1 merged, 2 border, 3 ambiguous
    claim = np.full(n_ref, -1, np.int64)  # nearest spot within reach at the last try
    disp = np.zeros((n_ref, 2))
    match[seed] = int(tree.query(ref_px[seed])[1])
    owner[match[seed]] = seed
    disp[seed] = spots.centres_px[match[seed]] - ref_px[seed]
    nbrs = np.stack([lat.neighbour(s) for s in _DIRS4], axis=1)

    while True:  # one iteration per BFS wave, vectorised over the frontier
        matched = match >= 0
        touch = ((nbrs >= 0) & matched[np.maximum(nbrs, 0)]).any(axis=1)
        front = np.flatnonzero(~matched & touch)
        if len(front) == 0:
            break
        pred = ref_px[front] + _predict_displacement(lat, disp, matched, front)
        d1, i1, d2 = _nearest_two(tree, pred)
        near = d1 < accept * spacing[front]
        clear = d1 < ratio * d2
        taken = owner[i1] >= 0
        dup = np.bincount(i1[near & clear & ~taken], minlength=len(spots))[i1] > 1
        ok = near & clear & ~taken & ~dup & usable[i1]
        reason[front] = np.select(
            [~near, spots.merged[i1], ~usable[i1], ~clear | taken | dup], [0, 1, 2, 3], 0
        )
        claim[front] = np.where(near, i1, -1)
        if not ok.any():
            break
        acc = front[ok]
        match[acc] = i1[ok]
        owner[i1[ok]] = acc
        disp[acc] = spots.centres_px[i1[ok]] - ref_px[acc]

    # A spot within reach of a node that failed is claimed twice: neither claim is trusted.
    failed = (match < 0) & (claim >= 0)
    holders = owner[claim[failed]]
    holders = holders[holders >= 0]
    match[holders] = -1
    reason[holders] = 3
    reason[failed & (reason == 0)] = 3

    kept = np.flatnonzero(match >= 0)
    bad = order_violations(ij[kept], ref_px[kept], spots.centres_px[match[kept]], order_margin_px)
    rejected_order = int(bad.sum())
    kept = kept[~bad]
    lost = np.ones(n_ref, bool)
    lost[kept] = False
    lost_reason = np.where(match >= 0, 4, reason)[lost]  # 4: dropped by the order check
    counts.update(
        matched=int(len(kept)),
        rejected_order=rejected_order,
        rejected_merged=int(np.sum(lost_reason == 1)),
        rejected_border=int(np.sum(lost_reason == 2)),
        rejected_ambiguous=int(np.sum(lost_reason == 3)),
        unmatched_reference=int(np.sum(lost_reason == 0)),
        unassigned_spots=int(len(spots) - len(kept)),
    )
    return Matches(ij[kept], ref_px[kept], spots.centres_px[match[kept]], counts)


# ----------------------------------------------------------------------------------------------
# 5. All steps
# ----------------------------------------------------------------------------------------------


def find_features(
    pattern_img: NDArray,
    pattern_flat_img: NDArray,
    cfg: SystemConfig,
    *,
    min_features: int = 16,
) -> Matches:
    """Detect, predict and match: grid index, flat and wavy spot centre of every usable dot.

    Parameters
    ----------
    pattern_img : (h, w) or (h, w, 3) ndarray
        Camera-s image of the pattern over the wavy water (linear intensity).
    pattern_flat_img : (h, w) or (h, w, 3) ndarray
        The same over flat water (the reference).
    cfg : SystemConfig
        System calibration; camera s must be ``w x h`` pixels.
    min_features : int
        Fewest kept matches accepted.

    Returns
    -------
    Matches
        With ``timings_ms`` for ``detect_flat``, ``detect``, ``predict``, ``match_reference``,
        ``match`` and ``total``.

    Raises
    ------
    WaiInputError
        On bad images (shape, NaN) or fewer than ``min_features`` matches.
    """
    cam = cfg.camera_s
    for name, img in (("pattern", pattern_img), ("flat pattern", pattern_flat_img)):
        if np.shape(img)[:2] != (cam.height_px, cam.width_px):
            raise WaiInputError(
                f"{name} image is {np.shape(img)[:2]}, camera s is {cam.height_px}x{cam.width_px}"
            )
    timings: dict[str, float] = {}
    t_all = t0 = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t0
        t1 = time.perf_counter()
        timings[name] = 1e3 * (t1 - t0)
        t0 = t1

    flat = detect_spots(pattern_flat_img)
    lap("detect_flat")
    wavy = detect_spots(pattern_img)
    lap("detect")
    predicted = predict_flat_spots(cfg)
    lap("predict")
    ref = match_reference(flat, predicted)
    lap("match_reference")
    if len(ref.ij) < min_features:
        raise WaiInputError(f"too few reference features on flat water: {len(ref.ij)}")
    matches = match_distorted(ref, wavy)
    lap("match")
    timings["total"] = 1e3 * (time.perf_counter() - t_all)
    if len(matches) < min_features:
        raise WaiInputError(f"too few features matched: {len(matches)} (need {min_features})")
    matches.timings_ms.update(timings)
    return matches
