"""Synthetic Schlieren: Snell's law inverted per pixel, surfaces from exact displacements, and
rendered frames through a speckle object (the issue's target) and through the paper's
checkerboard (where the flow cannot follow the waves: never ``ok``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from restoration import Schlieren, SchlierenCalibration, SchlierenOptions, surface_errors
from restoration.schlieren import SightLines, reconstruct_schlieren, slopes_on_sight_lines
from tests.conftest import render_paper_frame
from wai.cli import main
from wai_core.geometry import refract
from wai_core.heightfield import Heightfield
from wai_core.optics import trace_to_object


def test_snells_law_is_inverted_at_every_pixel():
    # Sight lines refracted out of the water by known normals (wai_core's Snell, eq. 20) reach
    # object points; from those points the normals and slopes come back exactly.
    rng = np.random.default_rng(3)
    k = 500
    d = rng.normal([0.0, 0.0, 1.0], 0.2, (k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    slopes = rng.uniform(-0.15, 0.15, (k, 2))
    normal = np.column_stack([-slopes, np.ones(k)])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    air, tir = refract(d, normal, 1.34)
    d, normal, slopes, air = d[~tir], normal[~tir], slopes[~tir], air[~tir]  # (a few: TIR)
    k = len(d)
    assert k > 400
    points = rng.uniform(-100.0, 100.0, (k, 3))
    obj = points + rng.uniform(200.0, 2000.0, (k, 1)) * air
    n_back, s_back = slopes_on_sight_lines(points, d, obj, 1.34)
    np.testing.assert_allclose(n_back, normal, atol=1e-12)
    np.testing.assert_allclose(s_back, slopes, atol=1e-12)


@pytest.fixture(scope="module")
def cal():
    from wai_core import load_system

    return SchlierenCalibration(load_system("paper"))


def _waves(cal, amplitude_mm=3.0):
    h0 = cal.cfg.water.h0_mm
    x = np.linspace(-700.0, 900.0, 801)
    y = np.linspace(-700.0, 700.0, 701)
    xx, yy = np.meshgrid(x, y)
    z = h0 + amplitude_mm * (np.sin(2 * np.pi * xx / 420.0 + 0.3)
                             * np.cos(2 * np.pi * yy / 610.0) + 0.2)
    return Heightfield(x, y, z)


def _reconstruct_exact(cal, truth, level_mm=None):
    """The method's surface from the object points each sample's line of sight reaches through
    ``truth``, traced by the restoration's own forward model (wai_core.optics, not the
    method), at ``level_mm`` (None: the gauge's h0)."""
    options = SchlierenOptions()
    lines = SightLines.build(cal, options.sample_step_px)
    cfg = cal.cfg
    traced = trace_to_object(cal.camera_v, truth, cfg.water.h0_mm, cfg.water.n_water,
                             cfg.object_z_mm, lines.px[:, 0], lines.px[:, 1])
    index = np.flatnonzero(traced.ok)
    return reconstruct_schlieren(lines, index, traced.object_mm[index], cal, options, level_mm)


def test_exact_displacements_give_the_surface_to_its_shape(cal):
    # The object points each pixel sees through a known surface, traced by the restoration's
    # own forward model (wai_core.optics, not the method): the method recovers the surface
    # to well under the 0.1 mm (de-meaned), its mean at the gauge's h0.
    truth = _waves(cal)
    est = _reconstruct_exact(cal, truth)
    err = surface_errors(est.heightfield, truth)
    assert err["rmse_demeaned_mm"] < 0.03
    assert np.mean(est.points_mm[:, 2]) == pytest.approx(cal.cfg.water.h0_mm, abs=1e-6)
    # The samples lie where their lines of sight cross the true surface (up to the level).
    lift = est.points_mm[:, 2] - truth.height(est.points_mm[:, 0], est.points_mm[:, 1])
    assert np.std(lift) < 0.03
    true_slopes = np.column_stack(truth.gradient(est.points_mm[:, 0], est.points_mm[:, 1]))
    # (the slopes carry the level's error: 0.6 mm off here tilts them by ~1 % of their 0.045)
    assert np.sqrt(np.mean((est.slopes - true_slopes) ** 2)) < 1e-3


def test_the_shape_is_only_as_right_as_the_level(cal):
    # The same waves with the patch raised 20 mm above the gauge's h0 (a long wave under it):
    # exact displacements, reconstructed at h0, bend into another shape; at the patch's true
    # mean they give it back. Nothing in the view tells the two apart, so the method cannot
    # call its own frames right: its status is the gauge's level (rendered frames below).
    raised = _waves(cal)
    raised = Heightfield(raised.x, raised.y, raised.z + 20.0)
    at_gauge = _reconstruct_exact(cal, raised)
    pts = at_gauge.points_mm
    true_mean = float(np.mean(raised.height(pts[:, 0], pts[:, 1])))
    at_truth = _reconstruct_exact(cal, raised, true_mean)
    bent = surface_errors(at_gauge.heightfield, raised)["rmse_demeaned_mm"]
    right = surface_errors(at_truth.heightfield, raised)["rmse_demeaned_mm"]
    assert right < 0.03 < 0.1 < bent


def _render(root, name, texture, seed, wind=1.0):
    return render_paper_frame(root / name, seed=seed, texture=texture, wind=wind)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    root = tmp_path_factory.mktemp("schlieren")
    return {"speckle": _render(root, "speckle", "speckle", seed=5),
            "checkerboard": _render(root, "checkerboard", "checkerboard", seed=5)}


def test_a_speckle_object_gives_the_surface_within_the_target(frames):
    # U = 1 m/s, a seed the method's design never saw: de-meaned RMSE <= 0.1 mm (the issue's
    # target; the linearised method's own floor here is 0.06-0.10 mm). The flow's checks
    # pass, and the frame says its level is the gauge's: nothing in the view pins it.
    assert main(["restore", str(frames["speckle"]), "--method", "schlieren", "--quiet"]) == 0
    out = frames["speckle"] / "restore_schlieren"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "schlieren" and metrics["status"] == "gauge_level"
    assert metrics["consistency"]["consistent"]
    assert metrics["wai_rmse_demeaned_mm"] <= 0.1
    assert metrics["anchor"]["method"] == "gauge"
    assert metrics["feature_counts"]["used"] > 0.5 * metrics["feature_counts"]["samples"]
    assert not (frames["speckle"] / "restore").exists()  # the folder's own method's place


def test_the_paper_checkerboard_is_never_ok(frames):
    # 200 mm squares: inside them the flow has nothing to follow, so most samples fail the
    # round trip or the surface does not reproduce them; the status says so.
    cal = SchlierenCalibration.from_folder(frames["checkerboard"])
    result = Schlieren()(cal.load_images(frames["checkerboard"]), cal)
    assert result.status in ("sparse", "inconsistent")


def test_a_frame_without_its_flat_view_is_bad_input(frames, tmp_path, capsys):
    import shutil

    folder = tmp_path / "no_flat"
    shutil.copytree(frames["speckle"], folder, ignore=shutil.ignore_patterns("view_truth*",
                                                                            "restore*"))
    assert main(["restore", str(folder), "--method", "schlieren", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "view_flat" in err[0]



def test_a_sequence_restored_by_both_methods_keeps_both(tmp_path):
    # The structured light's restore/ and Schlieren's restore_schlieren/, in the sequence's
    # folder and in every frame's: one method's run never replaces the other's.
    from mitsuba_wai import render_sequence
    from restoration import restore_sequence
    from wai_core.system import load_rig

    folder = tmp_path / "seq"
    render_sequence(load_rig("schlieren").replace("waves", seed=6), folder, 2, 30.0,
                    progress=False)
    restore_sequence(folder, movie=False)
    done = restore_sequence(folder, "schlieren", movie=False)
    assert [r["status"] for r in done.rows] == ["gauge_level", "gauge_level"]
    for where in (folder, folder / "frame000", folder / "frame001"):
        kinds = {p.name for p in where.iterdir() if p.name.startswith("restore")}
        assert kinds == {"restore", "restore_schlieren"}, where
    ours = json.loads((folder / "frame001" / "restore_schlieren" / "metrics.json").read_text())
    theirs = json.loads((folder / "frame001" / "restore" / "metrics.json").read_text())
    assert (ours["method"], theirs["method"]) == ("schlieren", "structured-light")


def test_samples_the_flow_puts_near_the_objects_edge_are_left_out():
    # A lattice whose right part does not see the object (beyond its edge): flat-water
    # pixels within the margin of that part, or of the image's border, are not kept.
    from restoration.schlieren import _inside_view

    rows, cols = np.mgrid[4:100:8, 4:160:8]
    px = np.column_stack([cols.ravel(), rows.ravel()]).astype(float)
    lines = SightLines(np.zeros((len(px), 2), np.int64), px, np.zeros((len(px), 3)),
                       np.zeros((len(px), 3)), px[:, 0] < 100.0)
    q = np.array([[60.0, 50.0], [90.0, 50.0], [8.0, 50.0], [60.0, 95.0], [np.nan, 50.0]])
    assert _inside_view(lines, q, 16.0, (100, 160)).tolist() == [True, False, False, False,
                                                                   False]
    assert _inside_view(lines, q[:4], 0.0, (100, 160)).all()
