"""Inverse rendering: the pattern model's image and its exact gradient, and the method on a
rendered frame against the structured light it starts from."""

from __future__ import annotations

import json

import numpy as np
import pytest

from restoration import InverseRenderingOptions
from restoration.fit import BSplineSurface
from restoration.inverse_rendering import _Objective
from restoration.pattern_model import DotParticles, PatternModel, Raster
from wai.cli import main
from wai_core import load_system
from wai_core.light_paths import spots_through


@pytest.fixture(scope="module")
def rig():
    return load_system("paper").rig


def test_splat_and_sample_are_adjoint():
    # <splat(p, w), I> = sum_p w_p I(p): the gradient's chain through the image is exact.
    rng = np.random.default_rng(0)
    raster = Raster((40, 60), sigma_px=1.0)
    px = rng.uniform([-0.4, -0.4], [59.4, 39.4], (300, 2))
    w = rng.uniform(0.1, 1.0, 300)
    img = rng.normal(size=(40, 60))
    ok = np.ones(300, bool)
    value, grad = raster.sample(img, px)
    assert np.isclose(np.sum(raster.splat(px, w, ok) * img), np.sum(w * value))
    # And the sample's gradient is the derivative of the bilinear value (inside a cell).
    eps = 1e-6
    for axis in (0, 1):
        step = px.copy()
        step[:, axis] += eps
        fd = (raster.sample(img, step)[0] - value) / eps
        inside = np.floor(step[:, axis]) == np.floor(px[:, axis])
        np.testing.assert_allclose(grad[inside, axis], fd[inside], atol=1e-4)


def _on_flat_water(rig, panel):
    """The particles of the dots at ``panel`` (order 4), their model, flat water at h0 as a
    spline and the particles traced through it."""
    parts = DotParticles.of(rig, panel, order=4)
    model = PatternModel(rig, parts, (rig.camera_s.height_px, rig.camera_s.width_px))
    h0 = rig.cfg.water.h0_mm
    xy = (parts.origin_mm + model.flat_t(h0)[:, None] * parts.dirs)[:, :2]
    flat = BSplineSurface.covering(xy, 10.0, h0)
    return parts, model, flat, model.trace(flat, model.flat_t(h0))


def test_a_dots_light_centres_where_its_ray_lands(rig):
    # Flat water: each dot's particles (Gauss-Hermite points of its Gaussian) land around the
    # spot of its centre ray, as the light path puts it (wai_core.light_paths).
    panel = rig.dot_panel_px[rig.lit]
    parts, model, flat, traced = _on_flat_water(rig, panel)
    w = np.where(traced.ok, parts.weight, 0.0)
    total = np.bincount(parts.dot, w)
    full = total > 0.999
    centroid = np.column_stack([np.bincount(parts.dot, w * traced.px[:, a]) for a in (0, 1)])
    centroid = centroid[full] / total[full, None]
    ray = spots_through(rig, None, panel)[full]
    err = np.linalg.norm(centroid - ray, axis=1)
    assert full.sum() > 0.8 * len(panel)
    assert np.median(err) < 0.02 and err.max() < 0.1


def test_micro_facets_spread_the_slopes_by_the_roughness(rig):
    # GGX's median slope magnitude is alpha; the facets' mean slope is zero.
    for alpha in (0.005, 0.02):
        parts = DotParticles.of(rig, rig.dot_panel_px[:3], order=2, roughness=alpha, facets=32)
        s = parts.slope_offset
        np.testing.assert_allclose(s.mean(axis=0), 0.0, atol=1e-12)
        assert 0.7 * alpha < np.median(np.linalg.norm(s, axis=1)) < 1.4 * alpha


def test_each_particle_carries_fresnels_share_of_its_dots_light(rig):
    # Flat water: a dot met beyond the critical angle (48.6 degrees) is totally reflected, its
    # particles keep their quadrature weights; below it the reflectance climbs with the angle,
    # so a dot's more oblique particles carry more than their weight.
    panel = rig.dot_panel_px[rig.lit]
    parts, model, flat, traced = _on_flat_water(rig, panel)
    light = model.reflectance(flat, traced, 4.0 / 3.0)
    incidence = np.degrees(np.arccos(np.abs(parts.dirs[:, 2])))
    lowest = np.full(parts.n_dots, 90.0)
    np.minimum.at(lowest, parts.dot, incidence)
    full = np.bincount(parts.dot, traced.ok) == 16
    tir = (lowest > 49.0)[parts.dot] & full[parts.dot]
    np.testing.assert_allclose(light[tir], parts.weight[tir], rtol=1e-9)
    below = (incidence < 45.0) & full[parts.dot]
    ratio = light[below] / parts.weight[below]
    # Within each dot the ratio rises with the incidence, by over 1 % across many dots.
    dots = 0
    for k in np.unique(parts.dot[below]):
        own = parts.dot[below] == k
        if own.sum() < 16:
            continue
        order = np.argsort(incidence[below][own])
        r = ratio[own][order]
        assert np.all(np.diff(r) > -1e-12 * r.max())
        dots += r[-1] > 1.01 * r[0]
    assert dots > 20


