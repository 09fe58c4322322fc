"""Synthetic Schlieren at the structured light's level (``--method schlieren-sl``): the level
rule against surfaces of known offset, and a rendered frame whose patch lies millimetres
from the gauge's h0 (a long wave under it), restored against its truth."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from restoration import RaySurface, RestoreResult, Status
from restoration.frame import anchor_line
from restoration.level import Anchor
from restoration.schlieren_level import MAX_DIFFERENCE_MM, MIN_SHARED, structured_light_level
from tests.conftest import render_paper_frame
from wai.cli import main
from wai_core.heightfield import Heightfield


def _sea(offset_mm=0.0):
    x = np.linspace(-200.0, 200.0, 201)
    y = np.linspace(-150.0, 150.0, 151)
    xx, yy = np.meshgrid(x, y)
    return Heightfield(x, y, 150.0 + offset_mm + 2.0 * np.sin(xx / 40.0) * np.cos(yy / 55.0))


def _samples(sea, xy):
    """A Schlieren surface whose samples lie on ``sea`` at ``xy`` (K, 2)."""
    z = sea.height(xy[:, 0], xy[:, 1])
    return RaySurface(heightfield=sea, ij=np.zeros((len(xy), 2), int),
                      points_mm=np.column_stack([xy, z]), normals=np.zeros((len(xy), 3)),
                      slopes=np.zeros((len(xy), 2)), iterations=0, height_change_mm=0.0,
                      kept=np.arange(len(xy)))


def _light(sea, status=Status.OK, message=""):
    surface = SimpleNamespace(heightfield=sea, anchor=Anchor("view", 151.0, sigma_mm=0.004))
    return RestoreResult("structured-light-view", status, message, surface=surface)


@pytest.fixture
def xy():
    return np.random.default_rng(4).uniform([-150.0, -100.0], [150.0, 100.0], (400, 2))


def test_the_level_moves_by_the_structured_lights_offset(xy):
    # The structured light's surface is the same sea 3.7 mm higher: the rule puts the
    # samples' mean 3.7 mm higher, and passes no verdict on an ok level.
    at_gauge = _samples(_sea(), xy)
    anchor, verdict = structured_light_level(_light(_sea(3.7)), 150.0)(at_gauge)
    assert anchor.method == "structured_light" and verdict is None
    assert anchor.anchor_mm == pytest.approx(np.mean(at_gauge.points_mm[:, 2]) + 3.7, abs=1e-9)
    assert anchor.sigma_mm == 0.004


def test_an_uncertain_or_missing_level_is_said(xy):
    at_gauge = _samples(_sea(), xy)
    _, (status, message) = structured_light_level(
        _light(_sea(0.5), Status.UNCERTAIN_LEVEL, "the level's standard error is 0.2 mm"),
        150.0)(at_gauge)
    assert status is Status.UNCERTAIN_LEVEL and "0.2 mm" in message
    # A failed frame, and a surface over too little of the patch: the gauge's level.
    failed = RestoreResult("structured-light-view", Status.FAILED, "too few spots")
    anchor, (status, message) = structured_light_level(failed, 150.0)(at_gauge)
    assert (anchor.method, anchor.anchor_mm, status) == ("gauge_fallback", 150.0,
                                                          Status.GAUGE_LEVEL)
    assert "too few spots" in message
    edge = at_gauge.points_mm[:, 0].min() + 0.5 * MIN_SHARED * 300.0
    corner = _sea(1.0)
    corner = Heightfield(corner.x, corner.y, np.where(corner.x[None, :] < edge, corner.z, np.nan))
    anchor, (status, _) = structured_light_level(_light(corner), 150.0)(at_gauge)
    assert status is Status.GAUGE_LEVEL and anchor.anchor_mm == 150.0


def test_two_shapes_that_differ_in_a_part_are_inconsistent(xy):
    # The structured light's surface carries a 0.3 mm bump over a tenth of the patch that
    # Schlieren's samples lack (one of the two is wrong there): RMS about 0.3 * sqrt(0.1) ~
    # 0.09 mm, past the bound; the same surfaces without the bump agree, and the level the
    # rule sets is the median's, which the bump does not move.
    sea = _sea(2.0)
    bump = np.where(sea.x[None, :] > 120.0, 0.3, 0.0) * np.ones_like(sea.z)
    at_gauge = _samples(_sea(), xy)
    anchor, (status, message) = structured_light_level(
        _light(Heightfield(sea.x, sea.y, sea.z + bump)), 150.0)(at_gauge)
    assert status is Status.INCONSISTENT and "wrong in a part" in message
    assert anchor.source_difference_mm > MAX_DIFFERENCE_MM
    assert anchor.anchor_mm == pytest.approx(np.mean(at_gauge.points_mm[:, 2]) + 2.0, abs=1e-9)
    anchor, verdict = structured_light_level(_light(sea), 150.0)(at_gauge)
    assert verdict is None and anchor.source_difference_mm < 1e-9
    # The verdict outranks an uncertain level: a wrong shape is worse news.
    _, (status, _) = structured_light_level(
        _light(Heightfield(sea.x, sea.y, sea.z + bump), Status.UNCERTAIN_LEVEL), 150.0)(at_gauge)
    assert status is Status.INCONSISTENT


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    # U = 1 m/s, sea 7: the patch camera v sees lies ~17 mm below h0 (a long wave's trough).
    return render_paper_frame(tmp_path_factory.mktemp("schlieren_sl") / "f", seed=7,
                              texture="speckle")


@pytest.mark.slow
def test_the_structured_lights_level_takes_schlieren_to_its_floor(frame):
    # At the gauge's level the slopes bend (de-meaned 0.25 mm, absolute ~17 mm); at the
    # structured light's, the truth says within 0.1 mm de-meaned and 0.2 mm absolute.
    for method in ("schlieren", "schlieren-sl"):
        assert main(["restore", str(frame), "--method", method, "--quiet"]) == 0
    plain, levelled = (json.loads((frame / f"restore_{m}" / "metrics.json").read_text())
                       for m in ("schlieren", "schlieren-sl"))
    assert plain["wai_rmse_mm"] > 5.0 and plain["wai_rmse_demeaned_mm"] > 0.15
    assert levelled["status"] == "ok" and levelled["anchor"]["method"] == "structured_light"
    assert levelled["wai_rmse_demeaned_mm"] <= 0.1
    assert levelled["wai_rmse_mm"] <= 0.2


@pytest.mark.slow
def test_one_frame_computes_its_flow_once(frame, monkeypatch):
    # The structured light's level from the view and Schlieren's surface read one flow; a new
    # frame's images (new arrays) get their own.
    import restoration.schlieren as schlieren
    from restoration import SchlierenLevelled, ViewLevelCalibration

    calls = []
    real = schlieren.flat_view_flow
    monkeypatch.setattr(schlieren, "flat_view_flow",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    cal = ViewLevelCalibration.from_folder(frame)
    images = cal.load_images(frame)
    method = SchlierenLevelled()
    assert method(images, cal).status == "ok" and len(calls) == 1
    method({name: image.copy() for name, image in images.items()}, cal)
    assert len(calls) == 2


def test_a_frame_that_stops_early_says_so_with_its_time(monkeypatch):
    # Schlieren's flow serving too few samples (a sparse frame, no surface, no timings of its
    # own) beside a structured light that failed: the frame is sparse, timed by the level's
    # source.
    import restoration.schlieren_level as module
    from restoration import SchlierenLevelled

    monkeypatch.setattr(module, "restore_schlieren", lambda images, cal, options, rule:
                        RestoreResult("schlieren", Status.SPARSE, "the flow serves 3 %"))
    method = SchlierenLevelled()
    monkeypatch.setattr(method, "light", lambda images, cal, track: RestoreResult(
        "structured-light-view", Status.FAILED, "no spots", timings_ms={"end_to_end": 12.5}))
    cal = SimpleNamespace(cfg=SimpleNamespace(water=SimpleNamespace(h0_mm=150.0)))
    result = method({}, cal)
    assert (result.method, result.status, result.message) == ("schlieren-sl", Status.SPARSE,
                                                               "the flow serves 3 %")
    assert result.timings_ms == {"level": 12.5, "end_to_end": 12.5}


def test_an_ok_frame_is_right_where_its_lines_of_sight_could_not_be_checked(tmp_path):
    # U = 1 m/s, sea 1, 10.233 s, a speckle object: near the view's right edge the flow bent
    # Schlieren's surface up to 4 mm off while every sample the forward check traced lay
    # within 0.03 mm, and the frame said ok at 0.27 mm RMSE. The samples whose lines of sight
    # the check cannot trace through the surface are not vouched for: the truth must find an
    # ok frame within 0.1 mm everywhere it restored.
    frame = render_paper_frame(tmp_path / "f", seed=1, texture="speckle",
                               waves={"time_s": 10.0 + 7 / 30})
    assert main(["restore", str(frame), "--method", "schlieren-sl", "--quiet"]) == 0
    metrics = json.loads((frame / "restore_schlieren-sl" / "metrics.json").read_text())
    assert metrics["status"] == "ok"
    assert metrics["wai_rmse_mm"] <= 0.1
    assert metrics["feature_counts"]["unverified"] > 0


def _found(score, runner_up, residual_px=0.2):
    from restoration.pattern_level import PatternLevel

    return PatternLevel(level_mm=148.6, score=score, runner_up=runner_up, matched_share=0.5,
                        residual_px=residual_px, spacing_px=13.0, evaluations=70)


def test_without_the_structured_lights_level_the_search_runs_once_and_says_if_it_is_unique(xy):
    # The structured light failed: the level is the search's, asked once however often the
    # rule is; a level another fits nearly as well is uncertain, and so is one whose spots
    # miss by 0.8 px of a 13 px spacing; a search that finds none leaves the gauge's.
    from wai_core.errors import RestorationFailed

    at_gauge = _samples(_sea(), xy)
    failed = _light(_sea(), Status.FAILED, "too few spots")
    calls = []

    def search(rebuild):
        calls.append(rebuild)
        return _found(0.3, 0.6)

    rule = structured_light_level(failed, 150.0, search)
    for _ in range(3):
        anchor, verdict = rule(at_gauge, "rebuild")
    assert calls == ["rebuild"] and verdict is None
    assert (anchor.method, anchor.anchor_mm) == ("pattern", 148.6)
    assert anchor.pattern_alias_ratio == pytest.approx(0.5)
    _, (status, message) = structured_light_level(
        failed, 150.0, lambda rebuild: _found(0.5, 0.55))(at_gauge, "rebuild")
    assert status is Status.UNCERTAIN_LEVEL and "not unique" in message
    _, (status, message) = structured_light_level(
        failed, 150.0, lambda rebuild: _found(0.3, 0.6, residual_px=0.8))(at_gauge, "rebuild")
    assert status is Status.UNCERTAIN_LEVEL and "too blurred" in message

    def none(rebuild):
        raise RestorationFailed("no level sends the dots onto the spots")

    anchor, (status, message) = structured_light_level(failed, 150.0, none)(at_gauge, "r")
    assert (anchor.method, anchor.anchor_mm, status) == ("gauge_fallback", 150.0,
                                                        Status.GAUGE_LEVEL)
    assert "no level sends" in message


def test_where_the_structured_light_fails_the_patterns_spots_give_the_level(tmp_path):
    # U = 1 m/s, sea 1, gravity-capillary waves to 6 omega_p: caustics fold the pattern and the
    # structured light labels too few spots to give a surface (the compare case capillary_6,
    # frame 0). Schlieren's shape is right to 0.004 mm at the true level and millimetres off
    # at the gauge's: the spots, unlabelled, must give the level, the frame ok within 0.1 mm of
    # the renderer's truth; without the search the frame keeps the gauge's level.
    from restoration import SchlierenOptions, get_method, restore_folder

    frame = render_paper_frame(tmp_path / "f", seed=1, texture="speckle",
                               waves={"dispersion": "capillary", "omega_max_rel": 6.0})
    light = restore_folder(frame, "structured-light-view", write=False)
    assert light.result.status not in (Status.OK, Status.UNCERTAIN_LEVEL)
    assert main(["restore", str(frame), "--method", "schlieren-sl", "--quiet"]) == 0
    metrics = json.loads((frame / "restore_schlieren-sl" / "metrics.json").read_text())
    assert metrics["status"] == "ok" and metrics["anchor"]["method"] == "pattern"
    assert metrics["wai_rmse_mm"] <= 0.1
    line = anchor_line(metrics["anchor"])
    assert "from camera s's spots" in line and "gauge" not in line
    plain = restore_folder(frame, get_method("schlieren-sl", SchlierenOptions(level_search_mm=0)),
                           write=False)
    assert plain.result.status is Status.GAUGE_LEVEL
    assert plain.metrics["wai_rmse_mm"] > 0.25


def test_a_dot_takes_a_spot_only_where_the_spot_is_clearly_its_own():
    from restoration.pattern_level import LABEL_RATIO, LABEL_REACH, dots_on_spots

    # A lattice of spots 10 px apart, each dot predicted 0.5 px off its own: all labelled,
    # each with its own spot. Then the cases the rule refuses.
    ii, jj = np.meshgrid(np.arange(6), np.arange(5))
    spots = 10.0 * np.column_stack([ii.ravel(), jj.ravel()])
    predicted = spots + 0.5
    dots, found = dots_on_spots(predicted, spots, spacing_px=10.0)
    assert dots.tolist() == list(range(30)) and found.tolist() == list(range(30))
    moved = predicted.copy()
    moved[0] = spots[0] + LABEL_REACH * 10.0 + 0.1         # too far from any spot
    moved[1] = (spots[1] + spots[2]) / 2                    # halfway: not clearly either
    moved[3] = spots[4] + 0.3                               # claims dot 4's spot too
    moved[5] = [np.nan, np.nan]                             # off the surface
    dots, found = dots_on_spots(moved, spots, spacing_px=10.0)
    assert not set(dots) & {0, 1, 3, 4, 5} and len(dots) == 25
    assert (found == dots).all()
    # The ratio rule: the nearest spot 2 px away, the next beyond or within 2 / LABEL_RATIO.
    for beyond, labelled in ((2.0 / LABEL_RATIO + 0.2, [0]), (2.0 / LABEL_RATIO - 0.2, [])):
        two = np.array([[2.0, 0.0], [-beyond, 0.0]])
        assert dots_on_spots(np.zeros((1, 2)), two, spacing_px=10.0)[0].tolist() == labelled
