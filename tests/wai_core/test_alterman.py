"""The sun sensor's configuration and geometry, checked against Snell's law worked by hand."""

import dataclasses

import numpy as np
import pytest

from tests.conftest import ROOT
from wai_core.alterman import (
    AltermanConfig,
    AltermanSystem,
    alterman_from_dict,
    chief_rays,
    load_alterman,
    sensor_layout,
    spot_shift_mm_per_rad,
)
from wai_core.errors import WaiInputError
from wai_core.geometry import critical_angle_rad
from wai_core.heightfield import Heightfield
from wai_core.layout import observed_patch

SENSOR = ROOT / "scenes" / "alterman.toml"


@pytest.fixture(scope="module")
def system():
    return load_alterman(SENSOR)


def _at(system, zenith, azimuth=0.0):
    sensor = system.sensor.replace("sun", zenith_deg=zenith, azimuth_deg=azimuth)
    return AltermanSystem(system.base, sensor)


def test_scene_file_shares_the_paper_system(system, paper_cfg):
    assert system.base == paper_cfg
    assert system.sensor.camera_a.width_px == 800 and system.sensor.camera_a.height_px == 600
    assert system.sensor.sun.enabled


@pytest.mark.parametrize(
    "section, key, value, needle",
    [
        ("sun", "zenith_deg", 95.0, "zenith_deg"),
        ("sun", "enabled", "yes", "enabled"),
        ("plate", "pitch_mm", 2.0, "pitch_mm"),
        ("screen", "gap_mm", 0.0, "gap_mm"),
        ("render", "beam", "wide", "beam"),
        ("plate", "holes", 3, "holes"),
    ],
)
def test_bad_sensor_values_are_named(section, key, value, needle):
    data = AltermanConfig().to_dict()
    data[section][key] = value
    with pytest.raises(WaiInputError, match=needle):
        alterman_from_dict(data)