def test_the_loss_gradient_is_its_finite_difference(rig):
    # The adjoint (blur, splat, pixel Jacobians, coefficients) against central differences of
    # the loss along random directions.
    rng = np.random.default_rng(1)
    parts = DotParticles.of(rig, rig.dot_panel_px[rig.lit][::7], order=3, roughness=0.005,
                            facets=4)
    shape = (rig.camera_s.height_px, rig.camera_s.width_px)
    model = PatternModel(rig, parts, shape)
    h0 = rig.cfg.water.h0_mm
    xy = (parts.origin_mm + model.flat_t(h0)[:, None] * parts.dirs)[:, :2]
    spline = BSplineSurface.covering(xy, 12.0, h0)
    spline.coeffs += rng.normal(0.0, 0.3, spline.coeffs.shape)
    truth = BSplineSurface(spline.x0_mm, spline.y0_mm, spline.step_mm,
                           spline.coeffs + rng.normal(0.0, 0.3, spline.coeffs.shape))
    image_of = _Objective(model, Raster(shape, 1.5), np.zeros(shape), truth.coeffs.shape,
                          model.flat_t(h0), 0.0)
    observed = image_of.image(model.trace(truth, model.flat_t(h0)))
    obj = _Objective(model, Raster(shape, 1.5), observed, spline.coeffs.shape,
                     model.flat_t(h0), 1e-4)
    traced = model.trace(spline, obj.t)
    obj.set_mask(traced, 8.0)
    obj.fit_amplitudes(traced)
    c = spline.coeffs.ravel()
    for _ in range(3):
        obj.t = model.trace(spline, model.flat_t(h0)).t  # a converged start: same hits
        _, grad = obj(c, spline)
        v = rng.normal(size=c.size)
        eps = 1e-4
        up = obj(c + eps * v, spline)[0]
        down = obj(c - eps * v, spline)[0]
        fd = (up - down) / (2 * eps)
        # Bilinear footprints bend where a particle crosses a pixel's edge: a small absolute
        # part of the gradient's size (a random direction's derivative is ~ |grad|).
        assert np.isclose(grad @ v, fd, rtol=0.02, atol=0.005 * np.linalg.norm(grad))


def test_the_light_of_dots_the_fit_leaves_out_stays_out_of_its_loss(rig):
    # Flat water, every dot lit, half of them (a checkerboard of the lattice) modelled: the
    # other half's spots, named as unmodelled, take the pixels nearer them out of the loss.
    # At the true surface the loss is then near zero and the modelled dots' brightness near
    # its truth (1); scored with the neighbours' light the same fit is off in both.
    lit = np.flatnonzero(rig.lit)
    ij = rig.dot_ij[lit]
    kept = lit[(ij.sum(axis=1) % 2) == 0]
    left = lit[(ij.sum(axis=1) % 2) == 1]
    _, model_all, flat_all, traced_all = _on_flat_water(rig, rig.dot_panel_px[lit])
    shape = model_all.shape
    h0 = rig.cfg.water.h0_mm
    observed = _Objective(model_all, Raster(shape, 1.5), np.zeros(shape),
                          flat_all.coeffs.shape, model_all.flat_t(h0), 0.0).image(traced_all)
    parts, model, flat, traced = _on_flat_water(rig, rig.dot_panel_px[kept])
    unmodelled = np.array([traced_all.px[model_all.particles.dot == k].mean(axis=0)
                           for k in np.flatnonzero(np.isin(lit, left))])
    result = {}
    for name, spots in (("scored", None), ("left out", unmodelled)):
        obj = _Objective(model, Raster(shape, 1.5), observed, flat.coeffs.shape,
                         model.flat_t(h0), 0.0)
        obj.set_mask(traced, 8.0, spots)
        obj.fit_amplitudes(traced)
        result[name] = (obj(flat.coeffs.ravel(), flat)[0], np.median(np.abs(obj.amplitudes - 1)))
    assert result["left out"][0] < 0.2 * result["scored"][0]
    assert result["left out"][1] < 0.5 * result["scored"][1]


