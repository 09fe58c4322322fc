"""The structured light's level pinned by camera v's view (restoration.view_level), on renders
the restoration did not make: rough water, whose blurred spots leave the integrability level
uncertain, seen through by camera v at a speckle object. The truth is the renderer's surface."""

from __future__ import annotations

import json
import shutil

import pytest

from restoration import StructuredLightView, ViewLevelCalibration
from tests.conftest import render_paper_frame
from wai.cli import main

ROUGH_SEED = 3  # U = 1 m/s; the spots' labels hold on this sea at alpha 0.01 (many fail)


def _render(root, name, seed, texture, roughness):
    rough = {"water": {"roughness": roughness}, "render": {"spp_pattern": 64}}
    return render_paper_frame(root / name, seed=seed, texture=texture,
                              **(rough if roughness else {}))


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    root = tmp_path_factory.mktemp("view_level")
    return {"rough": _render(root, "rough", ROUGH_SEED, "speckle", 0.01),
            "checkerboard": _render(root, "checkerboard", ROUGH_SEED, "checkerboard", 0.01)}


def _metrics(folder, method):
    out = folder / ("restore" if method == "structured-light" else f"restore_{method}")
    return json.loads((out / "metrics.json").read_text())


def test_the_view_pins_the_level_that_rough_spots_leave_uncertain(frames):
    # GGX alpha 0.01 blurs every spot: the slopes' integrability leaves the level's standard
    # error past the bound (uncertain_level). The view's lines of sight through the surface
    # pin it: ok, within 0.05 mm of the truth and nearer it than the integrability level.
    folder = frames["rough"]
    assert main(["restore", str(folder), "--quiet"]) == 0
    assert main(["restore", str(folder), "--method", "structured-light-view", "--quiet"]) == 0
    plain, view = _metrics(folder, "structured-light"), _metrics(folder, "structured-light-view")
    assert plain["status"] == "uncertain_level", plain["message"]
    assert view["status"] == "ok", view["message"]
    assert view["anchor"]["method"] == "view" and view["anchor"]["sigma_mm"] < 0.02
    assert view["anchor"]["view_served_share"] >= 0.6
    assert view["wai_rmse_mm"] <= min(0.05, plain["wai_rmse_mm"])


def test_a_checkerboard_object_never_pins_a_wrong_level_as_ok(frames):
    # The paper's 200 mm squares leave the flow nothing to follow inside them: the view's
    # level is as uncertain as the spots' (or not searched), and the frame says so.
    cal = ViewLevelCalibration.from_folder(frames["checkerboard"])
    result = StructuredLightView()(cal.load_images(frames["checkerboard"]), cal)
    assert result.status != "ok", result.surface.anchor
    assert result.surface.anchor.view_textured_share < 0.45


@pytest.fixture(scope="module")
def ripples(tmp_path_factory):
    # Gravity-capillary ripples to 5 omega_p at U = 1 m/s (the compare case, seed 0, its first
    # frame): they fold the pattern, and only a patch of about a hundred dots is matched,
    # with no marker dot among them to pin its lattice shift.
    root = tmp_path_factory.mktemp("ripples")
    waves = {"dispersion": "capillary", "omega_max_rel": 5.0}
    return {texture: render_paper_frame(root / texture, seed=0, texture=texture, waves=waves)
            for texture in ("speckle", "checkerboard")}


def test_the_view_pins_a_small_patch_s_labels_that_the_pattern_leaves_open(ripples):
    # Labels a dot off send camera v's lines of sight millimetres astray on the object (6-15
    # px of flat-water view on rough water, against 0.25 px for the right ones): the view
    # tells the labellings apart where the integrability of a small patch cannot, and the
    # patch is no longer sparse. The truth: the surface within a tenth of a spot's worth.
    from restoration import StructuredLight, surface_errors
    from wai_core.heightfield import load_heightfield

    folder = ripples["speckle"]
    cal = ViewLevelCalibration.from_folder(folder)
    images = cal.load_images(folder)
    plain = StructuredLight()(images, cal)
    assert plain.status == "sparse" and plain.features.counts["labels_ambiguous"] == 1
    view = StructuredLightView()(images, cal)
    assert view.features.counts["labels_pinned_by_view"] == 1
    assert view.features.counts["labels_ambiguous"] == 0
    assert view.status == "ok", view.message
    err = surface_errors(view.surface.heightfield, load_heightfield(folder / "heightfield.npz"))
    assert err["rmse_mm"] < 0.02


def test_without_texture_the_view_pins_no_labels(ripples):
    # The same ripples over the paper's checkerboard: no flow, no lines of sight to weigh the
    # labellings, and the patch stays sparse.
    folder = ripples["checkerboard"]
    cal = ViewLevelCalibration.from_folder(folder)
    view = StructuredLightView()(cal.load_images(folder), cal)
    assert view.features.counts["labels_pinned_by_view"] == 0
    assert view.status == "sparse"


def test_on_water_rougher_than_the_view_can_level_the_frame_is_not_called_ok(tmp_path):
    # GGX alpha 0.02 (U = 1 m/s, sea 20, the compare's second frame; a patch of about 130 dots
    # whose labels the view pinned): camera v's lines of sight miss by about 0.4 px where
    # right surfaces at alpha 0.01 leave at most 0.34, and the level the view picks follows
    # the blurred spots' bias (on this frame 0.26 mm off, with a standard error of about
    # 0.01 mm). The shape is right; the level is not to be trusted: uncertain_level, not ok.
    from restoration import surface_errors
    from restoration.frame_status import VIEW_LEVEL_MAX_RESIDUAL_PX
    from wai_core.heightfield import load_heightfield

    folder = render_paper_frame(tmp_path / "rough_0.02", seed=20, texture="speckle",
                                water={"roughness": 0.02}, render={"spp_pattern": 64},
                                waves={"time_s": 10.0 + 1.0 / 30.0})
    cal = ViewLevelCalibration.from_folder(folder)
    result = StructuredLightView()(cal.load_images(folder), cal)
    err = surface_errors(result.surface.heightfield, load_heightfield(folder / "heightfield.npz"))
    assert result.surface.anchor.method == "view"
    assert result.surface.anchor.view_residual_px > VIEW_LEVEL_MAX_RESIDUAL_PX
    assert result.status == "uncertain_level" and "blurred spots" in result.message, \
        result.message
    assert err["rmse_demeaned_mm"] < 0.05


