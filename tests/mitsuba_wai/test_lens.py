"""Real cameras in the renders: distortion, principal offset and port, traced per ray.

The facts: where the numpy model (checked against OpenCV in tests/wai_core/test_lens.py) says a
ray goes, radiance is unchanged by distortion (a uniformly bright surface stays uniform), and a
port passes the Fresnel transmittance of its two faces over n_water^2 (written out here)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy import ndimage

from mitsuba_wai.lens import CameraLens, scene_lenses
from mitsuba_wai.particles import render_particles
from mitsuba_wai.render import FrameRenderer
from mitsuba_wai.scenes import rectangle_to_world, sensor_dict
from mitsuba_wai.surface_sampling import wave_surface
from mitsuba_wai.variant import mitsuba, select_variant
from tests.conftest import shrink
from wai_core.errors import WaiInputError
from wai_core.geometry import pinhole_of
from wai_core.lens import DeviceOptics
from wai_core.light_paths import real_spot_px

K_V = (-0.15, 0.02, 0.001, -0.001, 0.0)
K_S = (-0.06, 0.01, 0.0005, 0.0005, 0.0)


def _fresnel_port(sin_air, n_port, n_water):
    """Unpolarised transmittance of air | port | water (Fresnel's equations, each face)."""
    def t_sp(n1, n2, sin1):
        c1 = np.sqrt(1 - sin1**2)
        c2 = np.sqrt(1 - (n1 * sin1 / n2) ** 2)
        rs = (n1 * c1 - n2 * c2) / (n1 * c1 + n2 * c2)
        rp = (n1 * c2 - n2 * c1) / (n1 * c2 + n2 * c1)
        return 1 - rs**2, 1 - rp**2

    ts1, tp1 = t_sp(1.0, n_port, sin_air)
    ts2, tp2 = t_sp(n_port, n_water, sin_air / n_port)
    return 0.5 * (ts1 * ts2 + tp1 * tp2)


def _flat(cfg):
    return cfg.replace("waves", wind_speed_m_s=0.0)


def _view(cfg, texture=None, spp=16):
    surface = wave_surface(cfg)
    r = FrameRenderer(cfg, surface, texture=texture, systems=("view",))
    return r.render(surface, seed=3, which=("view",), spp=spp)["view"]


def _pinhole_remap(image, optics, cam, n_water):
    """The pinhole (in water) image resampled at each pixel's water-side ray of ``optics``."""
    cols, rows = cam.pixel_grid()
    _, d, _ = optics.rays_cam(cols, rows, n_water)
    f = cam.focal_px
    mx = (f * d[..., 0] / d[..., 2] + (cam.width_px - 1) / 2).astype(np.float32)
    my = (f * d[..., 1] / d[..., 2] + (cam.height_px - 1) / 2).astype(np.float32)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=np.nan), d


@pytest.fixture(scope="module")
def view_cfg(paper_cfg):
    return _flat(shrink(paper_cfg, factor=4))


def test_distorted_view_is_the_pinhole_view_remapped(view_cfg):
    dist = view_cfg.replace("camera_v", distortion=K_V, principal_offset_px=(5.0, -3.0))
    pinhole, ours = _view(view_cfg), _view(dist)
    optics = DeviceOptics.from_config(dist.camera_v)
    expected, _ = _pinhole_remap(pinhole, optics, view_cfg.rig.camera_v, 4 / 3)
    ok = np.isfinite(expected).all(axis=2)
    assert ok.mean() > 0.6  # barrel distortion: the corners see beyond the pinhole's field
    err = np.abs(ours - expected)[ok].mean()
    moved = np.abs(ours - pinhole)[ok].mean()
    # Bilinear resampling of the board's anti-aliased edges leaves a little; a pixel away
    # from the model's ray (e.g. the image warped the other way) leaves as much as no remap.
    assert err < 0.15 * moved