def test_bad_options_are_refused():
    from wai_core.errors import WaiInputError

    for bad in ({"blur_px": 0.0}, {"passes": 0}, {"roughness": 1.5}, {"min_explained": 1.0},
                {"start": "flat-water"}):
        with pytest.raises(WaiInputError):
            InverseRenderingOptions(**bad)


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    from mitsuba_wai import render_folder
    from wai_core.system import load_rig

    folder = tmp_path_factory.mktemp("inverse") / "frame"
    render_folder(load_rig("paper").replace("waves", seed=11), folder, progress=False)
    return folder


def test_a_rendered_frame_is_refitted_as_well_as_the_structured_light(frame):
    # Ideal water, a seed the method never saw: the refit keeps the structured light's
    # accuracy (the target: within + 0.005 mm), says ok, and writes beside it.
    assert main(["restore", str(frame), "--quiet"]) == 0
    assert main(["restore", str(frame), "--method", "inverse-rendering", "--quiet"]) == 0
    sl = json.loads((frame / "restore" / "metrics.json").read_text())
    ir = json.loads((frame / "restore_inverse-rendering" / "metrics.json").read_text())
    assert ir["method"] == "inverse-rendering" and ir["status"] == "ok"
    assert ir["wai_rmse_mm"] <= sl["wai_rmse_mm"] + 0.005
    assert ir["feature_counts"]["dots_fitted"] > 500
    # The loss curve: one entry at the start and one per L-BFGS iteration, each pass's own
    # iterations never raising it (a line search accepts only a decrease).
    anchor = ir["anchor"]
    curve = np.array(anchor["image_fit_curve"])
    assert 2 <= len(curve) <= anchor["image_fit_evaluations"] + 1
    assert curve[-1] < curve[0] and curve[-1] == pytest.approx(anchor["image_fit_loss"][-1])
    assert np.sum(np.diff(curve) > 1e-12) <= len(anchor["image_fit_loss"]) - 1
    assert anchor["image_fit_ms_per_evaluation"] > 0


def test_a_fit_that_explains_too_little_is_inconsistent(frame):
    from restoration import Calibration, InverseRendering

    cal = Calibration.from_folder(frame)
    images = cal.load_images(frame)
    result = InverseRendering(InverseRenderingOptions(min_explained=0.99, passes=1,
                                                      iterations=3))(images, cal)
    assert result.status == "inconsistent" and "median dot's light" in result.message


@pytest.mark.slow
def test_a_fit_started_at_the_views_level_keeps_it(tmp_path):
    # wai restore --method inverse-rendering-view: the fit starts from the surface whose
    # level camera v's view pins (an object with texture, so that the view has one to give),
    # keeps that level (the image hardly determines it) and its accuracy.
    from mitsuba_wai import render_folder
    from wai_core.system import load_rig

    frame = tmp_path / "speckle"
    render_folder(load_rig("paper").replace("waves", seed=11).replace("object",
                                                                       texture="speckle"),
                  frame, progress=False)
    for method in ("structured-light-view", "inverse-rendering-view"):
        assert main(["restore", str(frame), "--method", method, "--quiet"]) == 0
    slv = json.loads((frame / "restore_structured-light-view" / "metrics.json").read_text())
    ir = json.loads((frame / "restore_inverse-rendering-view" / "metrics.json").read_text())
    assert slv["anchor"]["method"] == "view"
    assert ir["method"] == "inverse-rendering-view" and ir["status"] == "ok"
    assert ir["anchor"]["method"] == "view" and ir["anchor"]["image_fit_evaluations"] > 0
    z = {m: np.load(frame / f"restore_{m}" / "heightfield_est.npz")["z"]
         for m in ("structured-light-view", "inverse-rendering-view")}
    level = np.nanmean(z["inverse-rendering-view"] - z["structured-light-view"])
    assert abs(level) < 0.005
    assert ir["wai_rmse_mm"] <= slv["wai_rmse_mm"] + 0.005
    # Where that start is ok, the fit that falls back on Schlieren's surface is this one.
    from restoration import restore_folder

    fallback = restore_folder(frame, "inverse-rendering-schlieren", write=False)
    assert fallback.result.surface.anchor.image_fit_start == "structured-light-view"
    np.testing.assert_array_equal(fallback.result.surface.heightfield.z,
                                  z["inverse-rendering-view"])


