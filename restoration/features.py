"""Pattern features on camera s and their correspondence with the projector's dot grid.

The paper (Jian et al. 2022, section 3.2.1) needs, for every projected dot ``k``, its spot
``s_k`` on the diffuser in the wavy image and the dot's grid index, so that the projector ray
``v_k^p`` is known. Section 4.2 (eq. 33) states when this correspondence can be made by ordering
alone: neighbouring spots must keep their order with a margin, ``s_k + dp/2 < s_{k+1}``. This
module

1. detects the spots (:func:`detect_spots`) with sub-pixel centres,
2. predicts where each dot lands for flat water from calibration only
   (:func:`predict_flat_spots`),
3. labels the flat-water spots with grid indices (:func:`match_reference`),
4. labels the wavy-water spots by region growing over the grid from a confident seed, drops
   matches that break eq. 33's ordering, merged blobs and doubly claimed spots, and anchors the
   labels on the pattern's visible boundary or unlit marker dots (:func:`match_distorted`),

and :func:`find_features` runs the four steps. Pixel coordinates are continuous ``(col, row)``
with integer values at pixel centres (see :mod:`wai_core.geometry`).

Ordering fixes labels only up to a whole-lattice shift: where the spots move by more than half a
spacing (the paper's system at U = 1 m/s moves them by 1-4 spacings) the shift must come from
something the pattern shows, such as its edge or dots left dark on purpose.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import cKDTree

from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.geometry import intersect_plane_z, reflect
from wai_core.layout import diffuser_rect, lit_dots
from wai_core.pattern import dot_grid

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_LATTICE_PAD = 2
# Centroid window: covariance _WINDOW_VAR x the segment's second moments, which hold 0.55-0.85 of
# the spot's variance, so k^2 ~ 1.75 (k ~ 1.3) and the step gain is 1 + 1 / k^2.
_WINDOW_VAR = 2.5
_WINDOW_GAIN = 1.0 + 1.0 / (0.7 * _WINDOW_VAR)
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
        Second moments of the spot's segment in the smoothed image, pixels^2: 0.55-0.85 of the
        spot's own covariance (the segment is cut at a fraction of the peak).
    merged : (P,) ndarray of bool
        Flat-topped or two-humped profile: probably two or more dots run together.
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
    """The dot lattice in camera s for flat water: where each dot's spot is, or would be.

    The lattice holds every grid dot plus a margin of *virtual* nodes beyond the grid (never lit),
    which let the correspondence notice a labelling shifted by whole spacings.

    Attributes
    ----------
    ij : (G, 2) ndarray of int
        Lattice index ``(i, j)`` of each node (grid dots as in :func:`wai_core.pattern.dot_grid`).
    ref_px : (G, 2) ndarray
        Flat-water spot centre, pixels: detected where ``observed``, else the calibrated
        prediction (which may lie off the diffuser or off the image).
    observed : (G,) ndarray of bool
        The dot's spot was detected on flat water.
    lit : (G,) ndarray of bool
        The node is a projected dot (False for virtual nodes and unlit dots).
    spacing_px : (G,) ndarray
        Local spot spacing: distance to the nearest lattice neighbour in the image, pixels.
    cov_px2 : (G, 2, 2) ndarray
        Flat-water spot covariance where ``observed`` (NaN elsewhere), pixels^2.
    unmatched_ij : (M, 2) ndarray of int
        Dots predicted in view for which no flat-water spot was found.
    counts : dict of str to int
        ``predicted_in_view``, ``observed``, ``unmatched_predicted``, ``unassigned_spots``.
    rms_px : float
        RMS distance between detected and calibration-predicted centres, pixels.
    """

    ij: IntArray
    ref_px: FloatArray
    observed: BoolArray
    lit: BoolArray
    spacing_px: FloatArray
    cov_px2: FloatArray
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
        Flat-water spot centre (detected, or predicted where ``observed`` is False), pixels.
    spot_px : (K, 2) ndarray
        Wavy-water spot centre, pixels.
    observed : (K,) ndarray of bool
        The dot's spot was also seen on flat water.
    counts : dict of str to int
        ``detected``: spots in the wavy image. ``reference``: dots seen on flat water.
        ``matched``: kept matches, of which ``matched_unobserved`` are dots not seen on flat water.
        Lattice nodes dropped: ``rejected_order`` (break eq. 33 with a grid neighbour),
        ``rejected_merged`` (their spot is a merged blob), ``rejected_ambiguous`` (two candidate
        spots, or a spot claimed by two nodes), ``rejected_border`` (spot cut by the image or
        diffuser edge, or saturated), ``rejected_unlit`` (matched to a node that is not a lit dot).
        ``unmatched_reference``: dots seen on flat water but lost in the wavy image.
        ``unassigned_spots``: detected spots given to no dot. ``anchor_di``, ``anchor_dj``:
        lattice shift applied to the proximity labelling; ``anchor_candidates``: how many shifts
        fit the evidence equally well (1: the labelling is pinned by the pattern's visible
        boundary; more: it is only the one nearest to flat water, and may be off by whole
        spacings).
    timings_ms : dict of str to float
        Wall time per step, ms (filled by :func:`find_features`).
    """

    ij: IntArray
    ref_px: FloatArray
    spot_px: FloatArray
    observed: BoolArray
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
        raise WaiInputError(
            f"pattern image must be (h, w) or (h, w, 3), got shape {np.shape(image)}"
        )
    if not np.issubdtype(img.dtype, np.number):
        raise WaiInputError(f"pattern image must be numeric, got {img.dtype}")
    img = img.astype(np.float32)
    if not np.isfinite(img).all():
        raise WaiInputError("pattern image contains NaN or infinite values")
    return img


def _upsample(small: NDArray[np.float32], shape: tuple[int, ...]) -> NDArray[np.float32]:
    """Bilinear resize of a coarse map back to the image size (h, w)."""
    return cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


