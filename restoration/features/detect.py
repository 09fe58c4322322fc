"""Spot detection: find the pattern's spots in one camera-s image and measure their sub-pixel
centres (:func:`detect_spots`, which returns :class:`Spots`). To fit a 30 frames/s pipeline the
image-wide filters are OpenCV's, and the per-pixel and per-spot loops (segment moments, centroid
windows) are compiled kernels (:mod:`restoration.features._kernels`). Pixel coordinates are
continuous ``(col, row)`` with integer values at pixel centres (see :mod:`wai_core.geometry`).
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.features._segments import (
    _chunks,
    _major_axis_kurtosis,
    _scratch,
    _segment,
    _segmented,
    _spot_covariance,
    _typical_flux,
    _upsample,
)
from restoration.features._spot_kernels import centroid_chunk
from restoration.features._types import BoolArray, FloatArray, IntArray
from wai_core.errors import WaiInputError
from wai_core.parallel import run_beside, run_chunks

# The pixel-scale constants of detection (the defaults of detect_spots, _segment's wide test)
# were tuned on the paper's rig with an 800 x 600 camera s, where a dot's spot has the
# calibrated standard deviation _TUNED_SIGMA_PX (restoration.features.reference.spot_sigma_px:
# the panel dot's sigma times the panel -> camera-s magnification). Given another spot size they
# scale with it (areas with its square), so a finer camera sees the same spot the same way.
# Constants tied to the pixel grid itself (pixelisation limits, numerical floors, the 4x coarse
# grids of slowly varying maps) stay in pixels.
_TUNED_SIGMA_PX = 1.517788

# A segment this large (pixels, at the tuned spot size) holds several spots or one spread by
# the waves: it is checked for saddles (restoration.features._segments._split_joined). A
# single tuned spot's segment covers ~20 px; a caustic's, a few hundred.
_SPLIT_AREA_PX = 200

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
    joined : int
        Segments that held several spots joined by a pedestal, split at their saddles.
    image_px : (P, 2) ndarray or None
        The centres in the image as taken, where ``centres_px`` were mapped to a lens's ideal
        pinhole (:func:`~restoration.features.camera_s.pinhole_spots`); None: the same.
    """

    centres_px: FloatArray
    flux: FloatArray
    peak: FloatArray
    area_px: IntArray
    cov_px2: FloatArray
    merged: BoolArray
    border: BoolArray
    saturated: BoolArray
    joined: int = 0
    image_px: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.centres_px.shape[0])

    @property
    def in_image_px(self) -> FloatArray:
        """The centres in the image as taken (:attr:`image_px`, else :attr:`centres_px`)."""
        return self.centres_px if self.image_px is None else self.image_px

    @property
    def suspicious(self) -> BoolArray:
        """True for spots whose centre should not be trusted (merged, border or saturated)."""
        return self.merged | self.border | self.saturated


