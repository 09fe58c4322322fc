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

Per frame, :func:`features_from_reference` must fit a 30 frames/s pipeline, so every step works
on whole arrays: segment moments are sparse (label x pixel) products, centroid windows are
evaluated for batches of equal-sized boxes with matrix products, and the region growing
re-evaluates only the lattice nodes whose matched neighbours changed (everything that depends
on the reference alone is built once with the :class:`ReferenceGrid`).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.lib.stride_tricks import as_strided
from numpy.typing import NDArray
from scipy import ndimage, sparse
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
    tables: _LatticeTables = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Neighbour tables for the per-frame matching: they depend on the lattice only.
        object.__setattr__(self, "tables", _LatticeTables.of(self.ij, self.lit))

    def lit_at(self, ij: NDArray) -> BoolArray:
        """Whether each lattice index ``ij`` (K, 2) is a lit dot of this lattice."""
        node = self.tables.lat.lookup(ij)
        return (node >= 0) & self.lit[np.maximum(node, 0)]


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
        boundary; more: it is only the one nearest to flat water). ``labels_ambiguous``: 1 when
        ``anchor_candidates > 1``, i.e. the labels may be shifted by whole grid steps; the
        pipeline reports it (with all counts, as ``feature_counts``).
    timings_ms : dict of str to float
        Wall time per step, ms: ``detect`` and ``match`` from :func:`features_from_reference`,
        plus ``reference`` and ``total`` from :func:`find_features`.
    alt_shifts : (C, 2) ndarray of int
        Lattice shifts, relative to ``ij``, that fit the lit/unlit evidence as well as the one
        applied (``[0, 0]`` included); more than one row when ``labels_ambiguous``. A caller
        with more evidence (:func:`restoration.pipeline.restore` uses the integrability of the
        slopes) may relabel ``ij + shift``.
    """

    ij: IntArray
    ref_px: FloatArray
    spot_px: FloatArray
    observed: BoolArray
    counts: dict[str, int]
    timings_ms: dict[str, float] = field(default_factory=dict)
    alt_shifts: IntArray = field(default_factory=lambda: np.zeros((1, 2), np.int64))

    def __len__(self) -> int:
        return int(self.ij.shape[0])


# ----------------------------------------------------------------------------------------------
# 1. Spot detection
# ----------------------------------------------------------------------------------------------


def _luminance(image: NDArray, pad: int) -> NDArray[np.float32]:
    """Sum of the colour channels, float32, in a new array with ``pad`` zeros around it
    (h + 2 pad, w + 2 pad); rejects bad shapes and non-finite values."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (1, 3, 4):
        shape = img.shape[:2]
    elif img.ndim == 2:
        shape = img.shape
    else:
        shape = (0, 0)
    if min(shape) < 8:
        raise WaiInputError(
            f"pattern image must be (h, w) or (h, w, 3), got shape {np.shape(image)}"
        )
    if img.ndim == 2 and not np.issubdtype(img.dtype, np.number):
        raise WaiInputError(f"pattern image must be numeric, got {img.dtype}")
    padded = np.zeros((shape[0] + 2 * pad, shape[1] + 2 * pad), np.float32)
    lum = padded[pad : pad + shape[0], pad : pad + shape[1]]
    if img.ndim == 2:
        lum[:] = img
    elif img.dtype in (np.float32, np.float64) and img.shape[2] > 1:
        # cv2.transform sums the channels in one pass, ~50x faster than numpy's reduction
        # over a short last axis; an alpha channel gets weight 0.
        weights = np.ones((1, img.shape[2]))
        weights[0, 3:] = 0.0
        if img.dtype == np.float32:
            cv2.transform(np.ascontiguousarray(img), weights, dst=lum)
        else:
            lum[:] = cv2.transform(np.ascontiguousarray(img), weights)
    else:
        lum[:] = img[..., :3].sum(axis=2, dtype=np.float64)
    if not np.isfinite(lum).all():
        raise WaiInputError("pattern image contains NaN or infinite values")
    return padded


def _upsample(
    small: NDArray[np.float32], shape: tuple[int, ...], out: NDArray[np.float32] | None = None
) -> NDArray[np.float32]:
    """Bilinear resize of a coarse map back to the image size (h, w), into ``out`` if given."""
    return cv2.resize(small, (shape[1], shape[0]), dst=out, interpolation=cv2.INTER_LINEAR)


