"""Alterman's method on sun spots computed geometrically (no renderer), against facts that do not
depend on its code: Snell's law in the plane of incidence, exact planes, flat-water geometry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from restoration.alterman import (
    NO_SUN,
    OK,
    SUN_OUT_OF_VIEW,
    TOO_FEW_SPOTS,
    AltermanCalibration,
    match_spots,
    prepare_spot_reference,
    reconstruct_alterman,
    restore_alterman,
    snell_normals,
    sun_status,
)
from restoration.features import Spots
from restoration.options import AltermanOptions, StructuredLightOptions
from restoration.reverse_trace import restore_view, trace_to_object
from tests.conftest import ROOT, shrink
from wai_core.alterman import AltermanSystem, chief_rays, load_alterman, sensor_layout
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera, Pose
from wai_core.heightfield import Heightfield

SENSOR = ROOT / "scenes" / "alterman.toml"
OPTIONS = AltermanOptions()
PERIOD_MM = 150.0  # texture period on the object plane


@pytest.fixture(scope="module")
def system():
    loaded = load_alterman(SENSOR)
    # Camera v 4x smaller (same optics) keeps the geometric views fast; camera a stays 800x600.
    return AltermanSystem(shrink(loaded.base), loaded.sensor)


def _cal(system) -> AltermanCalibration:
    return AltermanCalibration.from_system(system, system.base.water.n_water**2)


def _surface(h0, fn):
    x, y = np.linspace(-150.0, 700.0, 171), np.linspace(-350.0, 350.0, 141)
    xx, yy = np.meshgrid(x, y)
    return Heightfield(x, y, h0 + fn(xx, yy))


def _spot_image(camera: PinholeCamera, spots_mm, sigma_px=0.9):
    """Gaussian spots (H, W, 3) at the camera-a projections of ``spots_mm`` (K, 3)."""
    cols, rows, _ = camera.project(spots_mm)
    c, r = np.arange(camera.width_px), np.arange(camera.height_px)
    gx = np.exp(-((c[None, :] - cols[:, None]) ** 2) / (2 * sigma_px**2))
    gy = np.exp(-((r[None, :] - rows[:, None]) ** 2) / (2 * sigma_px**2))
    return np.repeat((gy.T @ gx)[..., None], 3, axis=2).astype(np.float32)


def _texture(p):
    return 0.5 + 0.35 * np.sin(2 * np.pi * p[..., 0] / PERIOD_MM) * np.cos(
        2 * np.pi * p[..., 1] / PERIOD_MM
    )


def _view(cfg, surface):
    cam = cfg.rig.camera_v
    tr = trace_to_object(
        cam, surface, cfg.water.h0_mm, cfg.water.n_water, cfg.object_z_mm, *cam.pixel_grid()
    )
    img = np.where(tr.ok, _texture(np.nan_to_num(tr.object_mm)), 0.0)
    return np.repeat(img[..., None], 3, axis=2).astype(np.float32)


@pytest.mark.parametrize("theta_deg", [0.0, 30.0, 75.0])
@pytest.mark.parametrize("alpha", [-0.2, 0.05, 0.2])
def test_snell_normals_undo_refraction_in_the_plane_of_incidence(theta_deg, alpha):
    # Normal tilted by alpha towards -x; sun in the xz-plane at theta from the zenith on +x.
    # The sun meets the surface at theta + alpha from the normal and goes on at
    # asin(sin(theta + alpha) / n), i.e. that minus alpha from the vertical (towards -x).
    n, th = 4.0 / 3.0, np.radians(theta_deg)
    sun = -np.array([np.sin(th), 0.0, np.cos(th)])
    tilt = np.arcsin(np.sin(th + alpha) / n) - alpha
    t = np.array([[-np.sin(tilt), 0.0, -np.cos(tilt)]])
    assert np.allclose(snell_normals(sun, t, n), [[-np.sin(alpha), 0.0, np.cos(alpha)]], atol=1e-12)


@pytest.mark.parametrize("theta_deg", [0.0, 45.0])
def test_tilted_plane_is_reconstructed_exactly(system, theta_deg):
    sys_t = AltermanSystem(system.base, system.sensor.replace("sun", zenith_deg=theta_deg))
    lay = sensor_layout(sys_t)
    h0 = lay.h0_mm
    gx, gy = 0.06, -0.03
    plane = _surface(h0, lambda x, y: gx * (x - 220.0) + gy * y)
    rays = chief_rays(lay, plane)
    est = reconstruct_alterman(
        lay.ij, lay.pinholes_mm, rays.spots_mm, lay, AltermanOptions(n_refine=8)
    )
    assert np.allclose(est.slopes, [gx, gy], atol=1e-9)
    # The refined samples lie on the lines through the pinholes, on a plane parallel to the truth
    # whose mean height is the gauge's h0 (the only anchor the method has).
    # (to the refinement's convergence: it stops once no height moves by refine_tol_mm).
    p = est.points_mm
    offset = p[:, 2] - plane.height(p[:, 0], p[:, 1])
    assert np.ptp(offset) < 0.1 * AltermanOptions().refine_tol_mm
    pin, spot = lay.pinholes_mm[est.kept], rays.spots_mm[est.kept]
    t = (p[:, 2] - pin[:, 2]) / (spot[:, 2] - pin[:, 2])
    on_line = pin + t[:, None] * (spot - pin)
    np.testing.assert_allclose(p, on_line, atol=1e-9)
    assert np.mean(p[:, 2]) == pytest.approx(h0, abs=1e-9)
    hf = est.heightfield
    xx, yy = np.meshgrid(hf.x, hf.y)
    err = hf.z - plane.height(xx, yy)
    assert np.nanstd(err) < 1e-6


def test_matching_counts_every_failure(system):
    lay = sensor_layout(system)
    px, seen = lay.flat_spots_px()
    ref = prepare_spot_reference(_spot_image(lay.camera, lay.flat_spots_mm), lay)
    assert ref.counts["observed"] == seen.sum() == len(lay.ij)
    wavy = px.copy() + 1.5  # a smooth shift of 1.5 px
    wavy[0] += 0.6 * lay.pitch_px  # beyond half the pitch: too far
    stray = px[5] + [0.2 * lay.pitch_px, 0.0]  # a second spot by pinhole 5: it takes one of them
    centres = np.concatenate([np.delete(wavy, 10, axis=0), stray[None]])
    k = len(centres)
    spots = Spots(centres, np.ones(k), np.ones(k), np.full(k, 5), np.zeros((k, 2, 2)),
                  np.zeros(k, bool), np.zeros(k, bool), np.zeros(k, bool))
    m = match_spots(spots, ref, max_px=0.5 * lay.pitch_px)
    c = m.counts
    assert c["detected"] == k and c["reference"] == len(lay.ij)
    assert c["rejected_far"] >= 1
    assert c["matched"] + c["unmatched_reference"] == len(lay.ij)
    assert c["unmatched_reference"] == c["rejected_far"] + c["rejected_ambiguous"] + c[
        "rejected_border"]
    assert c["unassigned_spots"] == k - c["matched"]
    # Every kept match is the right pinhole: its spot is its own (shifted) position.
    rows = lay.index_of(m.ij)
    assert np.all(np.linalg.norm(m.spot_px - px[rows], axis=1) < 0.25 * lay.pitch_px)


def test_overcast_and_clouds_give_no_sun(system):
    lay = sensor_layout(system)
    black = np.zeros((lay.camera.height_px, lay.camera.width_px, 3), np.float32)
    cam_v = system.base.camera_v
    images = {
        "sunspots": black,
        "sunspots_flat": black,
        "view": np.zeros((cam_v.height_px, cam_v.width_px, 3), np.float32),
    }
    for sun in (dict(enabled=False), dict(irradiance=0.0)):
        overcast = AltermanSystem(system.base, system.sensor.replace("sun", **sun))
        out = restore_alterman(images, _cal(overcast), OPTIONS)
        assert out.status == NO_SUN and out.surface is None
    # The sun is configured but the frame shows none (a cloud): the images say no_sun too.
    out = restore_alterman(images, _cal(system), OPTIONS)
    assert out.status == NO_SUN and out.surface is None


def test_spots_out_of_view_and_too_few_spots(system):
    lay = sensor_layout(system)
    # A camera a looking at another part of the lab sees none of the spots.
    away = Pose.from_center(np.eye(3), lay.camera.pose.center_lab_mm + [2000.0, 0.0, 0.0])
    blind = dataclasses.replace(lay, camera=dataclasses.replace(lay.camera, pose=away))
    assert sun_status(system, blind)[0] == SUN_OUT_OF_VIEW
    assert sun_status(system, lay)[0] == OK
    cal = _cal(system)
    few = _spot_image(lay.camera, lay.flat_spots_mm[:5])
    cam_v = system.base.camera_v
    images = {
        "sunspots": few,
        "sunspots_flat": _spot_image(lay.camera, lay.flat_spots_mm),
        "view": np.zeros((cam_v.height_px, cam_v.width_px, 3), np.float32),
    }
    out = restore_alterman(images, cal, OPTIONS)
    assert out.status == TOO_FEW_SPOTS and out.surface is None


def test_an_anchor_or_the_structured_lights_options_are_refused():
    # The sun sensor's normals do not depend on the height: it has no level to choose.
    from restoration import Alterman, get_method

    with pytest.raises(WaiInputError, match="no option 'anchor'"):
        get_method("alterman", anchor="integrability")
    with pytest.raises(WaiInputError, match="AltermanOptions"):
        Alterman(StructuredLightOptions())


def test_wavy_surface_is_recovered_and_restores_the_view(system):
    # The whole method on exact spots: detection, matching, Snell normals, refined samples,
    # integration, gridding, reverse tracing. Its view must match the one restored with the
    # true surface, and both the flat-water truth.
    cfg = system.base
    sys30 = AltermanSystem(cfg, system.sensor.replace("sun", zenith_deg=30.0))
    lay = sensor_layout(sys30)
    h0 = lay.h0_mm
    truth = _surface(h0, lambda x, y: 3.0 * np.sin(x / 40.0) * np.cos(y / 50.0))
    rays = chief_rays(lay, truth)
    images = {
        "sunspots": _spot_image(lay.camera, rays.spots_mm),
        "sunspots_flat": _spot_image(lay.camera, lay.flat_spots_mm),
        "view": _view(cfg, truth) * cfg.water.n_water**2,
    }
    out = restore_alterman(images, _cal(sys30), OPTIONS)
    assert out.status == OK and out.counts["matched"] == len(lay.ij)
    est = out.surface.heightfield
    xx, yy = np.meshgrid(est.x, est.y)
    err = est.z - truth.height(xx, yy)
    # The shape to a few hundredths of a mm; the offset is the samples' true mean minus h0.
    assert np.nanstd(err) < 0.03
    q = out.surface.points_mm
    true_mean = np.mean(truth.height(q[:, 0], q[:, 1]))
    assert np.nanmean(err) == pytest.approx(h0 - true_mean, abs=0.03)
    flat_truth = _view(cfg, None)
    with_truth = restore_view(
        images["view"] / cfg.water.n_water**2, cfg.rig.camera_v, truth, h0,
        cfg.water.n_water, cfg.object_z_mm,
    )
    ours = out.view
    both = ours.valid & with_truth.valid & (flat_truth[..., 0] > 0)
    assert both.mean() > 0.5
    distorted = np.abs(images["view"] / cfg.water.n_water**2 - flat_truth)[both].mean()
    restored = np.abs(ours.image - flat_truth)[both].mean()
    # Resampling a texture of ~10 px period costs both restorations alike (~0.03).
    assert restored < 0.25 * distorted
    assert np.abs(ours.image - with_truth.image)[both].mean() < 0.1 * restored
