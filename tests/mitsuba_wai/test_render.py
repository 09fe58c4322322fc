"""Rendering: physics visible in the images, and the render folder's contract."""

import json

import numpy as np
import pytest

from mitsuba_wai.mesh import flat_like
from mitsuba_wai.render import FrameRenderer, RenderSteps, render_folder
from mitsuba_wai.surface_sampling import wave_surface
from wai_core.errors import WaiInputError
from wai_core.geometry import refract
from wai_core.heightfield import Heightfield, load_heightfield
from wai_core.io import read_exr


@pytest.fixture(scope="module")
def flat_frame(small_cfg):
    grid = wave_surface(small_cfg)
    renderer = FrameRenderer(small_cfg, grid)
    return renderer.render(flat_like(grid, small_cfg.water.h0_mm), seed=1)


def test_view_goes_dark_at_the_edge_of_snells_window(small_cfg, flat_frame):
    # Geometry alone says which pixels look beyond the critical angle (TIR: no sky).
    cam = small_cfg.rig.camera_v
    _, d = cam.pixel_rays(*cam.pixel_grid())
    _, tir = refract(d, np.array([0, 0, 1.0]), small_cfg.water.n_water)
    lum = flat_frame["view"].mean(axis=2)
    inside = ~tir & (cam.pixel_grid()[0] < cam.width_px * 0.5)  # the object covers this part
    assert lum[tir].max() < 1e-6
    assert np.median(lum[inside]) > 0.05


def test_one_way_diffuser_lets_the_beam_through(small_cfg, flat_frame):
    # Spots whose flat-water path lands where the projector's upward beam crosses the diffuser
    # plane are still seen: the screen passes light from below and diffuses light from above.
    from wai_core.geometry import intersect_plane_z
    from wai_core.layout import flat_pattern_hits

    proj = small_cfg.rig.projector
    o, d = proj.pixel_rays(*proj.pixel_grid(20))
    beam, _ = intersect_plane_z(o, d.reshape(-1, 3), small_cfg.diffuser.z_mm)
    _, s, seen = flat_pattern_hits(small_cfg)
    inside_beam = seen & (s[:, 0] < np.nanmax(beam[:, 0]) - 20) & (np.abs(s[:, 1]) < 50)
    assert inside_beam.sum() > 10
    cam = small_cfg.rig.camera_s
    cols, rows, _ = cam.project(s[inside_beam])
    img = flat_frame["pattern"].sum(axis=2)
    at_spots = img[np.round(rows).astype(int), np.round(cols).astype(int)]
    # The adaptive pattern makes up for the weak (~2 %) Fresnel reflection of these steep rays.
    assert np.median(at_spots) > 0.2 * np.percentile(img, 99.9)


def test_render_folder_contract(small_cfg, tmp_path):
    out = tmp_path / "frame"
    record = render_folder(small_cfg, out, progress=False).record
    for name in ("pattern", "pattern_flat", "view", "view_truth"):
        img = read_exr(out / f"{name}.exr")
        assert img.shape == (small_cfg.camera_s.height_px, small_cfg.camera_s.width_px, 3)
        assert (out / f"{name}.png").is_file()
    assert (out / "heightfield.npz").is_file() and (out / "surface.ply").is_file()
    saved = json.loads((out / "scene.json").read_text())
    assert saved["seed"] == small_cfg.waves.seed and saved["variant"] == record["variant"]
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())


def _tiny_folder_parts():
    surface = Heightfield(np.linspace(0, 10, 5), np.linspace(0, 10, 5), np.full((5, 5), 150.0))
    return surface, {"view": np.full((4, 6, 3), 0.5, np.float32)}


def test_render_steps_time_each_step_and_write_the_folder(tmp_path):
    surface, images = _tiny_folder_parts()
    out = tmp_path / "frame"
    with RenderSteps(out, ("surface", "render", "write"), "test", progress=False) as steps:
        with steps("surface"):
            steps.check_output()
        with steps("render"):
            sum(range(10**5))
        steps.write({"format": "test"}, images, surface, {"view": 0}, view_gain=1.0)
    saved = json.loads((out / "scene.json").read_text())
    assert list(saved["timings_s"]) == ["surface", "render", "write"]
    assert all(s >= 0 for s in saved["timings_s"].values())
    assert saved["format"] == "test" and saved["nonfinite_pixels_zeroed"] == {"view": 0}
    assert np.array_equal(read_exr(out / "view.exr"), images["view"])
    assert np.array_equal(load_heightfield(out / "heightfield.npz").z, surface.z)


