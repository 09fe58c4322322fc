"""The spots' centroid bias: its direction and size against Fresnel's law and the water's
roughness, and the correction on rendered frames against the renderer's true surface."""

from __future__ import annotations

import numpy as np
import pytest

from restoration import StructuredLight
from restoration.spot_bias import SpotBiasModel, spot_bias_px
from wai_core import load_system
from wai_core.geometry import intersect_plane_z
from wai_core.light_paths import dot_rays, spots_through


@pytest.fixture(scope="module")
def rig():
    return load_system("paper").rig


def _fresnel(cos_i, n1=4.0 / 3.0, n2=1.0):
    # Unpolarised reflectance (Hecht, Optics, eq. 4.34 and 4.40), from water into air.
    sin_t = n1 / n2 * np.sqrt(1.0 - cos_i**2)
    cos_t = np.sqrt(np.clip(1.0 - sin_t**2, 0.0, None))
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return np.where(sin_t >= 1.0, 1.0, 0.5 * (rs**2 + rp**2))


def _brute_force_bias(rig, panel, roughness):
    # Each dot's light on a fine grid: points of its Gaussian out to 4.5 sigma, and on rough
    # water GGX slopes at 40 quantiles of P(|s| < r) = r^2 / (alpha^2 + r^2) (up to the model's
    # cap, whose tail spreads over the background) by 48 angles, each reflected about its facet
    # off flat water and weighted by the reflectance and the facet's share of the projected
    # area; the weighted mean pixel less the centre ray's.
    from restoration.pattern_model import GGX_CAP

    h0, z_h = rig.cfg.water.h0_mm, rig.cfg.diffuser.z_mm
    u = np.arange(-4.5, 4.51, 0.3 if roughness else 0.1)
    ux, uy = np.meshgrid(u, u)
    grid = np.column_stack([ux.ravel(), uy.ravel()])
    g = np.exp(-0.5 * np.sum(grid**2, axis=1))
    if roughness:
        q = (np.arange(40) + 0.5) / 40 * GGX_CAP
        r = np.repeat(roughness * np.sqrt(q / (1.0 - q)), 48)
        phi = np.tile(2 * np.pi * (np.arange(48) + 0.5) / 48, 40)
        slopes = np.column_stack([r * np.cos(phi), r * np.sin(phi)])
    else:
        slopes = np.zeros((1, 2))
    out = []
    for p in panel:
        o, d = dot_rays(rig, p + rig.cfg.pattern.sigma_px * grid)
        q, _ = intersect_plane_z(o, d, h0)
        d, q = np.repeat(d, len(slopes), 0), np.repeat(q, len(slopes), 0)
        s = np.tile(slopes, (len(grid), 1))
        m = np.column_stack([-s, np.ones(len(s))])
        m /= np.linalg.norm(m, axis=1, keepdims=True)
        cos_m = np.abs(np.sum(d * m, axis=1))
        w = np.repeat(g, len(slopes)) * _fresnel(cos_m) * cos_m / np.abs(d[:, 2])
        x, _ = intersect_plane_z(q, d - 2 * cos_m[:, None] * m, z_h)  # d's mirror about m
        cols, rows, _ = rig.camera_s.project(x)
        out.append(np.sum(w[:, None] * np.column_stack([cols, rows]), axis=0) / w.sum())
    return np.array(out) - spots_through(rig, None, panel)


@pytest.mark.parametrize(("roughness", "tolerance"), [(0.0, 0.05), (0.01, 0.15)])
def test_a_spots_light_centre_is_fresnels(rig, roughness, tolerance):
    # The model's quadrature (4 x 4 Gauss-Hermite points; 4 rings of 8 facets) against the
    # fine grid, on the dots in view met at 40 degrees, where the reflectance climbs towards
    # the critical angle (48.6 degrees): a constant reflectance would leave an eighth of the
    # shift there. (Half the dots in view are beyond it, totally reflected.)
    panel = rig.dot_panel_px[rig.lit]
    spot = spots_through(rig, None, panel)
    cam = rig.camera_s
    seen = (spot > 20).all(axis=1) & (spot < [cam.width_px - 20, cam.height_px - 20]).all(axis=1)
    _, d = dot_rays(rig, panel[seen])
    incidence = np.degrees(np.arccos(np.abs(d[:, 2])))
    near = panel[seen][np.argsort(np.abs(incidence - 40.0))[:4]]
    model = spot_bias_px(rig, near, None, rig.cfg.water.h0_mm,
                         SpotBiasModel(roughness=roughness, window=0.0))
    brute = _brute_force_bias(rig, near, roughness)
    assert np.linalg.norm(brute, axis=1).min() > 0.02  # a shift the test can see
    np.testing.assert_allclose(model, brute, atol=tolerance * np.abs(brute).max() + 0.001)


