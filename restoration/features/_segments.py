"""Spot segmentation for :func:`restoration.features.detect_spots`: the smoothed image's peaks
grown into segments, each segment's moments and pixels, the test for a blob wider than one
spot, and a spot's covariance and typical flux."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.features._spot_kernels import peak_axis_moments, peak_moments, segmented_pixels
from restoration.features._types import BoolArray, FloatArray, IntArray
from wai_core.parallel import restore_threads, run_beside


def _scratch(
    store: dict[str, NDArray] | None, name: str, shape: tuple[int, ...], dtype: type
) -> NDArray:
    """``store``'s array ``name`` if it has this shape and dtype, else a new one of zeros
    (kept there). Only the first gets zeros: callers that need zeros where they do not write
    (the frame of :func:`_luminance`) never write there."""
    arr = None if store is None else store.get(name)
    if arr is None or arr.shape != shape or arr.dtype != dtype:
        arr = np.zeros(shape, dtype)
        if store is not None:
            store[name] = arr
    return arr


def _upsample(
    small: NDArray[np.float32], shape: tuple[int, ...], out: NDArray[np.float32] | None = None
) -> NDArray[np.float32]:
    """Bilinear resize of a coarse map back to the image size (h, w), into ``out`` if given."""
    return cv2.resize(small, (shape[1], shape[0]), dst=out, interpolation=cv2.INTER_LINEAR)


def _segment(
    smooth: NDArray[np.float32],
    radius_px: int,
    rel_level: float,
    floor: float,
    work: NDArray[np.float32],
    wide_px: int = 40,
    wide_level: float = 0.005,
    wide_blur_px: float = 4.0,
    store: dict[str, NDArray] | None = None,
    labels_out: NDArray[np.int32] | None = None,
    split_area_px: int | None = None,
    split_all: bool = False,
) -> tuple[int, int, NDArray[np.int32], BoolArray]:
    """Label pixels above ``rel_level`` x their local maximum (and above ``floor``).

    The max filter's radius is under half the spot spacing, so a pixel is compared with its own
    dot's peak: a dim dot next to a bright one is segmented like the bright one. On a wide spot
    that test holds far into the tails (the slope there is gentle), so pixels must also exceed
    ``wide_level`` x the maximum within ``wide_px`` of a copy blurred by a ``wide_blur_px``
    Gaussian (both scale with the spot size: :class:`SpotScales`). A wide
    spot keeps its peak under that blur, so its segment ends at ~3.5 sigma, short of its
    neighbours; a small bright dot loses most of its peak, so a small dim neighbour survives.

    ``work`` (h, w) is scratch space, overwritten: the local maximum and then the labels are
    written there rather than into fresh image-sized arrays (each new one costs more in page
    faults than the filter does), and so are the masks and the wide-spot test (on another
    thread, :func:`_wide_test`), into ``store``'s (:func:`_scratch`).
    Spots blurred into one another (a rough water surface spreads each spot's light over a
    pedestal that joins its neighbours) make one segment of many: a segment larger than
    :data:`JOINED_FACTOR` x ``split_area_px`` (any larger than ``split_area_px`` with
    ``split_all``) is split at its saddles (:func:`_split_joined`).

    Returns the number of labels (background included), the number of segments split, the
    label image (h, w: ``labels_out`` if given, else a view of ``work``) and the mask.
    """
    # The wide-spot test (on a coarse grid) beside the local maximum: both only read smooth.
    wide_of = run_beside(functools.partial(
        _wide_test, smooth, wide_px, wide_level, wide_blur_px,
        _scratch(store, "wide", smooth.shape, np.float32),
        _scratch(store, "wide_mask", smooth.shape, np.bool_),
    ))
    size = 2 * radius_px + 1
    level = cv2.dilate(smooth, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)), dst=work)
    level *= rel_level
    mask = np.greater(smooth, level, out=_scratch(store, "mask", smooth.shape, np.bool_))
    mask &= np.greater(smooth, floor, out=_scratch(store, "above", smooth.shape, np.bool_))
    mask &= wide_of()
    # Plain labelling: cv2's per-component statistics cost 6x the labelling itself, and the
    # moments below give the same from the pixel list.
    dst = work.view(np.int32) if labels_out is None else labels_out
    n, labels = cv2.connectedComponents(mask.view(np.uint8), dst, 8, cv2.CV_32S)
    n_split = 0
    if split_area_px is not None:
        area = split_area_px if split_all else JOINED_FACTOR * split_area_px
        n, n_split = _split_joined(smooth, labels, n, area)
    return n, n_split, labels, mask


JOINED_FACTOR = 30
"""A segment this many times :attr:`~restoration.features.detect.SpotScales.split_area_px`
(6000 px at the tuned spot size) is never one spot, even a caustic's (the largest on the paper's
smooth seas: ~3400 px): it is always split at its saddles."""


SPLIT_PROMINENCE = 0.2
"""A peak inside a joined segment is a spot of its own when the saddle to any higher peak lies
below it by this share of its own height (a spot blurred by roughness keeps ~0.7 of its peak
above the pedestal; noise on one spot's ridge ~0.05). Its own, not the segment's: on rough
water a row of spots smears into one ridge whose dim spots' saddles are a small share of its
brightest spot's peak."""


def _split_joined(smooth: NDArray[np.float32], labels: NDArray[np.int32], n: int,
                  area_px: int) -> tuple[int, int]:
    """Split, in place, every segment of ``labels`` larger than ``area_px`` pixels at the
    saddles between its prominent peaks (:data:`SPLIT_PROMINENCE`: h-maxima of the logarithm,
    where a peak's height over its saddle is their ratio, then a watershed of ``smooth`` from
    them); returns the new number of labels and the segments split. Without such segments (a
    smooth surface's) this costs one count of the labels."""
    from scipy import ndimage
    from skimage.morphology import h_maxima
    from skimage.segmentation import watershed

    area = np.bincount(labels.ravel(), minlength=n)
    big = np.flatnonzero(area[1:] > area_px) + 1
    if not big.size:
        return n, 0
    boxes = ndimage.find_objects(labels)
    split = 0
    for lab in big:
        box = boxes[lab - 1]
        inside = labels[box] == lab
        sub = np.where(inside, smooth[box], 0.0).astype(np.float64)
        # Outside the segment (and at its faintest) the logarithm stops 1e-3 of its maximum.
        log_sub = np.log(np.maximum(sub, 1e-3 * float(sub.max())))
        peaks = h_maxima(log_sub, -np.log1p(-SPLIT_PROMINENCE)).astype(bool) & inside
        markers, n_peaks = ndimage.label(peaks, structure=np.ones((3, 3)))
        if n_peaks < 2:
            continue
        parts = watershed(-sub, markers, mask=inside)
        # Part 1 keeps the label; the others take new ones.
        mine = labels[box]
        moved = inside & (parts > 1)
        mine[moved] = n + parts[moved] - 2
        n += n_peaks - 1
        split += 1
    return n, split


def _wide_test(
    smooth: NDArray[np.float32],
    wide_px: int,
    wide_level: float,
    wide_blur_px: float,
    work: NDArray[np.float32],
    out: BoolArray,
) -> BoolArray:
    """Pixels of ``smooth`` (h, w) above ``wide_level`` x the maximum within ``wide_px`` of a
    copy blurred by ``wide_blur_px`` (see :func:`_segment`), into ``out`` (h, w); ``work``
    (h, w) is scratch space."""
    # On a 4x coarser grid: a 4 x 4 block average and a wide_blur_px / 4 blur there make the
    # ~wide_blur_px blur.
    h, w = smooth.shape
    small = cv2.resize(smooth, (w // 4, h // 4), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), wide_blur_px / 4.0, borderType=cv2.BORDER_REFLECT)
    k = 2 * (wide_px // 4) + 1
    level = _upsample(cv2.dilate(small, np.ones((k, k), np.uint8)), smooth.shape, work)
    level *= wide_level
    return np.greater(smooth, level, out=out)


def _moments(first: FloatArray, second: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-label total (n,), mean (n, 2) and covariance (n, 2, 2) from the weighted sums
    ``first`` (n, 3: ``w``, ``w x``, ``w y``) and ``second`` (n, 3: ``w x^2``, ``w x y``,
    ``w y^2``) of a compiled pass over the pixels. Raw moments: keep ``x, y`` small against
    the image size. ``second`` is overwritten."""
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
    taken from the segment's ``centre`` (n, 2) rounded to a pixel: exact small integers. Two
    compiled passes over the pixels, which make the weights and offsets as they go.
    """
    n = len(peak)
    origin = np.rint(np.nan_to_num(centre)).astype(np.int32)  # NaN: no weight at all
    tot, mean, cov = _moments(*peak_moments(px.lab, px.smooth, px.cols, px.rows, peak, origin, n))
    # Major-axis direction of each 2 x 2 covariance, in closed form.
    angle = 0.5 * np.arctan2(2.0 * cov[:, 0, 1], cov[:, 0, 0] - cov[:, 1, 1])
    m2, m4 = peak_axis_moments(
        px.lab, px.smooth, px.cols, px.rows, peak, origin, mean, np.cos(angle), np.sin(angle), n
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        kurt = m4 * tot / m2**2
    return np.where(np.isfinite(kurt), kurt, 3.0)


def _chunks(n: int) -> int:
    """Chunks of ``n`` independent items for :func:`~wai_core.parallel.run_chunks`: a few
    per thread (their costs vary), none empty."""
    return max(min(4 * restore_threads(), n), 1)


@dataclass(frozen=True)
class _Pixels:
    """The segmented pixels (N,) in raster order: row, column, label, smoothed (float64) and
    raw value."""

    rows: NDArray[np.int32]
    cols: NDArray[np.int32]
    lab: NDArray[np.int32]
    smooth: FloatArray
    raw: NDArray[np.float32]


@dataclass(frozen=True)
class _Segments:
    """Per-label statistics of the segmented image (index 0 is the background)."""

    tot: FloatArray  # smoothed intensity (clipped at 0) summed over the segment
    mean: FloatArray  # (n, 2) smoothed-intensity centroid, px
    cov: FloatArray  # (n, 2, 2) smoothed-intensity second moments, px^2
    peak: FloatArray  # peak of the smoothed image
    flux: FloatArray  # raw intensity summed over the segment
    area: IntArray  # pixels in the segment


def _segmented(
    labels: NDArray[np.int32], n: int, count: int, smooth: NDArray, padded: NDArray, pad: int
) -> tuple[_Pixels, _Segments]:
    """The ``count`` pixels of ``labels`` (h, w) > 0 (of ``n`` labels) with their smoothed and
    raw values (``padded``: the image in a frame of ``pad`` pixels), and every segment's
    moments, in one compiled pass (no segment loop)."""
    h, w = labels.shape
    # Coordinates from the image centre: the raw second moments lose < 1e-10 px^2 that way.
    # Weights max(smooth, 0); peak, flux and area in the same pass.
    *pixels, first, second, peak, flux, area = segmented_pixels(
        labels, smooth, padded, pad, n, count, 0.5 * (w - 1), 0.5 * (h - 1)
    )
    tot, mean, cov = _moments(first, second)
    mean += [0.5 * (w - 1), 0.5 * (h - 1)]
    return _Pixels(*pixels), _Segments(tot, mean, cov, peak, flux, area)


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
