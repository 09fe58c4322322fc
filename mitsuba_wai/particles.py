"""A particle tracer whose image is the same, bit for bit, on every run with the same seed.

Mitsuba's ``ptracer`` splats each light path's camera connections into the film with atomic
float additions from all threads at once, so the order of the additions, and with it the last
bits of a pixel, changes from run to run (two renders of the same seed differ by ~1e-8 in a few
thousand pixels). This tracer follows Mitsuba's ``ptracer`` step by step (same emitter, sensor
and BSDF sampling, same random numbers in the same order, same shading-normal corrections), but
instead of splatting it returns each connection's pixel and value, and the image is summed on
the CPU in sample order, in float64 (:func:`numpy.bincount`'s sums, all channels in one compiled
pass): a fixed order, whatever the number of threads or the device.

Water (:func:`render_particles_water`): no Mitsuba medium (``ptracer`` has none), but each
path's length in the water is known, so every camera connection is weighted by Beer-Lambert's
``exp(-(a + b) L)`` per channel (scattered light leaves the beam), ``L`` the path's length from
its first underwater segment to the camera; the scattered share ``exp(-a L)(1 - exp(-b L))`` is
summed into a second image for the caller's veiling glow (:mod:`mitsuba_wai.seawater`).

Stratified emission (``stratified=True``, the default of the repository's renders through
``[render] sampling``): the emitter's samples come from a shifted Kronecker sequence
(:func:`emitter_samples`) instead of the sampler, which spreads every dot's particles evenly
over it. In systems S and A the emitter's sample is the only random choice of a path (the
water and the pass-through are deterministic, the camera a pinhole), so the image is then a
quasi-Monte Carlo estimate: same expectation, and spot centres as good at 4 paths per pixel as
with 32 independent ones. The repository's pattern renders go one step further and draw the
projector's dots directly (``emitter``: :class:`mitsuba_wai.dots.DotEmitter`), each dot a
stratified point set of its own, for half the time of the projector's image sampling.

Only what the repository's particle-traced scenes use is supported: no media, no directly
visible emitters (``hide_emitters``), a box reconstruction filter and ``max_depth`` up to
``rr_depth + 1`` (no Russian roulette), as in systems S and A.

Work is split into passes of at most :data:`MAX_PASS_SAMPLES` light paths (whole samples per
pixel), which bounds memory and keeps every pass below Dr.Jit's 2^32 wavefront limit for any
``spp``; pass ``k > 0`` seeds its sampler with ``seed + k * PASS_SEED_STRIDE``.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from mitsuba_wai.variant import mitsuba
from mitsuba_wai.water_hit import WaterGeometry

# Light paths per pass (the paper's 800 x 600 film at 8 spp is one pass): 16 bytes per path and
# bounce come back to the CPU, ~0.2 GB at most.
MAX_PASS_SAMPLES = 1 << 22
# Seed offset between passes (an odd constant, so passes never reuse a sampler seed).
PASS_SEED_STRIDE = 0x9E3779B1
_RR_DEPTH = 5


# Generators of the stratified emitter samples, a Kronecker sequence: 2^32/g and 2^32/g^2 for the
# emitter's 2D sample, g the plastic number (Roberts' R2 sequence, the additive recurrence
# whose points spread most evenly in the square, for any count), and 2^32 (sqrt(2) - 1) for the
# 1D sample that picks one of several emitters.
_KRONECKER = (3242174889, 2447445413, 1779033703)


def emitter_samples(n: int, seed: int) -> tuple[Any, Any]:
    """Stratified emitter samples of ``n`` light paths: a randomly shifted Kronecker sequence.

    A projector maps its 2D sample through the irradiance image's inverse CDF, so evenly spread
    samples give every dot its share of particles, spread evenly over the dot: a spot's centroid
    then converges much faster than with independent samples (4 paths per pixel give the spot
    agreement of 32 independent ones; docs/results.md). The shift (Cranley-Patterson rotation)
    comes from ``seed``, so a seed gives one point set and other seeds give independent ones.

    Parameters
    ----------
    n : int
        Number of light paths.
    seed : int
        Seed of the shift.

    Returns
    -------
    select : mitsuba.Float, (n,)
        Sample in [0, 1) that picks the emitter (unused with one emitter).
    position : mitsuba.Point2f, (n,)
        The emitter's 2D sample in [0, 1)^2 (a projector's point on its image).
    """
    import drjit as dr

    mi = mitsuba()
    shifts = np.random.default_rng([int(seed), 0x5EED]).integers(0, 2**32, 3, dtype=np.uint64)
    index = dr.arange(mi.UInt32, n)

    # The shift is opaque (a kernel parameter, not a literal): one compiled kernel serves every
    # seed, where a literal would recompile the whole path kernel per frame.
    select, x, y = (kronecker(index, k, dr.opaque(mi.UInt32, int(shifts[k]))) for k in (2, 0, 1))
    return select, mi.Point2f(x, y)


def kronecker(index: Any, k: int, shift: Any) -> Any:
    """Coordinate ``k`` (0, 1: the R2 sequence's two; 2: the emitter pick) of the shifted
    Kronecker points ``index``: ``frac(index * alpha_k + shift / 2^32)``, in 32-bit fixed point
    (the product wraps modulo 2^32 exactly), as a float32 in [0, 1).

    Parameters
    ----------
    index : mitsuba.UInt32, (n,)
        Point numbers.
    k : int
        Coordinate, 0 .. 2.
    shift : mitsuba.UInt32, (n,) or (1,)
        Cranley-Patterson shift, in units of 2^-32.

    Returns
    -------
    mitsuba.Float, (n,)
    """
    mi = mitsuba()
    bits = index * mi.UInt32(_KRONECKER[k]) + shift
    return mi.Float(bits >> 8) * (1.0 / 2**24)  # 24 bits: a float32 below 1


def pass_split(spp: int, pixels: int, max_samples: int | None = None) -> list[int]:
    """Samples per pixel of each pass: ``spp`` split into near-equal whole counts, each pass at
    most ``max_samples`` samples (or one sample per pixel, if a single one is already more).

    Parameters
    ----------
    spp : int
        Samples per pixel in all, >= 1.
    pixels : int
        Pixels of the film, >= 1.
    max_samples : int, optional
        Most samples (light paths) in one pass; default :data:`MAX_PASS_SAMPLES`.

    Returns
    -------
    list of int
        Positive counts summing to ``spp``; the larger ones first.
    """
    if spp < 1 or pixels < 1:
        raise ValueError("spp and pixels must be at least 1")
    limit = MAX_PASS_SAMPLES if max_samples is None else max_samples
    per_pass = max(1, limit // pixels)
    n = -(-spp // per_pass)
    q, r = divmod(spp, n)
    return [q + 1] * r + [q] * (n - r)


def _trace_pass(
    scene: Any, spp: int, spp_total: int, seed: int, max_depth: int, water: Any = None,
    stratified: bool = False, emitter: Any = None, camera: Any = None,
    geometry: WaterGeometry | None = None,
) -> list[tuple[Any, ...]]:
    """One pass: for each bounce, the film pixel (``W * H`` where none), the RGB value and the
    pixel of a non-finite value (``W * H`` where finite) of every path's camera connection, as
    Dr.Jit arrays (evaluated); with ``water`` (``(a, b, air_segments)``, 1/mm) the value is the
    direct light and the scattered share follows as a fourth array; ``camera`` connects in place
    of the scene's sensor (its ``sample_direction``); ``geometry`` answers the direct pass's
    questions about the water (:func:`_trace_direct`)."""
    import drjit as dr

    if emitter is not None and _direct_scene(scene, max_depth, emitter):
        return _trace_direct(scene, spp, spp_total, seed, water, emitter, camera, geometry)
    mi = mitsuba()
    sensor = scene.sensors()[0]
    film = sensor.film()
    width, height = (int(v) for v in film.crop_size())
    n = width * height * spp
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(seed, n)
    scale = 1.0 / spp_total
    ctx = mi.BSDFContext(mi.TransportMode.Importance)

    time = sensor.shutter_open()
    wavelength_sample = sampler.next_1d()
    direction_sample, position_sample = sampler.next_2d(), sampler.next_2d()
    length = mi.Float(0.0)  # path length in the water so far, mm
    shadow = emitter is None or not emitter.camera_unoccluded
    if emitter is not None:
        ray, throughput, length = emitter(time, n, seed)
        max_depth -= emitter.skipped_vertices
    else:
        if stratified:
            wavelength_sample, position_sample = emitter_samples(n, seed)
        ray, throughput, _ = scene.sample_emitter_ray(
            time, wavelength_sample, direction_sample, position_sample, True
        )
    active = dr.max(throughput) != 0.0
    si = scene.ray_intersect(ray, active)
    active = active & si.is_valid() & (1 < max_depth)
    splats = []
    for depth in range(1, max_depth):
        bsdf = si.bsdf(ray)
        sensor_ds, sensor_weight = (sensor if camera is None else camera).sample_direction(
            si, sampler.next_2d(), active)
        if water is not None:
            if depth > water[2]:
                length = length + dr.select(active, si.t, 0.0)
        splats.append(_connect(scene, si, sensor_ds, bsdf, throughput * sensor_weight,
                               scale, (width, height), ctx, active,
                               None if water is None else (water[0], water[1], length), shadow))
        if depth == max_depth - 1:
            break
        bs, bsdf_val = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active),
                                   active)
        wi_dot_n = dr.dot(si.n, -ray.d)
        wo_world = si.to_world(bs.wo)
        wo_dot_n = dr.dot(si.n, wo_world)
        cos_wi, cos_wo = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(bs.wo)
        # Shading normals: no light leaks, and the adjoint correction (Veach, p. 155).
        active = active & (wi_dot_n * cos_wi > 0.0) & (wo_dot_n * cos_wo > 0.0)
        throughput = throughput * bsdf_val * dr.abs((cos_wi * wo_dot_n) / (cos_wo * wi_dot_n))
        active = active & dr.any(throughput != 0.0)
        ray = si.spawn_ray(wo_world)
        si = scene.ray_intersect(ray, active)
        active = active & si.is_valid()
    dr.eval(*[v for splat in splats for v in splat])
    return splats


def _direct_scene(scene: Any, max_depth: int, emitter: Any) -> bool:
    """Whether a pass can take :func:`_trace_direct`: an emitter whose rays start past the
    diffuser towards the water, nothing between a vertex and the camera, and the scene of
    system S alone (its ``water`` and ``diffuser``), paths of two vertices."""
    ids = sorted(shape.id() for shape in scene.shapes())
    return (emitter.camera_unoccluded and max_depth - emitter.skipped_vertices == 3
            and ids == ["diffuser", "water"])


def _trace_direct(
    scene: Any, spp: int, spp_total: int, seed: int, water: Any, emitter: Any, camera: Any,
    geometry: WaterGeometry | None = None,
) -> list[tuple[Any, ...]]:
    """:func:`_trace_pass` for system S's two-vertex paths (:func:`_direct_scene`): emitter
    -> water (a delta BSDF, called directly) -> the diffuser (the rectangle's own
    intersection; the water only where it can lie in the way) -> camera.

    The general pass's steps with their choices fixed: the water vertex connects to nothing
    (its BSDF is a delta), no path can take a third vertex, and none of the steps draws a
    random number (the emitter's samples are its own), so it gives the same image without
    the sampler, the BSDF dispatch or the general intersection of the second segment.
    The water's hits and whether it lies in a ray's way come from ``geometry``
    (:class:`~mitsuba_wai.water_hit.WaterGeometry`: the water alone, the same answers), by
    default the scene's own.
    """
    import drjit as dr

    mi = mitsuba()
    sensor = scene.sensors()[0]
    width, height = (int(v) for v in sensor.film().crop_size())
    n = width * height * spp
    shapes = {shape.id(): shape for shape in scene.shapes()}
    water_bsdf, diffuser = shapes["water"].bsdf(), shapes["diffuser"]
    geometry = WaterGeometry.of(scene) if geometry is None else geometry
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    ray, throughput, length = emitter(sensor.shutter_open(), n, seed)
    active = dr.max(throughput) != 0.0
    slope = geometry.slope
    # The water's hit on its grid (mitsuba_wai.water_hit): the rays start past the diffuser,
    # the scene's only other shape, so the water's first hit is the scene's.
    si = geometry.intersect(ray, active)
    active = active & si.is_valid()
    if water is not None:
        length = length + dr.select(active, si.t, 0.0)
    bs, bsdf_val = water_bsdf.sample(ctx, si, 0.0, mi.Point2f(0.0), active)
    wi_dot_n = dr.dot(si.n, -ray.d)
    wo_world = si.to_world(bs.wo)
    wo_dot_n = dr.dot(si.n, wo_world)
    cos_wi, cos_wo = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(bs.wo)
    # Shading normals: no light leaks, and the adjoint correction (Veach, p. 155).
    active = active & (wi_dot_n * cos_wi > 0.0) & (wo_dot_n * cos_wo > 0.0)
    throughput = throughput * bsdf_val * dr.abs((cos_wi * wo_dot_n) / (cos_wo * wi_dot_n))
    active = active & dr.any(throughput != 0.0)
    ray = si.spawn_ray(wo_world)
    si = diffuser.ray_intersect(ray, mi.RayFlags.Minimal | mi.RayFlags.ShadingFrame, active)
    active = active & si.is_valid()
    # The water lies in the way only of rays flatter than its steepest facet (module notes).
    flat = -ray.d.z <= slope * dr.norm(mi.Vector2f(ray.d.x, ray.d.y))
    blocked = geometry.occluded(mi.Ray3f(ray.o, ray.d, si.t * (1.0 - 1e-4), ray.time,
                                         ray.wavelengths), active & flat)
    active = active & ~blocked
    if water is not None:
        length = length + dr.select(active, si.t, 0.0)
    sensor_ds, sensor_weight = (sensor if camera is None else camera).sample_direction(
        si, mi.Point2f(0.5), active)
    splat = _connect(scene, si, sensor_ds, diffuser.bsdf(), throughput * sensor_weight,
                     1.0 / spp_total, (width, height), ctx, active,
                     None if water is None else (water[0], water[1], length), False)
    dr.eval(*splat)
    return [splat]


def _connect(
    scene: Any, si: Any, sensor_ds: Any, bsdf: Any, weight: Any, scale: float,
    size: tuple[int, int], ctx: Any, active: Any, water: Any = None, shadow: bool = True,
) -> tuple[Any, ...]:
    """Mitsuba ptracer's ``connect_sensor`` for a surface vertex: the film pixel (``W * H``
    where nothing lands), the RGB value of the connection and the pixel of a non-finite value
    (``W * H`` where it is finite), as Dr.Jit arrays; with ``water`` (``(a, b, L)``: 1/mm per
    channel and the path's water length so far, mm) the direct value and the scattered one;
    ``shadow=False`` skips the shadow ray (nothing can lie between the vertex and the camera)."""
    import drjit as dr

    mi = mitsuba()
    width, height = size
    active = active & (sensor_ds.pdf > 0.0) & dr.any(weight != 0.0)
    sensor_ray = si.spawn_ray_to(sensor_ds.p)
    local_d = si.to_local(sensor_ray.d)
    wi_dot_n = dr.dot(si.n, si.to_world(si.wi))
    wo_dot_n = dr.dot(si.n, sensor_ray.d)
    cos_wi, cos_wo = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(local_d)
    valid = (wi_dot_n * cos_wi > 0.0) & (wo_dot_n * cos_wo > 0.0)
    correction = dr.select(valid, dr.abs((cos_wi * wo_dot_n) / (cos_wo * wi_dot_n)), 0.0)
    value = weight * correction * bsdf.eval(ctx, si, local_d, active) * scale
    # The shadow ray last, and only where light would arrive: a delta BSDF's vertex (the water,
    # the diffuser's pass-through) connects to nothing, and its test would be wasted work.
    active = active & dr.any(value != 0.0)
    if shadow:
        active = active & ~scene.ray_test(sensor_ray, active)
    # Box filter: a splat lands in the one pixel that contains it; the others go to an extra
    # pixel W * H, with value 0. A non-finite value (a degenerate connection) is zeroed and its
    # pixel reported in ``bad`` (Mitsuba's film would hold it as NaN / inf).
    pos = mi.Vector2i(dr.floor(sensor_ds.uv))
    inside = (pos.x >= 0) & (pos.y >= 0) & (pos.x < width) & (pos.y < height)
    active = active & inside
    finite = dr.all(dr.isfinite(value))
    none = mi.UInt32(width * height)
    pixel = dr.select(active, mi.UInt32(pos.y * width + pos.x), none)
    rgb = dr.select(active & finite, mi.Color3f(value), 0.0)
    bad = dr.select(active & ~finite, pixel, none)
    if water is None:
        return pixel, rgb, bad
    # The connection to the camera runs in the water too (the whole rig is submerged).
    a, b, length = water
    total = length + sensor_ds.dist
    kept = dr.exp(-mi.Color3f(a) * total)
    direct = dr.exp(-mi.Color3f(b) * total)
    return pixel, rgb * kept * direct, rgb * kept * (1.0 - direct), bad


@numba.njit(cache=True, nogil=True)
def _splat(total: NDArray, pixel: NDArray, r: NDArray, g: NDArray, b: NDArray,
           lit: NDArray) -> None:
    """Add each path's value (``r, g, b``: (n,) each) to ``total[pixel[i]]`` (W H + 1, 3),
    float64, in path order: :func:`numpy.bincount`'s sums, bit for bit (the same on every
    run), the lit channels ``lit`` (3,) in one pass."""
    for i in range(pixel.size):
        p = pixel[i]
        if lit[0]:
            total[p, 0] += np.float64(r[i])
        if lit[1]:
            total[p, 1] += np.float64(g[i])
        if lit[2]:
            total[p, 2] += np.float64(b[i])


def render_particles(
    scene: Any, spp: int, seed: int, max_depth: int, stratified: bool = False,
    emitter: Any = None, camera: Any = None, geometry: WaterGeometry | None = None,
) -> tuple[NDArray[np.float32], int]:
    """Render a particle-traced scene (see the module notes) to linear RGB (H, W, 3).

    Parameters
    ----------
    scene : mitsuba.Scene
        Loaded scene; its one sensor's film (box filter) is the image.
    spp : int
        Light paths per pixel, >= 1.
    seed : int
        Sampler seed, 0 .. 2^32 - 1; the same seed gives the same image, bit for bit.
    max_depth : int
        Longest path, as the ``ptracer``'s ``max_depth`` (2 .. 6).
    stratified : bool
        Emitter samples from :func:`emitter_samples` instead of the sampler (the same
        expectation, far less noise in the spots); False: Mitsuba's ``ptracer`` image.
    emitter : callable, optional
        Draws the particles in place of the scene's emitters and of ``stratified``,
        ``emitter(time, n, seed) -> (ray, weight, travelled_mm)``, its rays starting past
        ``emitter.skipped_vertices`` vertices of no effect, no shadow rays where
        ``emitter.camera_unoccluded`` (:class:`mitsuba_wai.dots.DotEmitter`:
        the projector's dots, each a stratified point set of its own); default: Mitsuba's
        ``Scene.sample_emitter_ray``.
    camera : mitsuba_wai.lens.CameraLens, optional
        The camera's principal point, distortion and port: each vertex connects through them
        (:meth:`~mitsuba_wai.lens.CameraLens.sample_direction`); default the scene's sensor.
    geometry : mitsuba_wai.water_hit.WaterGeometry, optional
        The water the direct pass asks (its hits, whether it is in a ray's way), when the
        scene's own is not up to date; default the scene's.

    Returns
    -------
    image : (H, W, 3) ndarray of float32
        The mean over paths (as ``mitsuba.render`` of the same scene with ``ptracer``).
    n_nonfinite : int
        Pixels that received a non-finite splat (rare degenerate camera connections): zeroed,
        as :func:`mitsuba_wai.render.render_image` does with Mitsuba's image.
    """
    images, n_bad = _render(scene, spp, seed, max_depth, None, stratified, emitter, camera,
                            geometry)
    return images[0], n_bad


def render_particles_water(
    scene: Any, spp: int, seed: int, max_depth: int, absorption_per_mm: NDArray,
    scattering_per_mm: NDArray, air_segments: int = 0, stratified: bool = False,
    emitter: Any = None, camera: Any = None, geometry: WaterGeometry | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32], int]:
    """:func:`render_particles` with Beer-Lambert weights along each path (module notes).

    Parameters
    ----------
    scene, spp, seed, max_depth, stratified, emitter, camera, geometry
        As :func:`render_particles`.
    absorption_per_mm, scattering_per_mm : (3,) array_like
        a and b per channel (R, G, B), 1/mm.
    air_segments : int
        Leading segments of each path that run in air (1 for light from the sky; 0 for the
        projector, which is under water).

    Returns
    -------
    direct : (H, W, 3) ndarray of float32
        Light that was neither absorbed nor scattered, ``exp(-(a + b) L)``.
    scattered : (H, W, 3) ndarray of float32
        Light scattered out of the beam but not absorbed, ``exp(-a L)(1 - exp(-b L))``.
    n_nonfinite : int
    """
    water = (
        [float(v) for v in absorption_per_mm], [float(v) for v in scattering_per_mm],
        int(air_segments),
    )
    images, n_bad = _render(scene, spp, seed, max_depth, water, stratified, emitter, camera,
                            geometry)
    return images[0], images[1], n_bad


def _render(
    scene: Any, spp: int, seed: int, max_depth: int, water: Any, stratified: bool,
    emitter: Any = None, camera: Any = None, geometry: WaterGeometry | None = None,
) -> tuple[list[NDArray[np.float32]], int]:
    """The images of :func:`render_particles` (one) or :func:`render_particles_water` (two)."""
    import drjit as dr

    if not 2 <= max_depth <= _RR_DEPTH + 1:
        raise ValueError(f"max_depth must be 2..{_RR_DEPTH + 1}, not {max_depth}")
    film = scene.sensors()[0].film()
    width, height = (int(v) for v in film.crop_size())
    n_pix = width * height
    n_images = 1 if water is None else 2
    if not scene.emitters():  # e.g. an overcast sky: no light, as Mitsuba's ptracer says
        return [np.zeros((height, width, 3), dtype=np.float32)] * n_images, 0
    # Pixel-major, as the image is laid out (no transposition at the end).
    totals = [np.zeros((n_pix + 1, 3)) for _ in range(n_images)]
    bad = np.zeros(n_pix + 1, dtype=bool)
    for k, spp_k in enumerate(pass_split(spp, n_pix)):
        pass_seed = (int(seed) + k * PASS_SEED_STRIDE) % 2**32
        for pixel, *rgbs, nonfinite in _trace_pass(scene, spp_k, spp, pass_seed, max_depth,
                                                   water, stratified, emitter, camera,
                                                   geometry):
            if dr.all(pixel == n_pix):  # a bounce that never reaches the camera (delta BSDFs)
                continue
            if not dr.all(nonfinite == n_pix):
                bad[np.asarray(nonfinite)] = True
            idx = np.asarray(pixel)
            for total, rgb in zip(totals, rgbs, strict=True):
                # Channel by channel: each a view of Dr.Jit's buffer (the Color3f as a whole
                # would be copied into one (3, n) array first).
                r, g, b = (np.asarray(rgb[c]) for c in range(3))
                # A channel that no light reaches adds nothing (a dot colour without it).
                _splat(total, idx, r, g, b, np.array([r.any(), g.any(), b.any()]))
    bad = bad[:n_pix]
    images = []
    for total in totals:
        total = total[:n_pix]
        total[bad] = 0.0
        images.append(total.reshape(height, width, 3).astype(np.float32))
    return images, int(bad.sum())
