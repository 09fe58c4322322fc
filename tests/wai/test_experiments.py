"""Experiments in their --quick form: every figure and table is produced, and the facts they
report hold (the meridional dψ/dθ = 2, restoration beats distortion)."""

import json
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT
from wai.cli import main
from wai.experiments.paper import deflection_curves
from wai_core.limits import correspondence_limit


def test_meridional_deflection_is_twice_the_tilt_and_sagittal_is_not():
    fits = deflection_curves(np.linspace(-10, 10, 201))["dpsi_dtheta"]
    for pro in (30, 45):
        assert fits[f"θ_pro = {pro}°, meridional"] == pytest.approx(2.0, abs=1e-3)
        # A sagittal tilt turns the ray by 2 sin(theta_pro), not 2 (derived by hand).
        assert fits[f"θ_pro = {pro}°, sagittal"] == pytest.approx(
            2 * np.sin(np.radians(pro)), abs=2e-3
        )


def test_correspondence_limit_follows_eq_35(paper_cfg):
    lim = correspondence_limit(paper_cfg)
    h0, zh = paper_cfg.water.h0_mm, paper_cfg.diffuser.z_mm
    # Plug the bound back into eq. 35: both sides equal.
    lhs = lim["D_mm"] * (2 * h0 - zh) / h0 - lim["delta_p_mm"] / 2
    rhs = (h0 - zh) / np.cos(np.radians(lim["theta_flat_deg"])) ** 2 * 2 * 2 * lim["phi_max_rad"]
    assert lhs == pytest.approx(rhs)
    assert lim["theta_flat_deg"] == pytest.approx(50.0, abs=0.1)  # 90° - 40° elevation


@pytest.mark.slow
def test_paper_experiment_quick(tmp_path):
    out = tmp_path / "paper"
    assert main(["experiment", "paper", "--quick", "--out", str(out)]) == 0
    for name in (
        "report.md",
        "report.html",
        "paper.json",
        "fig8_deflection.png",
        "fig10_surface.png",
        "fig11_features.png",
        "fig11_surfaces.png",
        "fig12_error_map.png",
        "fig15_views.png",
        "fig15d_corners.png",
        "sweep_amplitude.png",
    ):
        assert (out / name).is_file(), name
    data = json.loads((out / "paper.json").read_text())
    for run in data["seeds"]:
        for ds in run["datasets"].values():
            assert ds["restored"]["ssim"] > ds["distorted"]["ssim"]
            assert ds["restored"]["mse"] < ds["distorted"]["mse"]
        assert run["metrics"]["corner_std_restored_px"] < run["metrics"]["corner_std_distorted_px"]


def test_command_line_hands_typed_arguments_to_each_experiment(tmp_path, monkeypatch):
    from pathlib import Path

    from wai.experiments import budget, validate
    from wai.sweep import SweepOptions

    calls = {}
    monkeypatch.setattr(budget, "run_budget", lambda *a, **k: calls.setdefault("budget", (a, k)))
    monkeypatch.setattr(validate, "run_validate", lambda *a: calls.setdefault("validate", a))
    monkeypatch.setattr(validate, "print_validate", lambda res: None)
    out = tmp_path / "b"
    argv = ["experiment", "budget", "--quick", "--out", str(out), "--workers", "0", "--no-progress"]
    assert main(argv) == 0
    assert calls["budget"] == (("paper", out, 1, True, SweepOptions(workers=0, progress=False)), {})
    assert main(["experiment", "validate", "--config", "x.toml"]) == 0
    assert calls["validate"] == ("x.toml", Path("renders/validate"), False)


def test_run_experiment_runs_the_registrys_runner_with_its_seeds(monkeypatch, tmp_path):
    import dataclasses

    from wai import experiments
    from wai_core.errors import WaiInputError

    calls = []

    def recorder(name):
        return lambda *args, **kw: calls.append((name, *args))

    for name, exp in experiments.EXPERIMENTS.items():
        monkeypatch.setitem(experiments.EXPERIMENTS, name,
                            dataclasses.replace(exp, run=recorder(name)))
    for name in experiments.EXPERIMENTS:
        experiments.run_experiment(name, out=tmp_path / name)
    assert [c[0] for c in calls] == list(experiments.EXPERIMENTS)
    for name, _config, out, seeds, _quick, _sweep in calls:
        assert out == tmp_path / name and seeds == experiments.EXPERIMENTS[name].seeds
    experiments.run_experiment("paper", seeds=4)
    assert calls[-1][2:4] == (Path("renders/paper"), 4)
    # --quick takes the quick default unless --seeds is given (what --help says it does)
    experiments.run_experiment("compare", quick=True)
    assert calls[-1][3] == experiments.EXPERIMENTS["compare"].quick_seeds == 1
    experiments.run_experiment("compare", seeds=3, quick=True)
    assert calls[-1][3] == 3
    with pytest.raises(WaiInputError, match="no experiment 'nope'"):
        experiments.run_experiment("nope")
    with pytest.raises(WaiInputError, match="takes no --method"):
        experiments.run_experiment("paper", methods=["mine.py:Mine"])


