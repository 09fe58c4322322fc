"""The deterministic particle tracer: Mitsuba's ptracer's image, the same bits on every run, any
number of samples (passes)."""

import numpy as np
import pytest

from mitsuba_wai import particles
from mitsuba_wai import render as render_mod
from mitsuba_wai.particles import pass_split, render_particles
from mitsuba_wai.render import FrameRenderer, render_image
from mitsuba_wai.scenes import SCENE_S_DEPTH
from mitsuba_wai.surface_sampling import wave_surface
from tests.conftest import shrink


@pytest.fixture(scope="module")
def tiny(paper_cfg):
    cfg = shrink(paper_cfg, factor=8, spp=2)
    return cfg, FrameRenderer(cfg, wave_surface(cfg))


@pytest.mark.parametrize(
    "spp, pixels, limit, expected",
    [(8, 100, 10_000, [8]), (7, 100, 300, [3, 2, 2]), (5, 100, 50, [1, 1, 1, 1, 1]),
     (9, 480_000, 2**32 - 1, [9]), (8951, 480_000, 2**32 - 1, [4476, 4475])],
)
def test_pass_split(spp, pixels, limit, expected):
    split = pass_split(spp, pixels, limit)
    assert split == expected and sum(split) == spp
    assert all(s * pixels <= limit for s in split) or split == [1] * spp


def test_pattern_is_mitsubas_ptracer_image_and_bit_reproducible(tiny):
    from mitsuba_wai.variant import mitsuba

    cfg, renderer = tiny
    scene = renderer.scene("pattern")
    ours, bad = render_particles(scene, 4, 123, SCENE_S_DEPTH)
    again, _ = render_particles(scene, 4, 123, SCENE_S_DEPTH)
    assert ours.tobytes() == again.tobytes()
    # Same random numbers as Mitsuba's ptracer: equal up to the order of the additions.
    ref = np.asarray(mitsuba().render(scene, spp=4, seed=123), dtype=np.float32)[..., :3]
    finite = np.isfinite(ref).all(axis=2)
    assert bad == int((~finite).sum())
    assert ours.sum() > 0
    assert np.abs(ours[finite] - ref[finite]).max() <= 1e-5 * ref[finite].max()
    other, _ = render_particles(scene, 4, 124, SCENE_S_DEPTH)
    assert other.tobytes() != ours.tobytes()


def test_passes_keep_the_expectation(tiny, monkeypatch):
    cfg, renderer = tiny
    scene = renderer.scene("pattern")
    pixels = cfg.camera_s.width_px * cfg.camera_s.height_px
    one, _ = render_particles(scene, 12, 5, SCENE_S_DEPTH)
    monkeypatch.setattr(particles, "MAX_PASS_SAMPLES", 5 * pixels)  # passes of 4 spp
    split, _ = render_particles(scene, 12, 5, SCENE_S_DEPTH)
    again, _ = render_particles(scene, 12, 5, SCENE_S_DEPTH)
    assert split.tobytes() == again.tobytes() and split.tobytes() != one.tobytes()
    assert split.sum() == pytest.approx(one.sum(), rel=0.05)


def test_view_in_passes_beyond_the_wavefront_limit(tiny, monkeypatch):
    # Mitsuba refuses a wavefront over 2^32 samples whose spp its own split does not divide;
    # render_image splits first. Shown with the limit lowered to 3 spp of this film.
    cfg, renderer = tiny
    scene = renderer.scene("view")
    pixels = cfg.camera_v.width_px * cfg.camera_v.height_px
    single, _ = render_image(scene, 7, 3)
    monkeypatch.setattr(render_mod, "MAX_WAVEFRONT", 3 * pixels)
    split, bad = render_image(scene, 7, 3)
    assert bad == 0 and split.dtype == np.float32
    assert split.mean() == pytest.approx(single.mean(), rel=0.05)
    assert render_image(scene, 7, 3)[0].tobytes() == split.tobytes()


def test_no_emitter_gives_black(tiny):
    from mitsuba_wai.variant import mitsuba

    cfg, _ = tiny
    mi = mitsuba()
    from mitsuba_wai.scenes import sensor_dict

    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "ptracer", "max_depth": 3},
        "sensor": sensor_dict(cfg.rig.camera_s),
    })
    img, bad = render_particles(scene, 2, 0, 3)
    assert bad == 0 and img.shape == (cfg.camera_s.height_px, cfg.camera_s.width_px, 3)
    assert not img.any()


