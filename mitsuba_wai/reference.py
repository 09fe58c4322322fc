"""Reference renders from Mitsuba's stock plugins and integrators, to check the default renderer.

The default renderer draws the projector's dots directly (:mod:`mitsuba_wai.dots`), traces the
view in three steps (:mod:`mitsuba_wai.view_tracer`) and gives the water a BSDF that follows
one branch with its Fresnel weight (``water_interface``). The reference shares none of that:

- system S: Mitsuba's ``ptracer`` integrator, its ``projector`` emitter with the pattern's
  irradiance image, the stock ``dielectric`` water (reflection or refraction picked at random
  with probability F), the ``independent`` sampler;
- system V: the ``path`` integrator, the stock ``dielectric`` water, the ``independent``
  sampler.

Both keep the scene's geometry, camera sensors and the one-way diffuser (Mitsuba has no
one-way screen; :mod:`mitsuba_wai.bsdfs`).

Mitsuba's ``projector`` emits about one ray in a million with an infinite or absurd weight
(its bitmap's sampling density is zero or nearly so where the interpolated irradiance is
not), which at any affordable spp puts a few pixels of camera s thousands of times above the
rest. System S's reference is therefore traced by :func:`mitsuba_wai.particles.render_particles`
(Mitsuba's ``ptracer`` step by step, summed in a fixed order) from the projector's own
``sample_emitter_ray``, dropping those rays (:class:`StockEmission` counts them).

:func:`windowed_centroids` measures spot centres with no part of the restoration's detector:
intensity-weighted centroids in fixed windows.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai import mesh as meshes
from mitsuba_wai.particles import render_particles
from mitsuba_wai.render import render_image
from mitsuba_wai.scenes import pattern_depth, pattern_scene, view_scene
from mitsuba_wai.textures import object_texture
from mitsuba_wai.variant import mitsuba, select_variant
from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield

__all__ = ["StockEmission", "render_reference", "stock_water", "windowed_centroids"]

OUTLIER_WEIGHT = 10.0
"""Emitted rays weighing more than this many times the median (or not finite) are dropped."""


class StockEmission:
    """The scene's own emitters sampled as Mitsuba's ``ptracer`` does (independent samples),
    less the rays of non-finite or outlying weight (see the module notes).

    Parameters
    ----------
    scene : mitsuba.Scene
        A loaded system-S scene with Mitsuba's ``projector``.

    Attributes
    ----------
    dropped : int
        Rays dropped so far.
    emitted : int
        Rays drawn so far.
    """

    skipped_vertices = 0
    camera_unoccluded = False

    def __init__(self, scene: Any) -> None:
        self._scene = scene
        self.dropped = 0
        self.emitted = 0

    def __call__(self, time: float, n: int, seed: int) -> tuple[Any, Any, Any]:
        """``n`` rays and weights of the scene's emitters, seeded; ``travelled_mm`` 0."""
        import drjit as dr

        mi = mitsuba()
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(seed, n)
        ray, weight, _ = self._scene.sample_emitter_ray(
            time, sampler.next_1d(), sampler.next_2d(), sampler.next_2d(), True
        )
        peak = dr.max(weight)
        values = np.asarray(peak)
        typical = float(np.median(values[np.isfinite(values) & (values > 0)]))
        bad = ~dr.isfinite(peak) | (peak > OUTLIER_WEIGHT * typical)
        self.dropped += int(np.count_nonzero(np.asarray(bad)))
        self.emitted += n
        return ray, dr.select(bad, 0.0, weight), mi.Float(0.0)


def stock_water(cfg: SystemConfig) -> dict[str, Any]:
    """Mitsuba's own smooth ``dielectric``: water below (``[water].n_water``), air above."""
    return {"type": "dielectric", "int_ior": cfg.water.n_water, "ext_ior": 1.0}


