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

__all__ = ["render_flat_water", "render_frame_images"]


def render_flat_water(
    renderer: RendersFrames, cfg: SystemConfig, surface: Heightfield, seed: int,
    spp: int | None = None,
) -> dict[str, NDArray[np.float32]]:
    """The flat-water renders at ``h0``: ``pattern`` (camera s) and ``view`` (camera v, the
    object's own light: no projector light, :mod:`~mitsuba_wai.crosstalk`'s truth), linear
    radiance before any sensor.

    They depend on the rig and the seed only, so frames of one rig may share them (a
    sequence's reference, a dataset's): :func:`render_frame_images`'s ``flat``.

    Parameters
    ----------
    renderer : RendersFrames
        Loaded for ``cfg``'s geometry, both systems prepared.
    cfg : SystemConfig
    surface : Heightfield
        A surface on the renderer's grid (its heights are not used), mm.
    seed : int
        Sampler seed (0 .. 2^32 - 1).
    spp : int, optional
        Samples per pixel (default: the configuration's).

    Returns
    -------
    dict of str to (H, W, 3) ndarray of float32
        ``pattern`` and ``view``.
    """
    return renderer.render(flat_like(surface, cfg.water.h0_mm), seed, spp=spp, crosstalk=False)


def render_frame_images(
    renderer: RendersFrames,
    cfg: SystemConfig,
    surface: Heightfield,
    seed: int,
    *,
    spp: int | None = None,
    surface_at: Callable[[float], Heightfield] | None = None,
    plan: SubframePlan | None = None,
    flat: dict[str, NDArray[np.float32]] | None = None,
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
    flat : dict, optional
        Flat-water renders shared with other frames of the rig (:func:`render_flat_water`'s,
        any seed); default: rendered here with ``seed``. The sensor reads them afresh each frame.

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
    if flat is None:
        flat = render_flat_water(renderer, cfg, surface, seed, spp)
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
