"""Image-only baselines for a still scene seen through moving water, and a truth-free score.

They need no rig and no calibration: only a sequence of frames of a still scene
(:func:`read_frames`; :func:`iter_frames` one at a time). :func:`temporal_mean` is the classic
reference (:func:`streamed_mean` for a sequence of any length);
:func:`register_frames` registers every frame to the iterated mean by dense optical flow
(:mod:`~restoration.video.registration`); :func:`lucky_fusion` keeps, per patch, the frames the
water distorted least (:mod:`~restoration.video.lucky`). For a planar checkerboard,
:func:`checkerboard_score` measures how far the restored corners are from a homography of a
regular grid, :func:`track_corners` follows its corners through raw frames the detector misses,
and :func:`stability_px` how much they move from frame to frame
(:mod:`~restoration.video.checkerboard`). :func:`grid_score` scores the part of a board a view
shows, by default against the map of a grid seen from under flat water
(:mod:`~restoration.video.gridscore`), for a camera that looks up at a board in air.
"""

from restoration.video.checkerboard import (
    FLAT_WATER_TRIM,
    GRID_MODELS,
    CheckerScore,
    GridScore,
    checkerboard_score,
    grid_residual_px,
    grid_score,
    stability_px,
    track_corners,
)
from restoration.video.frames import (
    VIDEO_SUFFIXES,
    VideoRestoration,
    frames_shape,
    fusion_bytes,
    iter_frames,
    read_frames,
    streamed_mean,
    temporal_mean,
)
from restoration.video.lucky import lucky_fusion
from restoration.video.registration import register_frames

__all__ = [
    "FLAT_WATER_TRIM",
    "GRID_MODELS",
    "VIDEO_SUFFIXES",
    "CheckerScore",
    "GridScore",
    "VideoRestoration",
    "checkerboard_score",
    "frames_shape",
    "fusion_bytes",
    "grid_residual_px",
    "grid_score",
    "iter_frames",
    "lucky_fusion",
    "read_frames",
    "register_frames",
    "stability_px",
    "streamed_mean",
    "temporal_mean",
    "track_corners",
]