def test_missing_base_is_named(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(SENSOR.read_text().replace("[base]", "[nobase]"))
    with pytest.raises(WaiInputError, match="base"):
        load_alterman(path)


@pytest.mark.parametrize("zenith, azimuth", [(0.0, 0.0), (40.0, 30.0), (75.0, -120.0)])
def test_flat_water_path_is_snells_law_by_hand(system, zenith, azimuth):
    lay = sensor_layout(_at(system, zenith, azimuth))
    n = system.base.water.n_water
    th_w = np.arcsin(np.sin(np.radians(zenith)) / n)
    away = -np.array([np.cos(np.radians(azimuth)), np.sin(np.radians(azimuth))])
    depth, gap = system.sensor.plate.depth_mm, system.sensor.screen.gap_mm
    # Sample on z = h0 -> pinhole: depth tan(theta_w) away from the sun; pinhole -> spot: gap.
    step = lay.pinholes_mm - lay.samples_mm
    assert np.allclose(step[:, :2], depth * np.tan(th_w) * away, atol=1e-9)
    assert np.allclose(step[:, 2], -depth)
    spot = lay.flat_spots_mm - lay.pinholes_mm
    assert np.allclose(spot[:, :2], gap * np.tan(th_w) * away, atol=1e-9)
    assert np.allclose(lay.samples_mm[:, 2], system.base.water.h0_mm)


def test_samples_are_a_square_grid_inside_the_observed_patch(system):
    lay = sensor_layout(system)
    patch = observed_patch(system.base, margin_mm=0.0)
    xy, p = lay.samples_mm[:, :2], system.sensor.plate.pitch_mm
    assert np.all((xy >= patch[:, 0] - 1e-9) & (xy <= patch[:, 1] + 1e-9))
    assert np.all(xy.max(axis=0) - xy.min(axis=0) > (patch[:, 1] - patch[:, 0]) - p)
    assert np.allclose((xy - xy[0]) / p, lay.ij - lay.ij[0], atol=1e-9)
    assert np.array_equal(lay.index_of(lay.ij[::7]), np.arange(len(lay.ij))[::7])


@pytest.mark.parametrize("zenith", [0.0, 75.0])
def test_camera_sees_every_flat_spot_and_the_plate_shades_the_screen(system, zenith):
    lay = sensor_layout(_at(system, zenith))
    _, seen = lay.flat_spots_px()
    assert seen.all()
    # Sunlight in water is never steeper than the critical angle: the plate must overhang the
    # screen by at least gap tan(theta_c).
    overhang = system.sensor.screen.gap_mm * np.tan(critical_angle_rad(lay.n_water))
    assert np.all(lay.plate_rect_mm[:, 0] <= lay.screen_rect_mm[:, 0] - overhang)
    assert np.all(lay.plate_rect_mm[:, 1] >= lay.screen_rect_mm[:, 1] + overhang)
    # Camera a looks straight up from below the screen.
    assert np.allclose(lay.camera.pose.axis_lab, [0, 0, 1])
    assert lay.camera.pose.center_lab_mm[2] < lay.screen_z_mm


def test_chief_rays_through_a_tilted_plane_follow_snell_in_its_plane(system):
    # A plane rising by alpha towards +x (the sun's side) has its normal tilted by alpha away
    # from the sun: in the plane of incidence the sun meets it at theta + alpha and goes on at
    # asin(sin(theta + alpha) / n) from the normal, i.e. that minus alpha from the vertical,
    # towards -x.
    theta, alpha = np.radians(45.0), 0.08
    sys45 = _at(system, 45.0)
    lay = sensor_layout(sys45)
    x, y = np.linspace(-100, 600, 71), np.linspace(-300, 300, 61)
    h0 = system.base.water.h0_mm
    plane = Heightfield(x, y, h0 + np.tan(alpha) * (x[None, :] - 200.0) + 0 * y[:, None])
    rays = chief_rays(lay, plane)
    assert rays.ok.all()
    tilt = np.arcsin(np.sin(theta + alpha) / system.base.water.n_water) - alpha
    expect = np.array([-np.sin(tilt), 0.0, -np.cos(tilt)])
    assert np.allclose(rays.water_dirs, expect, atol=1e-9)
    assert np.allclose(rays.normals, [-np.sin(alpha), 0, np.cos(alpha)], atol=1e-9)
    # Each chief ray starts on the plane and passes through its pinhole.
    q = rays.surface_mm
    assert np.allclose(q[:, 2], plane.height(q[:, 0], q[:, 1]), atol=1e-9)
    back = lay.pinholes_mm - q
    assert np.allclose(np.cross(back, rays.water_dirs), 0.0, atol=1e-7)


def test_flat_chief_rays_are_the_layout(system):
    lay = sensor_layout(system)
    x, y = np.linspace(0, 500, 6), np.linspace(-250, 250, 6)
    flat = Heightfield(x, y, np.full((6, 6), system.base.water.h0_mm))
    rays = chief_rays(lay, flat)
    assert np.allclose(rays.surface_mm, lay.samples_mm, atol=1e-9)
    assert np.allclose(rays.spots_mm, lay.flat_spots_mm, atol=1e-9)


def test_config_round_trips_through_a_dict(system):
    again = alterman_from_dict(system.sensor.to_dict())
    assert again == system.sensor
    assert dataclasses.replace(again.sun, enabled=False) != system.sensor.sun


def test_gain_at_a_high_sun_is_gap_times_one_minus_one_over_n(system):
    # Sun at the zenith, surface tilted by d: the light leaves at d - asin(sin d / n) ~
    # d (1 - 1/n) from the vertical, so the spot moves gap (1 - 1/n) per radian.
    n, gap = system.base.water.n_water, system.sensor.screen.gap_mm
    assert spot_shift_mm_per_rad(sensor_layout(_at(system, 0.0))) == pytest.approx(
        gap * (1 - 1 / n), rel=1e-6
    )
    assert spot_shift_mm_per_rad(sensor_layout(_at(system, 75.0))) > 5 * gap * (1 - 1 / n)
