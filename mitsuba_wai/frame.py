"""One frame of both systems rendered in memory: the four images and the true surface."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai.frame_images import render_frame_images
from mitsuba_wai.render import FrameRenderer
from mitsuba_wai.scene_record import render_seed
from mitsuba_wai.surface_sampling import file_surface, moving_surface, wave_surface
from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield
from wai_core.optics import radiance_gain

__all__ = ["Frame", "render_frame"]


@dataclass
class Frame:
    """A rendered frame: what a ``wai render`` folder holds, in memory.

    Attributes
    ----------
    cfg : SystemConfig
        The configuration rendered (with the sensor's exposures resolved when it is on).
    surface : Heightfield
        The true surface on the mesh grid, absolute heights, mm, lab frame.
    images : dict of str to (H, W, 3) ndarray of float32
        ``pattern`` / ``pattern_flat`` (camera s, wavy / flat water) and ``view`` /
        ``view_truth`` (camera v), linear radiance; with ``[sensor]`` on, the sensor's
        reading ``DN / full scale`` (:mod:`mitsuba_wai.degrade`). With ``[motion]`` the wavy
        images are blurred over the exposure (the wave model's surface only).
    view_gain : float
        The views carry this factor (n^2) over the object's radiance.
    render_s : dict of str to float
        ``frame``: wall time of the four renders (and the sensor), s.
    """

    cfg: SystemConfig
    surface: Heightfield
    images: dict[str, NDArray[np.float32]]
    view_gain: float
    render_s: dict[str, float] = field(default_factory=dict)


def render_frame(
    cfg: SystemConfig,
    surface: Heightfield | None = None,
    *,
    spp: int | None = None,
    renderer: FrameRenderer | None = None,
    seed: int | None = None,
) -> Frame:
    """Render both systems through wavy and flat water, in memory.

    Parameters
    ----------
    cfg : SystemConfig
        The system, e.g. :func:`wai_core.load_system` ``("paper")``.
    surface : Heightfield, optional
        Any surface covering the observed patch (resampled onto the modelled extent, flat at
        h0 beyond it); default: the sea state of ``cfg.waves``.
    spp : int, optional
        Samples per pixel of every render (default: the configuration's).
    renderer : FrameRenderer, optional
        A renderer already loaded for this configuration and grid, reused across frames.
    seed : int, optional
        Sampler seed of the renders (0 .. 2^32 - 1); default: derived from ``cfg.waves.seed``
        (:func:`mitsuba_wai.scene_record.render_seed`), as ``wai render`` does.

    Returns
    -------
    Frame

    Examples
    --------
    >>> import mitsuba_wai as mw
    >>> from wai_core import load_system
    >>> frame = mw.render_frame(load_system("paper"), spp=1)      # doctest: +SKIP
    >>> sorted(frame.images)                                      # doctest: +SKIP
    ['pattern', 'pattern_flat', 'view', 'view_truth']
    """
    grid = wave_surface(cfg) if surface is None else file_surface(cfg, surface)
    renderer = FrameRenderer(cfg, grid) if renderer is None else renderer
    seed = render_seed(cfg) if seed is None else int(seed)
    t0 = time.perf_counter()
    surface_at = moving_surface(cfg) if surface is None else None
    cfg, images = render_frame_images(renderer, cfg, grid, seed, spp=spp, surface_at=surface_at)
    t1 = time.perf_counter()
    return Frame(
        cfg, grid, images, radiance_gain(cfg.water.n_water), {"frame": t1 - t0}
    )