def _background(smooth: NDArray[np.float32], size_px: int) -> NDArray[np.float32]:
    """Slowly varying background: local minimum over a window wider than a spot, then averaged.

    Runs on a 4x coarser grid (the background varies slowly): a 5 x 5 minimum first, so the
    subsampled pixels are the darkest of their neighbourhood, not a spot's core.
    """
    k = max(size_px // 4, 1) | 1
    low = cv2.erode(smooth, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_REPLICATE)[::4, ::4]
    low = cv2.erode(np.ascontiguousarray(low), np.ones((k, k), np.uint8),
                    borderType=cv2.BORDER_REPLICATE)
    return _upsample(cv2.blur(low, (k, k), borderType=cv2.BORDER_REPLICATE), smooth.shape)


def _noise_sigma(lum: NDArray[np.float32], smooth: NDArray[np.float32], smooth_px: float) -> float:
    """Noise standard deviation of the smoothed image (image units).

    Taken from the high-pass residual ``lum - smooth``, scaled by what the Gaussian does to white
    noise. The scale is the lower quartile of ``|residual|`` (0.3186 sigma for Gaussian noise),
    which the residuals of the dots themselves disturb less than the median. Zero for Monte
    Carlo renders (an empty background is exactly 0); over-estimated when sub-pixel-sharp dots
    (sigma < ~1 px) crowd the image, which then loses dots dimmer than ~5 % of the bright ones.
    """
    g = cv2.getGaussianKernel(2 * int(np.ceil(4 * smooth_px)) + 1, smooth_px).ravel()
    g2 = float(np.sum(g**2)) ** 2  # sum of the squared 2-D kernel
    g0 = float(g.max()) ** 2  # its centre weight
    sub = (lum[::3, ::3] - smooth[::3, ::3]).ravel()  # every 9th pixel is plenty
    scale = float(np.percentile(np.abs(sub - np.median(sub)), 25.0)) / 0.3186
    return scale * float(np.sqrt(g2 / (1.0 - 2.0 * g0 + g2)))


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
    kurtosis: FloatArray  # along the major axis, of the part above 0.2 x peak


def _major_axis_kurtosis(
    lab: IntArray, rows: IntArray, cols: IntArray, s: FloatArray, peak: FloatArray, n: int
) -> FloatArray:
    """Kurtosis ``m4 / m2^2`` along each segment's major axis of ``max(s - 0.2 peak, 0)``.

    Measured relative to the segment's own peak, it is nearly the same for every single Gaussian
    spot, whatever its size, elongation or brightness (2.2-2.45 after the smoothing, the spread
    from pixelisation of the smallest), and falls as two spots run together into a flat-topped
    or two-humped blob (below 2.15 once they are more than ~3 sigma apart).
    """
    w = np.clip(s - 0.2 * peak[lab], 0.0, None)
    _, mean, cov = _weighted_moments(lab, rows, cols, w, n)
    # Major-axis direction of each 2 x 2 covariance, in closed form.
    angle = 0.5 * np.arctan2(2.0 * cov[:, 0, 1], cov[:, 0, 0] - cov[:, 1, 1])
    ux, uy = np.cos(angle), np.sin(angle)
    proj = (cols - mean[lab, 0]) * ux[lab] + (rows - mean[lab, 1]) * uy[lab]
    tot = np.bincount(lab, w, n)
    m2 = np.bincount(lab, w * proj**2, n)
    m4 = np.bincount(lab, w * proj**4, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        kurt = m4 * tot / m2**2
    return np.where(np.isfinite(kurt), kurt, 3.0)


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
    kurt = _major_axis_kurtosis(lab, rows, cols, s, peak, n)
    return _Segments(tot, mean, cov, peak, np.bincount(lab, r, n), kurt)


def _windowed_centroids(
    img: NDArray[np.float32],
    labels: NDArray[np.int32],
    keep_label: IntArray,
    own: IntArray,
    start: FloatArray,
    cov: FloatArray,
    half_px: tuple[int, int],
    n_iter: int,
) -> FloatArray:
    """Gaussian-windowed centroids (as SExtractor's ``XWIN``) of spots sharing one box size.

    A Gaussian spot of covariance C seen through a Gaussian window of covariance ``k^2 C``
    centred at ``x_n`` has its weighted mean ``m`` a fraction ``k^2 / (1 + k^2)`` of the way to
    the true centre, so ``x_{n+1} = x_n + (1 + 1/k^2) (m - x_n)`` converges in one step and stays
    unbiased for any symmetric profile (a wrong C only slows convergence). Unlike a thresholded
    centroid it has no pixel-locking bias. ``k`` trades noise (``k = 1``: 1.33x the Poisson
    limit; ``k = 1.5``: 1.1x) against light from neighbours; pixels of *other* kept segments are
    masked so a much brighter neighbour cannot pull the centre. The box is ``2 half_px + 1``
    pixels wide and high (``half_px = (along cols, along rows)``).
    """
    off_x = np.arange(-half_px[0], half_px[0] + 1)
    off_y = np.arange(-half_px[1], half_px[1] + 1)
    base = np.rint(start).astype(np.int64)
    h, w = img.shape
    cols = base[:, 0, None, None] + off_x[None, None, :]
    rows = base[:, 1, None, None] + off_y[None, :, None]
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    rc, cc = np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)
    lab = keep_label[labels[rc, cc]]
    keep = inside & ((lab == 0) | (lab == own[:, None, None]))
    vals = np.where(keep, img[rc, cc], np.float32(0.0))
    inv = np.linalg.inv(_WINDOW_VAR * cov).astype(np.float32)
    a, b, c = inv[:, 0, 0, None], inv[:, 0, 1, None, None], inv[:, 1, 1, None]
    fx, fy = off_x.astype(np.float32)[None, :], off_y.astype(np.float32)[None, :]
    x = start.copy()
    for _ in range(n_iter):
        dx = fx - (x[:, 0] - base[:, 0]).astype(np.float32)[:, None]  # (n, wx)
        dy = fy - (x[:, 1] - base[:, 1]).astype(np.float32)[:, None]  # (n, wy)
        q = (a * dx * dx)[:, None, :] + (c * dy * dy)[:, :, None]
        q += 2.0 * b * dy[:, :, None] * dx[:, None, :]
        wv = vals * np.exp(-0.5 * q)
        col_sum = wv.sum(axis=1)  # (n, wx): summed over rows
        row_sum = wv.sum(axis=2)  # (n, wy)
        tot = col_sum.sum(axis=1).astype(np.float64)
        mx = np.einsum("nw,nw->n", col_sum, dx).astype(np.float64)
        my = np.einsum("nw,nw->n", row_sum, dy).astype(np.float64)
        ok = tot > 0
        step = _WINDOW_GAIN * np.stack([mx, my], axis=1) / np.where(ok, tot, 1.0)[:, None]
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
    n_iter: int = 2,
) -> FloatArray:
    """Windowed centroids for all spots, batched by box size (a loop over a few sizes).

    The box reaches 3.5 segment sigmas + 1 px along each image axis (about 3 spot sigmas):
    beyond it the spot times the window is below 0.5 %.
    """
    sd = np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1))
    half = np.clip(np.ceil(3.5 * sd + 1.0), 3, 48).astype(int)
    half = 3 * np.ceil(half / 3).astype(int)  # a handful of box sizes
    out = start.copy()
    sizes, group = np.unique(half, axis=0, return_inverse=True)
    for g, (hx, hy) in enumerate(sizes):
        sel = group.ravel() == g
        out[sel] = _windowed_centroids(
            img, labels, keep_label, own[sel], start[sel], cov[sel], (int(hx), int(hy)), n_iter
        )
    return out


