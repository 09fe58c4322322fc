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
from mitsuba_wai.water_hit import WaterGeometry

__all__ = ["render_view"]


def _trace_pass(scene: Any, spp: int, seed: int, lens: Any = None,
                geometry: WaterGeometry | None = None) -> tuple[Any, int]:
    """Sum (Color3f, W * H) of each pixel's radiance over one pass's camera samples (non-finite
    where a sample is) and their number ``s`` per pixel: ``spp`` as the sampler takes it
    (``multijitter`` rounds 5 up to 6, as in ``mi.render``); with ``lens``
    (:class:`mitsuba_wai.lens.CameraLens`) the rays are its, not the sensor's; ``geometry``
    answers the direct steps' questions about the water (:func:`_direct_radiance`)."""
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
    direct = _direct_parts(scene)
    if direct is None:
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
    else:
        radiance = weight * _direct_radiance(scene, ray, sampler, *direct, geometry)
    # Each pixel's samples are consecutive: their sum here, a non-finite one making it so
    # (the three channels evaluated together first: one trace, not one per channel).
    dr.eval(radiance)
    pixel_sum = dr.block_sum(radiance, spp, mode="evaluated")
    dr.eval(pixel_sum)
    return pixel_sum, spp


def _direct_parts(scene: Any) -> tuple[Any, Any] | None:
    """The water mesh and the object plane of system V's scene when it holds only those and
    the object's emitter (what :func:`_direct_radiance` traces); None otherwise."""
    shapes = {shape.id(): shape for shape in scene.shapes()}
    if sorted(shapes) != ["object", "water"] or len(scene.emitters()) != 1:
        return None
    if shapes["object"].emitter() is None or scene.environment() is not None:
        return None
    return shapes["water"], shapes["object"]


def _direct_radiance(scene: Any, ray: Any, sampler: Any, water: Any, plane: Any,
                     geometry: WaterGeometry | None = None) -> Any:
    """Radiance (Color3f) along camera rays of system V's two-shape scene: the general
    steps with their choices fixed. The first hit, through the scene; the water's BSDF,
    called directly (the same random numbers drawn); then the object plane's own
    intersection and emitter. A ray that meets the object without the water reaches it
    with weight 1; the water lies in the way of a refracted ray only where that ray is
    flatter than the steepest facet, and only there is it tested. The water's hits and
    whether it lies in a ray's way come from ``geometry`` (the water alone: the object is
    met on its own plane), by default the scene's."""
    import drjit as dr

    mi = mitsuba()
    geometry = WaterGeometry.of(scene) if geometry is None else geometry
    slope = geometry.slope
    # The water's hit on its grid (mitsuba_wai.water_hit); the object plane, where it is met
    # first, is the first hit (a borrowed scene's own hit may be the object already).
    si = geometry.intersect(ray, True)
    before = plane.ray_intersect(ray, mi.RayFlags.Minimal, True).t < si.t
    hit = si.is_valid() | before
    on_water = si.is_valid() & (si.shape == mi.ShapePtr(geometry.mesh)) & ~before
    bs, bsdf_weight = water.bsdf().sample(
        mi.BSDFContext(), si, sampler.next_1d(hit), sampler.next_2d(hit), on_water
    )
    refracted = on_water & dr.any(bsdf_weight != 0.0)
    onward = refracted | (hit & ~on_water)
    spawned = si.spawn_ray(si.to_world(bs.wo))
    next_ray = mi.Ray3f(dr.select(on_water, spawned.o, ray.o),
                        dr.select(on_water, spawned.d, ray.d), ray.time, ray.wavelengths)
    si_next = plane.ray_intersect(
        next_ray, mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame, onward)
    onward = onward & si_next.is_valid()
    d = next_ray.d
    flat = d.z <= slope * dr.norm(mi.Vector2f(d.x, d.y))
    blocked = geometry.occluded(
        mi.Ray3f(next_ray.o, d, si_next.t * (1.0 - 1e-4), ray.time, ray.wavelengths),
        onward & refracted & flat,
    )
    onward = onward & ~blocked
    arriving = plane.emitter().eval(si_next, onward)
    return dr.select(onward, dr.select(on_water, bsdf_weight, 1.0) * arriving, 0.0)


def render_view(
    scene: Any, spp: int, seed: int, lens: Any = None, geometry: WaterGeometry | None = None,
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
    geometry : mitsuba_wai.water_hit.WaterGeometry, optional
        The water the direct steps ask (its hits, whether it is in a ray's way), when the
        scene's own is not up to date; default the scene's.

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
    >>> image, bad = render_view(renderer.scene("view"), 1, seed=0)
    >>> image.shape, bad
    ((600, 800, 3), 0)
    """
    if spp < 1:
        raise ValueError("spp must be at least 1")
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    passes = particles.pass_split(spp, width * height, particles.MAX_PASS_SAMPLES)
    if len(passes) == 1:
        return _mean_image(*_trace_pass(scene, spp, int(seed) % 2**32, lens, geometry),
                           width, height)
    total = np.zeros((height, width, 3))
    bad = np.zeros((height, width), dtype=bool)
    count = 0
    for k, spp_k in enumerate(passes):
        sums, taken = _trace_pass(scene, spp_k, (int(seed) + k) % 2**32, lens, geometry)
        sums = np.stack([np.asarray(sums[c]) for c in range(3)], axis=1)
        sums = sums.reshape(height, width, 3)
        bad |= ~np.isfinite(sums).all(axis=2)
        total += sums
        count += taken
    image = (total / count).astype(np.float32)
    image[bad] = 0.0
    return image, int(bad.sum())


def _mean_image(sums: Any, count: int, width: int, height: int) -> tuple[NDArray[np.float32], int]:
    """One pass's image: the pixels' sums (Color3f, W * H) over their ``count`` samples, the
    non-finite pixels zeroed, laid out (H, W, 3) in Dr.Jit, as the passes' float64 mean
    rounds it (a float32 quotient is the float64 one rounded: double rounding is innocuous
    for a division, 53 >= 2 * 24 + 2 bits) and the number of pixels zeroed."""
    import drjit as dr

    mi = mitsuba()
    mean = sums / count
    bad = ~(dr.isfinite(mean.x) & dr.isfinite(mean.y) & dr.isfinite(mean.z))
    mean = dr.select(bad, 0.0, mean)
    n = width * height
    flat = dr.zeros(mi.Float, 3 * n)
    index = dr.arange(mi.UInt32, n) * 3
    for c in range(3):
        dr.scatter(flat, mean[c], index + c)
    dr.eval(flat)
    return np.array(flat, dtype=np.float32).reshape(height, width, 3), int(dr.count(bad)[0])
