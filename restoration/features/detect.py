"""Spot detection: find the pattern's spots in one camera-s image and measure their sub-pixel
centres (:func:`detect_spots`, which returns :class:`Spots`). To fit a 30 frames/s pipeline
every step works on whole arrays: segment moments are sparse (label x pixel) products, and the
centroid windows are evaluated for batches of equal-sized boxes with matrix products. Pixel
coordinates are continuous ``(col, row)`` with integer values at pixel centres (see
:mod:`wai_core.geometry`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.lib.stride_tricks import as_strided
from numpy.typing import NDArray
from scipy import sparse

from restoration.features._types import BoolArray, FloatArray, IntArray
from wai_core.errors import WaiInputError

# Centroid window: covariance _WINDOW_VAR x the segment's second moments, which hold 0.55-0.85 of
# the spot's variance, so k^2 ~ 1.75 (k ~ 1.3) and the step gain is 1 + 1 / k^2.
_WINDOW_VAR = 2.5
_WINDOW_GAIN = 1.0 + 1.0 / (0.7 * _WINDOW_VAR)


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