def _segment(
    smooth: NDArray[np.float32],
    radius_px: int,
    rel_level: float,
    floor: float,
    wide_px: int = 40,
    wide_level: float = 0.005,
) -> tuple[int, NDArray[np.int32], NDArray[np.int32]]:
    """Label pixels above ``rel_level`` x their local maximum (and above ``floor``).

    The max filter's radius is under half the spot spacing, so a pixel is compared with its own
    dot's peak: a dim dot next to a bright one is segmented like the bright one. On a wide spot
    that test holds far into the tails (the slope there is gentle), so pixels must also exceed
    ``wide_level`` x the maximum within ``wide_px`` of a copy blurred by a 4 px Gaussian. A wide
    spot keeps its peak under that blur, so its segment ends at ~3.5 sigma, short of its
    neighbours; a small bright dot loses most of its peak, so a small dim neighbour survives.
    """
    size = 2 * radius_px + 1
    local_max = cv2.dilate(smooth, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
    # On a 4x coarser grid: a 4 x 4 block average and a 1 px blur there make the ~4 px blur.
    h, w = smooth.shape
    small = cv2.resize(smooth, (w // 4, h // 4), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), 1.0, borderType=cv2.BORDER_REFLECT)
    k = 2 * (wide_px // 4) + 1
    wide = _upsample(cv2.dilate(small, np.ones((k, k), np.uint8)), smooth.shape)
    mask = (smooth > rel_level * local_max) & (smooth > wide_level * wide) & (smooth > floor)
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


def _typical_flux(flux: FloatArray) -> float:
    """Flux-weighted median: the flux of a typical bright spot, however many faint specks."""
    if flux.size == 0:
        return 0.0
    f = np.sort(flux)
    cum = np.cumsum(f)
    return float(f[np.searchsorted(cum, 0.5 * cum[-1])])


def detect_spots(
    image: NDArray,
    *,
    smooth_px: float = 1.0,
    local_radius_px: int = 3,
    rel_level: float = 0.25,
    snr_min: float = 6.0,
    rel_flux: float = 5e-3,
    min_area_px: int = 3,
    merge_kurtosis: float = 2.15,
    background_px: int = 25,
    saturation: float | None = None,
) -> Spots:
    """Detect the pattern's spots and measure their sub-pixel centres.

    A pixel belongs to a spot when the smoothed, background-subtracted image exceeds
    ``rel_level`` x its own local maximum (a max filter of radius ``local_radius_px``), so a dot
    100x dimmer than its neighbour is segmented as well as a bright one: the window is smaller
    than the spot spacing, hence a pixel is compared with its own dot's peak (see
    :func:`_segment` for how the tails of wide spots are cut). Segments whose peak is not
    significant (below ``snr_min`` x noise) or whose flux is a tiny fraction of a typical spot's
    are dropped. Each centre starts at the segment's intensity centroid and is refined by a
    Gaussian-windowed centroid of the raw image (no pixel-locking bias; ~1.1x the Poisson
    limit in noise).

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
    rel_flux : float
        Minimum flux relative to the typical bright spot's (flux-weighted median of all
        segments): rejects Monte Carlo speckle and stray fragments of a spot's skirt while keeping
        dots up to 1 / ``rel_flux`` times dimmer than the bright ones.
    min_area_px : int
        Smallest segment kept, pixels.
    merge_kurtosis : float
        A spot is flagged ``merged`` when the kurtosis of its profile along its major axis is
        below this: 2.2-2.45 for a single Gaussian spot, below 2.15 for two equal dots more than
        ~3 sigma apart (closer pairs look like one dot and are caught by the matching as a spot
        claimed twice). Segments narrower than 1.3 px (second moment) are never flagged.
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
    tiny = 1e-6 * max(float(smooth.max()), 1e-30)  # keeps a noiseless zero background out
    n, labels, stats = _segment(smooth, local_radius_px, rel_level, max(2.0 * noise, tiny))
    seg = _segment_stats(labels, n, smooth, raw)
    area = stats[:, cv2.CC_STAT_AREA]
    good = (seg.peak > max(snr_min * noise, tiny)) & (area >= min_area_px) & (seg.tot > 0)
    good[0] = False  # label 0 is the background
    good &= seg.flux > rel_flux * _typical_flux(seg.flux[good])
    idx = np.flatnonzero(good)
    keep_label = np.where(good, np.arange(n), 0)  # rejected segments count as background
    cov = _spot_covariance(seg.cov[idx])
    centres = _refine_centres(raw, labels, keep_label, idx, seg.mean[idx], cov)

    x, y, wd, ht = (stats[idx, k] for k in range(4))
    h, w = raw.shape
    border = (x == 0) | (y == 0) | (x + wd == w) | (y + ht == h)
    # Too few pixels across to tell a shape (single spots of sigma <~ 1.2 px): never "merged".
    wide_enough = np.linalg.eigvalsh(seg.cov[idx])[:, 1] >= 1.3**2
    merged = (seg.kurtosis[idx] < merge_kurtosis) & wide_enough
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


def _diffuser(cfg: SystemConfig) -> FloatArray:
    """Diffuser extent ``[[x0, x1], [y0, y1]]``, mm (:func:`wai_core.layout.diffuser_rect`)."""
    try:
        return diffuser_rect(cfg)
    except ValueError as exc:
        raise WaiInputError(f"config: {exc}") from None


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
        The system (projector, pattern, water level, diffuser height and extent, camera s).
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
        The ray goes up to the water, comes down onto the (finite) diffuser, and the spot is in
        front of and inside camera s.
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
    (x0, x1), (y0, y1) = _diffuser(cfg)
    with np.errstate(invalid="ignore"):
        on_diffuser = (spot[:, 0] >= x0) & (spot[:, 0] <= x1)
        on_diffuser &= (spot[:, 1] >= y0) & (spot[:, 1] <= y1)
        in_view = (
            (dirs[:, 2] > 0)
            & on_diffuser
            & np.isfinite(spot_px).all(axis=1)
            & in_front
            & cam.in_image(cols, rows, margin_px)
        )
    return ij.astype(np.int64), panel, spot_px, in_view


def _outline_px(cfg: SystemConfig) -> FloatArray:
    """The diffuser's corners (4, 2) in camera s, pixels, in order around it."""
    (x0, x1), (y0, y1) = _diffuser(cfg)
    z = cfg.diffuser.z_mm
    corners = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    cols, rows, _ = cfg.camera_s.camera().project(corners)
    return np.stack([cols, rows], axis=1)


def flag_diffuser_edge(spots: Spots, outline_px: FloatArray, n_sigma: float = 2.5) -> Spots:
    """Flag as ``border`` the spots that the diffuser's edge cuts (or that lie off it).

    A spot is cut when its centre is closer to an edge of the outline than ``n_sigma`` of its
    own standard deviation across that edge; its centroid is then pulled inwards.

    Parameters
    ----------
    spots : Spots
        Detected spots.
    outline_px : (M, 2) ndarray
        Convex outline of the diffuser in the image, pixels, in order around it.
    n_sigma : float
        Clearance needed, in spot standard deviations.

    Returns
    -------
    Spots
        A copy with ``border`` updated.
    """
    if len(spots) == 0:
        return spots
    dist, normal = _edge_distances(np.asarray(outline_px, dtype=float), spots.centres_px)
    sd = np.sqrt(np.einsum("mk,pkl,ml->pm", normal, spots.cov_px2, normal))
    cut = (dist < n_sigma * sd).any(axis=1)
    return replace(spots, border=spots.border | cut)


def _edge_distances(poly: FloatArray, pts: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Signed distances (N, M) of points (N, 2) inside each edge of a convex polygon (M, 2),
    positive inwards, and the edges' inward unit normals (M, 2)."""
    edge = np.roll(poly, -1, axis=0) - poly
    normal = np.stack([-edge[:, 1], edge[:, 0]], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal *= np.sign(np.sum((poly.mean(axis=0) - poly) * normal, axis=1, keepdims=True))
    return np.einsum("pmk,mk->pm", pts[:, None, :] - poly[None], normal), normal


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
        self._cache: dict[tuple[int, int], IntArray] = {}

    def neighbour(self, step: NDArray) -> IntArray:
        """Node number of each node's neighbour at ``(i, j) + step`` (|step| <= 2), or -1."""
        key = (int(step[0]), int(step[1]))
        if key not in self._cache:  # the growth asks for the same few steps every wave
            q = self.ij + np.asarray(key) - self.lo
            self._cache[key] = self.grid[q[:, 1], q[:, 0]]
        return self._cache[key]

    def lookup(self, ij: NDArray) -> IntArray:
        """Node number at any lattice indices (..., 2), -1 where there is none."""
        q = np.asarray(ij) - self.lo
        nj, ni = self.grid.shape
        ok = (q[..., 0] >= 0) & (q[..., 0] < ni) & (q[..., 1] >= 0) & (q[..., 1] < nj)
        q = np.where(ok[..., None], q, 0)
        return np.where(ok, self.grid[q[..., 1], q[..., 0]], -1)


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


def _lattice_homography(ij: IntArray, px: FloatArray) -> FloatArray:
    """Homography (3, 3) from lattice indices to image pixels (exact for flat water: panel ->
    camera s is a plane projective map and the panel position is affine in ``(i, j)``)."""
    hom, _ = cv2.findHomography(ij.astype(np.float64), px.astype(np.float64), 0)
    if hom is None:
        raise WaiInputError("cannot relate the dot grid to camera s: degenerate prediction")
    return hom


def _apply_homography(hom: FloatArray, pts: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Map points (N, 2); also return the projective depth ``w`` (its sign marks the side)."""
    p = np.c_[pts, np.ones(len(pts))] @ hom.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:], p[:, 2]


def _extended_lattice(ij: IntArray, margin: int) -> IntArray:
    """All lattice indices of the grid's bounding box grown by ``margin`` nodes, (G, 2)."""
    lo, hi = ij.min(axis=0) - margin, ij.max(axis=0) + margin
    jj, ii = np.mgrid[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
    return np.stack([ii.ravel(), jj.ravel()], axis=1)


def match_reference(
    ref_spots: Spots,
    predicted: tuple[IntArray, FloatArray, FloatArray, BoolArray],
    *,
    tol: float = 0.35,
    lit: BoolArray | None = None,
    margin: int = 6,
) -> ReferenceGrid:
    """Label the flat-water spots with grid indices by proximity to the prediction.

    A first mutual-nearest pass (radius 0.5 spacing) fits a homography from predicted to detected
    centres (RANSAC): both lie on the diffuser plane, so a small calibration error of camera s is
    a plane projective map. The final pass pairs mutual nearest neighbours closer than ``tol`` x
    the local spacing, so each dot and each spot is used once. The lattice is then extended by
    ``margin`` virtual nodes on every side (positions from the same homography).

    Parameters
    ----------
    ref_spots : Spots
        Spots detected in the flat-water image; suspicious ones are not used.
    predicted : tuple
        The output of :func:`predict_flat_spots`.
    tol : float
        Acceptance radius, in units of the local spot spacing.
    lit : (K,) ndarray of bool, optional
        Which grid dots the projector lights, in :func:`~wai_core.pattern.dot_grid` order
        (default: all).
    margin : int
        Virtual nodes added beyond the grid on each side.

    Returns
    -------
    ReferenceGrid
    """
    ij_grid, _, pred_grid, in_view = predicted
    lit_grid = np.ones(len(ij_grid), bool) if lit is None else np.asarray(lit, bool)
    finite = np.isfinite(pred_grid).all(axis=1)
    if finite.sum() < 4:
        raise WaiInputError(f"too few dots reach camera s: {int(finite.sum())}")
    to_px = _lattice_homography(ij_grid[finite], pred_grid[finite])
    ij = _extended_lattice(ij_grid, margin)
    pred, depth = _apply_homography(to_px, ij.astype(np.float64))
    # Nodes on the far side of the horizon (depth sign flipped) have no spot at all.
    _, grid_depth = _apply_homography(to_px, ij_grid[finite].astype(np.float64))
    keep = np.sign(depth) == np.sign(np.median(grid_depth))
    ij, pred = ij[keep], pred[keep]
    grid_lat = _Lattice(ij_grid)
    node_dot = grid_lat.lookup(ij)  # index into the grid arrays, -1 for virtual nodes
    is_dot = node_dot >= 0
    view = np.zeros(len(ij), bool)
    view[is_dot] = in_view[node_dot[is_dot]]
    lit_node = np.zeros(len(ij), bool)
    lit_node[is_dot] = lit_grid[node_dot[is_dot]]
    spacing = _local_spacing(ij, pred)

    good = ~ref_spots.suspicious
    det, det_cov = ref_spots.centres_px[good], ref_spots.cov_px2[good]
    cand = np.flatnonzero(view & lit_node)
    pa, pb = _mutual_nearest(pred[cand], det, 0.5 * spacing[cand])
    moved = pred
    if len(pa) >= 8:
        corr, _ = cv2.findHomography(
            pred[cand[pa]], det[pb], cv2.RANSAC, max(0.5, 0.05 * float(np.median(spacing)))
        )
        if corr is not None:
            moved, _ = _apply_homography(corr, pred)
    pa, pb = _mutual_nearest(moved[cand], det, tol * spacing[cand])
    observed = np.zeros(len(ij), bool)
    observed[cand[pa]] = True
    ref_px = moved.copy()
    ref_px[cand[pa]] = det[pb]
    cov = np.full((len(ij), 2, 2), np.nan)
    cov[cand[pa]] = det_cov[pb]
    res = det[pb] - pred[cand[pa]]
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if len(pa) else 0.0
    counts = {
        "predicted_in_view": int(np.sum(view & lit_node)),
        "observed": int(len(pa)),
        "unmatched_predicted": int(np.sum(view & lit_node & ~observed)),
        "unassigned_spots": int(len(ref_spots) - len(pa)),
    }
    return ReferenceGrid(
        ij=ij,
        ref_px=ref_px,
        observed=observed,
        lit=lit_node,
        spacing_px=_local_spacing(ij, ref_px),
        cov_px2=cov,
        unmatched_ij=ij[view & lit_node & ~observed],
        counts=counts,
        rms_px=rms,
    )


# ----------------------------------------------------------------------------------------------
# 4. Wavy-water correspondence: region growing + ordering check (eq. 33) + anchoring
# ----------------------------------------------------------------------------------------------

# Why a lattice node was not matched (the last reason seen while it was on the frontier).
_NONE, _MERGED, _BORDER, _AMBIGUOUS, _ORDER, _UNLIT = range(6)


@dataclass(frozen=True)
class _Growth:
    """State of a region growing, per node: its spot (-1: none), why not, the last spot within
    reach (-1: none), the last predicted position, and whether it was ever tried."""

    match: IntArray
    reason: NDArray[np.int8]
    claim: IntArray
    pred_px: FloatArray
    tried: BoolArray


def _nearest_two(tree: cKDTree, pts: FloatArray) -> tuple[FloatArray, IntArray, FloatArray]:
    """Distance and index of the nearest spot, and distance of the second nearest (inf if none)."""
    k = min(2, tree.n)
    d, idx = tree.query(pts, k=k)
    d, idx = d.reshape(len(pts), k), idx.reshape(len(pts), k)
    d2 = d[:, 1] if k == 2 else np.full(len(pts), np.inf)
    return d[:, 0], idx[:, 0], d2


def _choose_seed(
    lat: _Lattice,
    base_px: FloatArray,
    ref: ReferenceGrid,
    spots: Spots,
    tree: cKDTree,
    accept: float,
    ratio: float,
) -> int:
    """Node whose nearest spot is most confidently its own, in a calm part of the image.

    Among observed nodes whose nearest spot is close, unambiguous and usable, and so are those
    of at least 6 of their 8 neighbours (or as many as any node has), the score adds (in units
    of the local spacing) the largest displacement difference to a neighbour and the node's own
    displacement, plus the change of spot size from flat water (``|log|`` of the area ratio:
    near a caustic, focusing shrinks or swells spots and the displacement field is at its least
    smooth), plus a small pull towards the middle of the pattern.
    """
    spacing = ref.spacing_px
    d1, i1, d2 = _nearest_two(tree, base_px)
    disp = tree.data[i1] - base_px
    ok = ref.observed & (d1 < accept * spacing) & (d1 < ratio * d2) & ~spots.suspicious[i1]
    if not ok.any():
        return -1
    worst = np.zeros(len(base_px))
    n_ok = np.zeros(len(base_px), int)
    for step in _DIRS8:
        nb = lat.neighbour(step)
        has = (nb >= 0) & ok[np.maximum(nb, 0)]
        diff = np.linalg.norm(disp - disp[np.maximum(nb, 0)], axis=1)
        worst = np.where(has, np.maximum(worst, diff), worst)
        n_ok += has
    with np.errstate(divide="ignore", invalid="ignore"):
        size = np.abs(0.5 * np.log(np.linalg.det(spots.cov_px2[i1]) / np.linalg.det(ref.cov_px2)))
    size = np.where(np.isfinite(size), size, 0.0)
    centre = np.median(base_px[ref.observed], axis=0)
    extent = np.ptp(base_px[ref.observed], axis=0).max() + 1.0
    reach = np.linalg.norm(base_px - centre, axis=1) / extent
    score = (worst + np.linalg.norm(disp, axis=1)) / spacing + size + 0.1 * reach
    score = np.where(ok & (n_ok >= min(6, int(n_ok[ok].max()))), score, np.inf)
    best = int(np.argmin(score))
    return best if np.isfinite(score[best]) else -1


@dataclass(frozen=True)
class _Lines:
    """Matched neighbours of frontier nodes along each of the 8 grid directions: ``near`` (F, 8)
    has a matched neighbour ``n1`` at ``p1`` (F, 8, 2); ``line`` also the next one ``n2`` at
    ``p2`` beyond it, on the same grid line."""

    near: BoolArray
    line: BoolArray
    p1: FloatArray
    p2: FloatArray


def _frontier_lines(
    back: tuple[IntArray, IntArray], matched: BoolArray, pos: FloatArray, front: IntArray
) -> _Lines:
    """Gather, for every frontier node and direction at once, its matched grid-line neighbours.

    ``back`` holds the (G + 1, 8) tables of the neighbour one and two steps back along each
    direction, with -1 mapped to the sentinel row G (never matched).
    """
    b1, b2 = back[0][front], back[1][front]
    near = matched[b1]
    return _Lines(near, near & matched[b2], pos[b1], pos[b2])


def _predicted_positions(
    lines: _Lines, back: tuple[IntArray, IntArray], disp: FloatArray, front: IntArray
) -> FloatArray:
    """Displacement of frontier nodes from their matched 8-neighbours, (F, 2): linear
    extrapolation along the grid line through two matched nodes where possible, else the
    neighbour's own displacement; averaged over directions."""
    d1, d2 = disp[back[0][front]], disp[back[1][front]]
    pred = np.where(lines.line[..., None], 2.0 * d1 - d2, d1)
    total = np.where(lines.near[..., None], pred, 0.0).sum(axis=1)
    return total / np.maximum(lines.near.sum(axis=1), 1)[:, None]


def _step_jumps(lines: _Lines, cand_px: FloatArray, max_ratio: float) -> BoolArray:
    """Candidates whose step from a matched neighbour differs from the next step along the same
    grid line by more than ``max_ratio`` either way: the candidate skips a spot or doubles one."""
    now = np.linalg.norm(cand_px[:, None, :] - lines.p1, axis=2)
    before = np.linalg.norm(lines.p1 - lines.p2, axis=2)
    bad = (now > max_ratio * before) | (max_ratio * now < before)
    return (lines.line & bad).any(axis=1)


def _grow(
    lat: _Lattice,
    base_px: FloatArray,
    spacing: FloatArray,
    spots: Spots,
    tree: cKDTree,
    seed: tuple[int, int],
    visible: FloatArray,
    accept: float,
    ratio: float,
    max_step_ratio: float = 1.7,
) -> _Growth:
    """Region growing over the lattice from ``seed = (node, spot)``, best-supported nodes first.

    Each wave predicts the frontier nodes' spots from their matched neighbours and finds the
    nearest spot; it is acceptable if within ``accept`` x spacing, at most ``ratio`` x as far as
    the second nearest, usable, claimed by no other node, and keeps the spacing along every grid
    line through matched neighbours within ``max_step_ratio`` (:func:`_step_jumps`). A wave accepts
    only the best tier present: nodes with at least 3 matched 8-neighbours and a clear-cut
    nearest spot, then with at least 2, then any, so the region fills in (interpolating) before it
    reaches out (extrapolating). Nodes not accepted stay on the frontier, unless predicted more
    than two spacings outside ``visible``; growth stops when a wave accepts nothing.
    """
    n = len(base_px)
    usable = ~spots.suspicious
    owner = np.full(len(spots), -1, np.int64)
    match = np.full(n, -1, np.int64)
    reason = np.full(n, _NONE, np.int8)
    claim = np.full(n, -1, np.int64)
    pred_px = base_px.copy()
    tried = np.zeros(n, bool)
    retired = np.zeros(n, bool)
    # Row n is a sentinel for "no neighbour": never matched, zero displacement.
    disp = np.zeros((n + 1, 2))
    back = tuple(
        np.vstack([np.where(t < 0, n, t), np.full((1, 8), n)])
        for t in (
            np.stack([lat.neighbour(-k * step) for step in _DIRS8], axis=1) for k in (1, 2)
        )
    )
    nbrs4 = np.stack([lat.neighbour(step) for step in _DIRS4], axis=1)
    touch = np.zeros(n + 1, bool)  # slot n absorbs the -1 (no neighbour) entries
    match[seed[0]], owner[seed[1]] = seed[1], seed[0]
    disp[seed[0]] = spots.centres_px[seed[1]] - base_px[seed[0]]
    touch[nbrs4[seed[0]]] = True
    while True:
        matched = np.append(match >= 0, False)
        front = np.flatnonzero(~matched[:n] & touch[:n] & ~retired)
        if len(front) == 0:
            break
        pos = np.vstack([base_px, np.zeros((1, 2))]) + disp
        lines = _frontier_lines(back, matched, pos, front)
        pred = base_px[front] + _predicted_positions(lines, back, disp, front)
        pred_px[front] = pred
        tried[front] = True
        far = ~_inside(visible, pred, -2.0 * spacing[front])
        retired[front[far]] = True
        d1, i1, d2 = _nearest_two(tree, pred)
        near = d1 < accept * spacing[front]
        clear = d1 < ratio * d2
        taken = owner[i1] >= 0
        dup = np.bincount(i1[near & clear & ~taken], minlength=len(spots))[i1] > 1
        jump = _step_jumps(lines, spots.centres_px[i1], max_step_ratio)
        ok = near & clear & ~taken & ~dup & usable[i1] & ~jump & ~far
        reason[front] = np.select(
            [~near, spots.merged[i1], ~usable[i1]], [_NONE, _MERGED, _BORDER], _AMBIGUOUS
        )
        claim[front] = np.where(near, i1, -1)
        support = lines.near.sum(axis=1)
        tiers = (ok & (support >= 3) & (d1 < 0.5 * ratio * d2), ok & (support >= 2), ok)
        ok = next((t for t in tiers if t.any()), ok)
        if not ok.any():
            break
        acc = front[ok]
        match[acc] = i1[ok]
        owner[i1[ok]] = acc
        disp[acc] = spots.centres_px[i1[ok]] - base_px[acc]
        touch[nbrs4[acc].ravel()] = True
    return _Growth(match, reason, claim, pred_px, tried)


def _drop_double_claims(g: _Growth) -> None:
    """A spot within reach of a node that failed is claimed twice: trust neither claim."""
    failed = (g.match < 0) & (g.claim >= 0)
    holder = np.full(len(g.match), -1, np.int64)
    matched = np.flatnonzero(g.match >= 0)
    owner = np.full(int(max(g.match.max(), g.claim.max())) + 1, -1, np.int64)
    owner[g.match[matched]] = matched
    holder[failed] = owner[g.claim[failed]]
    held = holder[holder >= 0]
    g.match[held] = -1
    g.reason[held] = _AMBIGUOUS


def order_violations(
    ij: IntArray,
    ref_px: FloatArray,
    spot_px: FloatArray,
    margin_px: float = 0.5,
    all_spots_px: FloatArray | None = None,
) -> BoolArray:
    """Matches that break eq. 33 with a grid neighbour along a row or a column.

    For grid neighbours ``k`` and ``k+1`` (``i`` or ``j`` + 1, both matched), the flat-water image
    direction ``u = (ref_{k+1} - ref_k) / |.|`` orders the spots; eq. 33 requires
    ``(s_{k+1} - s_k) . u > dp/2``. If ``all_spots_px`` is given, the pair is also wrong when
    another detected spot lies between them (within 0.6 x half their distance of the midpoint):
    a spot has been skipped, so the two labels cannot both be right. Both ends of a bad pair are
    flagged.

    Parameters
    ----------
    ij : (K, 2) ndarray of int
        Grid indices of the matches.
    ref_px, spot_px : (K, 2) ndarray
        Flat-water and wavy-water spot centres, pixels.
    margin_px : float
        ``dp / 2``: half the spot-position uncertainty, pixels.
    all_spots_px : (P, 2) ndarray, optional
        Every detected spot in the wavy image, pixels.

    Returns
    -------
    (K,) ndarray of bool
    """
    bad = np.zeros(len(ij), bool)
    if len(ij) == 0:
        return bad
    lat = _Lattice(ij)
    tree = cKDTree(all_spots_px) if all_spots_px is not None and len(all_spots_px) else None
    for step in ([1, 0], [0, 1]):
        nb = lat.neighbour(step)
        a = np.flatnonzero(nb >= 0)
        b = nb[a]
        u = ref_px[b] - ref_px[a]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        gap = np.sum((spot_px[b] - spot_px[a]) * u, axis=1)
        viol = gap <= margin_px
        if tree is not None and len(a):
            dist, _ = tree.query(0.5 * (spot_px[a] + spot_px[b]))
            viol |= dist < 0.3 * np.linalg.norm(spot_px[b] - spot_px[a], axis=1)
        bad[a[viol]] = True
        bad[b[viol]] = True
    return bad


def _inside(poly: FloatArray, pts: FloatArray, margin: FloatArray) -> BoolArray:
    """Points (N, 2) at least ``margin`` (N,) inside a convex polygon (M, 2), pixels."""
    dist, _ = _edge_distances(poly, pts)
    return (dist >= margin[:, None]).all(axis=1)


def _anchor_shift(
    lat: _Lattice, lit: BoolArray, matched: BoolArray, absent: BoolArray, max_shift: int
) -> tuple[IntArray, int]:
    """Lattice shift that best explains where spots are and are not, and how many tie.

    A shift ``d`` relabels node ``ij`` as ``ij + d``. Its cost counts the contradictions: each
    matched node that would not be a lit dot (weight 3: a spot where no dot shines), and each
    node seen empty (``absent``: nothing there although it is in view) that would be a lit dot.
    Near the pattern's visible boundary or its unlit marker dots only the right shift is free of
    contradictions; elsewhere all shifts tie, and the unshifted labelling is kept.
    """
    r = np.arange(-max_shift, max_shift + 1)
    shifts = np.stack(np.meshgrid(r, r, indexing="ij"), axis=-1).reshape(-1, 2)

    def lit_at(ij: IntArray) -> BoolArray:
        node = lat.lookup(ij[None, :, :] + shifts[:, None, :])
        return (node >= 0) & lit[np.maximum(node, 0)]

    cost = 3 * (~lit_at(lat.ij[matched])).sum(axis=1) + lit_at(lat.ij[absent]).sum(axis=1)
    best = cost.min()
    tied = cost <= best + 3 + best // 4
    zero = (shifts == 0).all(axis=1)
    if tied[zero].any():
        return np.zeros(2, np.int64), int(tied.sum())
    pick = np.flatnonzero(tied)[np.argmin(np.abs(shifts[tied]).sum(axis=1))]
    return shifts[pick].astype(np.int64), int(tied.sum())


def _absent_nodes(
    lat: _Lattice, g: _Growth, tree: cKDTree, spacing: FloatArray, visible: FloatArray
) -> BoolArray:
    """Nodes seen empty: unmatched, predicted from at least two matched neighbours to a place
    well inside the visible area where no spot at all lies within half a spacing."""
    nbrs8 = np.stack([lat.neighbour(step) for step in _DIRS8], axis=1)
    support = ((nbrs8 >= 0) & (g.match[np.maximum(nbrs8, 0)] >= 0)).sum(axis=1)
    cand = g.tried & (g.match < 0) & (support >= 2)
    cand &= _inside(visible, g.pred_px, spacing)
    idx = np.flatnonzero(cand)
    dist, _ = tree.query(g.pred_px[idx])
    cand[idx] = dist > 0.5 * spacing[idx]
    return cand


def _largest_component(lat: _Lattice, nodes: IntArray) -> BoolArray:
    """Which of ``nodes`` belong to their largest 4-connected piece of the lattice."""
    if len(nodes) == 0:
        return np.zeros(0, bool)
    q = lat.ij[nodes] - lat.lo
    occupied = np.zeros(lat.grid.shape, bool)
    occupied[q[:, 1], q[:, 0]] = True
    labels, _ = ndimage.label(occupied)
    lab = labels[q[:, 1], q[:, 0]]
    return lab == np.argmax(np.bincount(lab)[1:]) + 1


def _relabel(
    lat: _Lattice, match: IntArray, reason: NDArray[np.int8], shift: IntArray
) -> tuple[IntArray, NDArray[np.int8], int]:
    """Move every node's result to node ``ij + shift``; also count matches shifted off the
    lattice."""
    if not shift.any():
        return match.copy(), reason.copy(), 0
    dest = lat.lookup(lat.ij + shift)
    ok = dest >= 0
    new_match = np.full_like(match, -1)
    new_reason = np.full_like(reason, _NONE)
    new_match[dest[ok]] = match[ok]
    new_reason[dest[ok]] = reason[ok]
    return new_match, new_reason, int(np.sum((match >= 0) & ~ok))


def match_distorted(
    ref: ReferenceGrid,
    spots: Spots,
    *,
    accept: float = 0.35,
    ratio: float = 0.6,
    order_margin_px: float = 0.5,
    visible_px: FloatArray | None = None,
    prior_px: FloatArray | None = None,
    anchor: bool = True,
    max_shift: int = 6,
) -> Matches:
    """Label the wavy-water spots with grid indices (robust ordering-based correspondence).

    1. Region growing over the lattice (:func:`_grow`) from the node whose nearest spot is most
       confidently its own (close to the flat-water position, or to ``prior_px``).
    2. Spots claimed by two nodes are dropped, then pairs that break eq. 33
       (:func:`order_violations`).
    3. Anchoring: growing fixes labels only up to a whole-lattice shift when spots move by more
       than half a spacing. The shift is chosen so that matched nodes are lit dots and in-view
       nodes seen empty are not (:func:`_anchor_shift`), and applied to all labels.
       ``counts['anchor_candidates']`` says whether it was unique.

    Parameters
    ----------
    ref : ReferenceGrid
        Flat-water lattice (:func:`match_reference`).
    spots : Spots
        Spots detected in the wavy-water image.
    accept : float
        Acceptance radius, in units of the local spot spacing.
    ratio : float
        Largest allowed ratio of nearest to second-nearest spot distance.
    order_margin_px : float
        ``dp / 2`` of eq. 33, pixels.
    visible_px : (M, 2) ndarray, optional
        Convex outline where a spot would be seen (diffuser within the image), pixels; default:
        the convex hull of the flat-water spots.
    prior_px : (G, 2) ndarray, optional
        Expected wavy-water position of each lattice node (e.g. from a previous frame), pixels;
        NaN where unknown. Default: the flat-water positions.
    anchor : bool
        Look for a lattice shift (step 3); off, the labelling nearest to flat water is kept.
    max_shift : int
        Largest lattice shift tried when anchoring, nodes.

    Returns
    -------
    Matches
    """
    n_obs = int(ref.observed.sum())
    counts = {
        "detected": len(spots), "reference": n_obs, "matched": 0, "matched_unobserved": 0,
        "rejected_order": 0, "rejected_merged": 0, "rejected_ambiguous": 0,
        "rejected_border": 0, "rejected_unlit": 0, "unmatched_reference": n_obs,
        "unassigned_spots": len(spots), "anchor_di": 0, "anchor_dj": 0, "anchor_candidates": 0,
    }
    empty = Matches(
        np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool), counts
    )
    if n_obs == 0 or len(spots) == 0:
        return empty
    lat = _Lattice(ref.ij)
    base = ref.ref_px.copy()
    if prior_px is not None:
        prior = np.asarray(prior_px, dtype=float)
        base = np.where(np.isfinite(prior), prior, base)
    tree = cKDTree(spots.centres_px)
    seed = _choose_seed(lat, base, ref, spots, tree, accept, ratio)
    if seed < 0:
        return empty
    seed_spot = int(tree.query(base[seed])[1])
    if visible_px is None:
        hull = cv2.convexHull(ref.ref_px[ref.observed].astype(np.float32))[:, 0]
    else:
        hull = visible_px
    hull = np.asarray(hull, dtype=np.float64)
    g = _grow(lat, base, ref.spacing_px, spots, tree, (seed, seed_spot), hull, accept, ratio)
    _drop_double_claims(g)

    shift, n_tied = np.zeros(2, np.int64), 1
    if anchor:
        absent = _absent_nodes(lat, g, tree, ref.spacing_px, hull)
        shift, n_tied = _anchor_shift(lat, ref.lit, g.match >= 0, absent, max_shift)
    match, reason, n_off = _relabel(lat, g.match, g.reason, shift)
    counts.update(anchor_di=int(shift[0]), anchor_dj=int(shift[1]), anchor_candidates=n_tied)

    kept = np.flatnonzero(match >= 0)
    spot_px = spots.centres_px[match[kept]]
    bad = order_violations(
        ref.ij[kept], ref.ref_px[kept], spot_px, order_margin_px, spots.centres_px
    )
    reason[kept[bad]] = _ORDER
    unlit = ~ref.lit[kept] & ~bad
    reason[kept[unlit]] = _UNLIT
    kept = kept[~bad & ~unlit]
    # Labels are only consistent within one connected piece of the lattice: keep the largest.
    main = _largest_component(lat, kept)
    reason[kept[~main]] = _AMBIGUOUS
    kept = kept[main]
    lost = np.ones(len(ref.ij), bool)
    lost[kept] = False
    why = reason[lost & ref.lit]  # virtual and unlit nodes are nobody's loss
    counts.update(
        matched=int(len(kept)),
        matched_unobserved=int(np.sum(~ref.observed[kept])),
        rejected_order=int(np.sum(why == _ORDER)),
        rejected_merged=int(np.sum(why == _MERGED)),
        rejected_ambiguous=int(np.sum(why == _AMBIGUOUS)),
        rejected_border=int(np.sum(why == _BORDER)),
        rejected_unlit=int(np.sum(reason == _UNLIT)) + n_off,
        unmatched_reference=int(np.sum(lost & ref.observed & (reason == _NONE))),
        unassigned_spots=int(len(spots) - len(kept)),
    )
    return Matches(
        ref.ij[kept], ref.ref_px[kept], spots.centres_px[match[kept]], ref.observed[kept], counts
    )


# ----------------------------------------------------------------------------------------------
# 5. All steps
# ----------------------------------------------------------------------------------------------


def _visible_outline(cfg: SystemConfig) -> FloatArray:
    """Where camera s can see a spot: the diffuser's outline clipped to the image, (M, 2) px."""
    cam = cfg.camera_s
    w, h = cam.width_px - 0.5, cam.height_px - 0.5
    frame = np.array([[-0.5, -0.5], [w, -0.5], [w, h], [-0.5, h]], np.float32)
    area, poly = cv2.intersectConvexConvex(_outline_px(cfg).astype(np.float32), frame)
    if area <= 0 or poly is None:
        raise WaiInputError("camera s does not see the diffuser")
    return poly[:, 0].astype(np.float64)


def find_features(
    pattern_img: NDArray,
    pattern_flat_img: NDArray,
    cfg: SystemConfig,
    *,
    lit: BoolArray | None = None,
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
    lit : (K,) ndarray of bool, optional
        Dots the projector lit, in :func:`~wai_core.pattern.dot_grid` order (default: those the
        renderer lights, :func:`wai_core.layout.lit_dots`).
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

    if not np.isfinite(pattern_img).all():
        raise WaiInputError("pattern image holds NaN or inf")
    ref = prepare_reference(pattern_flat_img, cfg, lit=lit, min_features=min_features)
    timings["reference"] = 1e3 * (time.perf_counter() - t_all)
    matches = features_from_reference(pattern_img, ref, cfg, min_features=min_features)
    matches.timings_ms["reference"] = timings["reference"]
    matches.timings_ms["total"] = 1e3 * (time.perf_counter() - t_all)
    return matches


def prepare_reference(
    pattern_flat_img: NDArray, cfg: SystemConfig, *, lit: BoolArray | None = None,
    min_features: int = 16,
) -> ReferenceGrid:
    """The flat-water reference grid: calibration, computed once per rig, not per frame."""
    flat = flag_diffuser_edge(detect_spots(pattern_flat_img), _outline_px(cfg))
    predicted = predict_flat_spots(cfg)
    ref = match_reference(flat, predicted, lit=lit_dots(cfg) if lit is None else lit)
    if ref.counts["observed"] < min_features:
        raise WaiInputError(f"too few features on flat water: {ref.counts['observed']}")
    return ref


def features_from_reference(
    pattern_img: NDArray, ref: ReferenceGrid, cfg: SystemConfig, *, min_features: int = 16
) -> Matches:
    """Detect the spots of one wavy frame and match them to a prepared reference grid."""
    cam = cfg.camera_s
    if np.shape(pattern_img)[:2] != (cam.height_px, cam.width_px):
        raise WaiInputError(
            f"pattern image is {np.shape(pattern_img)[:2]}, camera s is "
            f"{cam.height_px}x{cam.width_px}"
        )
    t0 = time.perf_counter()
    wavy = flag_diffuser_edge(detect_spots(pattern_img), _outline_px(cfg))
    t1 = time.perf_counter()
    matches = match_distorted(ref, wavy, visible_px=_visible_outline(cfg))
    t2 = time.perf_counter()
    if len(matches) < min_features:
        raise WaiInputError(f"too few features matched: {len(matches)} (need {min_features})")
    matches.timings_ms.update({"detect": 1e3 * (t1 - t0), "match": 1e3 * (t2 - t1)})
    return matches