def test_render_steps_leave_nothing_when_the_write_fails(tmp_path, monkeypatch):
    from mitsuba_wai import render

    def fail(folder, surface):
        raise OSError("disk full")

    monkeypatch.setattr(render, "write_surface", fail)
    surface, images = _tiny_folder_parts()
    with pytest.raises(OSError, match="disk full"), RenderSteps(
        tmp_path / "frame", ("write",), "test", progress=False
    ) as steps:
        steps.write({}, images, surface, {}, view_gain=1.0)
    assert list(tmp_path.iterdir()) == []


def test_heightfield_not_covering_the_patch_leaves_nothing(small_cfg, tmp_path):
    x = np.linspace(0, 100, 11)
    y = np.linspace(-20, 20, 5)
    small = Heightfield(x, y, np.full((5, 11), 150.0))
    with pytest.raises(WaiInputError, match="observed patch"):
        render_folder(small_cfg, tmp_path / "frame", heightfield=small, progress=False)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
@pytest.mark.parametrize("system", ["S", "V"])
def test_water_interface_has_the_expectation_of_mitsubas_dielectric(small_cfg, system):
    # Same scene, Mitsuba's own stochastic dielectric at many spp vs the one-branch interface:
    # mean images agree (the dropped branch contributes nothing in these scenes).
    from mitsuba_wai import scenes
    from mitsuba_wai.mesh import heightfield_mesh, to_mitsuba
    from mitsuba_wai.textures import object_texture
    from mitsuba_wai.variant import mitsuba

    mi = mitsuba()
    grid = wave_surface(small_cfg)
    tm = heightfield_mesh(grid)
    dielectric = {"type": "dielectric", "int_ior": small_cfg.water.n_water, "ext_ior": 1.0}
    images = []
    for bsdf in (dielectric, scenes.water_bsdf(small_cfg, system)):
        water = to_mitsuba(tm, "water", bsdf)
        if system == "S":
            scene = scenes.pattern_scene(small_cfg, water)
        else:
            scene = scenes.view_scene(small_cfg, water, object_texture(small_cfg.object))
        img = np.asarray(mi.render(mi.load_dict(scene), spp=256, seed=2))
        images.append(np.nan_to_num(img, nan=0.0, posinf=0.0).sum(axis=2))
    ref, ours = images
    assert ours.sum() == pytest.approx(ref.sum(), rel=0.03)
    # Pixel by pixel, on 4x4 blocks to average the reference's noise down.
    h, w = (s - s % 4 for s in ref.shape)
    blk = [a[:h, :w].reshape(h // 4, 4, w // 4, 4).mean(axis=(1, 3)) for a in (ref, ours)]
    lit = blk[0] > 0.2 * np.percentile(blk[0], 99)
    assert lit.sum() > 20
    assert np.nanmedian(np.abs(blk[1][lit] / blk[0][lit] - 1)) < 0.1


def test_stratified_view_is_less_noisy_than_independent(small_cfg):
    # Multi-jittered pixel samples against independent ones, both at 4 spp, measured against a
    # 64-spp render: the board's edges converge faster (at 800 x 600, 4 multi-jittered spp
    # beat 16 independent ones; docs/results.md).
    surface = wave_surface(small_cfg)
    error = {}
    reference = None
    for sampling in ("independent", "stratified"):
        renderer = FrameRenderer(small_cfg.replace("render", sampling=sampling), surface,
                                 systems=("view",))
        if reference is None:
            reference = renderer.render(surface, 99, ("view",), spp=64)["view"]
        view = renderer.render(surface, 5, ("view",), spp=4)["view"]
        error[sampling] = np.sqrt(np.mean((view - reference) ** 2))
    assert error["stratified"] < 0.7 * error["independent"]


def test_flat_water_renders_on_a_plane_as_on_the_wave_mesh(small_cfg):
    # Flat water is one plane whatever mesh carries it: the renderer's plane of 4 x 4 vertices
    # gives the images the wave grid's own flat mesh gives, to the rounding of the hit points
    # (a sample near a checker edge or a pixel border may fall the other side).
    grid = wave_surface(small_cfg)
    flat = flat_like(grid, small_cfg.water.h0_mm)
    renderer = FrameRenderer(small_cfg, grid)
    on_plane = renderer.render(flat, seed=3)
    on_mesh = FrameRenderer(small_cfg, grid, flat_only=True).render(flat, seed=3)
    assert renderer.flat is not None and renderer.flat.grid.z.size == 16
    for key in ("pattern", "view"):
        a, b = on_plane[key], on_mesh[key]
        assert abs(a.mean() / b.mean() - 1) < 1e-3
        moved = np.abs(a - b).max(axis=-1) > 1e-3 * b.max()
        assert moved.mean() < 0.01, key
    # The wave mesh was left as it was: a wavy render after the flat one is the same image.
    wavy = renderer.render(grid, seed=4)
    again = FrameRenderer(small_cfg, grid).render(grid, seed=4)
    for key in ("pattern", "view"):
        np.testing.assert_array_equal(wavy[key], again[key])