def _background(smooth: NDArray[np.float32], size_px: int) -> NDArray[np.float32]:
    """Slowly varying background: local minimum over a window wider than a spot, then averaged.

    Runs on a 4x coarser grid (the background varies slowly): a 5 x 5 minimum first, so the
    subsampled pixels are the darkest of their neighbourhood, not a spot's core.
    """
    k = max(size_px // 4, 1) | 1
    full = cv2.erode(smooth, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_REPLICATE)
    low = cv2.erode(np.ascontiguousarray(full[::4, ::4]), np.ones((k, k), np.uint8),
                    borderType=cv2.BORDER_REPLICATE)
    return _upsample(cv2.blur(low, (k, k), borderType=cv2.BORDER_REPLICATE), smooth.shape, full)


@functools.lru_cache(maxsize=8)
def _minimum_bias(smooth_px: float, size_px: int) -> float:
    """How far :func:`_background` lies below the mean of pure noise, in units of the smoothed
    noise's standard deviation (about 2.5): measured once on seeded white noise smoothed as the
    images are."""
    white = np.random.default_rng(0).normal(size=(256, 256)).astype(np.float32)
    smooth = cv2.GaussianBlur(white, (0, 0), smooth_px, borderType=cv2.BORDER_REFLECT)
    smooth /= smooth.std()
    return -float(np.mean(_background(smooth, size_px)[32:-32, 32:-32]))


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


def _segment(
    smooth: NDArray[np.float32],
    radius_px: int,
    rel_level: float,
    floor: float,
    work: NDArray[np.float32],
    wide_px: int = 40,
    wide_level: float = 0.005,
) -> tuple[int, NDArray[np.int32], BoolArray]:
    """Label pixels above ``rel_level`` x their local maximum (and above ``floor``).

    The max filter's radius is under half the spot spacing, so a pixel is compared with its own
    dot's peak: a dim dot next to a bright one is segmented like the bright one. On a wide spot
    that test holds far into the tails (the slope there is gentle), so pixels must also exceed
    ``wide_level`` x the maximum within ``wide_px`` of a copy blurred by a 4 px Gaussian. A wide
    spot keeps its peak under that blur, so its segment ends at ~3.5 sigma, short of its
    neighbours; a small bright dot loses most of its peak, so a small dim neighbour survives.

    ``work`` (h, w) is scratch space, overwritten: the maps above and then the labels are
    written there rather than into fresh image-sized arrays (each new one costs more in page
    faults than the filter does). Returns the number of labels (background included), the
    label image (h, w, a view of ``work``) and the mask.
    """
    size = 2 * radius_px + 1
    level = cv2.dilate(smooth, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)), dst=work)
    level *= rel_level
    mask = smooth > level
    # On a 4x coarser grid: a 4 x 4 block average and a 1 px blur there make the ~4 px blur.
    h, w = smooth.shape
    small = cv2.resize(smooth, (w // 4, h // 4), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), 1.0, borderType=cv2.BORDER_REFLECT)
    k = 2 * (wide_px // 4) + 1
    level = _upsample(cv2.dilate(small, np.ones((k, k), np.uint8)), smooth.shape, work)
    level *= wide_level
    mask &= smooth > level
    mask &= smooth > floor
    # Plain labelling: cv2's per-component statistics cost 6x the labelling itself, and the
    # moments below give the same from the pixel list.
    n, labels = cv2.connectedComponents(mask.view(np.uint8), work.view(np.int32), 8, cv2.CV_32S)
    return n, labels, mask


def _moments(
    weights: sparse.csc_matrix, x: FloatArray, y: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-label total (n,), mean (n, 2) and covariance (n, 2, 2) of pixels at ``(x, y)`` (N,),
    px, with the weights of ``weights`` (labels x pixels): two sparse products of three columns
    each, not one bincount per column (and small temporaries). Raw moments: keep ``x, y`` small
    against the image size."""
    cols = np.empty((len(x), 3))
    cols[:, 0], cols[:, 1], cols[:, 2] = 1.0, x, y
    first = weights @ cols
    np.multiply(x, x, out=cols[:, 0])
    np.multiply(x, y, out=cols[:, 1])
    np.multiply(y, y, out=cols[:, 2])
    second = weights @ cols
    tot = first[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = first[:, 1:] / tot[:, None]
        second /= tot[:, None]
    cov = np.empty((len(tot), 2, 2))
    cov[:, 0, 0] = second[:, 0] - mean[:, 0] ** 2
    cov[:, 0, 1] = cov[:, 1, 0] = second[:, 1] - mean[:, 0] * mean[:, 1]
    cov[:, 1, 1] = second[:, 2] - mean[:, 1] ** 2
    return tot, mean, cov


def _major_axis_kurtosis(px: _Pixels, peak: FloatArray, centre: FloatArray) -> FloatArray:
    """Kurtosis ``m4 / m2^2`` along each segment's major axis of ``max(smooth - 0.2 peak, 0)``.

    Measured relative to the segment's own peak, it is nearly the same for every single Gaussian
    spot, whatever its size, elongation or brightness (2.2-2.45 after the smoothing, the spread
    from pixelisation of the smallest), and falls as two spots run together into a flat-topped
    or two-humped blob (below 2.15 once they are more than ~3 sigma apart). Pixel offsets are
    taken from the segment's ``centre`` (n, 2) rounded to a pixel: exact small integers.
    """
    lab = px.lab
    origin = np.rint(np.nan_to_num(centre)).astype(np.int32)  # NaN: no weight at all
    x = (px.cols - origin[lab, 0]).astype(np.float64)
    y = (px.rows - origin[lab, 1]).astype(np.float64)
    w = np.clip(px.smooth - 0.2 * peak[lab], 0.0, None)
    weights = px.weigh(w, len(peak))
    tot, mean, cov = _moments(weights, x, y)
    # Major-axis direction of each 2 x 2 covariance, in closed form.
    angle = 0.5 * np.arctan2(2.0 * cov[:, 0, 1], cov[:, 0, 0] - cov[:, 1, 1])
    x -= mean[lab, 0]
    y -= mean[lab, 1]
    x *= np.cos(angle)[lab]
    y *= np.sin(angle)[lab]
    x += y  # the projection on the major axis
    x *= x
    m2 = weights @ x
    x *= x
    m4 = weights @ x
    with np.errstate(divide="ignore", invalid="ignore"):
        kurt = m4 * tot / m2**2
    return np.where(np.isfinite(kurt), kurt, 3.0)


@dataclass(frozen=True)
class _Pixels:
    """The segmented pixels (N,) in raster order: flat index in the padded image (see
    :func:`detect_spots`), row, column, label, smoothed (float64) and raw value."""

    at: IntArray
    rows: NDArray[np.int32]
    cols: NDArray[np.int32]
    lab: NDArray[np.int32]
    smooth: FloatArray
    raw: NDArray[np.float32]

    @classmethod
    def of(
        cls, labels: NDArray[np.int32], mask: BoolArray, smooth: NDArray, padded: NDArray, pad: int
    ) -> _Pixels:
        pix = np.flatnonzero(mask)
        rows, cols = np.divmod(pix.astype(np.int32), labels.shape[1])
        at = pix + 2 * pad * rows + pad * (padded.shape[1] + 1)
        return cls(at, rows, cols, labels.ravel()[pix], smooth.ravel()[pix].astype(np.float64),
                   padded.ravel()[at])

    def weigh(self, weight: FloatArray, n: int) -> sparse.csc_matrix:
        """Labels x pixels (n, N) sparse matrix holding ``weight`` (N,): times a column of
        per-pixel values, it sums them per label, weighted."""
        ptr = np.arange(len(self.at) + 1, dtype=np.int32)
        return sparse.csc_matrix((weight, self.lab, ptr), shape=(n, len(self.at)))


@dataclass(frozen=True)
class _Segments:
    """Per-label statistics of the segmented image (index 0 is the background)."""

    tot: FloatArray  # smoothed intensity (clipped at 0) summed over the segment
    mean: FloatArray  # (n, 2) smoothed-intensity centroid, px
    cov: FloatArray  # (n, 2, 2) smoothed-intensity second moments, px^2
    peak: FloatArray  # peak of the smoothed image
    flux: FloatArray  # raw intensity summed over the segment
    area: IntArray  # pixels in the segment
    kurtosis: FloatArray  # along the major axis, of the part above 0.2 x peak


def _segment_stats(px: _Pixels, n: int, shape: tuple[int, ...]) -> _Segments:
    """Moments of every segment at once, from the list of segmented pixels (no segment loop)."""
    h, w = shape
    # Coordinates from the image centre: the raw second moments lose < 1e-10 px^2 that way.
    tot, mean, cov = _moments(
        px.weigh(np.clip(px.smooth, 0.0, None), n), px.cols - 0.5 * (w - 1),
        px.rows - 0.5 * (h - 1),
    )
    mean += [0.5 * (w - 1), 0.5 * (h - 1)]
    peak = np.full(n, -np.inf)
    np.maximum.at(peak, px.lab, px.smooth)
    flux = np.bincount(px.lab, px.raw, n)
    area = np.bincount(px.lab, minlength=n)
    return _Segments(tot, mean, cov, peak, flux, area, _major_axis_kurtosis(px, peak, mean))


def _spot_covariance(cov_seg: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Spot covariance (n, 2, 2) for the centroid window, from the segments' second moments,
    and the larger eigenvalue of the latter (n,), px^2.

    The segment (cut at a fraction of the smoothed peak) holds about 0.55 of the variance of a
    large spot and, because the smoothing widens a small one, about 0.85 of a small one's; the
    window needs only a rough width (a wrong one just slows convergence), so the moments are used
    as they are, with eigenvalues kept above (0.3 px)^2.
    """
    a, b, c = cov_seg[:, 0, 0], cov_seg[:, 0, 1], cov_seg[:, 1, 1]
    mid, rad = 0.5 * (a + c), np.hypot(0.5 * (a - c), b)  # eigenvalues mid -+ rad
    cov = cov_seg.copy()
    thin = mid - rad < 0.3**2
    if thin.any():
        evals, evecs = np.linalg.eigh(cov_seg[thin])
        evals = np.clip(evals, 0.3**2, None)
        cov[thin] = np.einsum("nij,nj,nkj->nik", evecs, evals, evecs)
    return cov, mid + rad


def _typical_flux(flux: FloatArray) -> float:
    """Flux-weighted median: the flux of a typical bright spot, however many faint specks."""
    if flux.size == 0:
        return 0.0
    f = np.sort(flux)
    cum = np.cumsum(f)
    return float(f[np.searchsorted(cum, 0.5 * cum[-1])])


# Spot boxes: half widths are multiples of 3 px up to 48, padded to these tiers so that a few
# batches of equal-sized boxes cover all spots; each spot still uses only its own box.
_BOX_TIERS = np.array([3, 6, 9, 12, 18, 24, 36, 48])
_BOX_MAX = int(_BOX_TIERS[-1])
# OpenBLAS runs a matrix product on one thread up to this many multiply-adds. Above it, its
# worker threads cost more than they save on these small products (tenfold, on two busy cores)
# and then spin, taking a core from whatever runs next.
_BLAS_ONE_THREAD = 65536 * 4


def _matmul(a: NDArray, b: NDArray, out: NDArray) -> None:
    """``out = a @ b`` in row blocks that BLAS runs single-threaded."""
    rows = max(1, _BLAS_ONE_THREAD // (b.shape[0] * b.shape[1]))
    for i in range(0, len(a), rows):
        np.matmul(a[i : i + rows], b, out=out[i : i + rows])


@functools.cache
def _box_basis(hx: int, hy: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Bases over a box of half widths ``(hx, hy)``, pixels row by row (E = box area), px:
    ``quad`` (6, E), ``fx^2, fx fy, fy^2, fx, fy, 1`` (a quadratic form in the offsets is then
    one matrix product), and ``lin`` (E, 3), ``1, fx, fy`` (so are the first moments)."""
    gx, gy = (g.ravel() for g in np.meshgrid(np.arange(-hx, hx + 1.0), np.arange(-hy, hy + 1.0)))
    quad = np.stack([gx * gx, gx * gy, gy * gy, gx, gy, np.ones_like(gx)]).astype(np.float32)
    lin = np.ascontiguousarray(quad[[5, 3, 4]].T)
    for arr in (quad, lin):
        arr.setflags(write=False)
    return quad, lin


@functools.cache
def _axis_masks(h: int) -> NDArray[np.float32]:
    """(h // 3, 2 h + 1): along an axis of a box of half width ``h``, row ``k`` marks the
    pixels within ``3 (k + 1)`` of the centre (a spot's own half width, padded to ``h``)."""
    f = np.abs(np.arange(-h, h + 1))
    mask = (f <= 3 * np.arange(1, h // 3 + 1)[:, None]).astype(np.float32)
    mask.setflags(write=False)
    return mask


@dataclass(frozen=True)
class _Boxes:
    """Boxes around the spots, batched by padded size, stored end to end in one flat buffer.

    Spots are handled in ``order`` (P,), which sorts them by batch; ``batch`` (B + 1,) are the
    batch boundaries in that order and ``dims`` (B, 2) each batch's padded half widths
    ``(hx, hy)``. Per spot, in that order: ``half`` (P, 2) its own half widths, ``base`` (P, 2)
    the box centre ``(col, row)``, and ``frame`` (P + 1, 6): its own box's first column and
    row, width and height, where that first pixel is in the buffer, and the padded width (last
    row: an empty box, for "no spot"). ``start`` (P + 1,): where each padded box starts.
    """

    order: IntArray
    batch: IntArray
    dims: IntArray
    half: IntArray
    base: IntArray
    frame: IntArray
    start: IntArray

    @classmethod
    def around(cls, start: FloatArray, cov: FloatArray) -> _Boxes:
        """Boxes reaching 3.5 segment sigmas + 1 px along each image axis (about 3 spot sigmas:
        beyond it the spot times the centroid window is below 0.5 %), centred on ``start``."""
        sd = np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1))
        half = np.clip(np.ceil(3.5 * sd + 1.0), 3, _BOX_MAX).astype(np.int64)
        half = 3 * ((half + 2) // 3)  # as few distinct sizes as possible
        tier = np.searchsorted(_BOX_TIERS, half)
        key = tier[:, 0] * len(_BOX_TIERS) + tier[:, 1]
        order = np.argsort(key, kind="stable")
        key = key[order]
        batch = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True])
        half, padded = half[order], _BOX_TIERS[tier[order]]
        base = np.rint(start[order]).astype(np.int64)
        width = 2 * padded + 1
        begin = np.r_[0, np.cumsum(width[:, 0] * width[:, 1])]
        frame = np.zeros((len(order) + 1, 6), np.int32)  # small gathers: int32
        frame[:-1, :2] = base - half
        frame[:-1, 2:4] = 2 * half + 1
        margin = padded - half  # own box within the padded one
        frame[:-1, 4] = begin[:-1] + margin[:, 1] * width[:, 0] + margin[:, 0]
        frame[:-1, 5] = width[:, 0]
        return cls(order, batch, padded[batch[:-1]], half, base, frame, begin)

    @property
    def size(self) -> int:
        """Length of the buffer."""
        return int(self.start[-1])

    def batches(self):
        """``(slice of spots, slice of the buffer, hx, hy)`` of every batch."""
        start = self.start[self.batch].tolist()
        for b, (hx, hy) in enumerate(self.dims.tolist()):
            yield slice(self.batch[b], self.batch[b + 1]), slice(start[b], start[b + 1]), hx, hy

    def locate(self, rows: IntArray, cols: IntArray, spot: IntArray) -> tuple[IntArray, BoolArray]:
        """Buffer position (N,) of pixels ``(rows, cols)`` in the box of spot ``spot`` (box
        order, -1 for none), valid where ``inside`` (N,) the spot's own box."""
        f = self.frame[spot]
        ux, uy = cols - f[:, 0], rows - f[:, 1]
        # As unsigned, a negative offset is huge: one comparison per axis.
        inside = ux.view(np.uint32) < f[:, 2].view(np.uint32)
        inside &= uy.view(np.uint32) < f[:, 3].view(np.uint32)
        return f[:, 4] + uy * f[:, 5] + ux, inside


def _windowed_centroids(
    boxes: _Boxes,
    vals: NDArray[np.float32],
    q: NDArray[np.float32],
    start: FloatArray,
    cov: FloatArray,
    n_iter: int,
) -> FloatArray:
    """Gaussian-windowed centroids (as SExtractor's ``XWIN``), spots in box order.

    A Gaussian spot of covariance C seen through a Gaussian window of covariance ``k^2 C``
    centred at ``x_n`` has its weighted mean ``m`` a fraction ``k^2 / (1 + k^2)`` of the way to
    the true centre, so ``x_{n+1} = x_n + (1 + 1/k^2) (m - x_n)`` converges in one step and stays
    unbiased for any symmetric profile (a wrong C only slows convergence). Unlike a thresholded
    centroid it has no pixel-locking bias. ``k`` trades noise (``k = 1``: 1.33x the Poisson
    limit; ``k = 1.5``: 1.1x) against light from neighbours. ``vals`` (the boxes' pixels) is
    zero at pixels of *other* kept segments, so a much brighter neighbour cannot pull the
    centre, and beyond each spot's own box (in a padded one). ``q`` is scratch space as long.

    Per step, the window's exponent over a batch of boxes is one matrix product (coefficients
    times :func:`_box_basis`'s ``quad``), and its weighted moments another.
    """
    det = _WINDOW_VAR * (cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2)
    a, b, c = cov[:, 1, 1] / det, -cov[:, 0, 1] / det, cov[:, 0, 0] / det  # inverse window
    sums = np.empty((len(start), 3), np.float32)  # summed in float32, as the pixels
    x = start - boxes.base
    for _ in range(n_iter):
        sx, sy = x[:, 0], x[:, 1]
        # -q/2 of the window centred at (sx, sy), as coefficients of fx^2, fx fy, fy^2, fx, fy, 1.
        coef = np.stack(
            [a, 2 * b, c, -2 * (a * sx + b * sy), -2 * (b * sx + c * sy),
             a * sx * sx + 2 * b * sx * sy + c * sy * sy], axis=1
        )
        coef = (-0.5 * coef).astype(np.float32)
        for spots, buf, hx, hy in boxes.batches():
            quad = _box_basis(hx, hy)[0]
            _matmul(coef[spots], quad, q[buf].reshape(-1, quad.shape[1]))
        np.exp(q, out=q)
        q *= vals
        for spots, buf, hx, hy in boxes.batches():
            lin = _box_basis(hx, hy)[1]
            _matmul(q[buf].reshape(-1, lin.shape[0]), lin, sums[spots])  # w, w fx, w fy
        tot = sums[:, 0]
        ok = tot > 0
        step = _WINDOW_GAIN * (sums[:, 1:] / np.where(ok, tot, 1.0)[:, None] - x)
        # A step longer than a pixel means noise dominates the window: do not wander off.
        x += np.where(ok[:, None], np.clip(step, -1.0, 1.0), 0.0)
    return x + boxes.base


def _refine_centres(
    padded: NDArray[np.float32],
    px: _Pixels,
    n: int,
    keep: IntArray,
    start: FloatArray,
    cov: FloatArray,
    n_iter: int = 2,
) -> FloatArray:
    """Windowed centres (P, 2) of the kept segments ``keep`` (of ``n`` labels), from ``start``
    (P, 2), px.

    Each spot's box (:class:`_Boxes`) holds the raw image there with the pixels of the other
    kept segments blanked (:func:`_windowed_centroids`). ``padded`` is the raw image with
    ``_BOX_MAX`` zeros around it; it is used up (blanked, then scratch space).
    """
    if len(keep) == 0:
        return np.zeros((0, 2))
    pad, wp = _BOX_MAX, padded.shape[1]
    boxes = _Boxes.around(start, cov)
    rank = np.empty(len(keep), np.int64)
    rank[boxes.order] = np.arange(len(keep))
    spot_of = np.full(n, -1, np.int64)
    spot_of[keep] = rank
    spot = spot_of[px.lab]  # -1: a pixel of a dropped segment
    pos, inside = boxes.locate(px.rows, px.cols, spot)

    # The boxes' pixels from the image without the kept segments, then each spot's own segment
    # put back in its own box. Index 0 is padding, always zero: where dropped segments' pixels
    # would be blanked.
    padded.ravel()[np.where(spot >= 0, px.at, 0)] = 0.0
    vals = np.empty(boxes.size, np.float32)
    for spots, buf, hx, hy in boxes.batches():
        wy, wx = 2 * hy + 1, 2 * hx + 1
        shape = (padded.shape[0] - wy + 1, wp - wx + 1, wy, wx)
        win = as_strided(padded, shape, padded.strides * 2)
        corner = boxes.base[spots] - (hx, hy) + pad
        box = vals[buf].reshape(-1, wy, wx)
        box[:] = win[corner[:, 1], corner[:, 0]]
        half = boxes.half[spots]
        if (half < (hx, hy)).any():  # padded boxes: zero beyond the spot's own box
            box *= _axis_masks(hy)[half[:, 1] // 3 - 1][:, :, None]
            box *= _axis_masks(hx)[half[:, 0] // 3 - 1][:, None, :]
    vals[pos[inside]] = px.raw[inside]
    # The image is no longer needed: its memory holds the window weights (no new allocation).
    q = padded.ravel()[: vals.size] if vals.size <= padded.size else np.empty_like(vals)
    centres = _windowed_centroids(boxes, vals, q, start[boxes.order], cov[boxes.order], n_iter)
    return centres[rank]


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
    # The image sits in a frame of zeros, where the centroid boxes may reach past its edge.
    padded = _luminance(image, _BOX_MAX)
    lum = padded[_BOX_MAX:-_BOX_MAX, _BOX_MAX:-_BOX_MAX]
    h, w = lum.shape
    smooth = cv2.GaussianBlur(lum, (0, 0), smooth_px, borderType=cv2.BORDER_REFLECT)
    noise = _noise_sigma(lum, smooth, smooth_px)
    bg = _background(smooth, background_px)
    # A local minimum sits below the mean of noise: without this, read noise would lift every
    # pixel above the floor. Capped by the lower quartile of what remains, which is ~0 where
    # there is no noise (there the noise estimate is only the dots' sharpness).
    lifted = float(np.percentile(smooth[::4, ::4] - bg[::4, ::4], 25.0))
    bg += min(noise * _minimum_bias(smooth_px, background_px), max(lifted, 0.0))
    smooth -= bg
    saturated_px = None if saturation is None else lum >= saturation
    lum -= bg  # now the raw, background-subtracted image
    tiny = 1e-6 * max(float(smooth.max()), 1e-30)  # keeps a noiseless zero background out
    # bg, no longer needed, is the scratch space (and then the labels).
    n, labels, mask = _segment(smooth, local_radius_px, rel_level, max(2.0 * noise, tiny), bg)
    px = _Pixels.of(labels, mask, smooth, padded, _BOX_MAX)
    edge = np.zeros(n, bool)  # the segment has a pixel in the image's outer rows or columns
    edge[np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])] = True
    n_saturated = None if saturated_px is None else np.bincount(labels[saturated_px], minlength=n)
    # Free the image-sized arrays no longer needed before the moments and centroids take their
    # memory: a lower peak lets the allocator reuse pages from frame to frame, not fault in new.
    del smooth, bg, labels, mask, saturated_px
    seg = _segment_stats(px, n, (h, w))
    good = (seg.peak > max(snr_min * noise, tiny)) & (seg.area >= min_area_px) & (seg.tot > 0)
    good[0] = False  # label 0 is the background
    good &= seg.flux > rel_flux * _typical_flux(seg.flux[good])
    idx = np.flatnonzero(good)
    saturated = np.zeros(idx.size, bool) if n_saturated is None else n_saturated[idx] > 0
    cov, major = _spot_covariance(seg.cov[idx])
    centres = _refine_centres(padded, px, n, idx, seg.mean[idx], cov)
    # Too few pixels across to tell a shape (single spots of sigma <~ 1.2 px): never "merged".
    merged = (seg.kurtosis[idx] < merge_kurtosis) & (major >= 1.3**2)
    return Spots(
        centres_px=centres,
        flux=seg.flux[idx],
        peak=seg.peak[idx],
        area_px=seg.area[idx].astype(np.int64),
        cov_px2=cov,
        merged=merged,
        border=edge[idx],
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


@functools.lru_cache(maxsize=8)  # per frame it would cost ~0.3 ms; the config is immutable
def _outline_px(cfg: SystemConfig) -> FloatArray:
    """The diffuser's corners (4, 2) in camera s, pixels, in order around it (read-only)."""
    (x0, x1), (y0, y1) = _diffuser(cfg)
    z = cfg.diffuser.z_mm
    corners = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    cols, rows, _ = cfg.camera_s.camera().project(corners)
    out = np.stack([cols, rows], axis=1)
    out.setflags(write=False)
    return out


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


@dataclass(frozen=True)
class _LatticeTables:
    """Neighbour tables of a reference lattice (built once with the :class:`ReferenceGrid`).

    Node numbers of neighbours, ``n`` (one past the last node) where there is none: ``back``
    (n + 1, 16) one step back along each of the 8 grid directions, then two steps, ``fwd``
    (n + 1, 16) the same forward, ``nbrs4`` (n, 4) and ``nbrs8`` (n, 8); the tables' last rows
    (node ``n``) point nowhere. ``lit_grid`` marks the lit dots on ``lat.grid``.
    """

    lat: _Lattice
    back: IntArray
    fwd: IntArray
    nbrs4: IntArray
    nbrs8: IntArray
    lit_grid: BoolArray

    @classmethod
    def of(cls, ij: IntArray, lit: BoolArray) -> _LatticeTables:
        lat = _Lattice(ij)
        n = len(lat.ij)

        def table(steps: NDArray, sentinel_row: bool = False) -> IntArray:
            t = np.stack([lat.neighbour(step) for step in steps], axis=1)
            t = np.where(t < 0, n, t)
            return np.vstack([t, np.full((1, len(steps)), n)]) if sentinel_row else t

        back = table(np.vstack([-_DIRS8, -2 * _DIRS8]), True)
        fwd = table(np.vstack([_DIRS8, 2 * _DIRS8]), True)
        lit_grid = np.zeros(lat.grid.shape, bool)
        q = lat.ij[np.asarray(lit, bool)] - lat.lo
        lit_grid[q[:, 1], q[:, 0]] = True
        return cls(lat, back, fwd, table(_DIRS4), table(_DIRS8), lit_grid)


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

# A growth that matches fewer than this fraction of the flat-water dots is tried once more from
# another seed (see match_distorted).
REGROW_BELOW = 0.5

# Why a lattice node was not matched (the last reason seen while it was on the frontier).
_NONE, _MERGED, _BORDER, _AMBIGUOUS, _ORDER, _UNLIT = range(6)


def _as_complex(xy: FloatArray) -> NDArray[np.complex128]:
    """Points (N, 2) as complex numbers ``col + 1j row`` (N,): a view, no arithmetic."""
    return np.ascontiguousarray(xy, dtype=np.float64).view(np.complex128)[:, 0]


def _as_xy(z: NDArray[np.complex128]) -> FloatArray:
    """Complex points (N,) as (N, 2) ``(col, row)``: a view."""
    return np.ascontiguousarray(z).view(np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class _Outline:
    """A convex polygon (M, 2) with its inward unit edge normals (M, 2), computed once."""

    poly: FloatArray
    normal: FloatArray

    @classmethod
    def of(cls, poly: FloatArray) -> _Outline:
        poly = np.asarray(poly, dtype=np.float64)
        return cls(poly, _edge_distances(poly, poly[:1])[1])

    def inside(self, pts: FloatArray, margin: FloatArray) -> BoolArray:
        """Points (N, 2) at least ``margin`` (N,) inside, pixels."""
        dist = np.einsum("pmk,mk->pm", pts[:, None, :] - self.poly[None], self.normal)
        return (dist >= margin[:, None]).all(axis=1)


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


def _det2(m: FloatArray) -> FloatArray:
    """Determinants of 2 x 2 matrices (N, 2, 2)."""
    return m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]


def _choose_seed(
    tab: _LatticeTables,
    base_px: FloatArray,
    ref: ReferenceGrid,
    spots: Spots,
    tree: cKDTree,
    accept: float,
    ratio: float,
    exclude: BoolArray | None = None,
) -> int:
    """Node whose nearest spot is most confidently its own, in a calm part of the image (and
    not ``exclude``, (G,) bool, if given).

    Among observed nodes whose nearest spot is close, unambiguous and usable, and so are those
    of at least 6 of their 8 neighbours (or as many as any node has), the score adds (in units
    of the local spacing) the largest displacement difference to a neighbour and the node's own
    displacement, plus the change of spot size from flat water (``|log|`` of the area ratio:
    near a caustic, focusing shrinks or swells spots and the displacement field is at its least
    smooth), plus a small pull towards the middle of the pattern.
    """
    n, spacing = len(base_px), ref.spacing_px
    obs = np.flatnonzero(ref.observed)  # only an observed node can be the seed or support it
    d1, i1, d2 = _nearest_two(tree, base_px[obs])
    good = (d1 < accept * spacing[obs]) & (d1 < ratio * d2) & ~spots.suspicious[i1]
    if exclude is not None:
        good &= ~exclude[obs]
    if not good.any():
        return -1
    ok = np.zeros(n + 1, bool)  # entry n: "no neighbour"
    ok[obs] = good
    disp = np.zeros((n + 1, 2))
    disp[obs] = tree.data[i1] - base_px[obs]
    cand = obs[good]
    nb = tab.nbrs8[cand]
    has = ok[nb]
    diff = disp[cand, None, :] - disp[nb]
    diff = np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2)
    worst = np.where(has, diff, 0.0).max(axis=1)
    n_ok = has.sum(axis=1)
    spot = i1[good]
    with np.errstate(divide="ignore", invalid="ignore"):
        size = np.abs(0.5 * np.log(_det2(spots.cov_px2[spot]) / _det2(ref.cov_px2[cand])))
    size = np.where(np.isfinite(size), size, 0.0)
    centre = np.median(base_px[obs], axis=0)
    extent = np.ptp(base_px[obs], axis=0).max() + 1.0
    reach = np.linalg.norm(base_px[cand] - centre, axis=1) / extent
    own = np.linalg.norm(disp[cand], axis=1)
    score = (worst + own) / spacing[cand] + size + 0.1 * reach
    score = np.where(n_ok >= min(6, int(n_ok.max())), score, np.inf)
    best = int(np.argmin(score))
    return int(cand[best]) if np.isfinite(score[best]) else -1


def _grow(
    tab: _LatticeTables,
    base_px: FloatArray,
    spacing: FloatArray,
    spots: Spots,
    tree: cKDTree,
    seed: tuple[int, int],
    visible: _Outline,
    accept: float,
    ratio: float,
    max_step_ratio: float = 1.7,
) -> _Growth:
    """Region growing over the lattice from ``seed = (node, spot)``, best-supported nodes first.

    Each wave predicts the frontier nodes' spots from their matched 8-neighbours (linear
    extrapolation along the grid line through two matched nodes where possible, else the
    neighbour's own displacement; averaged over directions) and finds the nearest spot; it is
    acceptable if within ``accept`` x spacing, at most ``ratio`` x as far as the second nearest,
    usable, claimed by no other node, and keeps the spacing along every grid line through matched
    neighbours within ``max_step_ratio`` either way (else it skips or doubles a spot). A wave
    accepts only the best tier present: nodes with at least 3 matched 8-neighbours and a
    clear-cut nearest spot, then with at least 2, then any, so the region fills in (interpolating)
    before it reaches out (extrapolating). Nodes not accepted stay on the frontier, unless
    predicted more than two spacings outside ``visible``; growth stops when a wave accepts
    nothing.

    A node's prediction and the tests on it change only when a node one or two steps back along
    one of its grid lines is accepted, so each wave re-evaluates just those nodes (``dirty``);
    positions are complex numbers to halve the array operations.
    """
    n, n_spots = len(base_px), len(spots)
    usable = ~spots.suspicious
    spot_c = _as_complex(spots.centres_px)
    base_c = np.append(_as_complex(base_px), 0.0)
    radius, margin = accept * spacing, -2.0 * spacing
    # The visible outline as half-planes: a point is m px inside edge k where
    # xy @ normal[k] - offset[k] = m.
    normal_t = visible.normal.T
    offset = np.einsum("mk,mk->m", visible.poly, visible.normal)
    # Entry n of the node arrays stands for "no neighbour": never matched, zero displacement.
    match = np.full(n, -1, np.int64)
    matched = np.zeros(n + 1, bool)
    blocked = np.zeros(n + 1, bool)  # matched, or retired (predicted far outside the view)
    blocked[n] = True
    touch = np.zeros(n + 1, bool)
    dirty = np.zeros(n + 1, bool)
    disp = np.zeros(n + 1, complex)
    pos = base_c.copy()
    free = np.ones(n_spots, bool)
    # Each node's last evaluation: prediction, nearest spot, whether it is near (and clear),
    # and the node's tier if it passes every test that does not depend on other nodes (else 0).
    pred_c = base_c[:n].copy()
    last_spot = np.full(n, -1, np.int64)
    last_near = np.zeros(n, bool)
    last_nc = np.zeros(n, bool)
    last_tier = np.zeros(n, np.int64)

    # Beyond reach / (0.5 ratio) a second spot changes no test on a node whose nearest spot is
    # within reach (and on any other the tests do not matter): the search stops there.
    bound = float(radius.max()) / (0.5 * ratio) if n and ratio > 0 else np.inf

    def nearest_two(xy: FloatArray) -> tuple[FloatArray, IntArray]:
        dist, spot = tree.query(xy, k=2, distance_upper_bound=bound)
        return dist, np.minimum(spot, n_spots - 1)  # none found: any spot, it is out of reach

    acc, spot_acc = np.array([seed[0]]), np.array([seed[1]])
    while True:
        match[acc] = spot_acc
        free[spot_acc] = False
        moved = spot_c[spot_acc] - base_c[acc]
        disp[acc] = moved
        pos[acc] = base_c[acc] + moved
        matched[acc] = blocked[acc] = True
        touch[tab.nbrs4[acc]] = True
        dirty[tab.fwd[acc]] = True

        front = np.flatnonzero(touch > blocked)
        if front.size == 0:
            break
        new = front[dirty[front]]
        if new.size:
            dirty[new] = False
            back = tab.back[new]  # (F, 16): one step back along each direction, then two
            near8 = matched[back]
            line = near8[:, 8:]
            near8 = near8[:, :8]
            line &= near8
            d = disp[back]
            d1 = d[:, :8]
            support = near8.sum(axis=1)
            pred = np.where(line, 2.0 * d1 - d[:, 8:], d1).sum(axis=1)
            xy = pred.view(np.float64).reshape(-1, 2)
            xy /= np.maximum(support, 1)[:, None]  # mean displacement, divided as (x, y)
            pred += base_c[new]
            pred_c[new] = pred
            far = (xy @ normal_t - offset).min(axis=1) < margin[new]
            blocked[new[far]] = True
            dist, spot = nearest_two(xy)
            dist1, dist2, spot = dist[:, 0], dist[:, 1], spot[:, 0]
            near = dist1 < radius[new]
            nc = dist1 < ratio * dist2
            nc &= near
            p = pos[back]
            p1 = p[:, :8]
            now = np.abs(spot_c[spot][:, None] - p1)
            before = np.abs(p1 - p[:, 8:])
            jump = now > max_step_ratio * before
            jump |= max_step_ratio * now < before
            jump &= line
            ok = nc & usable[spot]
            ok[far | jump.any(axis=1)] = False
            tier = 1 + (support >= 2) + ((support >= 3) & (dist1 < 0.5 * ratio * dist2))
            last_spot[new], last_near[new], last_nc[new] = spot, near, nc
            last_tier[new] = np.where(ok, tier, 0)
        # Acceptance: a spot is taken once, and not by two nodes in one wave.
        spot = last_spot[front]
        cand = last_nc[front] & free[spot]
        dup = np.bincount(spot[cand], minlength=n_spots)[spot] > 1
        level = np.where(cand & ~dup, last_tier[front], 0)
        best = level.max()
        if best == 0:
            break
        take = level == best
        acc, spot_acc = front[take], spot[take]

    tried = last_spot >= 0
    spot = np.maximum(last_spot, 0)
    reason = np.select(
        [~tried | ~last_near, spots.merged[spot], ~usable[spot]], [_NONE, _MERGED, _BORDER],
        _AMBIGUOUS,
    ).astype(np.int8)
    claim = np.where(tried & last_near, last_spot, -1)
    return _Growth(match, reason, claim, _as_xy(pred_c), tried)


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
    pairs = [(np.flatnonzero(nb >= 0), nb[nb >= 0]) for nb in map(lat.neighbour, _DIRS4[[0, 2]])]
    tree = cKDTree(all_spots_px) if all_spots_px is not None and len(all_spots_px) else None
    return _order_violations(pairs, ref_px, spot_px, margin_px, tree)


def _order_violations(
    pairs: list[tuple[IntArray, IntArray]],
    ref_px: FloatArray,
    spot_px: FloatArray,
    margin_px: float,
    tree: cKDTree | None,
) -> BoolArray:
    """:func:`order_violations` given the neighbour pairs ``(a, b)`` along rows and along
    columns, and the detected spots in a KD-tree (or None)."""
    bad = np.zeros(len(spot_px), bool)
    for a, b in pairs:
        u = ref_px[b] - ref_px[a]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        gap = np.sum((spot_px[b] - spot_px[a]) * u, axis=1)
        viol = gap <= margin_px
        if tree is not None and len(a):
            reach = 0.3 * np.linalg.norm(spot_px[b] - spot_px[a], axis=1)
            # Only whether a spot lies within reach matters: the search stops there.
            dist, _ = tree.query(0.5 * (spot_px[a] + spot_px[b]), distance_upper_bound=reach.max())
            viol |= dist < reach
        bad[a[viol]] = True
        bad[b[viol]] = True
    return bad


def _anchor_shift(
    tab: _LatticeTables, matched: BoolArray, absent: BoolArray, max_shift: int
) -> tuple[IntArray, IntArray]:
    """Lattice shift that best explains where spots are and are not, and all shifts that tie
    with it (C, 2), best first.

    A shift ``d`` relabels node ``ij`` as ``ij + d``. Its cost counts the contradictions: each
    matched node that would not be a lit dot (weight 3: a spot where no dot shines), and each
    node seen empty (``absent``: nothing there although it is in view) that would be a lit dot.
    Near the pattern's visible boundary or its unlit marker dots only the right shift is free of
    contradictions; elsewhere all shifts tie, and the unshifted labelling is kept.

    The counts for all shifts at once are cross-correlations, on the lattice grid, of the lit
    dots with the matched and with the absent nodes.
    """
    s = max_shift
    lit = np.pad(tab.lit_grid, s).astype(np.float32)  # nothing is lit off the lattice

    def lit_at(nodes: BoolArray) -> FloatArray:  # (2s + 1, 2s + 1) indexed [dj, di]
        grid = np.zeros(tab.lat.grid.shape, np.float32)
        q = tab.lat.ij[nodes] - tab.lat.lo
        grid[q[:, 1], q[:, 0]] = 1.0
        return np.rint(cv2.matchTemplate(lit, grid, cv2.TM_CCORR))

    cost = 3 * (matched.sum() - lit_at(matched)) + lit_at(absent)
    cost = cost.T.ravel().astype(np.int64)  # shift (di, dj), di slowest
    r = np.arange(-s, s + 1)
    shifts = np.stack(np.meshgrid(r, r, indexing="ij"), axis=-1).reshape(-1, 2)
    best = cost.min()
    tied = np.flatnonzero(cost <= best + 3 + best // 4)
    # Among ties, the labelling nearest to flat water first (the unshifted one if it ties).
    tied = tied[np.lexsort((np.abs(shifts[tied]).sum(axis=1), cost[tied]))]
    zero = (shifts[tied] == 0).all(axis=1)
    pick = tied[np.flatnonzero(zero)[0]] if zero.any() else tied[
        np.argmin(np.abs(shifts[tied]).sum(axis=1))
    ]
    return shifts[pick].astype(np.int64), shifts[tied].astype(np.int64)


def _absent_nodes(
    tab: _LatticeTables, g: _Growth, tree: cKDTree, spacing: FloatArray, visible: _Outline
) -> BoolArray:
    """Nodes seen empty: unmatched, predicted from at least two matched neighbours to a place
    well inside the visible area where no spot at all lies within half a spacing."""
    matched = np.append(g.match >= 0, False)
    cand = g.tried & (g.match < 0) & (matched[tab.nbrs8].sum(axis=1) >= 2)
    idx = np.flatnonzero(cand)
    idx = idx[visible.inside(g.pred_px[idx], spacing[idx])]
    dist, _ = tree.query(g.pred_px[idx])
    cand[:] = False
    cand[idx[dist > 0.5 * spacing[idx]]] = True
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
        "labels_ambiguous": 0,
    }
    empty = Matches(
        np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool), counts
    )
    if n_obs == 0 or len(spots) == 0:
        return empty
    tab = ref.tables
    base = ref.ref_px
    if prior_px is not None:
        prior = np.asarray(prior_px, dtype=float)
        base = np.where(np.isfinite(prior), prior, base)
    tree = cKDTree(spots.centres_px)
    if visible_px is None:
        hull = cv2.convexHull(ref.ref_px[ref.observed].astype(np.float32))[:, 0]
    else:
        hull = visible_px
    visible = _Outline.of(hull)

    def grow_from(exclude: BoolArray | None) -> _Growth | None:
        seed = _choose_seed(tab, base, ref, spots, tree, accept, ratio, exclude)
        if seed < 0:
            return None
        seed_spot = int(tree.query(base[seed])[1])
        g = _grow(tab, base, ref.spacing_px, spots, tree, (seed, seed_spot), visible, accept,
                  ratio)
        _drop_double_claims(g)
        return g

    g = grow_from(None)
    if g is None:
        return empty
    counts["regrown"] = 0
    if np.sum(g.match >= 0) < REGROW_BELOW * n_obs:
        # A fold of the pattern (a caustic) stops the growing: try once more from a seed away
        # from the first piece, and keep the larger piece.
        near_first = np.zeros(len(ref.ij) + 1, bool)
        near_first[tab.nbrs8[g.match >= 0]] = True
        near_first[np.flatnonzero(g.match >= 0)] = True
        other = grow_from(near_first[:-1])
        if other is not None and np.sum(other.match >= 0) > np.sum(g.match >= 0):
            g, counts["regrown"] = other, 1

    shift, tied = np.zeros(2, np.int64), np.zeros((1, 2), np.int64)
    if anchor:
        absent = _absent_nodes(tab, g, tree, ref.spacing_px, visible)
        shift, tied = _anchor_shift(tab, g.match >= 0, absent, max_shift)
    n_tied = len(tied)
    match, reason, n_off = _relabel(tab.lat, g.match, g.reason, shift)
    counts.update(
        anchor_di=int(shift[0]), anchor_dj=int(shift[1]), anchor_candidates=n_tied,
        labels_ambiguous=int(n_tied > 1),
    )

    kept = np.flatnonzero(match >= 0)
    spot_px = spots.centres_px[match[kept]]
    # Grid neighbours (i + 1 or j + 1) among the kept nodes, as positions in ``kept``.
    where = np.full(len(ref.ij) + 1, -1)
    where[kept] = np.arange(len(kept))
    pairs = []
    for step in (0, 2):  # _DIRS4: (1, 0), (0, 1)
        nb = where[tab.nbrs4[kept, step]]
        pairs.append((np.flatnonzero(nb >= 0), nb[nb >= 0]))
    bad = _order_violations(pairs, ref.ref_px[kept], spot_px, order_margin_px, tree)
    reason[kept[bad]] = _ORDER
    unlit = ~ref.lit[kept] & ~bad
    reason[kept[unlit]] = _UNLIT
    kept = kept[~bad & ~unlit]
    # Labels are only consistent within one connected piece of the lattice: keep the largest.
    main = _largest_component(tab.lat, kept)
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
        ref.ij[kept], ref.ref_px[kept], spots.centres_px[match[kept]], ref.observed[kept], counts,
        alt_shifts=tied - shift,
    )


# ----------------------------------------------------------------------------------------------
# 5. All steps
# ----------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _visible_outline(cfg: SystemConfig) -> FloatArray:
    """Where camera s can see a spot: the diffuser's outline clipped to the image, (M, 2) px
    (read-only)."""
    cam = cfg.camera_s
    w, h = cam.width_px - 0.5, cam.height_px - 0.5
    frame = np.array([[-0.5, -0.5], [w, -0.5], [w, h], [-0.5, h]], np.float32)
    area, poly = cv2.intersectConvexConvex(_outline_px(cfg).astype(np.float32), frame)
    if area <= 0 or poly is None:
        raise WaiInputError("camera s does not see the diffuser")
    out = poly[:, 0].astype(np.float64)
    out.setflags(write=False)
    return out


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