@pytest.mark.slow
def test_where_the_structured_light_gives_no_surface_the_fit_starts_from_schlieren(tmp_path):
    # U = 1 m/s, sea 3, gravity-capillary waves to 6 omega_p, 10 s (the compare case
    # capillary_6, frame 0): the structured light at the view's level gives no surface (too
    # few spots labelled, or a level it cannot pin). Schlieren's, at the
    # level camera s's spots show, predicts every dot's spot; the dots that land clearly on
    # one detected spot are the fit's. Those labels must be the renderer's (the spot nearest
    # each dot's true reflection, less flat water's shift), and the refit ok within 0.1 mm of
    # the truth.
    from restoration import Status, get_method, restore_folder
    from restoration.features import detect_spots
    from restoration.features.camera_s import pinhole_spots
    from restoration.inverse_rendering import MIN_DOTS
    from restoration.pattern_level import dots_on_spots, predicted_spots_px
    from tests.conftest import render_paper_frame
    from wai_core.heightfield import load_heightfield

    frame = render_paper_frame(tmp_path / "f", seed=3, texture="speckle",
                               waves={"dispersion": "capillary", "omega_max_rel": 6.0,
                                      "time_s": 10.0})
    light = restore_folder(frame, "structured-light-view", write=False).result
    assert light.status is not Status.OK
    assert main(["restore", str(frame), "--method", "inverse-rendering-schlieren",
                 "--quiet"]) == 0
    ir = json.loads((frame / "restore_inverse-rendering-schlieren" / "metrics.json").read_text())
    assert ir["status"] == "ok" and ir["anchor"]["image_fit_start"] == "schlieren-sl"
    assert ir["anchor"]["method"] == "pattern" and ir["wai_rmse_mm"] <= 0.1
    # Its time: the structured light's and Schlieren's, then the labels and the fit.
    times = ir["timings_ms"]
    assert 0 < times["image_fit"] < times["end_to_end"]
    assert times["end_to_end"] >= times["level"] + times["image_fit"]

    start = restore_folder(frame, "schlieren-sl", write=False).result
    cal = get_method("schlieren-sl").calibration_type.from_folder(frame)
    images = cal.load_images(frame)
    reference = cal.prepare(images["pattern_flat"])
    spots = pinhole_spots(detect_spots(images["pattern"], scales=reference.spot_scales),
                          cal.cfg).centres_px
    rig = cal.cfg.rig
    shift = reference.flat_shift_at(rig.dot_ij)
    level = float(np.mean(start.surface.points_mm[:, 2]))
    predicted = predicted_spots_px(start.surface.heightfield, level, cal) + shift
    dots, found = dots_on_spots(predicted, spots, reference.median_spacing_px)
    assert len(dots) >= MIN_DOTS
    truth = spots_through(rig, load_heightfield(frame / "heightfield.npz"),
                          rig.dot_panel_px[dots]) + shift[dots]
    nearest = np.argmin(np.linalg.norm(spots[None] - truth[:, None], axis=2), axis=1)
    assert np.mean(nearest == found) >= 0.99


def test_the_view_start_is_a_method_of_its_own():
    from restoration import InverseRenderingView, get_method

    # Its start is always the view's, whatever options it is given, and it reads the
    # view's calibration (the flat-water view pins the level).
    method = get_method("inverse-rendering-view", n_refine=0)
    assert isinstance(method, InverseRenderingView)
    assert method.options.start == "structured-light-view" and method.options.n_refine == 0
    assert InverseRenderingView(InverseRenderingOptions()).options.start == method.options.start
    assert method.calibration_type is get_method("structured-light-view").calibration_type


def test_the_schlieren_fallback_is_a_method_of_its_own():
    from restoration import InverseRenderingSchlieren, get_method

    # Its start is always "schlieren-sl", whatever options it is given, and it reads the
    # calibration Schlieren's surface needs (the flat-water view).
    method = get_method("inverse-rendering-schlieren", iterations=3)
    assert isinstance(method, InverseRenderingSchlieren)
    assert method.options.start == "schlieren-sl" and method.options.iterations == 3
    assert (InverseRenderingSchlieren(InverseRenderingOptions(start="structured-light"))
            .options.start == "schlieren-sl")
    assert method.calibration_type is get_method("schlieren-sl").calibration_type
    assert repr(method).startswith("InverseRenderingSchlieren(")