def test_port_dims_the_view_by_fresnel_and_n_squared(view_cfg):
    # Uniform object radiance: the pinhole's field is smooth (Fresnel at the water), so its
    # remap to the port's water rays is exact but for the rim; the ratio is T / n^2.
    n_w = view_cfg.water.n_water
    tex = np.ones((64, 64, 3), dtype=np.float32)
    port = view_cfg.replace("camera_v", port_thickness_mm=6.0, port_gap_mm=4.0, port_n=1.52)
    pinhole, ours = _view(view_cfg, tex, spp=4), _view(port, tex, spp=4)
    optics = DeviceOptics.from_config(port.camera_v)
    cam = view_cfg.rig.camera_v
    expected, _ = _pinhole_remap(pinhole, optics, cam, n_w)
    _, _, air = optics.rays_cam(*cam.pixel_grid(), n_w)
    factor = _fresnel_port(np.hypot(air[..., 0], air[..., 1]), 1.52, n_w) / n_w**2
    smooth = ndimage.maximum_filter(np.abs(np.gradient(pinhole[..., 1], axis=0)), 5) < 0.01
    ok = np.isfinite(expected[..., 1]) & smooth & (expected[..., 1] > 0.1)
    assert ok.mean() > 0.5
    ratio = ours[..., 1][ok] / expected[..., 1][ok]
    assert np.median(np.abs(ratio / factor[ok] - 1)) < 2e-3
    assert factor.max() < 0.6  # T / n^2: about 0.55 at the axis, less towards the rim


def _uniform_s_scene(cam):
    """A Lambertian sheet above camera s, lit evenly from below by a directional light."""
    mi = mitsuba()
    centre = cam.pose.center_lab_mm + np.array([0.0, 0.0, 250.0])
    return mi.load_dict({
        "type": "scene",
        "sensor": sensor_dict(cam),
        "sheet": {"type": "rectangle", "bsdf": {"type": "diffuse"},
                  "to_world": rectangle_to_world(centre, np.array([760.0, 620.0]), True)},
        "light": {"type": "directional", "direction": [0.0, 0.0, 1.0], "irradiance": 1.0},
    })


@pytest.fixture(scope="module")
def s_camera(paper_cfg):
    select_variant()
    dev = dataclasses.replace(paper_cfg.camera_s, width_px=40, height_px=30)
    return dev, _uniform_s_scene(pinhole_of(dev))


