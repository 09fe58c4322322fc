"""Lucky-region fusion: for every patch, keep the few frames the water distorted least.

After the "lucky imaging" idea for seeing through water (Efros et al. 2004; Donate & Ribeiro
2006; Wen et al. 2010): over a long enough sequence, each small region of the scene is now and
then seen through nearly flat water. The frames are compared with a reference of the scene's
geometry (the registration baseline's output, or the temporal mean) by dense optical flow; in
each overlapping patch the frames are ranked by how far the flow moved the patch (or how well
the patch, warped back, matches the reference), and the best few, warped onto the reference,
are averaged. Overlapping Hann windows blend the patches' choices so no seam shows.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.video.frames import VideoRestoration, check_frames, to_grey_u8
from restoration.video.registration import (
    MIN_VALID_SHARE,
    dis_flow,
    masked_mean,
    register_frames,
    warp_to_reference,
)
from wai_core.errors import WaiInputError

__all__ = ["CRITERIA", "lucky_fusion"]

CRITERIA = ("flow", "ncc")
"""Ways to rank the frames per patch: ``"flow"``, the smallest mean flow magnitude (the
patch moved least); ``"ncc"``, the largest normalised cross-correlation of the patch, warped
back, with the reference."""

_EPS = 1e-6


def _hann(size: int) -> NDArray[np.float64]:
    """Periodic Hann window of ``size`` samples: shifted by ``size / 2`` its copies sum to 1."""
    return 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(size) / size)


def _patch_means(maps: NDArray, size: int, cy: NDArray, cx: NDArray) -> NDArray[np.float64]:
    """Mean of each (N, H, W) map over the ``size`` px box around every patch centre
    (``cy`` x ``cx``), as (N, len(cy), len(cx))."""
    out = np.empty((maps.shape[0], cy.size, cx.size))
    for i, m in enumerate(maps):
        box = cv2.blur(m.astype(np.float32), (size, size), borderType=cv2.BORDER_REFLECT)
        out[i] = box[np.ix_(cy, cx)]
    return out


def _ncc_maps(
    warped: NDArray[np.float32], ref_grey: NDArray[np.float32], size: int
) -> NDArray[np.float32]:
    """Local normalised cross-correlation (box of ``size`` px) of each warped frame's grey
    image with the reference, as (N, H, W)."""
    k = (size, size)

    def box(a: NDArray) -> NDArray:
        return cv2.blur(a, k, borderType=cv2.BORDER_REFLECT)

    mr = box(ref_grey)
    vr = np.maximum(box(ref_grey * ref_grey) - mr * mr, 0.0)
    out = np.empty(warped.shape[:3], np.float32)
    for i, f in enumerate(warped):
        g = cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) if f.ndim == 3 else f
        mf = box(g)
        vf = np.maximum(box(g * g) - mf * mf, 0.0)
        out[i] = (box(g * ref_grey) - mf * mr) / np.sqrt(vf * vr + _EPS)
    return out


def lucky_fusion(
    frames: NDArray,
    reference: str | NDArray = "registration",
    patch_px: int = 32,
    keep: float = 0.2,
    criterion: str = "flow",
    preset: str = "fast",
) -> VideoRestoration:
    """Restore a still scene from the least distorted frames of every patch.

    Parameters
    ----------
    frames : (N, H, W[, 3]) array_like
        The distorted frames on the [0, 1] scale (N >= 2).
    reference : {"registration", "mean"} or (H, W[, 3]) array_like
        The image of the scene's geometry the frames are ranked against:
        :func:`~restoration.video.registration.register_frames`'s output, the temporal mean,
        or a given image.
    patch_px : int
        Patch side in px (even, >= 8); patches overlap by half.
    keep : float
        Share of the frames fused per patch, in (0, 1] (at least one frame).
    criterion : str
        How frames are ranked per patch (:data:`CRITERIA`).
    preset : str
        The DIS optical flow's preset (:data:`~restoration.video.registration.DIS_PRESETS`).

    Returns
    -------
    VideoRestoration
        ``method="lucky"``; ``frame_share`` is each frame's share of the fused weight.
        ``ms_per_frame`` includes the reference's registration when it is computed here.

    Raises
    ------
    WaiInputError
        A wrong frame or reference shape, NaN, or an option out of range.

    Examples
    --------
    >>> import numpy as np
    >>> y, x = np.mgrid[0:64, 0:64]
    >>> still = ((x // 8 + y // 8) % 2).astype(np.float32)
    >>> frames = np.stack([np.roll(still, s, axis=1) for s in (-1, 0, 0, 1)])
    >>> r = lucky_fusion(frames, reference="mean", keep=0.25)
    >>> r.image.shape, r.method, round(float(r.frame_share.sum()), 6)
    ((64, 64), 'lucky', 1.0)
    """
    t0 = time.perf_counter()
    arr = check_frames(frames)
    n, h, w = arr.shape[:3]
    if patch_px < 8 or patch_px % 2:
        raise WaiInputError(f"patch_px must be even and at least 8, got {patch_px}")
    if not 0.0 < keep <= 1.0:
        raise WaiInputError(f"keep must be in (0, 1], got {keep}")
    if criterion not in CRITERIA:
        raise WaiInputError(f"unknown criterion {criterion!r} (use {', '.join(CRITERIA)})")
    flow = dis_flow(preset)
    if isinstance(reference, str):
        if reference == "registration":
            ref = register_frames(arr, preset=preset).image
        elif reference == "mean":
            ref = arr.mean(axis=0, dtype=np.float64).astype(np.float32)
        else:
            raise WaiInputError(f"unknown reference {reference!r} (use registration, mean)")
    else:
        ref = np.asarray(reference, dtype=np.float32)
        if ref.shape != arr.shape[1:] or not np.all(np.isfinite(ref)):
            raise WaiInputError(f"reference must be finite of shape {arr.shape[1:]}")

    ref_u8 = to_grey_u8(ref)
    warped, inside, magnitude = warp_to_reference(arr, ref_u8, flow, centre=False)

    # Patch centres every half patch, covering the image; each patch ranks the frames.
    step = patch_px // 2
    cy = np.unique(np.arange(0, h + step - 1, step).clip(max=h - 1))
    cx = np.unique(np.arange(0, w + step - 1, step).clip(max=w - 1))
    if criterion == "flow":
        badness = _patch_means(magnitude, patch_px, cy, cx)
    else:
        ncc = _ncc_maps(warped, ref_u8.astype(np.float32) / 255.0, patch_px)
        badness = 1.0 - _patch_means(ncc, patch_px, cy, cx)
    # A patch partly mapped from beyond the image border ranks below every full one.
    badness = badness + 1e3 * (1.0 - _patch_means(inside, patch_px, cy, cx))

    # Top-k frames per patch, weighted by how much better they are than the k-th.
    k = max(1, int(round(keep * n)))
    order = np.argsort(badness, axis=0, kind="stable")
    ranked = np.take_along_axis(badness, order, axis=0)
    scale = ranked[k - 1] - ranked[0] + _EPS
    weights = np.zeros_like(badness)
    top = np.exp(-((ranked[:k] - ranked[0]) / scale))
    np.put_along_axis(weights, order[:k], top / top.sum(axis=0), axis=0)

    # Spread each patch's weights over its Hann window: per-frame weight maps that change
    # smoothly from patch to patch, so the patches' choices blend without seams.
    window = _hann(patch_px)
    pixel_w = np.empty((n, h, w), np.float32)
    for i in range(n):
        canvas = np.zeros((h, w), np.float32)
        np.add.at(canvas, (cy[:, None], cx[None, :]), weights[i])
        pixel_w[i] = cv2.sepFilter2D(canvas, -1, window, window, borderType=cv2.BORDER_CONSTANT)
    pixel_w *= inside
    image = masked_mean(warped, pixel_w, ref)
    valid = inside.mean(axis=0) >= MIN_VALID_SHARE
    share = pixel_w.sum(axis=(1, 2), dtype=np.float64)
    share /= max(share.sum(), _EPS)
    ms = (time.perf_counter() - t0) * 1e3 / n
    return VideoRestoration(
        image=image,
        valid=valid,
        frames_used=int(np.count_nonzero(share > 0)),
        ms_per_frame=ms,
        method="lucky",
        iterations=0,
        frame_share=share,
    )
