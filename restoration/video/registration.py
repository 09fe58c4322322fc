"""Iterative registration to the temporal mean, after Oreifej et al. (2011) and Halder et al.
(2014).

The water's distortion averages out over time, so the temporal mean of the frames has the
scene's true geometry, only blurred. Each frame is registered to that reference by dense
optical flow and warped back onto it; the mean of the registered frames is sharper, so it
becomes the next reference, and the loop repeats. Only the frames are used: no calibration.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.video.frames import VideoRestoration, check_frames, to_grey_u8
from wai_core.errors import WaiInputError

__all__ = ["DIS_PRESETS", "MIN_VALID_SHARE", "register_frames"]

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
"""OpenCV DIS optical-flow presets by name (speed against accuracy)."""

MIN_VALID_SHARE = 0.5
"""A fused pixel is valid when at least this share of the frames mapped it from inside the
image (the rest came from beyond the border and are left out of its mean)."""


def dis_flow(preset: str) -> cv2.DISOpticalFlow:
    """A DIS optical-flow solver of the named preset (:data:`DIS_PRESETS`)."""
    if preset not in DIS_PRESETS:
        raise WaiInputError(f"unknown DIS preset {preset!r} (use {', '.join(DIS_PRESETS)})")
    return cv2.DISOpticalFlow_create(DIS_PRESETS[preset])


def warp_to_reference(
    frames: NDArray[np.float32],
    ref_grey: NDArray[np.uint8],
    flow: cv2.DISOpticalFlow,
    centre: bool = True,
) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.float32]]:
    """Every frame warped onto the reference by the dense flow from the reference to it.

    Parameters
    ----------
    frames : (N, H, W[, 3]) ndarray of float32
    ref_grey : (H, W) ndarray of uint8
        The reference as the flow sees it.
    flow : cv2.DISOpticalFlow

    Returns
    -------
    warped : (N, H, W[, 3]) ndarray of float32
        ``warped[i](x) = frames[i](x + u_i(x))``, with ``u_i`` the flow (px) such that
        ``ref(x) ~ frames[i](x + u_i(x))``.
    inside : (N, H, W) ndarray of bool
        Where ``x + u_i(x)`` lies inside the frame.
    magnitude : (N, H, W) ndarray of float32
        ``|u_i(x)|`` in px: how far the water moved each pixel.
    """
    n, h, w = frames.shape[:3]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    warped = np.empty_like(frames)
    inside = np.empty((n, h, w), bool)
    magnitude = np.empty((n, h, w), np.float32)
    flows = np.stack([flow.calc(ref_grey, to_grey_u8(frames[i]), None) for i in range(n)])
    if centre:
        flows -= flows.mean(axis=0)
    for i in range(n):
        u = flows[i]
        mx, my = gx + u[..., 0], gy + u[..., 1]
        warped[i] = cv2.remap(frames[i], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        inside[i] = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
        magnitude[i] = np.hypot(u[..., 0], u[..., 1])
    return warped, inside, magnitude


def masked_mean(
    stack: NDArray[np.float32], weight: NDArray, fallback: NDArray[np.float32]
) -> NDArray[np.float32]:
    """Per-pixel weighted mean of ``stack`` (N, H, W[, 3]) with weights (N, H, W); where
    the weights sum to 0 the ``fallback`` image is kept."""
    wsum = weight.sum(axis=0, dtype=np.float64)
    wb = weight[..., None] if stack.ndim == 4 else weight
    num = (stack * wb).sum(axis=0, dtype=np.float64)
    den = wsum[..., None] if stack.ndim == 4 else wsum
    out = np.where(den > 0, num / np.maximum(den, 1e-300), fallback)
    return out.astype(np.float32)


def register_frames(
    frames: NDArray,
    iterations: int = 3,
    preset: str = "fast",
    centre: bool = True,
    keep_frames: bool = False,
) -> VideoRestoration:
    """Restore a still scene by registering every frame to the iterated temporal mean.

    Parameters
    ----------
    frames : (N, H, W[, 3]) array_like
        The distorted frames on the [0, 1] scale (N >= 2).
    iterations : int
        Rounds of register-then-average (at least 1); each round's mean is the next
        reference.
    preset : str
        The DIS optical flow's preset (:data:`DIS_PRESETS`).
    centre : bool
        Subtract the flows' per-pixel mean over the frames before warping: the water's
        displacements average to zero, so that mean is the reference's own geometric error
        (after Halder et al.), and the registered frames land on the scene's geometry rather
        than on the reference's.
    keep_frames : bool
        Return the frames registered onto the final reference in ``registered``.

    Returns
    -------
    VideoRestoration
        ``method="registration"``; ``image`` is the mean of the frames registered to the last
        reference, each pixel over the frames whose flow stayed inside the image; ``valid``
        marks pixels where at least :data:`MIN_VALID_SHARE` of the frames did.

    Raises
    ------
    WaiInputError
        A wrong frame shape, NaN, fewer than 1 iteration, an unknown preset.

    Examples
    --------
    >>> import numpy as np
    >>> y, x = np.mgrid[0:48, 0:64]
    >>> still = ((x // 8 + y // 8) % 2).astype(np.float32)
    >>> frames = np.stack([np.roll(still, s, axis=1) for s in (-1, 0, 1)])
    >>> r = register_frames(frames, iterations=2)
    >>> r.image.shape, r.method, r.iterations, r.frames_used
    ((48, 64), 'registration', 2, 3)
    """
    t0 = time.perf_counter()
    arr = check_frames(frames)
    if iterations < 1:
        raise WaiInputError(f"iterations must be at least 1, got {iterations}")
    flow = dis_flow(preset)
    reference = arr.mean(axis=0, dtype=np.float64).astype(np.float32)
    for _ in range(iterations):
        warped, inside, _mag = warp_to_reference(arr, to_grey_u8(reference), flow, centre)
        reference = masked_mean(warped, inside, reference)
    valid = inside.mean(axis=0) >= MIN_VALID_SHARE
    ms = (time.perf_counter() - t0) * 1e3 / arr.shape[0]
    return VideoRestoration(
        image=reference,
        valid=valid,
        frames_used=arr.shape[0],
        ms_per_frame=ms,
        method="registration",
        iterations=iterations,
        registered=warped if keep_frames else None,
    )
