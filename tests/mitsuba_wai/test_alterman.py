"""Rendering the sun sensor: spots where geometry puts them, radiometry as Mitsuba's own
dielectric, the same image from either sun beam, and the render folder's contract.

A small sensor keeps renders well under a second: camera a at 400 x 300 with holes and pitch
twice the paper scene's (spots stay ~2.3 px wide), camera v 4x smaller.
"""

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mitsuba_wai.alterman import (
    SunRenderer,
    alterman_surface,
    plate_mesh,
    render_alterman_folder,
    sun_scene,
)
from mitsuba_wai.mesh import flat_like
from restoration.features import detect_spots
from tests.conftest import ROOT, shrink
from wai_core.alterman import AltermanSystem, chief_rays, load_alterman, sensor_layout
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield
from wai_core.io import read_exr

SENSOR = ROOT / "scenes" / "alterman.toml"


@pytest.fixture(scope="module")
def small():
    loaded = load_alterman(SENSOR)
    sensor = (
        loaded.sensor.replace("camera_a", width_px=400, height_px=300)
        .replace("plate", pitch_mm=18.0, hole_mm=2.4)
        .replace("sun", zenith_deg=30.0)
    )
    return AltermanSystem(shrink(loaded.base), sensor)


def _waves(h0):
    x, y = np.linspace(-150.0, 700.0, 171), np.linspace(-350.0, 350.0, 141)
    xx, yy = np.meshgrid(x, y)
    # Slopes up to 0.15, as the paper's sea (0.18 at most).
    return Heightfield(x, y, h0 + 6.0 * np.sin(xx / 40.0) * np.cos(yy / 50.0))


@pytest.fixture(scope="module")
def rendered(small):
    """Flat and wavy sun-spot images of the small sensor (one loaded scene)."""
    surface = alterman_surface(small, _waves(small.base.water.h0_mm))
    renderer = SunRenderer(small, surface)
    flat = flat_like(surface, small.base.water.h0_mm)
    return {
        "surface": surface,
        "flat": renderer.render(flat, seed=3),
        "wavy": renderer.render(surface, seed=4),
    }


def _centre_errors(img, expected_px):
    """Offsets (K, 2) px from each expected centre to the nearest detected spot."""
    centres = detect_spots(img).centres_px
    dist, idx = cKDTree(centres).query(expected_px)
    assert dist.max() < 1.0, "a spot is missing"
    return centres[idx] - expected_px


def test_flat_water_spots_are_where_snells_law_puts_them(small, rendered):
    lay = sensor_layout(small)
    px, seen = lay.flat_spots_px()
    assert seen.all()
    err = _centre_errors(rendered["flat"], px)
    assert np.abs(err.mean(axis=0)).max() < 0.02  # no bias
    assert np.sqrt(np.mean(err**2)) < 0.1  # photon noise only
    assert len(detect_spots(rendered["flat"])) == len(lay.ij)  # no stray light


def test_wavy_spots_follow_the_geometric_chief_rays(small, rendered):
    lay = sensor_layout(small)
    rays = chief_rays(lay, rendered["surface"])
    cols, rows, _ = lay.camera.project(rays.spots_mm)
    err = _centre_errors(rendered["wavy"], np.stack([cols, rows], axis=1))
    assert np.abs(err.mean(axis=0)).max() < 0.02
    assert np.sqrt(np.mean(err**2)) < 0.1
    # ... while the flat-water places are off by several times that: the waves moved them.
    off = _centre_errors(rendered["wavy"], lay.flat_spots_px()[0])
    assert np.sqrt(np.mean(off**2)) > 4 * np.sqrt(np.mean(err**2))


def _render_with(system, surface, water_bsdf, spp, seed):
    from mitsuba_wai.mesh import heightfield_mesh, to_mitsuba
    from mitsuba_wai.variant import mitsuba

    mi = mitsuba()
    water = to_mitsuba(heightfield_mesh(surface), "water", water_bsdf)
    scene = mi.load_dict(sun_scene(system, sensor_layout(system), water))
    return np.asarray(mi.render(scene, spp=spp, seed=seed))[..., :3]


