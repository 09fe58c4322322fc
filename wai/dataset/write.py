"""Writing a dataset: its frames rendered in order into the store, continuing where it stopped."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from wai.dataset import store
from wai.dataset.maker import FrameMaker, grid_axes
from wai.dataset.records import append, open_store, rewrite_manifest, trim
from wai.dataset.schedule import make_frames
from wai.dataset.spec import DatasetSpec
from wai.dataset.store import DATASET_FILE, MANIFEST_FILE
from wai_core.errors import WaiInputError

__all__ = ["MANIFEST_EVERY_S", "write_dataset"]

MANIFEST_EVERY_S = 5.0
"""Seconds between the manifest's rewrites while frames are written (and once at the end)."""


def write_dataset(
    out_dir: str | Path,
    frames: int,
    spec: DatasetSpec = DatasetSpec(),  # noqa: B008 (frozen: one default is safe)
    *,
    workers: int = 0,
    scheduler: str | None = None,
    progress: bool = True,
) -> Path:
    """Render frames 0 to ``frames - 1`` of ``spec`` into ``out_dir/dataset.h5`` and its
    ``manifest.csv``, continuing an existing store of the same spec from its frame count.

    Parameters
    ----------
    out_dir : path
        The dataset folder (created if missing).
    frames : int
        The frames the store holds when done (>= 1); fewer than it holds adds none.
    spec : DatasetSpec
    workers : int
        Processes rendering frames (spawned; 0 or 1: in this process). The store is written
        here, in frame order.
    scheduler : str, optional
        A running Dask scheduler's address (``tcp://host:8786``) whose workers render the
        frames instead (they need this package, not the store's file system).
    progress : bool
        Show a progress bar.

    Returns
    -------
    Path
        The store, ``out_dir/dataset.h5``.

    Raises
    ------
    WaiInputError
        ``out_dir`` may not be written, holds another spec, or lacks memory or disk
        (:mod:`wai.dataset.store`).

    Examples
    --------
    >>> write_dataset("datasets/d1", 2, DatasetSpec(size_px=(80, 60), spp=1))  # doctest: +SKIP
    PosixPath('datasets/d1/dataset.h5')
    """
    from tqdm import tqdm

    if frames < 1:
        raise WaiInputError(f"--frames must be >= 1, not {frames}")
    if workers < 0:
        raise WaiInputError(f"--workers must be >= 0, not {workers}")
    if scheduler is not None and workers > 0:
        raise WaiInputError("--workers and --scheduler exclude each other: the scheduler's "
                            "workers render")
    out = Path(out_dir)
    store.check_dataset_folder(out)
    cfg = spec.base_config()
    if scheduler is None:  # a cluster's workers have their own memory
        store.check_dataset_memory(spec, cfg, max(workers, 1))
    store.mark_dataset_folder(out)
    path = out / DATASET_FILE
    f = open_store(path, spec, cfg)
    try:
        done = trim(f)
        todo = list(range(done, frames))
        t0 = time.perf_counter()  # the run's time: its processes' start and scene loads too
        maker = FrameMaker(spec) if todo and scheduler is None and workers <= 1 else None
        with tqdm(total=frames, initial=min(done, frames), desc="dataset", unit="frame",
                  disable=not progress) as bar:
            if todo:
                x_mm, y_mm = (maker.x_mm, maker.y_mm) if maker else grid_axes(spec, cfg)
                made, renderers = make_frames(spec, todo, workers, scheduler, maker)
                # The manifest follows the store every few seconds and at the end, interrupted
                # or not (rewritten after each frame, a store of 100,000 frames would spend its
                # time there).
                listed = time.perf_counter()
                for rec in made:
                    store.reserve_space(f, rec.nbytes, int(f.attrs["frames"]))
                    append(f, rec, x_mm, y_mm)
                    bar.update(1)
                    if time.perf_counter() - listed > MANIFEST_EVERY_S:
                        rewrite_manifest(f, out / MANIFEST_FILE)
                        listed = time.perf_counter()
                store.reserve_space(f, 0, int(f.attrs["frames"]))
                _record_run(f, done, len(todo), time.perf_counter() - t0, renderers)
    finally:
        try:
            rewrite_manifest(f, out / MANIFEST_FILE)
        finally:
            store.close_store(f)
    write_preview(out)
    # The folder's page; the marker names every file (a store written before the preview had
    # only the two).
    from wai_core.outputs import mark_output
    from wai_core.report import write_report

    write_report(out, title=f"{out.name}: wai dataset")
    mark_output(out, store.COMMAND, list(store.FOLDER_FILES))
    return path


def write_preview(out_dir: str | Path, frames: int = 4) -> Path:
    """``preview.png`` of a dataset folder: its first ``frames`` frames, each as camera v's
    view through the waves and its truth, camera s's pattern, the height map and how far the
    warp moves each pixel (what a training loader reads: :func:`~wai.dataset.read_frame`).

    Examples
    --------
    >>> write_preview("datasets/d1")                  # doctest: +SKIP
    PosixPath('datasets/d1/preview.png')
    """
    import numpy as np

    from restoration.figures import plt, save_figure
    from wai.dataset.records import read_frame, read_manifest
    from wai_core.io import to_srgb8

    out = Path(out_dir)
    n = min(frames, len(read_manifest(out)))
    fig, axes = plt.subplots(max(n, 1), 5, figsize=(13, 2.3 * max(n, 1)), squeeze=False)
    for k in range(n):
        rec = read_frame(out, k)
        p = rec.params
        panels = [
            ("view", to_srgb8(np.asarray(rec.view, np.float32), 1.0), None),
            ("view_truth", to_srgb8(np.asarray(rec.view_truth, np.float32), 1.0), None),
            ("pattern", to_srgb8(np.asarray(rec.pattern, np.float32), 10.0), None),
            ("height_mm", rec.height_mm, "viridis"),
            ("warp: pixels moved", _moved_px(rec.warp_px), "magma"),
        ]
        for ax, (name, img, cmap) in zip(axes[k], panels, strict=True):
            im = ax.imshow(img, cmap=cmap)
            if cmap is not None:
                fig.colorbar(im, ax=ax, fraction=0.04)
            ax.set_title(f"frame {k}: {name}" if name != "view" else
                         f"frame {k}: view (U {p.wind_speed_m_s:.2f} m/s)", fontsize=8)
            ax.set_axis_off()
    path = out / store.PREVIEW_FILE
    save_figure(fig, path)
    return path


def _record_run(f: Any, first: int, frames: int, seconds: float, renderers: str) -> None:
    """Append a run's throughput and the reference workload's time now to ``attrs['runs']``."""
    from wai.bench.timing import reference_workload

    ref = reference_workload()
    f.attrs["runs"] = json.dumps([*json.loads(f.attrs.get("runs", "[]")), {
        "first_frame": first, "frames": frames, "seconds": round(seconds, 3),
        "frames_per_s": frames / seconds, "renderers": renderers, "cores": os.cpu_count(),
        "reference": ref["workload"], "reference_ms": ref["median_ms"]}])


def _moved_px(warp_px: Any) -> Any:
    """How far the warp (H, W, 2: each pixel's flat-water coordinates) moves each pixel, px."""
    import numpy as np

    h, w = warp_px.shape[:2]
    rows, cols = np.mgrid[0:h, 0:w]
    return np.hypot(warp_px[..., 0] - cols, warp_px[..., 1] - rows)