def render_reference(
    cfg: SystemConfig, surface: Heightfield, spp_pattern: int = 256, spp_view: int = 64,
    seed: int = 0,
) -> dict[str, NDArray[np.float32]]:
    """Camera s's pattern and camera v's view through ``surface``, by stock Mitsuba only.

    Parameters
    ----------
    cfg : SystemConfig
        The scene (its renderer-only effects are not modelled here: the reference is the
        geometric model's idealised rig, rendered by Mitsuba's own plugins).
    surface : Heightfield
        Water surface, mm, lab frame.
    spp_pattern, spp_view : int
        Light paths per camera-s pixel and camera samples per camera-v pixel.
    seed : int
        Sampler seed.

    Returns
    -------
    dict of str to (H, W, 3) ndarray of float32
        ``pattern`` (linear RGB, the default renderer's units) and ``view`` (radiance, with
        the n^2 gain of the default renderer's views).

    Examples
    --------
    >>> from wai_core import load_system
    >>> from mitsuba_wai import wave_surface
    >>> cfg = load_system("paper")
    >>> ref = render_reference(cfg, wave_surface(cfg), 4, 1)      # doctest: +SKIP
    >>> sorted(ref)                                               # doctest: +SKIP
    ['pattern', 'view']
    """
    select_variant()
    mi = mitsuba()
    stock = cfg.replace("render", sampling="independent")
    water = meshes.heightfield_mesh(surface)
    scene_s = mi.load_dict(pattern_scene(stock, meshes.to_mitsuba(water, "water",
                                                                stock_water(cfg))))
    scene_v = mi.load_dict(view_scene(stock, meshes.to_mitsuba(water, "water", stock_water(cfg)),
                                      object_texture(cfg.object)))
    pattern, _ = render_particles(scene_s, spp_pattern, seed, pattern_depth(stock),
                                  emitter=StockEmission(scene_s))
    view, _ = render_image(scene_v, spp_view, seed + 1)
    return {"pattern": pattern, "view": view}


def windowed_centroids(
    image: NDArray, centres_px: NDArray, radius_px: int = 4, iterations: int = 2
) -> tuple[NDArray, NDArray]:
    """Intensity-weighted centroids of ``image`` in square windows about ``centres_px``.

    Each window (side ``2 radius_px + 1``) is re-centred on its centroid ``iterations`` times.

    Parameters
    ----------
    image : (H, W) or (H, W, C) ndarray
        Linear image (channels summed).
    centres_px : (K, 2) ndarray
        Starting centres ``(col, row)``, pixels.
    radius_px : int
        Half side of the windows, pixels.
    iterations : int
        Re-centrings, >= 1.

    Returns
    -------
    centroids_px : (K, 2) ndarray
        ``(col, row)``, pixels; NaN where a window leaves the image or holds no light.
    energy : (K,) ndarray
        Sum of the image in each final window.

    Examples
    --------
    >>> img = np.zeros((20, 20)); img[8:11, 5:8] = 1.0
    >>> c, e = windowed_centroids(img, np.array([[5.0, 8.0]]))
    >>> c.round(3).tolist(), float(e[0])
    ([[6.0, 9.0]], 9.0)
    """
    gray = np.asarray(image, dtype=np.float64)
    gray = gray.sum(axis=2) if gray.ndim == 3 else gray
    h, w = gray.shape
    offsets = np.arange(-radius_px, radius_px + 1)
    centres = np.asarray(centres_px, dtype=np.float64).copy()
    energy = np.zeros(len(centres))
    for _ in range(max(iterations, 1)):
        base = np.rint(centres)
        inside = ((base[:, 0] - radius_px >= 0) & (base[:, 0] + radius_px < w)
                  & (base[:, 1] - radius_px >= 0) & (base[:, 1] + radius_px < h))
        base = np.where(inside[:, None], base, radius_px)
        cols = base[:, 0, None, None].astype(int) + offsets[None, None, :]
        rows = base[:, 1, None, None].astype(int) + offsets[None, :, None]
        patch = gray[rows, cols]  # (K, side, side)
        energy = patch.sum(axis=(1, 2))
        lit = inside & (energy > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            cx = (patch * cols).sum(axis=(1, 2)) / energy
            cy = (patch * rows).sum(axis=(1, 2)) / energy
        centres = np.where(lit[:, None], np.stack([cx, cy], axis=1), np.nan)
    return centres, energy