def test_dots_beyond_the_surface_have_no_bias(rig):
    # Dots whose light leaves the surface given (a small patch) have no bias, not a wrong one.
    from restoration.fit import BSplineSurface

    panel = rig.dot_panel_px[rig.lit]
    o, d = dot_rays(rig, panel)
    hit, _ = intersect_plane_z(o, d, rig.cfg.water.h0_mm)
    centre = np.nanmedian(hit[:, :2], axis=0)
    patch = BSplineSurface.covering(np.array([centre - 20.0, centre + 20.0]), 10.0,
                                    rig.cfg.water.h0_mm)
    bias = spot_bias_px(rig, panel, patch, rig.cfg.water.h0_mm, SpotBiasModel())
    inside = np.all(np.abs(hit[:, :2] - centre) < 10.0, axis=1)
    far = np.any(np.abs(hit[:, :2] - centre) > 40.0, axis=1)
    assert np.isfinite(bias[inside]).all() and np.isnan(bias[far]).all()


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    from mitsuba_wai import render_folder
    from wai_core.system import load_rig

    folder = tmp_path_factory.mktemp("spot_bias") / "frame"
    render_folder(load_rig("paper").replace("waves", wind_speed_m_s=1.5, seed=23), folder,
                  progress=False)
    return folder


@pytest.mark.slow
def test_the_correction_moves_the_rendered_spots_onto_their_true_rays(frame):
    # A rendered frame (smooth water, a seed the model never saw): the dots whose modelled
    # correction is large (met near the critical angle) are where the renderer's spots lie off
    # the centre rays traced through its true surface, and the correction, made from the
    # restoration's own surface, takes most of that error away (docs/results.md: 0.21-0.27 px
    # to 0.03-0.05 px).
    from restoration import Calibration
    from restoration.spot_bias import spot_correction_px
    from wai_core.heightfield import load_heightfield

    cal = Calibration.from_folder(frame)
    result = StructuredLight()(cal.load_images(frame), cal)
    ij, spots = result.features.ij, result.features.spot_px
    detected = spots - cal.reference.flat_shift_at(ij)
    rig = cal.cfg.rig
    true = spots_through(rig, load_heightfield(frame / "heightfield.npz"),
                         rig.dot_panel_px[rig.dot_index(ij)])
    correction = spot_correction_px(cal, ij, result.surface, SpotBiasModel())
    large = np.linalg.norm(correction, axis=1) > 0.15
    assert large.sum() >= 10
    before = np.nanmedian(np.linalg.norm((detected - true)[large], axis=1))
    after = np.nanmedian(np.linalg.norm((detected - correction - true)[large], axis=1))
    assert before > 0.1 and after < 0.4 * before


@pytest.mark.slow
def test_wai_restore_spot_bias_records_it(frame):
    import json

    from wai.cli import main

    assert main(["restore", str(frame), "--spot-bias", "--quiet"]) == 0
    metrics = json.loads((frame / "restore" / "metrics.json").read_text())
    assert metrics["options"]["spot_bias"] is True
    assert metrics["timings_ms"]["spot_bias"] > 0


@pytest.fixture(scope="module")
def rough_frame(tmp_path_factory):
    from mitsuba_wai import render_folder
    from wai_core.system import load_rig

    folder = tmp_path_factory.mktemp("spot_bias_rough") / "frame"
    rig = load_rig("paper").replace("waves", wind_speed_m_s=1.0, seed=31)
    rig = rig.replace("water", roughness=0.01).replace("render", spp_pattern=128)
    render_folder(rig, folder, progress=False)
    return folder