class _Workspace:
    """The image-sized scratch arrays of :func:`detect_spots`, kept from frame to frame.

    A fresh image-sized array costs more in page faults than the filter that fills it, so a
    rig's :class:`SpotScales` keeps one set. One frame at a time uses them: a thread that finds
    them taken works in fresh arrays. Pickled, it starts empty.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._arrays: dict[str, NDArray] = {}

    @contextlib.contextmanager
    def borrow(self) -> Iterator[dict[str, NDArray] | None]:
        """The arrays by name, for :func:`_scratch` (None while another thread has them)."""
        if not self._lock.acquire(blocking=False):
            yield None
            return
        try:
            yield self._arrays
        finally:
            self._lock.release()

    def __getstate__(self) -> dict:
        return {}

    def __setstate__(self, state: dict) -> None:
        self.__init__()  # type: ignore[misc]


def _luminance(image: NDArray, pad: int, store: dict | None = None) -> NDArray[np.float32]:
    """Sum of the colour channels, float32, in an array with ``pad`` zeros around it
    (h + 2 pad, w + 2 pad): new, or ``store``'s (:class:`_Workspace`); rejects bad shapes and
    non-finite values."""
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
    padded = _scratch(store, "padded", (shape[0] + 2 * pad, shape[1] + 2 * pad), np.float32)
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


def _background(
    smooth: NDArray[np.float32], size_px: int, out: NDArray[np.float32] | None = None
) -> NDArray[np.float32]:
    """Slowly varying background: local minimum over a window wider than a spot, then averaged
    (into ``out``, (h, w), if given).

    Runs on a 4x coarser grid (the background varies slowly): a 5 x 5 minimum first, so the
    subsampled pixels are the darkest of their neighbourhood, not a spot's core.
    """
    k = max(size_px // 4, 1) | 1
    full = cv2.erode(smooth, np.ones((5, 5), np.uint8), dst=out, borderType=cv2.BORDER_REPLICATE)
    low = cv2.erode(np.ascontiguousarray(full[::4, ::4]), np.ones((k, k), np.uint8),
                    borderType=cv2.BORDER_REPLICATE)
    return _upsample(cv2.blur(low, (k, k), borderType=cv2.BORDER_REPLICATE), smooth.shape, full)


def _minimum_bias(smooth_px: float, size_px: int) -> float:
    """How far :func:`_background` lies below the mean of pure noise, in units of the smoothed
    noise's standard deviation: measured on seeded white noise smoothed as the images are (once
    per spot size, in :class:`SpotScales`: it costs more than a frame can spare)."""
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
    passed = 1.0 - 2.0 * g0 + g2  # white noise's share left in the residual
    if passed <= 1e-9:  # a one-tap kernel (tiny spots): no residual to read the noise from
        return 0.0
    sub = (lum[::3, ::3] - smooth[::3, ::3]).ravel()  # every 9th pixel is plenty
    scale = float(np.percentile(np.abs(sub - np.median(sub)), 25.0)) / 0.3186
    return scale * float(np.sqrt(g2 / passed))


# Half widths of the centroid boxes: multiples of 3 px, up to _BOX_MAX at the tuned spot size
# (scaled with it: SpotScales.box_max_px), the frame of zeros around the image in detect_spots.
_BOX_MAX = 48


def _refine_centres(
    padded: NDArray[np.float32],
    labels: NDArray[np.int32],
    n: int,
    keep: IntArray,
    start: FloatArray,
    cov: FloatArray,
    n_iter: int = 2,
    box_max: int = _BOX_MAX,
) -> FloatArray:
    """Gaussian-windowed centres (P, 2) of the kept segments ``keep`` (of ``n`` labels), from
    ``start`` (P, 2), px (as SExtractor's ``XWIN``).

    A Gaussian spot of covariance C seen through a Gaussian window of covariance ``k^2 C``
    centred at ``x_n`` has its weighted mean ``m`` a fraction ``k^2 / (1 + k^2)`` of the way to
    the true centre, so ``x_{n+1} = x_n + (1 + 1/k^2) (m - x_n)`` converges in one step and stays
    unbiased for any symmetric profile (a wrong C only slows convergence). Unlike a thresholded
    centroid it has no pixel-locking bias. ``k`` trades noise (``k = 1``: 1.33x the Poisson
    limit; ``k = 1.5``: 1.1x) against light from neighbours. A step longer than a pixel is
    clipped (noise dominates the window).

    Each spot's box reaches 3.5 segment sigmas + 1 px along each image axis (about 3 spot
    sigmas: beyond it the spot times the window is below 0.5 %), centred on ``start`` rounded
    to a pixel. It holds the raw image there with the pixels of the other kept segments
    blanked, so a much brighter neighbour cannot pull the centre. ``padded`` is the raw image
    with ``box_max`` zeros around it (a multiple of 3 px), ``labels`` the segment labels of
    its pixels (of ``n``; 0 in the frame). Compiled loops over the spots, in chunks shared by
    the restoration's threads (:func:`restoration.features._spot_kernels.centroid_chunk`).
    """
    if len(keep) == 0:
        return np.zeros((0, 2))
    sd = np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1))
    half = np.clip(np.ceil(3.5 * sd + 1.0), 3, box_max).astype(np.int64)
    half = 3 * ((half + 2) // 3)
    det = _WINDOW_VAR * (cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2)
    inv_win = np.stack([cov[:, 1, 1] / det, -cov[:, 0, 1] / det, cov[:, 0, 0] / det], axis=1)
    spot_of = np.full(n, -1, np.int64)
    spot_of[keep] = np.arange(len(keep))
    out = np.empty((len(keep), 2))
    run_chunks(
        centroid_chunk, _chunks(len(keep)), padded, labels, box_max, spot_of,
        np.rint(start).astype(np.int64), half, inv_win, np.ascontiguousarray(start, float),
        _WINDOW_GAIN, n_iter, out,
    )
    return out


@dataclass(frozen=True)
class SpotScales:
    """The detection's pixel-scale parameters for spots of one size, and the background's bias
    measured at them (:func:`_minimum_bias`): per rig, built once (:meth:`of`) and passed to
    every frame's :func:`detect_spots`.

    Lengths scale with the spot's standard deviation ``spot_sigma_px`` from their tuned values
    at :data:`_TUNED_SIGMA_PX`, the smallest area with its square; integers are rounded, and
    stay at least what a pixel grid needs.

    Attributes
    ----------
    spot_sigma_px : float or None
        Spot standard deviation the scales follow, pixels (None: the tuned one).
    smooth_px : float
        Standard deviation of the noise-suppressing Gaussian, pixels.
    local_radius_px : int
        Radius of the local maximum filter, pixels.
    min_area_px : int
        Smallest segment kept, pixels.
    background_px : int
        Window of the background estimate, pixels.
    wide_px : int
        Reach of the segmentation's wide-spot test, pixels.
    wide_blur_px : float
        Blur of the wide-spot test's copy, pixels.
    box_max_px : int
        Largest centroid box half width, and the frame of zeros around the image, pixels.
    split_area_px : int
        A segment larger than this may hold spots joined by a pedestal, pixels: with
        ``split_all`` it is split at its saddles
        (:func:`~restoration.features._segments._split_joined`); without, only one larger than
        :data:`~restoration.features._segments.JOINED_FACTOR` times it (never one spot, not
        even a caustic's).
    split_all : bool
        Split every segment larger than ``split_area_px`` (:meth:`joined`: where the flat-water
        reference's spots run together, :func:`~restoration.features.prepare_reference`).
    minimum_bias : float
        How far the background at ``smooth_px`` and ``background_px`` lies below the mean of
        pure noise, in the smoothed noise's standard deviations.
    workspace : _Workspace or None
        The image-sized scratch arrays :func:`detect_spots` reuses from frame to frame (None:
        fresh ones every frame). Private.
    """

    spot_sigma_px: float | None
    smooth_px: float
    local_radius_px: int
    min_area_px: int
    background_px: int
    wide_px: int
    wide_blur_px: float
    box_max_px: int
    minimum_bias: float
    split_area_px: int = 200
    split_all: bool = False
    workspace: _Workspace | None = field(default=None, compare=False, repr=False)

    @classmethod
    def of(cls, spot_sigma_px: float | None = None) -> SpotScales:
        """The scales for spots of standard deviation ``spot_sigma_px``, pixels (None: the
        tuned ones).

        Raises
        ------
        WaiInputError
            When ``spot_sigma_px`` is not a positive number.
        """
        k = 1.0 if spot_sigma_px is None else float(spot_sigma_px) / _TUNED_SIGMA_PX
        if not (np.isfinite(k) and k > 0):
            raise WaiInputError(f"spot_sigma_px must be positive, got {spot_sigma_px!r}")
        smooth_px, background_px = 1.0 * k, max(int(round(25 * k)), 5)
        return cls(
            spot_sigma_px=spot_sigma_px,
            smooth_px=smooth_px,
            local_radius_px=max(int(round(3 * k)), 1),
            min_area_px=max(int(round(3 * k * k)), 3),
            background_px=background_px,
            wide_px=max(int(round(40 * k)), 8),
            wide_blur_px=4.0 * k,
            box_max_px=max(3 * int(np.ceil(_BOX_MAX / 3 * k - 1e-9)), _BOX_MAX),
            minimum_bias=_minimum_bias(smooth_px, background_px),
            split_area_px=max(int(round(_SPLIT_AREA_PX * k * k)), 20),
            workspace=_Workspace(),
        )

    def joined(self) -> SpotScales:
        """These scales splitting every segment larger than :attr:`split_area_px`, with a
        workspace of their own."""
        return replace(self, split_all=True, workspace=_Workspace())


# The scales of detect_spots' defaults, for callers without a calibrated spot size (built at
# import: frozen, and a per-call measurement would cost more than some frames' detection).
# Without a workspace: shared by every caller.
_TUNED_SCALES = replace(SpotScales.of(None), workspace=None)


def _scales_for(spot_sigma_px: float | None) -> SpotScales:
    """:meth:`SpotScales.of`, without measuring again for the tuned spot size (None)."""
    if spot_sigma_px is None:
        return replace(_TUNED_SCALES, workspace=_Workspace())
    return SpotScales.of(spot_sigma_px)


def detect_spots(
    image: NDArray,
    *,
    spot_sigma_px: float | None = None,
    scales: SpotScales | None = None,
    smooth_px: float | None = None,
    local_radius_px: int | None = None,
    rel_level: float = 0.25,
    snr_min: float = 6.0,
    rel_flux: float = 5e-3,
    min_area_px: int | None = None,
    merge_kurtosis: float = 2.15,
    background_px: int | None = None,
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
    spot_sigma_px : float, optional
        Expected standard deviation of a spot, px, from calibration
        (:func:`restoration.features.reference.spot_sigma_px`). The pixel-scale parameters
        left at None (``smooth_px``, ``local_radius_px``, ``min_area_px``, ``background_px``
        and the segmentation's wide-spot test) follow from it: their tuned values (1.0, 3, 3,
        25 px at a spot sigma of 1.518 px, the paper's rig at 800 x 600) scale with it, areas
        with its square. None: the tuned values. Measures :attr:`SpotScales.minimum_bias`
        on every call: per frame, pass ``scales`` instead.
    scales : SpotScales, optional
        The pixel-scale parameters for the calibrated spot size, built once
        (:meth:`SpotScales.of`, :attr:`~restoration.features.reference.ReferenceGrid.spot_scales`);
        not with ``spot_sigma_px``.
    smooth_px : float, optional
        Standard deviation of the Gaussian that suppresses pixel noise before segmentation, px.
    local_radius_px : int, optional
        Radius of the local maximum filter, px; keep it under half the smallest spot spacing.
    rel_level : float
        Segment level relative to the local maximum (0-1).
    snr_min : float
        Minimum peak over the background noise (robust standard deviation of the smoothed image).
    rel_flux : float
        Minimum flux relative to the typical bright spot's (flux-weighted median of all
        segments): rejects Monte Carlo speckle and stray fragments of a spot's skirt while keeping
        dots up to 1 / ``rel_flux`` times dimmer than the bright ones.
    min_area_px : int, optional
        Smallest segment kept, pixels.
    merge_kurtosis : float
        A spot is flagged ``merged`` when the kurtosis of its profile along its major axis is
        below this: 2.2-2.45 for a single Gaussian spot, below 2.15 for two equal dots more than
        ~3 sigma apart (closer pairs look like one dot and are caught by the matching as a spot
        claimed twice). Segments narrower than 1.3 px (second moment) are never flagged.
    background_px : int, optional
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
        On a wrong shape or non-finite values, or both ``spot_sigma_px`` and ``scales``.
    """
    if scales is not None and spot_sigma_px is not None:
        raise WaiInputError("detect_spots: give spot_sigma_px or scales, not both")
    if scales is None:
        scales = _TUNED_SCALES if spot_sigma_px is None else SpotScales.of(spot_sigma_px)
    sc = scales
    smooth_px = sc.smooth_px if smooth_px is None else smooth_px
    local_radius_px = sc.local_radius_px if local_radius_px is None else local_radius_px
    min_area_px = sc.min_area_px if min_area_px is None else min_area_px
    background_px = sc.background_px if background_px is None else background_px
    # The scratch arrays are the rig's (see _Workspace), or new ones.
    borrowed = contextlib.nullcontext(None) if sc.workspace is None else sc.workspace.borrow()
    with borrowed as store:
        # The image sits in a frame of zeros, where the centroid boxes may reach past its edge.
        pad = sc.box_max_px
        padded = _luminance(image, pad, store)
        lum = padded[pad:-pad, pad:-pad]
        h, w = lum.shape
        smooth = cv2.GaussianBlur(
            lum, (0, 0), smooth_px, dst=_scratch(store, "smooth", (h, w), np.float32),
            borderType=cv2.BORDER_REFLECT,
        )
        # The noise (two selections over a sample) beside the background (filters): both only
        # read lum and smooth, which change below.
        noise_of = run_beside(functools.partial(_noise_sigma, lum, smooth, smooth_px))
        bg = _background(smooth, background_px, _scratch(store, "bg", (h, w), np.float32))
        # A local minimum sits below the mean of noise: without this, read noise would lift every
        # pixel above the floor. Capped by the lower quartile of what remains, which is ~0 where
        # there is no noise (there the noise estimate is only the dots' sharpness).
        lifted = float(np.percentile(smooth[::4, ::4] - bg[::4, ::4], 25.0))
        noise = noise_of()
        if (smooth_px, background_px) == (sc.smooth_px, sc.background_px):
            bias = sc.minimum_bias
        else:  # parameters given by the caller: measured for them
            bias = _minimum_bias(smooth_px, background_px)
        bg += min(noise * bias, max(lifted, 0.0))
        smooth -= bg
        saturated_px = None if saturation is None else lum >= saturation
        lum -= bg  # now the raw, background-subtracted image
        tiny = 1e-6 * max(float(smooth.max()), 1e-30)  # keeps a noiseless zero background out
        # bg, no longer needed, is the scratch space.
        # The labels sit in a frame of zeros too (the centroid boxes read them).
        framed = _scratch(store, "labels", padded.shape, np.int32)
        n, n_joined, labels, mask = _segment(
            smooth, local_radius_px, rel_level, max(2.0 * noise, tiny), bg, sc.wide_px,
            wide_blur_px=sc.wide_blur_px, store=store, labels_out=framed[pad:-pad, pad:-pad],
            split_area_px=sc.split_area_px, split_all=sc.split_all,
        )
        px, seg = _segmented(labels, n, int(np.count_nonzero(mask)), smooth, padded, pad)
        edge = np.zeros(n, bool)  # the segment has a pixel in the image's outer rows or columns
        edge[np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])] = True
        n_saturated = (
            None if saturated_px is None else np.bincount(labels[saturated_px], minlength=n)
        )
        good = (seg.peak > max(snr_min * noise, tiny)) & (seg.area >= min_area_px) & (seg.tot > 0)
        good[0] = False  # label 0 is the background
        good &= seg.flux > rel_flux * _typical_flux(seg.flux[good])
        idx = np.flatnonzero(good)
        saturated = np.zeros(idx.size, bool) if n_saturated is None else n_saturated[idx] > 0
        cov, major = _spot_covariance(seg.cov[idx])
        # The merge test's kurtosis beside the centroids (it reads only the pixel list).
        kurtosis_of = run_beside(functools.partial(_major_axis_kurtosis, px, seg.peak, seg.mean))
        # The centroids read the padded image and labels: still the borrowed ones.
        centres = _refine_centres(padded, framed, n, idx, seg.mean[idx], cov, box_max=pad)
        kurtosis = kurtosis_of()
    # Too few pixels across to tell a shape (single spots of sigma <~ 1.2 px): never "merged".
    merged = (kurtosis[idx] < merge_kurtosis) & (major >= 1.3**2)
    return Spots(
        centres_px=centres,
        flux=seg.flux[idx],
        peak=seg.peak[idx],
        area_px=seg.area[idx].astype(np.int64),
        cov_px2=cov,
        merged=merged,
        border=edge[idx],
        saturated=saturated,
        joined=n_joined,
    )