def _blocks(image, b=10):
    h, w = image.shape[0] // b * b, image.shape[1] // b * b
    return image[:h, :w, 1].reshape(h // b, b, w // b, b).mean(axis=(1, 3))


def test_camera_s_distortion_keeps_a_uniform_surface_uniform(s_camera):
    dev, scene = s_camera
    spp = 4096  # the directional light's points are independent samples
    plain, _ = render_particles(scene, spp, 1, 2)
    # Pincushion: the film stays inside the sheet (barrel corners would look past it).
    dist = dataclasses.replace(dev, distortion=(0.08, 0.0, 0.0, 0.0, 0.0),
                               principal_offset_px=(2.0, -1.0))
    optics = DeviceOptics.from_config(dist)
    ours, bad = render_particles(scene, spp, 1, 2, camera=CameraLens(optics, 1.0))
    assert bad == 0
    level = plain[..., 1].mean()  # the sheet's radiance (the pinhole's image is uniform)
    assert np.abs(_blocks(plain) / level - 1).max() < 0.015
    assert np.abs(_blocks(ours) / level - 1).max() < 0.015
    # The distortion changes the pixels' solid angles across the image by far more than that.
    c, r = pinhole_of(dev).pixel_grid()

    def spread(d):
        solid = np.linalg.norm(np.cross(np.gradient(d, axis=1), np.gradient(d, axis=0)), axis=2)
        return solid.max() / solid.min()

    assert spread(optics.rays_cam(c, r, 1.0)[1]) > 1.2 * spread(pinhole_of(dev).dirs_cam(c, r))


@pytest.mark.parametrize("tilt_deg", [(0.0, 0.0), (8.0, -5.0)])
def test_camera_s_port_passes_fresnel_over_n_squared(s_camera, tilt_deg):
    # Tilted, the port's Fresnel angles are taken to its own normal (tan a_x, tan a_y, 1),
    # and the film's importance still to the camera's axis: a wrong split leaves a gradient.
    dev, scene = s_camera
    n_w, n_p = 1.34, 1.49
    port = dataclasses.replace(dev, port_thickness_mm=8.0, port_gap_mm=6.0, port_n=n_p,
                               port_tilt_deg=tilt_deg)
    optics = DeviceOptics.from_config(port)
    plain, _ = render_particles(scene, 8192, 2, 2)
    ours, bad = render_particles(scene, 8192, 2, 2, camera=CameraLens(optics, n_w))
    assert bad == 0
    _, _, air = optics.rays_cam(*pinhole_of(dev).pixel_grid(), n_w)
    normal = np.array([*np.tan(np.radians(tilt_deg)), 1.0])
    cos_air = air @ (normal / np.linalg.norm(normal))
    factor = _fresnel_port(np.sqrt(1.0 - cos_air**2), n_p, n_w) / n_w**2
    expected = plain[..., 1].mean() * factor
    assert np.abs(_blocks(ours) / _blocks(expected[..., None].repeat(3, 2)) - 1).max() < 0.015


def _spots(image):
    lum = image[..., 1] + image[..., 2]
    labels, n = ndimage.label(lum > 0.15 * lum.max())
    size = ndimage.sum(np.ones_like(lum), labels, np.arange(1, n + 1))
    c = np.array(ndimage.center_of_mass(lum, labels, np.arange(1, n + 1)))[size >= 4]
    return c[:, ::-1]  # (col, row)


def test_camera_s_spots_land_where_the_model_projects_them(paper_cfg):
    # Shares by delivered power: every spot's centroid equally steady at 4 spp.
    cfg = _flat(paper_cfg).replace("render", particle_shares="delivered")
    dist = cfg.replace("camera_s", distortion=K_S, principal_offset_px=(4.0, 2.5))
    surface = wave_surface(cfg)
    images = []
    for c in (cfg, dist):
        r = FrameRenderer(c, surface, systems=("pattern",))
        images.append(r.render(surface, seed=5, which=("pattern",), spp=4)["pattern"])
    cam = cfg.rig.camera_s
    ref = _spots(images[0])
    # The undistorted spots' diffuser points, projected by the distorted model.
    o, d = cam.pixel_rays(ref[:, 0], ref[:, 1])
    points = o + d * ((cfg.diffuser.z_mm - o[2]) / d[:, 2:3])
    cols, rows, valid = DeviceOptics.from_config(dist.camera_s).project(points, 4 / 3)
    predicted = np.column_stack([cols, rows])[valid & cam.in_image(cols, rows, 8)]
    found = _spots(images[1])
    gap = np.linalg.norm(predicted[:, None] - found[None], axis=2).min(axis=1)
    assert len(predicted) > 100
    assert np.median(gap) < 0.1
    shift = np.linalg.norm(predicted[:, None] - ref[None], axis=2).min(axis=1)
    assert np.median(shift) > 2.0  # the distortion moved them


def test_camera_s_spots_behind_a_tilted_port_land_where_the_model_projects_them(paper_cfg):
    # The centroids of spots seen through a port sit off their chief rays' images by the
    # port's uneven transmittance and magnification across each spot (~0.1 px here, the same
    # tilted or not); the tilted port's model must leave no more than the square one's, while
    # the tilt moves every spot by pixels.
    cfg = _flat(paper_cfg).replace("render", particle_shares="delivered")
    surface = wave_surface(cfg)
    cam = cfg.rig.camera_s
    o, d = cam.pixel_rays(*_spots(_pattern(cfg, surface)).T)
    points = o + d * ((cfg.diffuser.z_mm - o[2]) / d[:, 2:3])
    gaps, predicted = [], []
    for tilt in ((0.0, 0.0), (5.0, 3.0)):
        c = cfg.replace("camera_s", port_thickness_mm=6.0, port_gap_mm=3.0, port_tilt_deg=tilt)
        cols, rows, valid = DeviceOptics.from_config(c.camera_s).project(points, 4 / 3)
        keep = valid & cam.in_image(cols, rows, 8)
        predicted.append(np.column_stack([cols, rows])[keep])
        found = _spots(_pattern(c, surface))
        gaps.append(np.linalg.norm(predicted[-1][:, None] - found[None], axis=2).min(axis=1))
    assert len(gaps[1]) > 100
    assert np.median(gaps[0]) < 0.15
    assert np.median(gaps[1]) < np.median(gaps[0]) + 0.02
    moved = np.linalg.norm(predicted[1][:, None] - predicted[0][None], axis=2).min(axis=1)
    assert np.median(moved) > 2.0


def _pattern(cfg, surface):
    r = FrameRenderer(cfg, surface, systems=("pattern",))
    return r.render(surface, seed=5, which=("pattern",), spp=4)["pattern"]


def test_lens_refused_where_mitsubas_integrators_render(paper_cfg):
    select_variant()
    cfg = paper_cfg.replace("camera_v", distortion=K_V)
    assert scene_lenses(paper_cfg) == {"pattern": None, "view": None}
    with pytest.raises(WaiInputError, match=r"\[camera_v\]\.distortion.*sampling"):
        scene_lenses(cfg.replace("render", sampling="independent"))


def test_daylight_composes_with_a_shifted_principal_point(paper_cfg):
    """A principal point moved by 16 px moves every pixel by 16 px and changes no radiance:
    the dots, the sun's caustics and the sky on the diffuser in camera s, the object and the
    sky beyond it in camera v, each image the pinhole's shifted (in expectation: the view
    takes another tracer, so its noise differs)."""
    select_variant()
    day = shrink(paper_cfg, factor=2, spp=4).replace("ambient", enabled=True, sun_spp=16)
    shift = 16
    moved = (day.replace("camera_s", principal_offset_px=(float(shift), 0.0))
             .replace("camera_v", principal_offset_px=(float(shift), 0.0)))
    surface = wave_surface(day)
    images = {}
    for name, cfg in (("pinhole", day), ("moved", moved)):
        images[name] = FrameRenderer(cfg, surface).render(surface, seed=3)
    for key, tol in (("pattern", 1e-3), ("view", 0.01)):
        a = ndimage.gaussian_filter(images["pinhole"][key][:, :-shift].sum(2), 2.0)
        b = ndimage.gaussian_filter(images["moved"][key][:, shift:].sum(2), 2.0)
        unshifted = ndimage.gaussian_filter(images["moved"][key][:, :-shift].sum(2), 2.0)
        assert np.abs(a - b).mean() < tol * a.mean(), key
        assert np.abs(a - unshifted).mean() > 10 * tol * a.mean(), key  # the check can tell


def test_the_sky_lit_diffuser_behind_a_port_is_the_ports_share_of_its_radiance(paper_cfg):
    """On camera s's axis the port passes (1 - R_air|port)(1 - R_port|water) of the water-side
    radiance over n_water^2 (Fresnel at normal incidence, written out here)."""
    from mitsuba_wai.ambient import sky_image

    cfg = paper_cfg.replace("ambient", enabled=True, sky_radiance=2.0)
    ported = cfg.replace("camera_s", port_thickness_mm=4.0, port_n=1.5)
    n = cfg.water.n_water
    r1, r2 = ((1.5 - 1) / 2.5) ** 2, ((1.5 - n) / (1.5 + n)) ** 2
    bare, seen = sky_image(cfg), sky_image(ported)
    h, w = seen.shape[:2]
    centre = seen[(h - 1) // 2, (w - 1) // 2] / bare[(h - 1) // 2, (w - 1) // 2]
    np.testing.assert_allclose(centre, (1 - r1) * (1 - r2) / n**2, rtol=2e-3)
    assert seen[0, 0, 0] < seen[(h - 1) // 2, (w - 1) // 2, 0]  # more reflected off axis


def _predicted_spots(cfg):
    """Camera s's image of each lit dot's chief ray (numpy model) via the flat water."""
    from wai_core.geometry import intersect_plane_z, reflect
    from wai_core.layout import dot_weights

    _, panel = cfg.rig.dot_grid
    panel = panel[dot_weights(cfg) > 0]
    o, d = DeviceOptics.from_config(cfg.projector).pixel_rays(panel[:, 0], panel[:, 1],
                                                             cfg.water.n_water)
    q, _ = intersect_plane_z(o, d, cfg.water.h0_mm)
    s, _ = intersect_plane_z(q, reflect(d, np.array([0.0, 0.0, 1.0])), cfg.diffuser.z_mm)
    cam = cfg.rig.camera_s
    cols, rows, _ = cam.project(s)
    keep = np.isfinite(cols) & cam.in_image(cols, rows, 8)
    return np.column_stack([cols, rows])[keep]


@pytest.mark.parametrize("tilt_deg", [(0.0, 0.0), (-6.0, 4.0)])
def test_projector_dots_leave_along_the_models_rays(paper_cfg, tilt_deg):
    cfg = _flat(paper_cfg)
    lensed = cfg.replace("projector", distortion=(-0.05, 0.0, 0.0005, 0.0, 0.0),
                         principal_offset_px=(6.0, -4.0), port_thickness_mm=5.0,
                         port_tilt_deg=tilt_deg)
    surface = wave_surface(cfg)
    gaps = []
    for c in (cfg, lensed):
        r = FrameRenderer(c, surface, systems=("pattern",))
        found = _spots(r.render(surface, seed=7, which=("pattern",), spp=4)["pattern"])
        predicted = _predicted_spots(c)
        gaps.append(np.linalg.norm(predicted[:, None] - found[None], axis=2).min(axis=1))
    # A spot's centroid is not its chief ray's image (the Fresnel weight varies across it): the
    # pinhole projector's gap is that bias; the lens must leave no more than it.
    assert len(gaps[1]) > 100
    assert np.median(gaps[1]) < np.median(gaps[0]) + 0.05
    moved = np.linalg.norm(_predicted_spots(lensed)[:, None] - _predicted_spots(cfg)[None],
                           axis=2).min(axis=1)
    assert np.median(moved) > 2.0


def test_barrel_lens_behind_a_port_sees_nothing_past_its_fold(paper_cfg):
    # A port bends wide water rays to near-grazing air rays; a barrel model (k1 = -0.05) bends
    # back past r^2 = 1 / (3 |k1|) and, past r^2 = 1 / |k1|, lands such rays on the image's far
    # side with a positive Jacobian. A real lens has no such rays: every light in the image is
    # a dot the one-to-one model puts there, a blur many pixels wide, never a lone pixel.
    cfg = _flat(paper_cfg).replace("render", particle_shares="delivered").replace(
        "camera_s", port_thickness_mm=5.0, distortion=(-0.05, 0.0, 0.0, 0.0, 0.0))
    surface = wave_surface(cfg)
    r = FrameRenderer(cfg, surface, systems=("pattern",))
    lum = r.render(surface, seed=5, which=("pattern",), spp=4)["pattern"][..., 1:].sum(axis=2)
    around = (ndimage.uniform_filter(lum, 3, mode="constant") * 9.0 - lum) / 8.0
    bright = np.percentile(lum, 99.5)
    lit = lum > 0.3 * bright  # past the spots' noisy tails
    lone = lit & (around < 0.25 * lum)
    assert lit.sum() > 10_000  # the dots fill the image
    assert lone.sum() == 0
    rig = cfg.rig  # and the dots are where the model puts them
    predicted = real_spot_px(rig, rig.flat_spots.px)
    cols, rows = np.rint(predicted[rig.camera_s.in_image(*predicted.T, 2)]).astype(int).T
    assert len(cols) > 500 and (lum[rows, cols] > 0.02 * bright).mean() > 0.99