def test_compare_takes_methods_of_ones_own_and_refuses_bad_ones_before_rendering(tmp_path):
    """--method reaches the comparison; a name that resolves to nothing stops it with one
    line (exit code 2) before any sequence is rendered."""
    argv = ["experiment", "compare", "--quick", "--out", str(tmp_path / "c"), "--workers", "0",
            "--no-progress", "--method", "no_such_module_xyz:Thing"]
    assert main(argv) == 2
    assert not (tmp_path / "c" / "cases").exists()


def test_compare_takes_its_frames_per_case_and_other_experiments_refuse_them(tmp_path,
                                                                             monkeypatch):
    """--frames reaches the comparison (its registry's defaults otherwise: 30, 8 with
    --quick); fewer than two stop it with one line before any render; an experiment that
    renders no sequences refuses it. Cases and rows of another frame count are other cases:
    other folders and other point ids, so a rerun never reuses or replaces them."""
    import dataclasses

    from wai import experiments
    from wai.experiments import compare
    from wai.sweep.points import point_ids
    from wai_core.errors import WaiInputError

    exp = experiments.EXPERIMENTS["compare"]
    assert (exp.frames, exp.quick_frames) == (compare.FRAMES, compare.QUICK_FRAMES)
    got = []
    monkeypatch.setitem(experiments.EXPERIMENTS, "compare", dataclasses.replace(
        exp, run=lambda *args, **kw: got.append(kw["frames"])))
    experiments.run_experiment("compare", out=tmp_path / "a")
    experiments.run_experiment("compare", out=tmp_path / "b", quick=True)
    experiments.run_experiment("compare", out=tmp_path / "c", frames=5)
    assert got == [30, 8, 5]
    with pytest.raises(WaiInputError, match="takes no --frames"):
        experiments.run_experiment("paper", frames=3)
    monkeypatch.undo()
    assert main(["experiment", "compare", "--quick", "--frames", "1", "--out",
                 str(tmp_path / "d"), "--workers", "0", "--no-progress"]) == 2
    assert not (tmp_path / "d").exists()
    eight, thirty = (compare.compare_points(["structured-light"], 1, True, n) for n in (8, 30))
    assert compare.case_name(eight[0]) != compare.case_name(thirty[0])
    assert compare.case_name(eight[0]).endswith("_8f")
    key = ("wind", "seed", "degradation", "method", "case_frames")
    assert not set(point_ids(eight, key)) & set(point_ids(thirty, key))
    # a point's fields and a row's scores share no name (the sweep refuses a result that
    # would overwrite its point's field)
    assert not set(eight[0]) & set(compare.SCORES)


def test_compare_runs_the_seeds_and_conditions_asked_for(tmp_path, monkeypatch):
    """--first-seed and --condition reach the comparison's cases (seeds a run has not looked
    at, a few conditions); an unknown condition or a negative seed stops it with one line
    before any render, and an experiment without conditions refuses both."""
    import dataclasses

    from wai import experiments
    from wai.experiments import compare
    from wai_core.errors import WaiInputError

    exp = experiments.EXPERIMENTS["compare"]
    assert exp.conditions == tuple(compare.DEGRADATIONS)  # the help lists them all
    assert set(compare.DEFAULT_DEGRADATIONS) == set(compare.DEGRADATIONS) - {"rough_0.01_256"}
    points = compare.compare_points(["structured-light"], 2, False, 8, 2,
                                    ["rough_0.01", "speckle", "rough_0.01"])
    assert {p["seed"] for p in points} == {2, 3}
    assert [p["degradation"] for p in points[:2]] == ["rough_0.01", "speckle"]
    assert len(points) == 2 * 2 * 2  # winds x seeds x conditions, a condition named twice once
    assert {compare.case_name(p) for p in points} >= {"U1_seed002_rough_0.01_8f",
                                                       "U1.5_seed003_speckle_8f"}
    default = compare.compare_points(["structured-light"], 1, False, 8)
    assert {p["degradation"] for p in default} == set(compare.DEFAULT_DEGRADATIONS)
    with pytest.raises(WaiInputError, match="--condition 'windy'"):
        compare.compare_points(["structured-light"], 1, False, 8, 0, ["windy"])
    got = []
    monkeypatch.setitem(experiments.EXPERIMENTS, "compare", dataclasses.replace(
        exp, run=lambda *args, **kw: got.append((kw["first_seed"], kw["conditions"]))))
    experiments.run_experiment("compare", out=tmp_path / "a")
    experiments.run_experiment("compare", out=tmp_path / "b", first_seed=4,
                               conditions=["rough_0.01_256"])
    assert got == [(0, []), (4, ["rough_0.01_256"])]
    with pytest.raises(WaiInputError, match="takes no --first-seed or --condition"):
        experiments.run_experiment("budget", first_seed=3)
    monkeypatch.undo()
    for bad in (["--first-seed", "-1"], ["--condition", "windy"]):
        assert main(["experiment", "compare", "--quick", "--out", str(tmp_path / "d"),
                     "--workers", "0", "--no-progress", *bad]) == 2
    assert not (tmp_path / "d").exists()


