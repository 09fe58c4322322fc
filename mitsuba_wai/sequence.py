"""Sequences: frames of one sea state at ``t, t + 1/fps, ...`` sharing one flat-water reference.

The scenes are loaded once (:class:`~mitsuba_wai.render.FrameRenderer`) and every frame only
rewrites the water mesh, so Dr.Jit's compiled kernels serve the whole sequence. The folder
layout is :mod:`wai_core.sequence`'s. Frames can be rendered by any runner that calls
:func:`render_frames` on subsets of the frame indices (the CLI spreads them over Dask
workers, each with its own loaded renderer).
"""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from mitsuba_wai.degrade import render_exposure, resolve_exposure, sense, subframe_plan
from mitsuba_wai.frame_images import render_flat_water
from mitsuba_wai.render import OUTPUT_COMMAND, FrameRenderer, Rendered
from mitsuba_wai.render_files import write_images, write_surface
from mitsuba_wai.scene_record import render_seed, scene_record
from mitsuba_wai.surface_sampling import moving_surface, wave_surface
from wai_core.config import SystemConfig, config_from_dict
from wai_core.io import write_json
from wai_core.optics import radiance_gain
from wai_core.outputs import atomic_dir, check_output_dir
from wai_core.rig_checks import check_surface_in_rig
from wai_core.sequence import SEQUENCE_FILE, frame_name, frame_times, link_reference
from wai_core.signals import raise_if_interrupted

__all__ = ["FrameRunner", "render_frames", "render_sequence"]

FrameRunner = Callable[[SystemConfig, Sequence[float], Sequence[int], Path], list[dict]]
"""Renders the frames with the given indices (of a sequence with these times) into a folder
and returns one timing row per frame: :func:`render_frames`, or a parallel runner of it."""


@lru_cache(maxsize=2)
def _renderer(cfg_json: str) -> FrameRenderer:
    """One loaded renderer per configuration and process (the time does not change the grid)."""
    cfg = config_from_dict(json.loads(cfg_json))
    return FrameRenderer(cfg, wave_surface(cfg))


def renderer_for(cfg: SystemConfig) -> FrameRenderer:
    """The process's loaded renderer of ``cfg`` (its scenes and kernels, reused); the sensor
    does not change the scenes, so a configuration whose exposures were resolved shares it."""
    data = cfg.to_dict()
    data.pop("sensor", None)
    return _renderer(json.dumps(data, sort_keys=True))


def render_frames(
    cfg: SystemConfig, times_s: Sequence[float], indices: Sequence[int], folder: Path
) -> list[dict[str, Any]]:
    """Render frames ``indices`` of the sequence into ``folder/frameNNN`` (the shared
    reference must already be in ``folder``); one row per frame with its render time, s.

    ``[motion]`` blurs each frame over its exposure (centred on the frame's time); ``[sensor]``
    reads each frame with its own noise (streams named ``frameNNN/pattern``, ``.../view``) at
    the exposures resolved on the reference (:func:`render_sequence` passes them in ``cfg``).
    """
    renderer = renderer_for(cfg)
    seed = render_seed(cfg)
    rows = []
    for k in indices:
        raise_if_interrupted()
        t0 = time.perf_counter()
        frame_cfg = cfg.replace("waves", time_s=float(times_s[k]))
        surface = wave_surface(frame_cfg)
        images = render_exposure(renderer, frame_cfg, surface, seed,
                                 surface_at=moving_surface(frame_cfg))
        if cfg.sensor.enabled:
            images = sense(frame_cfg, images, frame=frame_name(k))
        out = folder / frame_name(k)
        out.mkdir()
        write_images(out, images, view_gain=radiance_gain(cfg.water.n_water), sensor=cfg.sensor)
        write_surface(out, surface)
        link_reference(folder, out)
        record = scene_record(frame_cfg, renderer.variant, surface, "waves")
        record["sequence"] = {"index": int(k), "time_s": float(times_s[k]), "folder": ".."}
        write_json(out / "scene.json", record)
        rows.append({"frame": int(k), "render_s": time.perf_counter() - t0})
    return rows


