"""``wai bench``: every stage in bench.json with consistent figures, a chart, the old
``bench restore --json`` keys, and a stage mapping that survives renamed or missing timings."""

import json
import shlex
from pathlib import Path
from types import SimpleNamespace

import pytest

from mitsuba_wai.render import render_folder
from tests.conftest import paper_toml_with
from wai.bench.restore import stage_times
from wai.cli import build_parser, main
from wai_core.sequence import read_sequence

STAGES = (
    "render_s",
    "render_v",
    "waves_host",
    "waves_device",
    "features",
    "features.detect",
    "features.match",
    "surface",
    "normals",
    "integration",
    "grid",
    "reverse_trace",
    "resampling",
    "end_to_end",
)


@pytest.fixture(scope="module")
def quick_toml(tmp_path_factory):
    """The paper's scene at 1 sample per pixel (the dots stay resolved at 800x600)."""
    text = paper_toml_with(render={"spp_pattern": 1, "spp_view": 1})
    path = tmp_path_factory.mktemp("cfg") / "quick.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def frame_dir(quick_toml, tmp_path_factory):
    from wai_core.config import load_config

    out = tmp_path_factory.mktemp("bench") / "frame"
    render_folder(load_config(quick_toml), out, progress=False)
    return out


@pytest.fixture(scope="module")
def report(quick_toml, frame_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "bench"
    argv = ["bench", "--config", str(quick_toml), "--dir", str(frame_dir), "--out", str(out)]
    assert main([*argv, "--runs", "2"]) == 0
    return out, json.loads((out / "bench.json").read_text())


def test_every_stage_with_a_consistent_summary(report):
    _, rep = report
    stages = rep["stages"]
    assert set(STAGES) <= set(stages)
    for name, s in stages.items():
        assert 0 <= s["min_ms"] <= s["q1_ms"] <= s["median_ms"] <= s["q3_ms"] <= s["max_ms"], name
        assert s["iqr_ms"] >= 0 and s["runs"] == 2, name
    # Every restoration stage is a part of each run's end-to-end time, so of its median too.
    e2e = stages["end_to_end"]["median_ms"]
    assert all(s["median_ms"] <= e2e for s in stages.values() if s["group"] == "restore")
    assert all(stages[n]["group"] == "render" for n in ("render_s", "render_v"))


def test_setup_warmup_memory_and_derived(report):
    _, rep = report
    assert rep["runs"] == 2 and rep["machine"]["cores"] >= 1
    assert isinstance(rep["runtime"]["variant"], str) and rep["runtime"]["drjit_threads"] >= 1
    assert set(rep["warmup_ms"]) == {"render_s", "render_v", "restore"}
    assert all(v > 0 for v in rep["warmup_ms"].values())
    mem = rep["peak_memory_mib"]
    assert 0 < mem["rss_after_restore"] <= mem["rss_after_render"]  # a process-wide peak
    assert mem["tracemalloc_restore"] > 0
    assert set(rep["derived"]) <= set(rep["stages"]) and set(rep["derived"]) <= set(rep["notes"])


def test_chart_and_nothing_else_written(report):
    out, _ = report
    assert sorted(p.name for p in out.iterdir()) == ["bench.json", "bench.png", "index.html"]
    assert (out / "bench.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_restore_json_keeps_its_keys(frame_dir, capsys):
    assert main(["bench", "restore", "--dir", str(frame_dir), "--runs", "1", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["end_to_end_ms"] > 0
    assert {"features", "surface", "reverse_trace", "end_to_end"} <= set(res["stages_ms"])
    assert all(isinstance(v, float) for v in res["stages_ms"].values())


def test_restore_measures_frames_in_parallel(frame_dir, capsys):
    # Two workers restore the frame side by side: every frame comes back, each restored
    # in about the serial time (one thread each), none faster than the serial minimum allows.
    assert main(["bench", "restore", "--dir", str(frame_dir), "--runs", "1", "--workers", "2",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    par = res["parallel"]
    assert (par["workers"], par["frames"]) == (2, 20)
    assert par["fps"] == pytest.approx(par["frames"] / par["wall_s"])
    assert par["wall_s"] * 1e3 >= 10 * 0.5 * par["worker_ms_median"]
    assert main(["bench", "restore", "--dir", str(frame_dir), "--runs", "1", "--workers", "1",
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["parallel"] is None
    assert main(["bench", "restore", "--dir", str(frame_dir), "--workers", "0"]) == 2
    assert "--workers must be at least 1" in capsys.readouterr().err


@pytest.mark.slow
def test_restore_times_the_fit_to_the_pattern_image(frame_dir, capsys):
    # Another method timed the same way; inverse rendering's loss evaluations are a part of
    # its image fit's time, and no frames-in-parallel figure is claimed for it.
    assert main(["bench", "restore", "--dir", str(frame_dir), "--runs", "1", "--method",
                 "inverse-rendering", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    fit = res["image_fit"]
    assert res["method"] == "inverse-rendering" and res["parallel"] is None
    assert fit["evaluations"] >= 2 and fit["ms_per_evaluation"] > 0
    assert fit["evaluations"] * fit["ms_per_evaluation"] <= res["stages_ms"]["image_fit"]
    assert res["stages_ms"]["image_fit"] <= res["end_to_end_ms"]


def test_restore_refuses_a_method_it_cannot_time(frame_dir, capsys):
    assert main(["bench", "restore", "--dir", str(frame_dir), "--method", "nothing"]) == 2
    assert capsys.readouterr().err.startswith("wai: error: --method: unknown method")
    assert main(["bench", "restore", "--dir", str(frame_dir), "--method", "schlieren",
                 "--workers", "2"]) == 2
    assert "--workers 2" in capsys.readouterr().err


# The invocations README.md and docs/results.md give, one per option set.
DOCUMENTED = [
    "bench", "bench --runs 5 --out renders/bench", "bench render --runs 3 --json",
    "bench restore --runs 10 --json", "bench restore --runs 3 --method inverse-rendering",
    "bench accuracy --seeds 10",
    "bench accuracy --seeds 10 --config coded.toml --out renders/bench_acc_coded",
    "bench accuracy --seeds 10 --camera 1280x960", "bench surfaces --phi 0.8", "bench inputs",
    "bench video --workers 2 --frames 60", "bench video --workers 2 --fps 120 --track",
]


@pytest.mark.parametrize("command", DOCUMENTED)
def test_documented_invocations_parse(command):
    argv = shlex.split(command)
    named = argv[1:2] if len(argv) > 1 and not argv[1].startswith("-") else ["all"]
    assert build_parser().parse_args(argv).what == named[0]


def test_bench_alone_is_all_and_takes_its_options():
    args = build_parser().parse_args(["bench", "--runs", "3", "--dir", "d", "--json"])
    assert (args.what, args.runs, args.dir, args.json) == ("all", 3, Path("d"), True)
    assert args.out == Path("renders/bench")


@pytest.mark.parametrize("argv", [
    ["accuracy", "--runs", "3"], ["surfaces", "--seeds", "2"], ["render", "--out", "x"],
    ["inputs", "--phi", "0.5"], ["video", "--variant", "auto"], ["restore", "--frames", "2"],
])
def test_an_option_of_another_bench_is_bad_input(argv, capsys):
    assert main(["bench", *argv]) == 2
    assert argv[1] in capsys.readouterr().err


def test_zero_runs_is_bad_input(capsys):
    assert main(["bench", "restore", "--runs", "0"]) == 2
    assert "--runs" in capsys.readouterr().err


def _result(top=None, features=None, surface=None, view=None):
    return SimpleNamespace(
        timings_ms=top or {},
        features=SimpleNamespace(timings_ms=features or {}),
        surface=SimpleNamespace(timings_ms=surface or {}),
        view=SimpleNamespace(timings_ms=view or {}),
    )


def test_mapping_derives_renames_and_passes_unknown_keys_through():
    res = _result(
        top={"features": 10.0, "surface": 8.0, "reverse_trace": 6.0, "end_to_end": 25.0},
        features={"detect": 6.0, "match": 3.0, "subpixel": 1.0},
        surface={"normals": 3.0, "integrate": 3.0, "grid": 1.5, "total": 7.5},
        view={"plan": 0.1, "surface": 0.4, "solve": 2.0, "upsample": 1.0, "remap": 1.0},
    )
    times, derived = stage_times(res)
    assert times["view"] == 6.0 and times["grid"] == 1.5 and times["features.subpixel"] == 1.0
    assert times["normals"] == 3.0 and times["integration"] == 5.0
    assert times["reverse_trace"] == pytest.approx(2.5) and times["resampling"] == 2.0
    assert "end_to_end" not in times and "surface.total" not in times
    assert set(derived) == {"normals", "integration", "surface.anchor_search"} | {
        "reverse_trace",
        "resampling",
    }


def test_mapping_omits_what_it_cannot_compute_and_never_overwrites_a_measurement():
    times, derived = stage_times(_result(top={"surface": 8.0, "normals": 2.5}))
    assert times == {"surface": 8.0, "normals": 2.5, "integration": 5.5}
    assert derived == ["integration"]
    assert stage_times(SimpleNamespace()) == ({}, [])


@pytest.mark.slow
def test_bench_video_reports_latency_and_throughput(quick_toml, tmp_path, capsys):
    # One rendered frame restored by one worker process: the figures must be consistent
    # (each worker restores its frames one after another inside the timed wall, so the wall
    # cannot be shorter than the workers' summed time over their number; a median of three
    # frames can exceed their mean, so it is no bound), and the sequence is rendered once,
    # then reused.
    args = ["bench", "video", "--config", str(quick_toml), "--out", str(tmp_path / "v"),
            "--sequence", "1", "--frames", "3", "--workers", "1", "--runs", "1", "--json"]
    assert main(args) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["latency"]["median_ms"] > 0
    (one,) = res["throughput"]
    assert one["workers"] == 1 and one["frames"] == 3
    assert one["wall_s"] >= one["worker_ms_total"] / 1e3 / one["workers"]
    assert one["fps"] == pytest.approx(one["frames"] / one["wall_s"])
    assert (tmp_path / "v" / "sequence" / "frame000" / "scene.json").is_file()
    assert read_sequence(tmp_path / "v" / "sequence").fps == res["fps_rendered"] == 30.0
    assert main([*args[:-1]]) == 0  # a rerun renders nothing new and prints the report
    assert "throughput, 1 worker(s)" in capsys.readouterr().out


def test_bench_video_rejects_zero_workers(tmp_path, capsys):
    assert main(["bench", "video", "--workers", "0", "--out", str(tmp_path)]) == 2
    assert "--workers" in capsys.readouterr().err


@pytest.mark.parametrize("fps", ["0", "-30", "nan"])
def test_bench_video_rejects_a_frame_rate_that_is_not_positive(fps, tmp_path, capsys):
    assert main(["bench", "video", "--fps", fps, "--out", str(tmp_path / "v")]) == 2
    assert "--fps" in capsys.readouterr().err
    assert not (tmp_path / "v").exists()


@pytest.mark.parametrize("camera", ["abc", "800x", "8x8"])
def test_a_bad_camera_size_is_one_line(camera, tmp_path, capsys):
    assert main(["bench", "accuracy", "--camera", camera, "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--camera" in err[0]
    assert not (tmp_path / "a").exists()


def test_bench_inputs_flags_every_wrong_input_and_passes_the_right_ones(quick_toml, tmp_path,
                                                                      capsys):
    from wai.bench.inputs import CASES

    assert main(["bench", "inputs", "--config", str(quick_toml), "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "inputs.json").read_text())["rows"]
    assert [r["case"] for r in rows] == list(CASES)
    status = {r["case"]: r["status"] for r in rows}
    # What the data can show is flagged; a wrong view with nothing to compare it with cannot be.
    assert status["right images"] == status["right images, with view_flat"] == "ok"
    assert status["patterns swapped"] == "bad_reference"
    assert status["pattern.png of another moment"] == "ambiguous_input"
    assert status["view turned 180 deg, with view_flat"] == "view_mismatch"
    assert status["view 0.5 s later, with view_flat"] == "view_mismatch"
    assert "bad_reference" in capsys.readouterr().out
    # A calibration that is off: every ok frame is right (the truth agrees), and the
    # flat-water residual moves as the error does.
    by = {r["case"]: r for r in rows}
    right, pp1 = by["right images"], by["camera s principal point +1 px"]
    for r in rows:  # (1 spp: the views' noise sets the corners' spread)
        if r["case"].startswith("camera") and r["status"] == "ok":
            assert r["corner_std_px"] <= 1.3 * right["corner_std_px"], r
    # A principal point 1 px off moves every predicted spot by 1 px (the residual reads about
    # one pixel), and flat-water and wavy spots alike: referred to the reference, it cancels.
    assert pp1["status"] == "ok"
    assert pp1["rmse_mm"] == pytest.approx(right["rmse_mm"], rel=0.05, abs=0.002)
    assert pp1["reference_rms_spacings"] == pytest.approx(1 / 13.05, rel=0.15)  # 13.05 px apart
    assert by["camera s principal point +3 px"]["status"] == "bad_reference"
    f01 = by["camera s focal length +0.1 %"]["reference_rms_spacings"]
    f1 = by["camera s focal length +1 %"]["reference_rms_spacings"]
    assert right["reference_rms_spacings"] < 0.01 < f01 < f1  # docs/rig.md: 1 % for a good rig


@pytest.mark.parametrize("text", ["", "800", "10x10", "640x480,axb"])
def test_bench_sizes_names_its_option(text):
    from wai.bench.sizes import parse_sizes
    from wai_core.errors import WaiInputError

    with pytest.raises(WaiInputError, match="^--sizes"):
        parse_sizes(text)


@pytest.mark.parametrize("text", ["8", "8x", "axb", "1x6"])
def test_bench_capture_names_its_board_option(text):
    from wai.bench.capture import parse_board
    from wai_core.errors import WaiInputError

    with pytest.raises(WaiInputError, match="^--board"):
        parse_board(text)


def test_bench_capture_names_a_missing_video(tmp_path):
    assert main(["bench", "capture", "--video", str(tmp_path / "none.avi")]) == 2


def test_accuracy_verdicts_set_the_status_beside_the_truth():
    from wai.bench.accuracy import verdict_counts

    def run(seed, status, right):
        return {"seed": seed, "verdict": {"status": status, "right": right}}

    v = verdict_counts([run(0, "ok", True), run(1, "ok", False), run(2, "inconsistent", True),
                        run(3, "failed", False)])
    assert v["statuses"] == {"ok": 2, "inconsistent": 1, "failed": 1}
    assert (v["ok_but_wrong"], v["right_but_flagged"], v["right"]) == ([1], [2], 2)