def test_compare_reports_the_truth_free_grid_score_and_its_rank_agreement():
    """The table has the grid score's columns; Kendall's tau is +1 when the grid residual
    orders the methods as corner STD does, -1 when it reverses them, and no verdict with
    fewer than three methods scored by both."""
    from wai.experiments.compare import SCORES, rank_agreement, report

    assert {"grid_px", "grid_fraction"} <= set(SCORES)

    def entry(name, std, grid):
        e = dict.fromkeys(SCORES)
        return {**e, "name": name, "corner_std_px": std, "grid_px": grid, "grid_fraction": 0.5}

    same = [entry("a", 0.1, 0.05), entry("b", 1.5, 1.2), entry("c", 2.8, 3.5), entry("d", 1.8, 1.3)]
    assert rank_agreement(same) == (pytest.approx(1.0), 4)
    text = report(same, "cmd")
    assert "grid px (no truth)" in text and "corners found" in text
    assert "| 1.200 | 50% |" in text
    assert "orders the methods as corner STD does: Kendall tau = 1.00 over 4 methods" in text
    reversed_ = [entry(e["name"], e["corner_std_px"], 1.0 / e["grid_px"]) for e in same]
    assert rank_agreement(reversed_)[0] == pytest.approx(-1.0)
    assert "Kendall tau = -1.00" in report(reversed_, "cmd")
    few = [same[0], same[1], entry("e", None, 1.0)]
    assert rank_agreement(few) == (None, 2)
    assert "Too few methods with both scores (2)" in report(few, "cmd")


def test_compare_ranks_methods_within_each_case():
    from wai.experiments.compare import case_agreement, report

    def row(seed, method, std, grid):
        return {"wind": 1.0, "seed": seed, "degradation": "none", "method": method,
                "status": "ok", "corner_std_px": std, "grid_px": grid}

    rows = [row(0, "a", 0.1, 0.2), row(0, "b", 1.0, 0.9), row(0, "c", 2.0, 3.0),
            row(1, "a", 0.1, 3.0), row(1, "b", 1.0, 0.9), row(1, "c", 2.0, 0.2)]
    taus = case_agreement(rows)
    assert taus == [pytest.approx(1.0), pytest.approx(-1.0)]
    assert "Within each case: tau = 1.00, -1.00." in report([], "cmd", taus)


BROKEN_METHODS = ROOT / "tests" / "restoration" / "broken_methods.py"
BROKEN = {"Raises": "method 'raises' raised RuntimeError: a bug of mine",
          "ReturnsNone": "method 'returns-none' returned NoneType, not a RestoreResult",
          "WrongShape": "method 'wrong-shape' returned a view image of shape (5, 5, 3)",
          "Exits": "method 'exits' raised SystemExit: 3"}


def test_methods_of_ones_own_that_fail_get_an_error_row_and_the_others_run(tmp_path, small_cfg,
                                                                          capsys):
    """A method whose call raises, exits or returns no valid result fails its own rows, in one
    line naming it; the other methods' rows are scored and the report names the failures."""
    from mitsuba_wai.sequence import render_sequence
    from wai.experiments.compare import evaluate, report, summarize
    from wai.sweep import run_sweep

    folder = tmp_path / "case"
    render_sequence(small_cfg.replace("render", spp_pattern=1, spp_view=1), folder, 2, 30.0,
                    progress=False)
    plugin = BROKEN_METHODS
    specs = ["wai.examples.plugin_method:AsSeen", *(f"{plugin}:{c}" for c in BROKEN)]
    points = [{"wind": 1.0, "seed": 0, "degradation": "none", "method": m, "folder": str(folder)}
              for m in specs]
    rows = run_sweep(points, evaluate, tmp_path / "compare.csv", workers=0, progress=False,
                     key=("method",))
    status = {r["method"]: r["status"] for r in rows}
    assert status[specs[0]] == "ok"
    # The frame's time beside the reference workload timed in the same process.
    ok = next(r for r in rows if r["status"] == "ok")
    assert float(ok["reference_ms"]) > 0
    assert float(ok["frame_per_reference"]) == pytest.approx(
        float(ok["ms_per_frame"]) / float(ok["reference_ms"]))
    for cls, says in BROKEN.items():
        assert status[f"{plugin}:{cls}"].startswith(f"error: WaiInputError: {says}"), status
    text = report(summarize(rows), "cmd")
    assert "| ms per frame | x reference |" in text and "reference workload" in text
    assert f"- {plugin}:Raises failed on 1 of 1 cases: error: WaiInputError: method" in text
    assert "Traceback" not in capsys.readouterr().err