def render_sequence(
    cfg: SystemConfig,
    out_dir: str | Path,
    n_frames: int,
    fps: float,
    *,
    progress: bool = True,
    overwrite: bool = False,
    runner: FrameRunner | None = None,
) -> Rendered:
    """Render ``n_frames`` frames of ``cfg``'s sea state, ``1/fps`` s apart from
    ``cfg.waves.time_s``, into a sequence folder (atomically, as ``wai render``).

    Parameters
    ----------
    cfg : SystemConfig
    out_dir : path
        The sequence folder (the output policy of :mod:`wai_core.outputs` applies).
    n_frames : int
        Frames, >= 1.
    fps : float
        Frames per second, > 0.
    progress : bool
        A progress bar over the frames (sequential runner only).
    overwrite : bool
        Replace an existing folder that is not a previous render.
    runner : FrameRunner, optional
        Renders subsets of the frames (default: all of them here, in order).

    Returns
    -------
    Rendered
        The sequence folder and its ``sequence.json`` record, with each frame's render time.

    Examples
    --------
    >>> from mitsuba_wai import render_sequence
    >>> from wai_core import load_rig
    >>> render_sequence(load_rig("paper"), "renders/seq", 3, 30.0)   # doctest: +SKIP
    """
    from tqdm import tqdm

    times = frame_times(cfg.waves.time_s, fps, n_frames)
    first = cfg.replace("waves", time_s=times[0])
    # Every frame's surface (and its exposure's ends) is checked before any render starts.
    for t in times:
        plan = subframe_plan(cfg.replace("waves", time_s=t))
        for tt in sorted({t, plan.times_s[0], plan.times_s[-1]}):
            check_surface_in_rig(cfg, wave_surface(cfg.replace("waves", time_s=tt)), "[waves]")
    check_output_dir(out_dir, OUTPUT_COMMAND, overwrite)
    t0 = time.perf_counter()
    renderer = renderer_for(cfg)
    grid = wave_surface(first)
    flat = render_flat_water(renderer, cfg, grid, render_seed(cfg))
    reference = {"pattern_flat": flat["pattern"], "view_truth": flat["view"]}
    if cfg.sensor.enabled:
        # The exposures are fixed on the reference and travel in cfg to every frame.
        cfg = resolve_exposure(cfg, reference)
        reference = sense(cfg, reference)
    with atomic_dir(out_dir, command=OUTPUT_COMMAND, overwrite=overwrite) as tmp:
        write_images(tmp, reference, view_gain=radiance_gain(cfg.water.n_water),
                     sensor=cfg.sensor)
        reference_s = time.perf_counter() - t0
        if runner is None:
            rows = []
            for k in tqdm(range(n_frames), desc="frames", disable=not progress, leave=False):
                rows += render_frames(cfg, times, [k], tmp)
        else:
            rows = runner(cfg, times, list(range(n_frames)), tmp)
        rows = sorted(rows, key=lambda r: r["frame"])
        record = _sequence_record(cfg, renderer.variant, fps, times, rows, reference_s)
        write_json(tmp / SEQUENCE_FILE, record)
    return Rendered(Path(out_dir), record)


def _sequence_record(
    cfg: SystemConfig, variant: str, fps: float, times: list[float], rows: list[dict],
    reference_s: float,
) -> dict[str, Any]:
    import drjit
    import mitsuba as mi

    return {
        "format": "wai-sequence/1",
        "config": cfg.to_dict(),
        "fps": float(fps),
        "seed": cfg.waves.seed,
        "render_seed": render_seed(cfg),
        "variant": variant,
        "reference": {"images": ["pattern_flat", "view_truth"], "render_s": reference_s},
        "frames": [
            {"name": frame_name(r["frame"]), "time_s": times[r["frame"]],
             "render_s": r["render_s"]}
            for r in rows
        ],
        "versions": {
            "mitsuba": mi.__version__, "drjit": drjit.__version__, "numpy": np.__version__,
            "python": platform.python_version(),
        },
    }
