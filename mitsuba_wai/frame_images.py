"""The four images of a frame: the wavy pair over the exposure, the flat pair, then the sensor.

What :func:`~mitsuba_wai.render.render_folder` writes and :func:`~mitsuba_wai.frame.render_frame`
returns: ``pattern`` / ``pattern_flat`` (camera s, wavy / flat water) and ``view`` /
``view_truth`` (camera v). The degradations it applies are :mod:`mitsuba_wai.degrade`'s.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai.degrade import (
    RendersFrames,
    SubframePlan,
    render_exposure,
    resolve_exposure,
    sense,
)
from mitsuba_wai.mesh import flat_like
from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield

__all__ = ["render_frame_images"]


def render_frame_images(
    renderer: RendersFrames,
    cfg: SystemConfig,
    surface: Heightfield,
    seed: int,
    *,
    spp: int | None = None,
    surface_at: Callable[[float], Heightfield] | None = None,
    plan: SubframePlan | None = None,
) -> tuple[SystemConfig, dict[str, NDArray[np.float32]]]:
    """The four images of a frame: the wavy ones over the exposure
    (:func:`~mitsuba_wai.degrade.render_exposure`), the flat ones (at ``h0``) sharp, then the
    sensor when ``[sensor]`` is on.

    Parameters
    ----------
    renderer : RendersFrames
        Loaded for ``cfg``'s geometry and ``surface``'s grid, both systems prepared.
    cfg : SystemConfig
        The frame's configuration.
    surface : Heightfield
        The surface at the frame's time, on the renderer's grid, mm.
    seed : int
        Sampler seed of every render (0 .. 2^32 - 1).
    spp : int, optional
        Samples per pixel of every image (default: the configuration's).
    surface_at : callable, optional
        The surface at a time, s (the wave model's, for motion blur); None: a static surface.
    plan : SubframePlan, optional
        The exposure's sub-frames (default: :func:`~mitsuba_wai.degrade.subframe_plan`).

    Returns
    -------
    cfg : SystemConfig
        ``cfg`` with the sensor's exposures resolved (what ``scene.json`` records).
    images : dict of str to (H, W, 3) ndarray of float32
        ``pattern``, ``pattern_flat``, ``view``, ``view_truth``: linear radiance, or with the
        sensor on its reading ``DN / full scale``.
    """
    wavy = render_exposure(renderer, cfg, surface, seed, spp=spp, surface_at=surface_at,
                           plan=plan)
    # The flat-water view is the object's own (no projector light: [crosstalk]'s truth).
    flat = renderer.render(flat_like(surface, cfg.water.h0_mm), seed, spp=spp, crosstalk=False)
    images = {
        "pattern": wavy["pattern"],
        "pattern_flat": flat["pattern"],
        "view": wavy["view"],
        "view_truth": flat["view"],
    }
    if cfg.sensor.enabled:
        cfg = resolve_exposure(cfg, images)
        images = sense(cfg, images)
    return cfg, images