def test_one_branch_interface_carries_the_flux_of_mitsubas_dielectric(small, rendered):
    # Particle tracing is importance transport: the interface must weigh a refraction by 1 - F
    # without the eta^2 of radiance transport, as Mitsuba's stochastic dielectric does.
    flat = flat_like(rendered["surface"], small.base.water.h0_mm)
    n = small.base.water.n_water
    ref = _render_with(small, flat, {"type": "dielectric", "int_ior": n, "ext_ior": 1.0}, 32, 5)
    assert rendered["flat"].sum() == pytest.approx(ref.sum(), rel=0.01)


def test_full_beam_gives_the_same_spots(small, rendered):
    full = AltermanSystem(small.base, small.sensor.replace("render", beam="full", spp=32))
    img = SunRenderer(full, rendered["surface"]).render(
        flat_like(rendered["surface"], small.base.water.h0_mm), seed=6
    )
    assert img.sum() == pytest.approx(rendered["flat"].sum(), rel=0.03)
    err = _centre_errors(img, sensor_layout(small).flat_spots_px()[0])
    assert np.sqrt(np.mean(err**2)) < 0.15


def test_plate_has_one_open_hole_per_pinhole(small):
    lay = sensor_layout(small)
    plate = plate_mesh(lay)
    rect = lay.plate_rect_mm
    solid = np.prod(rect[:, 1] - rect[:, 0]) - len(lay.ij) * lay.hole_mm**2
    assert plate.area == pytest.approx(solid, rel=1e-9)
    assert np.all(plate.face_normals[:, 2] > 0.999)  # faces up, towards the sun
    assert np.allclose(plate.vertices[:, 2], lay.plate_z_mm)


def test_overcast_folder_is_dark_and_complete(small, tmp_path):
    overcast = AltermanSystem(small.base, small.sensor.replace("sun", enabled=False))
    out = tmp_path / "frame"
    record = render_alterman_folder(overcast, out, heightfield=_waves(150.0), progress=False).record
    for name in ("sunspots", "sunspots_flat", "view", "view_truth"):
        assert (out / f"{name}.exr").is_file() and (out / f"{name}.png").is_file()
    assert read_exr(out / "sunspots.exr").max() == 0.0
    assert read_exr(out / "view.exr").shape == (150, 200, 3)
    saved = json.loads((out / "scene.json").read_text())
    assert saved["alterman"]["sun"]["enabled"] is False and saved["method"] == "alterman"
    assert saved["seed"] == small.base.waves.seed and saved["variant"] == record["variant"]
    assert (out / "heightfield.npz").is_file() and (out / "surface.ply").is_file()
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())


def test_surface_down_to_the_plate_is_refused(small, tmp_path):
    deep = _waves(small.base.water.h0_mm)
    deep = Heightfield(deep.x, deep.y, deep.z - small.sensor.plate.depth_mm)
    with pytest.raises(WaiInputError, match="plate"):
        render_alterman_folder(small, tmp_path / "frame", heightfield=deep, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_sun_spots_are_mitsubas_ptracer_image_and_bit_reproducible(small):
    # The renderer's deterministic particle tracer against Mitsuba's ptracer on the loaded
    # scene: the same random numbers, so equal up to the order of the additions.
    from mitsuba_wai.alterman import SCENE_A_DEPTH
    from mitsuba_wai.particles import render_particles
    from mitsuba_wai.variant import mitsuba

    renderer = SunRenderer(small, alterman_surface(small, _waves(small.base.water.h0_mm)))
    scene = renderer._scene
    ours, _ = render_particles(scene, 2, 9, SCENE_A_DEPTH)
    again, _ = render_particles(scene, 2, 9, SCENE_A_DEPTH)
    assert ours.tobytes() == again.tobytes()
    ref = np.asarray(mitsuba().render(scene, spp=2, seed=9), dtype=np.float32)[..., :3]
    finite = np.isfinite(ref).all(axis=2)
    assert ours.sum() > 0
    assert np.abs(ours[finite] - ref[finite]).max() <= 1e-5 * ref[finite].max()