def test_stratified_emitter_samples_fill_every_cell_evenly():
    # A shifted Kronecker sequence: each of 32 x 32 cells holds n / 1024 points within a few,
    # where independent points would scatter by sqrt(n / 1024) = 8 around the mean.
    from mitsuba_wai.variant import select_variant

    select_variant()
    n = 1 << 16
    select, position = particles.emitter_samples(n, seed=3)
    u = np.stack([np.asarray(position.x), np.asarray(position.y)], axis=1)
    assert ((u >= 0) & (u < 1)).all()
    counts = np.histogram2d(u[:, 0], u[:, 1], bins=32, range=[[0, 1], [0, 1]])[0]
    assert np.abs(counts - n / 1024).max() <= 4
    halves = np.histogram(np.asarray(select), bins=2, range=(0, 1))[0]
    assert np.abs(halves - n / 2).max() <= 2
    _, other = particles.emitter_samples(n, seed=4)
    assert not np.array_equal(np.asarray(other.x), u[:, 0])


def _blocks(image, b=8):
    h, w = (n // b * b for n in image.shape[:2])
    return image[:h, :w].sum(axis=2).reshape(h // b, b, w // b, b).sum(axis=(1, 3))


def test_stratified_particles_keep_the_image_and_cut_its_noise(tiny):
    # Same expectation as Mitsuba's independent sampling (total flux), less noise where a spot
    # gathers its light (8 x 8 pixel sums; measured ~0.35x): the difference between two seeds'
    # images is what a frame's spot centres inherit.
    _, renderer = tiny
    scene = renderer.scene("pattern")
    img = {s: [render_particles(scene, 4, seed, SCENE_S_DEPTH, stratified=s)[0]
               for seed in (11, 12)] for s in (False, True)}
    again = render_particles(scene, 4, 11, SCENE_S_DEPTH, stratified=True)[0]
    assert img[True][0].tobytes() == again.tobytes()
    flux = {s: np.mean([i.sum() for i in v]) for s, v in img.items()}
    assert flux[True] == pytest.approx(flux[False], rel=0.01)
    noise = {s: np.sqrt(np.mean((_blocks(v[0]) - _blocks(v[1])) ** 2)) for s, v in img.items()}
    assert noise[True] < 0.5 * noise[False]


@pytest.mark.parametrize("stratified", [False, True])
def test_a_new_seed_reuses_the_compiled_kernels(tiny, stratified):
    # A frame's seed must enter the kernels as a parameter: a literal would make Dr.Jit compile
    # the whole path kernel again for every frame (measured: 0.8 s of a 1.8 s pattern frame).
    import drjit as dr

    _, renderer = tiny
    scene = renderer.scene("pattern")
    render_particles(scene, 2, 21, SCENE_S_DEPTH, stratified=stratified)
    dr.kernel_history()  # clears the history
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        render_particles(scene, 2, 22, SCENE_S_DEPTH, stratified=stratified)
        compiled = [k for k in dr.kernel_history()
                    if k["type"] == dr.KernelType.JIT and not k["cache_hit"]]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert compiled == []


@pytest.mark.parametrize("code", ["none", "colour"])
def test_dots_drawn_directly_are_the_projectors_emission(paper_cfg, code):
    # The dot emitter must give the projector's emission (the same bitmap of Gaussian dots):
    # the same flux per channel, and spots where the geometric model's chief rays land, no
    # farther than Mitsuba's projector puts them (whose rays also carry the pass-through's
    # spawn offset, ~0.03 mm, that the dots skip).
    from mitsuba_wai.dots import DotEmitter
    from wai.experiments.validate import spot_agreement

    cfg = paper_cfg.replace("pattern", code=code)
    surface = wave_surface(cfg)
    renderer = FrameRenderer(cfg, surface, systems=("pattern",))
    renderer._set_surface(surface)
    scene = renderer.scene("pattern")
    ref, _ = render_particles(scene, 4, 3, SCENE_S_DEPTH, stratified=True)
    dots, bad = render_particles(scene, 4, 3, SCENE_S_DEPTH, emitter=DotEmitter(cfg))
    assert bad == 0
    flux_ref, flux = ref.sum(axis=(0, 1)), dots.sum(axis=(0, 1))
    assert flux[1:] == pytest.approx(flux_ref[1:], rel=0.01)
    ours, theirs = (spot_agreement(cfg, surface, img) for img in (dots, ref))
    assert ours["n_found"] >= theirs["n_found"] - 3
    assert ours["median_px"] <= theirs["median_px"] + 0.003
    assert ours["p95_px"] <= theirs["p95_px"] + 0.02
    again, _ = render_particles(scene, 4, 3, SCENE_S_DEPTH, emitter=DotEmitter(cfg))
    assert again.tobytes() == dots.tobytes()


def test_dot_emitter_gives_every_dot_its_share(paper_cfg):
    # Systematic sampling: each dot's particle count is within one of n p_j, p_j its share
    # (counted here by the nearest dot direction, which a rare far tail can cross; independent
    # draws would scatter by sqrt(n p_j) ~ 14).
    import drjit as dr

    from mitsuba_wai.dots import DotEmitter
    from mitsuba_wai.variant import select_variant
    from wai_core.layout import dot_weights

    select_variant()
    emitter = DotEmitter(paper_cfg)
    w = emitter.share
    assert w.shape == (int((dot_weights(paper_cfg) > 0).sum()),) and w.sum() == pytest.approx(1)
    n = 200_000
    ray, weight, travelled = emitter(0.0, n, seed=9)
    dr.eval(ray.d, weight, travelled)
    d = np.asarray(ray.d)
    assert np.allclose(np.linalg.norm(d, axis=0), 1.0, atol=1e-5)
    # Every ray starts on the diffuser plane, its distance travelled from the projector.
    o, t = np.asarray(ray.o), np.asarray(travelled)
    assert np.allclose(o[2], paper_cfg.diffuser.z_mm, atol=2e-3)
    centre = paper_cfg.rig.projector.pose.center_lab_mm
    assert np.allclose(np.linalg.norm(o.T - centre, axis=1), t, rtol=1e-5)
    # Count particles per dot by their nearest dot direction.
    _, panel = paper_cfg.rig.dot_grid
    _, dirs = paper_cfg.rig.projector.pixel_rays(panel[:, 0], panel[:, 1])
    dirs = dirs[dot_weights(paper_cfg) > 0]
    nearest = np.argmax(d.T @ dirs.T, axis=1)
    counts = np.bincount(nearest, minlength=len(w))
    assert np.abs(counts - n * w).max() <= 2.0


def test_no_shadow_rays_needed_between_diffuser_and_camera(tiny, monkeypatch):
    # The dot emitter lets the tracer skip shadow rays: in system S nothing lies between the
    # diffuser and camera s. Casting them must change no bit of the general tracer's image.
    from mitsuba_wai import particles
    from mitsuba_wai.dots import DotEmitter

    cfg, renderer = tiny
    scene = renderer.scene("pattern")
    emitter = DotEmitter(cfg)
    monkeypatch.setattr(particles, "_direct_scene", lambda *args: False)
    fast, _ = render_particles(scene, 4, 8, SCENE_S_DEPTH, emitter=emitter)
    emitter.camera_unoccluded = False
    checked, _ = render_particles(scene, 4, 8, SCENE_S_DEPTH, emitter=emitter)
    assert fast.sum() > 0 and fast.tobytes() == checked.tobytes()


def test_two_vertex_tracer_gives_the_general_tracers_image(tiny, monkeypatch):
    # System S's direct tracer follows the same particles: the same flux, and each lands
    # where the general tracer puts it (the diffuser's own intersection rounds differently,
    # so a splat within float rounding of a pixel border may take the neighbour pixel; the
    # water's hit on its grid keeps the particle that meets a facet edge exactly, which may
    # slip through Embree's triangles, one in some 10^4 here).
    from mitsuba_wai import particles
    from mitsuba_wai.dots import DotEmitter

    cfg, renderer = tiny
    scene = renderer.scene("pattern")
    emitter = DotEmitter(cfg)
    assert particles._direct_scene(scene, SCENE_S_DEPTH, emitter)
    direct, _ = render_particles(scene, 4, 8, SCENE_S_DEPTH, emitter=emitter)
    monkeypatch.setattr(particles, "_direct_scene", lambda *args: False)
    general, _ = render_particles(scene, 4, 8, SCENE_S_DEPTH, emitter=emitter)
    assert direct.sum() == pytest.approx(general.sum(), rel=1e-4) and direct.sum() > 0
    moved = np.abs(direct - general).sum() / general.sum()
    assert moved < 1e-4
    h, w = direct.shape[:2]
    yy, xx = np.mgrid[:h, :w]
    for img in (direct, general):
        lum = img.sum(axis=2)
        centroid = (lum * xx).sum() / lum.sum(), (lum * yy).sum() / lum.sum()
        if img is direct:
            first = centroid
    assert np.allclose(first, centroid, atol=1e-3)


def test_splat_sums_as_bincount():
    # The compiled splat adds in path order in float64, as numpy.bincount does: the same bits;
    # an unlit channel stays zero.
    rng = np.random.default_rng(5)
    n_pix = 50
    pixel = rng.integers(0, n_pix + 1, 20000).astype(np.uint32)
    values = rng.normal(size=(3, pixel.size)).astype(np.float32) * 1e-3
    total = np.zeros((n_pix + 1, 3))
    particles._splat(total, pixel, *values, np.array([True, False, True]))
    for c in (0, 2):
        expected = np.bincount(pixel, weights=values[c], minlength=n_pix + 1)
        assert total[:, c].tobytes() == expected.tobytes()
    assert not total[:, 1].any()
