"""Datasets for learned methods: frames of random sea states rendered with their truth.

Frame ``i`` of a dataset of seed ``s`` draws its sea state from ``default_rng([s, i])``, so a
frame's parameters depend on neither the number of frames nor the workers that render them
(:func:`sample_params`). Each frame is rendered by :mod:`mitsuba_wai` on one mesh grid shared by
the whole dataset (the finest the wind range needs), and stored with:

``view``, ``view_truth``
    Camera v through the wavy and the flat water, (H, W, 3), radiance divided by the views'
    gain ``n^2`` (the object's radiance), float16. Flat water is rendered once per store
    (:func:`flat_seed`): ``view_truth`` and ``pattern_flat`` are the same in every frame, but
    for the sensor's noise when degraded.
``pattern``, ``pattern_flat``
    Camera s through the wavy and the flat water, grey (mean over channels), (Hs, Ws), float16.
``height_mm``, ``normals``
    The true surface ``z`` (ny, nx) mm and its unit normals (ny, nx, 3) on the grid ``x_mm``
    (nx,), ``y_mm`` (ny,) of the ``lab`` frame, float32.
``warp_px``
    For each camera-v pixel (col, row) of ``view``, the (col, row) of ``view_truth`` that sees
    the same object point, (H, W, 2) float32; NaN where the ray is totally reflected or misses
    (:func:`true_view_warp`). ``cv2.remap(view_truth, warp_px[..., 0], warp_px[..., 1], ...)``
    is the distorted view.
``params``
    Each frame's parameters (a compound dataset, also written to ``manifest.csv``).

The store is one HDF5 file, ``DIR/dataset.h5``, one chunk per frame and image; the attribute
``frames`` (the frames complete) is written after each frame's arrays, so an interrupted run
leaves a readable file and a rerun continues from there (:func:`write_dataset`).
"""

from wai.dataset.maker import FrameMaker
from wai.dataset.records import (
    ARRAYS,
    FramePacker,
    FrameRecord,
    PackedFrame,
    read_frame,
    read_manifest,
    read_runs,
)
from wai.dataset.spec import (
    DatasetSpec,
    FrameParams,
    Ranges,
    flat_seed,
    frame_config,
    sample_params,
)
from wai.dataset.store import DATASET_FILE, MANIFEST_FILE
from wai.dataset.truth import true_view_warp
from wai.dataset.write import write_dataset, write_preview

__all__ = [
    "ARRAYS",
    "DATASET_FILE",
    "MANIFEST_FILE",
    "DatasetSpec",
    "FrameMaker",
    "FramePacker",
    "FrameParams",
    "FrameRecord",
    "PackedFrame",
    "Ranges",
    "flat_seed",
    "frame_config",
    "read_frame",
    "read_manifest",
    "read_runs",
    "sample_params",
    "true_view_warp",
    "write_dataset",
    "write_preview",
]