def _flat_share(folder):
    """The share of the model's flat-water bias that a render's flat reference shows."""
    from restoration import Calibration
    from restoration.spot_bias import shown_share

    cal = Calibration.from_folder(folder)
    ref = cal.prepare(cal.load_images(folder)["pattern_flat"])
    use = ref.observed & ref.lit
    model = SpotBiasModel(roughness=cal.cfg.water.roughness)
    dots = cal.cfg.rig.dot_index(ref.ij[use])
    return shown_share(ref.shift_px[use], cal.flat_spot_bias_px(model)[dots])


@pytest.mark.slow
def test_the_flat_reference_shows_what_the_neighbours_take_back(frame, rough_frame):
    # A smooth spot stands alone and lies where the model puts it: the flat reference's
    # shifts follow the model's flat-water bias along the projector's tilt (x) one to one.
    # On rough water each spot's halo lies to one side and its neighbours' halos light its
    # other flank: the renders show about half the isolated spot's modelled shift
    # (docs/results.md: isolated spots +0.16-0.18 px below the critical angle, +0.04-0.06
    # with every dot lit), and that share is the rough correction's gain.
    smooth, rough = _flat_share(frame), _flat_share(rough_frame)
    print(f"share of the modelled shift (x, y): smooth {smooth}, rough {rough}")
    assert 0.9 < smooth[0] < 1.1
    assert 0.3 < rough[0] < 0.8 and 0.3 < rough[1] < 0.9


@pytest.mark.slow
def test_rough_water_corrects_its_spots_by_default(rough_frame):
    # GGX microfacets (alpha 0.01) weight the facets tilted towards the critical angle, whose
    # reflectance climbs steeply: the renderer's spots of the dots met near it (44-53 degrees
    # on the true surface) lie along the projector's tilt (+x), a fraction of a pixel off
    # their centre rays, past what the flat reference removes (docs/results.md, 0.2-0.4 px
    # before the correction). A rough scene is corrected without being asked (a smooth one
    # is not: StructuredLightOptions.spot_bias_for's example), by the share of the modelled
    # shift its flat reference shows (the test above), and the correction moves those spots
    # towards their rays; the neighbours take back less of the shift near the critical angle
    # than elsewhere, so a part of it stays there.
    from restoration import Calibration, StructuredLightOptions
    from restoration.spot_bias import spot_correction_px
    from wai_core.heightfield import load_heightfield

    cal = Calibration.from_folder(rough_frame)
    assert StructuredLightOptions().spot_bias_for(cal.cfg)
    result = StructuredLight()(cal.load_images(rough_frame), cal)
    assert "spot_bias" in result.timings_ms
    ij = result.features.ij
    rig = cal.cfg.rig
    panel = rig.dot_panel_px[rig.dot_index(ij)]
    truth = load_heightfield(rough_frame / "heightfield.npz")
    origin, dirs = dot_rays(rig, panel)
    _, _, normal = truth.intersect_normals(origin, dirs)
    incidence_deg = np.degrees(np.arccos(np.abs(np.sum(dirs * normal, axis=1))))
    near = (incidence_deg > 44) & (incidence_deg < 53)
    assert near.sum() >= 15
    referred = result.features.spot_px - cal.reference.flat_shift_at(ij)
    error = referred - spots_through(rig, truth, panel)
    correction = spot_correction_px(cal, ij, result.surface, SpotBiasModel.of_scene(cal.cfg))
    before = float(np.nanmean(error[near, 0]))
    after = float(np.nanmean((error - correction)[near, 0]))
    print(f"near the critical angle ({near.sum()} dots): mean x error {before:+.3f} -> "
          f"{after:+.3f} px")
    gain = cal.spot_bias_gain(SpotBiasModel.of_scene(cal.cfg))
    assert result.summary()["flat_reference"]["spot_bias_gain"] == list(gain)
    assert 0.3 < gain[0] < 0.8
    assert before > 0.1 and 0.0 < after < 0.8 * before
