"""System V's image traced directly: camera ray -> water -> the object plane, nothing more.

Mitsuba's ``path`` integrator at ``max_depth = 2`` does what system V needs, but carries in its
kernel the machinery of general paths (emitter sampling and MIS at every vertex, Russian
roulette, a symbolic loop, the film's splatting with atomic additions): on the CPU it took twice
the time of the three steps the scene needs (``docs/results.md``). This tracer follows those
steps for every camera sample:

1. the pixel sample and the camera ray, from the scene's sensor and sampler in Mitsuba's own
   order of pixels and samples (so ``multijitter`` stratifies each pixel as in ``mi.render``);
   a real camera's ray (principal point, distortion, port: :mod:`mitsuba_wai.lens`) from the
   same pixel sample;
2. at the first hit, the emitted radiance if it is an emitter (``hide_emitters = False``), and
   the water's BSDF sample (its one branch, :mod:`mitsuba_wai.bsdfs`);
3. the radiance of whatever the sampled ray reaches (the object plane's textured emitter, or
   the environment where there is one).

A delta BSDF gives the path integrator's estimate exactly here (MIS weight 1, no emitter
sampling), and a box filter puts each sample in its own pixel, so the image is the per-pixel
mean of the samples, summed on the CPU in sample order: the same expectation as ``mi.render``
(``tests/mitsuba_wai/test_view_tracer.py``), the same bits for a seed. Scenes that need more
(the ambient sun and sky, lit through smooth surfaces by emitter sampling) keep Mitsuba's
integrator (:meth:`mitsuba_wai.render.FrameRenderer.render`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai import particles
from mitsuba_wai.variant import mitsuba

__all__ = ["render_view"]


def _trace_pass(scene: Any, spp: int, seed: int, lens: Any = None) -> NDArray[np.float32]:
    """Radiance (3, W * H * s) of one pass's camera samples, pixel-major: ``s`` is ``spp`` as
    the sampler takes it (``multijitter`` rounds 5 up to 6, as in ``mi.render``); with
    ``lens`` (:class:`mitsuba_wai.lens.CameraLens`) the rays are its, not the sensor's."""
    import drjit as dr

    mi = mitsuba()
    sensor = scene.sensors()[0]
    width, height = (int(v) for v in sensor.film().crop_size())
    n = width * height * spp
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    spp = sampler.sample_count()
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(seed, n)
    pixel = dr.arange(mi.UInt32, n) // spp
    pos = mi.Vector2f(mi.Float(pixel % width), mi.Float(pixel // width)) + sampler.next_2d()
    if lens is None:
        ray, weight = sensor.sample_ray(
            sensor.shutter_open(), 0.5, pos * mi.ScalarVector2f(1.0 / width, 1.0 / height),
            mi.Point2f(0.5),
        )
    else:
        ray, weight = lens.sample_ray(sensor.shutter_open(), pos)
    si = scene.ray_intersect(ray)
    hit = si.is_valid()
    emitted = si.emitter(scene, hit).eval(si, hit)
    bs, bsdf_weight = si.bsdf(ray).sample(
        mi.BSDFContext(), si, sampler.next_1d(hit), sampler.next_2d(hit), hit
    )
    onward = hit & dr.any(bsdf_weight != 0.0)
    si_next = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), onward)
    # An invalid hit's emitter is the environment's, if any (Mitsuba's convention).
    arriving = si_next.emitter(scene, onward).eval(si_next, onward)
    radiance = weight * (emitted + dr.select(onward, bsdf_weight * arriving, 0.0))
    dr.eval(radiance)
    return np.asarray(radiance)


def render_view(
    scene: Any, spp: int, seed: int, lens: Any = None
) -> tuple[NDArray[np.float32], int]:
    """Render system V's scene (see the module notes) to linear RGB (H, W, 3).

    Parameters
    ----------
    scene : mitsuba.Scene
        Loaded scene with one sensor (box filter), its water a delta BSDF.
    spp : int
        Samples per pixel, >= 1 (a count the sampler rounds up is rendered as rounded, as
        ``mi.render`` does); more than one pass's worth
        (:data:`mitsuba_wai.particles.MAX_PASS_SAMPLES`) runs in passes of whole samples per
        pixel, pass ``k`` seeded ``seed + k``.
    seed : int
        Sampler seed, 0 .. 2^32 - 1; the same seed gives the same image, bit for bit.
    lens : mitsuba_wai.lens.CameraLens, optional
        The camera's principal point, distortion and port: each pixel sample's ray through
        them (:meth:`~mitsuba_wai.lens.CameraLens.sample_ray`); default the sensor's pinhole.

    Returns
    -------
    image : (H, W, 3) ndarray of float32
        Per-pixel mean radiance, as ``mitsuba.render`` with the ``path`` integrator.
    n_nonfinite : int
        Pixels with a non-finite sample, zeroed (as :func:`mitsuba_wai.render.render_image`).

    Examples
    --------
    >>> from wai_core import load_system
    >>> from mitsuba_wai import FrameRenderer, wave_surface
    >>> cfg = load_system("paper")
    >>> renderer = FrameRenderer(cfg, wave_surface(cfg), systems=("view",))
    >>> image, bad = render_view(renderer._scenes["view"], 1, seed=0)
    >>> image.shape, bad
    ((600, 800, 3), 0)
    """
    if spp < 1:
        raise ValueError("spp must be at least 1")
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    total = np.zeros((height, width, 3))
    bad = np.zeros((height, width), dtype=bool)
    count = 0
    passes = particles.pass_split(spp, width * height, particles.MAX_PASS_SAMPLES)
    for k, spp_k in enumerate(passes):
        samples = _trace_pass(scene, spp_k, (int(seed) + k) % 2**32, lens)
        samples = samples.T.reshape(height, width, -1, 3)
        bad |= ~np.isfinite(samples).all(axis=(2, 3))
        total += samples.sum(axis=2, dtype=np.float64)
        count += samples.shape[2]
    image = (total / count).astype(np.float32)
    image[bad] = 0.0
    return image, int(bad.sum())
