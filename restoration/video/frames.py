"""A sequence's frames from a video file or a folder of images, and the result of fusing them.

The video baselines see a still scene through moving water: the frames differ only by the
water's distortion (and noise), so each baseline turns the (N, H, W[, 3]) stack into one image.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from wai_core.errors import WaiInputError
from wai_core.images import IMAGE_SUFFIXES, read_image

__all__ = ["VIDEO_SUFFIXES", "VideoRestoration", "read_frames", "temporal_mean"]

VIDEO_SUFFIXES = (".avi", ".mp4", ".mov", ".mkv")
"""Suffixes :func:`read_frames` opens as a video (with ``cv2.VideoCapture``)."""

Frames = NDArray[np.float32]


@dataclass(frozen=True)
class VideoRestoration:
    """One image restored from a sequence of distorted frames.

    Attributes
    ----------
    image : (H, W) or (H, W, 3) ndarray of float32
        The restored view, on the frames' scale.
    valid : (H, W) ndarray of bool
        Pixels the fusion trusts: enough frames mapped them from inside the image.
    frames_used : int
        Frames of the sequence that went into ``image``.
    ms_per_frame : float
        Wall time of the fusion divided by the frame count, in ms.
    method : str
        ``"mean"``, ``"registration"`` or ``"lucky"``.
    iterations : int
        Reference updates (registration rounds); 0 for the temporal mean.
    registered : (N, H, W[, 3]) ndarray of float32 or None
        The frames warped onto the final reference, when asked for.
    frame_share : (N,) ndarray of float64 or None
        Each frame's share of the fused image's total weight (lucky fusion; sums to 1).
    """

    image: NDArray[np.float32]
    valid: NDArray[np.bool_]
    frames_used: int
    ms_per_frame: float
    method: str
    iterations: int = 0
    registered: NDArray[np.float32] | None = None
    frame_share: NDArray[np.float64] | None = None


def _natural_key(path: Path) -> tuple:
    """Sort key that orders ``frame_2`` before ``frame_10``."""
    parts = re.split(r"(\d+)", path.name)
    return tuple(int(p) if p.isdigit() else p.lower() for p in parts)


def _read_video(path: Path, max_frames: int | None) -> Frames:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise WaiInputError(f"{path}: not a readable video")
    frames = []
    try:
        while max_frames is None or len(frames) < max_frames:
            ok, bgr = cap.read()
            if not ok:
                break
            frames.append(bgr)
    finally:
        cap.release()
    if not frames:
        raise WaiInputError(f"{path}: the video holds no readable frame")
    stack = np.stack(frames)
    scale = 65535.0 if stack.dtype == np.uint16 else 255.0
    out = stack.astype(np.float32) / np.float32(scale)
    if out.ndim == 4:
        out = np.ascontiguousarray(out[..., :3][..., ::-1])  # BGR -> RGB
    return out


def _read_folder(path: Path, max_frames: int | None) -> Frames:
    files = sorted(
        (p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
        key=_natural_key,
    )
    if not files:
        raise WaiInputError(f"{path}: no image ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    files = files[:max_frames] if max_frames is not None else files
    images = [read_image(f) for f in files]
    shape = images[0].shape
    for f, img in zip(files, images, strict=True):
        if img.shape != shape:
            raise WaiInputError(f"{f}: shape {img.shape} differs from the first frame's {shape}")
    return np.stack(images).astype(np.float32, copy=False)


def read_frames(path: str | Path, max_frames: int | None = None) -> Frames:
    """Read a sequence's frames from a video file or a folder of numbered images.

    Parameters
    ----------
    path : str or Path
        A video (:data:`VIDEO_SUFFIXES`: 8-bit frames scaled to [0, 1], RGB order) or a folder
        whose EXR/PNG/TIFF images (read by :func:`wai_core.images.read_image`) are the frames
        in natural order (``f2`` before ``f10``).
    max_frames : int, optional
        Read at most this many frames (the first ones).

    Returns
    -------
    (N, H, W, 3) or (N, H, W) ndarray of float32
        Colour or grey frames; PNG, TIFF and video values in [0, 1], EXR values as stored.

    Raises
    ------
    WaiInputError
        A missing path, an unreadable or empty video or folder, frames of different shapes;
        the message names the path.

    Examples
    --------
    >>> import numpy as np, tempfile, cv2, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> for i in (1, 2, 10):
    ...     _ = cv2.imwrite(str(d / f"f{i}.png"), np.full((4, 6), 25 * i, np.uint8))
    >>> frames = read_frames(d)
    >>> frames.shape, np.round(frames[:, 0, 0] * 255).tolist()
    ((3, 4, 6), [25.0, 50.0, 250.0])
    """
    path = Path(path)
    if max_frames is not None and max_frames < 1:
        raise WaiInputError(f"max_frames must be at least 1, got {max_frames}")
    if path.is_dir():
        return _read_folder(path, max_frames)
    if not path.exists():
        raise WaiInputError(f"frames not found: {path}")
    if path.suffix.lower() in VIDEO_SUFFIXES:
        return _read_video(path, max_frames)
    raise WaiInputError(
        f"{path}: neither a folder of images nor a video ({', '.join(VIDEO_SUFFIXES)})"
    )


def check_frames(frames: NDArray) -> Frames:
    """The frames as float32 (N, H, W[, 3]); a wrong shape or NaN raises WaiInputError."""
    arr = np.asarray(frames, dtype=np.float32)
    if arr.ndim not in (3, 4) or (arr.ndim == 4 and arr.shape[3] != 3):
        raise WaiInputError(f"frames must be (N, H, W) or (N, H, W, 3), got {arr.shape}")
    if arr.shape[0] < 2:
        raise WaiInputError(f"a video baseline needs at least 2 frames, got {arr.shape[0]}")
    if arr.shape[1] < 8 or arr.shape[2] < 8:
        raise WaiInputError(f"frames of {arr.shape[1]}x{arr.shape[2]} px are too small")
    if not np.all(np.isfinite(arr)):
        raise WaiInputError("frames hold NaN or inf")
    return arr


def to_grey_u8(image: NDArray) -> NDArray[np.uint8]:
    """An image on the [0, 1] scale (H, W[, 3]) as grey uint8 (the optical flow's and the
    corner detector's input); values beyond [0, 1] are clipped."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)


def temporal_mean(frames: NDArray) -> VideoRestoration:
    """The classic baseline: the per-pixel mean of the frames.

    Parameters
    ----------
    frames : (N, H, W[, 3]) array_like
        The distorted frames (N >= 2).

    Returns
    -------
    VideoRestoration
        ``method="mean"``, every pixel valid.

    Examples
    --------
    >>> import numpy as np
    >>> r = temporal_mean(np.stack([np.zeros((8, 8)), np.ones((8, 8))]))
    >>> float(r.image[0, 0]), r.frames_used, r.method
    (0.5, 2, 'mean')
    """
    t0 = time.perf_counter()
    arr = check_frames(frames)
    image = arr.mean(axis=0, dtype=np.float64).astype(np.float32)
    ms = (time.perf_counter() - t0) * 1e3 / arr.shape[0]
    valid = np.ones(arr.shape[1:3], bool)
    return VideoRestoration(image, valid, arr.shape[0], ms, "mean")
