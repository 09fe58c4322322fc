"""A sequence's frames from a video file or a folder of images, and the result of fusing them.

The video baselines see a still scene through moving water: the frames differ only by the
water's distortion (and noise), so each baseline turns the (N, H, W[, 3]) stack into one image.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from wai_core.errors import WaiInputError
from wai_core.images import IMAGE_SUFFIXES, read_image

__all__ = ["VIDEO_SUFFIXES", "VideoRestoration", "frames_shape", "fusion_bytes", "iter_frames",
           "read_frames", "streamed_mean", "temporal_mean"]

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


def _video_frames(path: Path, max_frames: int | None) -> Iterator[NDArray]:
    """The video's frames as decoded (BGR or grey, 8 or 16 bit), one at a time."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise WaiInputError(f"{path}: not a readable video")
    count = 0
    try:
        while max_frames is None or count < max_frames:
            ok, raw = cap.read()
            if not ok:
                break
            count += 1
            yield raw
    finally:
        cap.release()
    if not count:
        raise WaiInputError(f"{path}: the video holds no readable frame")


def _scaled(raw: NDArray) -> Frames:
    """A decoded video frame as float32 on [0, 1], colour in RGB order."""
    scale = 65535.0 if raw.dtype == np.uint16 else 255.0
    out = raw.astype(np.float32) / np.float32(scale)
    if out.ndim == 3:
        out = np.ascontiguousarray(out[..., :3][..., ::-1])  # BGR -> RGB
    return out


def _read_video(path: Path, max_frames: int | None) -> Frames:
    return np.stack([_scaled(raw) for raw in _video_frames(path, max_frames)])


def _folder_files(path: Path, max_frames: int | None) -> list[Path]:
    files = sorted(
        (p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
        key=_natural_key,
    )
    if not files:
        raise WaiInputError(f"{path}: no image ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    return files[:max_frames] if max_frames is not None else files


def _folder_frames(path: Path, max_frames: int | None) -> Iterator[Frames]:
    """The folder's images in natural order, one at a time, each the first one's shape."""
    shape = None
    for f in _folder_files(path, max_frames):
        img = read_image(f)
        shape = img.shape if shape is None else shape
        if img.shape != shape:
            raise WaiInputError(f"{f}: shape {img.shape} differs from the first frame's {shape}")
        yield img


def _read_folder(path: Path, max_frames: int | None) -> Frames:
    return np.stack(list(_folder_frames(path, max_frames))).astype(np.float32, copy=False)


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
    if max_frames is not None and max_frames < 1:
        raise WaiInputError(f"max_frames must be at least 1, got {max_frames}")
    path = _checked_path(path)
    if path.is_dir():
        return _read_folder(path, max_frames)
    return _read_video(path, max_frames)


def _checked_path(path: str | Path) -> Path:
    """``path`` when it is a folder or a video file, else WaiInputError naming it."""
    path = Path(path)
    if path.is_dir():
        return path
    if not path.exists():
        raise WaiInputError(f"frames not found: {path}")
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise WaiInputError(
            f"{path}: neither a folder of images nor a video ({', '.join(VIDEO_SUFFIXES)})"
        )
    return path


def iter_frames(path: str | Path) -> Iterator[Frames]:
    """The frames of :func:`read_frames`, one (H, W[, 3]) float32 image at a time: a
    sequence of any length in the memory of one frame."""
    path = _checked_path(path)
    if path.is_dir():
        yield from _folder_frames(path, None)
    else:
        yield from map(_scaled, _video_frames(path, None))


def frames_shape(path: str | Path) -> tuple[int, int, int, int]:
    """``(frames, height, width, channels)`` of a video file or a folder of images, from the
    video's header or the folder's listing and first image, without reading the frames (a
    video whose header has no frame count says 0 frames)."""
    path = _checked_path(path)
    if path.is_dir():
        files = _folder_files(path, None)
        first = read_image(files[0])
        return len(files), first.shape[0], first.shape[1], first.shape[2] if first.ndim == 3 else 1
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise WaiInputError(f"{path}: not a readable video")
        n, w, h = (int(cap.get(p)) for p in (cv2.CAP_PROP_FRAME_COUNT, cv2.CAP_PROP_FRAME_WIDTH,
                                             cv2.CAP_PROP_FRAME_HEIGHT))
    finally:
        cap.release()
    return max(n, 0), h, w, 3


def fusion_bytes(frames: int, height: int, width: int, channels: int) -> int:
    """Peak memory of registering or lucky-fusing a sequence, bytes: per frame and pixel the
    float32 frames (4 bytes a channel) and, while a round of :func:`register_frames` replaces
    the previous one's, two generations of the warped frames (4 bytes a channel each), of the
    flow's magnitude (4) and of the inside mask (1), beside the flow (8). :func:`lucky_fusion`
    registers first, then holds one generation and its weights: less.

    Examples
    --------
    >>> round(fusion_bytes(900, 1080, 1920, 3) / 2**30, 1)   # 30 s of 1080p at 30 frames/s
    93.9
    """
    return int(frames) * int(height) * int(width) * (12 * int(channels) + 18)


def streamed_mean(frames: Iterable[NDArray]) -> VideoRestoration:
    """:func:`temporal_mean` of frames given one at a time (:func:`iter_frames`), summed in
    float64 as they come: the memory of two frames whatever the sequence's length.

    Examples
    --------
    >>> import numpy as np
    >>> r = streamed_mean(iter([np.zeros((8, 8)), np.ones((8, 8)), np.ones((8, 8))]))
    >>> round(float(r.image[0, 0]), 4), r.frames_used, r.method
    (0.6667, 3, 'mean')
    """
    t0 = time.perf_counter()
    total, n = None, 0
    for frame in frames:
        img = np.asarray(frame, np.float32)
        _check_frame(img, n, None if total is None else total.shape)
        if total is None:
            total = np.zeros(img.shape, np.float64)
        total += img
        n += 1
    if total is None or n < 2:
        raise WaiInputError(f"a video baseline needs at least 2 frames, got {n}")
    ms = (time.perf_counter() - t0) * 1e3 / n
    return VideoRestoration((total / n).astype(np.float32), np.ones(total.shape[:2], bool), n,
                            ms, "mean")


def _check_frame(img: NDArray, k: int, shape: tuple[int, ...] | None) -> None:
    """Frame ``k`` of a stream as :func:`check_frames` checks a stack: (H, W) or (H, W, 3), at
    least 8 x 8 px, finite, and of the first frame's ``shape``."""
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise WaiInputError(f"frames must be (H, W) or (H, W, 3), frame {k} is {img.shape}")
    if shape is not None and img.shape != shape:
        raise WaiInputError(f"frame {k}: shape {img.shape} differs from the first frame's {shape}")
    if img.shape[0] < 8 or img.shape[1] < 8:
        raise WaiInputError(f"frames of {img.shape[0]}x{img.shape[1]} px are too small")
    if not np.all(np.isfinite(img)):
        raise WaiInputError(f"frame {k} holds NaN or inf")


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