def test_a_frame_without_its_flat_view_is_bad_input(frames, tmp_path, capsys):
    folder = tmp_path / "no_flat"
    shutil.copytree(frames["rough"], folder, ignore=shutil.ignore_patterns("view_truth*",
                                                                          "restore*"))
    assert main(["restore", str(folder), "--method", "structured-light-view", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "view_flat" in err[0]


def test_the_flat_view_says_where_the_flow_cannot_follow(frames, monkeypatch):
    # The flow is computed only where the flat view has texture in two directions: a single
    # edge direction (stripes) has a rank-one structure tensor, corners have two; the paper's
    # large squares leave too few samples on texture and no flow is run for them.
    import numpy as np

    import restoration.view_level as view_level

    yy, xx = np.mgrid[0:200, 0:200].astype(np.float32)
    px = np.stack(np.meshgrid(np.arange(30, 170, 7.0), np.arange(30, 170, 7.0)), -1).reshape(-1, 2)
    stripes = ((xx // 10) % 2).astype(np.float32)
    checks = (((xx // 10) + (yy // 10)) % 2).astype(np.float32)
    assert view_level.textured_share(stripes, px) < 0.02
    assert view_level.textured_share(checks, px) > 0.3
    flows = []
    flow_samples = view_level.flow_samples
    monkeypatch.setattr(view_level, "flow_samples",
                        lambda *a, **k: flows.append(1) or flow_samples(*a, **k))
    for name, expected in (("checkerboard", []), ("rough", [1])):
        cal = ViewLevelCalibration.from_folder(frames[name])
        samples = view_level.view_samples(cal.load_images(frames[name]), cal)
        assert flows == expected, name
        assert samples.served == (name == "rough")
        assert (samples.textured_share is None) == (name == "rough")


def test_a_few_flow_errors_do_not_pull_the_level(monkeypatch):
    """Residuals whose truth is known: 2000 samples meet their flow points at level 0 (0.1 px
    of noise, each moving 0.5-1.5 px per mm of level), 5 % are flow errors that would meet
    theirs 0.4 mm higher and miss by 1-1.6 px at level 0, inside the search's 2 px clip. Clipped
    at the frame's own noise once found, the level is the samples', not the errors'."""
    import numpy as np

    from restoration import view_level
    from restoration.view_level import ViewSamples, find_view_level

    rng = np.random.default_rng(5)
    k, bad = 2000, 100
    gain = rng.uniform(0.5, 1.5, k)
    gain[:bad] = 3.0
    noise = np.abs(rng.normal(0.0, 0.1, k))
    noise[:bad] = 1.0
    at = np.zeros(k)
    at[:bad] = 0.4

    def residual(level, samples, cal):
        return np.hypot(gain * (level - at), noise)

    monkeypatch.setattr(view_level, "view_residual_px", residual)
    samples = ViewSamples(np.zeros((k, 2)), np.zeros((k, 3)), np.ones(k),
                          np.arange(k) % view_level.N_SETS, {})
    found = find_view_level(lambda level: level, 0.05, samples, None)
    assert abs(found.anchor_mm) < 0.01, found.anchor_mm
    # The errors' own pull, under the 2 px clip alone: what the fine clip removes.
    monkeypatch.setattr(view_level, "FINE_CLIP_MIN_PX", view_level.CLIP_PX)
    pulled = find_view_level(lambda level: level, 0.05, samples, None)
    assert pulled.anchor_mm > 0.05, pulled.anchor_mm


def test_the_view_s_tail_is_read_where_the_flow_is_trusted(frames):
    # Near the object's edge the flow matches the texture to what lies past it: through the
    # renderer's own surface those samples' lines of sight miss their flow points by far more
    # than the others', so a tail read over them would call the true surface wrong in a part.
    # The tail is read over the samples synthetic Schlieren's margin inside the texture.
    from types import SimpleNamespace

    import numpy as np

    import restoration.view_level as view_level
    from restoration.frame_status import VIEW_MAX_TAIL_PX
    from wai_core.heightfield import Heightfield

    folder = frames["rough"]
    cal = ViewLevelCalibration.from_folder(folder)
    samples = view_level.view_samples(cal.load_images(folder), cal)
    truth = np.load(folder / "heightfield.npz")
    true_surface = SimpleNamespace(heightfield=Heightfield(truth["x"], truth["y"], truth["z"]))
    miss = view_level.view_residual_px(true_surface, samples, cal)
    finite = np.isfinite(miss)
    inner, edge = miss[finite & samples.inner], miss[finite & ~samples.inner]
    assert inner.size > 0.6 * finite.sum() and edge.size > 0.05 * finite.sum()
    assert np.percentile(inner, 90) < 0.7 * VIEW_MAX_TAIL_PX
    assert np.percentile(edge, 90) > 3 * np.percentile(inner, 90)
    result = StructuredLightView()(cal.load_images(folder), cal)
    assert result.surface.anchor.view_residual_p90_px < VIEW_MAX_TAIL_PX