def test_the_methods_chart_shows_each_methods_spread_over_the_cases(tmp_path, monkeypatch):
    """Two methods over three cases: each point carries its cases' standard deviation as an
    error bar, and the axis names this machine's cores, not a fixed machine."""
    import os

    from matplotlib.container import ErrorbarContainer

    from wai.experiments import compare

    rows = []
    for method, ssims in (("a", (0.90, 0.92, 0.94)), ("b", (0.70, 0.80, 0.90))):
        for k, ssim in enumerate(ssims):
            row = {key: None for key in compare.SCORES}
            row.update(method=method, method_name=method, status="ok", ssim=ssim,
                       corner_std_px=0.1 * (k + 1), ms_per_frame=10.0 + k, frames_ok=1,
                       frames=1)
            rows.append(row)
    summary = compare.summarize(rows)
    assert abs(summary[1]["ssim_sd"] - 0.1) < 1e-12
    drawn = {}
    monkeypatch.setattr("matplotlib.figure.Figure.savefig",
                        lambda fig, path, **kw: drawn.update(fig=fig))
    compare._figure(summary, tmp_path / "compare.png")
    ssim_axis = drawn["fig"].axes[1]
    bars = [c for c in ssim_axis.containers if isinstance(c, ErrorbarContainer)]
    assert len(bars) == 2
    assert f"{os.cpu_count()} cores" in ssim_axis.get_xlabel()


def test_compare_counts_the_ok_frames_the_truth_finds_wrong():
    """A method's ``ok`` frames with a surface past WRONG_OK_MM are summed over its cases; a
    method without a surface (a video method) has no such count, and the report says so."""
    from wai.experiments import compare

    # Per case: an ok frame past the bound counts, a flagged one and a right one do not; a
    # method whose frames carry no surface has no count.
    frames = [{"ok": True, "rmse_mm": compare.WRONG_OK_MM + 0.05},
              {"ok": False, "rmse_mm": 1.0}, {"ok": True, "rmse_mm": 0.1}]
    assert compare._ok_but_wrong(frames) == 1
    assert compare._ok_but_wrong([{"ok": True}, {"ok": True, "rmse_mm": None}]) is None
    rows = []
    for method, wrong in (("dots", (0, 2, 1)), ("fused", (None, None, None))):
        for k, w in enumerate(wrong):
            row = {key: None for key in compare.SCORES}
            row.update(method=method, method_name=method, status="ok", ssim=0.9,
                       ms_per_frame=10.0 + k, frames_ok=8, frames=8, frames_ok_wrong=w)
            rows.append(row)
    summary = {e["method"]: e for e in compare.summarize(rows)}
    assert summary["dots"]["frames_ok_wrong"] == 3 and summary["dots"]["frames_ok"] == 24
    assert summary["fused"]["frames_ok_wrong"] is None
    table = compare.report(list(summary.values()), "wai experiment compare").splitlines()
    dots = next(line for line in table if line.startswith("| dots |"))
    fused = next(line for line in table if line.startswith("| fused |"))
    assert dots.split("|")[4].strip() == "3" and fused.split("|")[4].strip() == "-"


def test_compare_conditions_are_valid_scenes_and_give_schlieren_its_texture():
    # Every condition of the case set is a scene the renderer accepts; the ones where the
    # geometric method is weak are seen through the speckle object, so Schlieren (which
    # needs texture) is compared there too; --quick keeps the paper's scene and the speckle.
    from wai.experiments.compare import DEGRADATIONS, FRAME_METHODS, QUICK_DEGRADATIONS
    from wai_core.config import with_keys
    from wai_core.system import load_rig

    assert "schlieren" in FRAME_METHODS and set(QUICK_DEGRADATIONS) == {"none", "speckle"}
    base = load_rig("paper")
    for name, keys in DEGRADATIONS.items():
        cfg = with_keys(base, keys)
        assert (cfg.object.texture == "speckle") == (name not in ("none", "sensor")), name
    assert with_keys(base, DEGRADATIONS["rough_0.02"]).water.roughness == 0.02
