"""Every ``wai`` command but the experiments, as a user runs it: from a plain install (a wheel
of the checkout in a folder of its own), in another folder, at its smallest size. The slow
tier (the first restoration compiles the installed copy's kernels)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import ROOT

pytestmark = pytest.mark.slow

CAPTURE = ROOT.parent / "shared" / "data" / "cmu-water" / "checkboard.avi"


def ok(done) -> str:
    """The command's stdout, once it has exited 0 (else its stderr's end as the failure)."""
    assert done.returncode == 0, (done.args, done.stderr[-3000:])
    return done.stdout


def test_the_installed_copy_is_what_runs(installed):
    probe = ("import wai, restoration, wai_core, mitsuba_wai\n"
             "print(*(m.__file__ for m in (wai, restoration, wai_core, mitsuba_wai)))")
    done = installed.run("--version")
    assert ok(done).startswith("wai ")
    import subprocess
    import sys

    env = {"PYTHONPATH": str(installed.site), "PATH": "/usr/bin:/bin"}
    where = subprocess.run([sys.executable, "-c", probe], cwd=installed.elsewhere, env=env,
                           capture_output=True, text=True, check=True).stdout.split()
    assert all(Path(p).is_relative_to(installed.site) for p in where), where
    # The packaged scenes come with it, and the guide (copied in by setup.py's build step).
    assert (installed.site / "wai_core" / "scenes" / "paper.toml").is_file()
    listing = ok(installed.run("guide"))
    assert "rig  " in listing and str(installed.site / "wai" / "guide") in listing
    page = ok(installed.run("guide", "rig"))
    assert page == (ROOT / "docs" / "rig.md").read_text()
    assert (installed.site / "wai" / "guide" / "images" / "rig.png").is_file()


def test_demo_render_restore_and_a_sequence(installed):
    out = ok(installed.run("demo", "--out", "demo", "--quiet"))
    assert "status ok" in out and "the demo took" in out
    assert (installed.elsewhere / "demo" / "restore" / "metrics.json").is_file()
    ok(installed.run("render", "paper", "--out", "f1", "--seed", "3", "--quiet"))
    out = ok(installed.run("restore", "f1", "--quiet"))
    assert out.splitlines()[0].startswith("status ")
    ok(installed.run("render", "paper", "--out", "seq", "--frames", "3", "--quiet"))
    out = ok(installed.run("restore", "seq", "--quiet"))
    assert "3 frames" in out and "flat-water reference" in out
    # The image-only methods each write their own folder: none replaces another's results.
    for method in ("mean", "registration", "lucky"):
        ok(installed.run("restore", "seq", "--method", method))
    seq = installed.elsewhere / "seq"
    names = {p.name for p in seq.iterdir() if p.name.startswith("restore")}
    assert names == {"restore", "restore_mean", "restore_registration", "restore_lucky"}
    methods = {json.loads((seq / n / "metrics.json").read_text())["method"]
               for n in names - {"restore"}}
    assert len(methods) == 3


def test_calibrate_and_restore_with_the_rig(installed):
    ok(installed.run("render", "paper", "--checkerboards", "6", "--out", "cb", "--quiet"))
    ok(installed.run("calibrate", "cb/checkerboards", "--out", "rig.json"))
    ok(installed.run("render", "paper", "--out", "f2", "--quiet"))
    out = ok(installed.run("restore", "f2", "--rig", "rig.json", "--quiet"))
    assert "rig.json applied" in out
    metrics = json.loads((installed.elsewhere / "f2" / "restore" / "metrics.json").read_text())
    assert Path(metrics["rig"]["file"]) == installed.elsewhere / "rig.json"
    assert metrics["rig"]["config_keys"]


def test_the_sun_sensor_renders_and_restores(installed):
    ok(installed.run("render", "alterman", "--out", "a1", "--quiet"))
    out = ok(installed.run("restore", "a1", "--method", "alterman", "--quiet"))
    assert "status" in out


def test_synthetic_schlieren_beside_the_structured_light(installed):
    # The packaged speckle scene (a variant of the paper's by `extends`), both methods on one
    # render, each in its own folder.
    ok(installed.run("render", "schlieren", "--out", "k1", "--quiet"))
    out = ok(installed.run("restore", "k1", "--method", "schlieren", "--quiet"))
    # Its checks pass; its level is the gauge's, and the frame says so.
    assert out.splitlines()[0].startswith("status gauge_level: the slopes do not pin the level")
    ok(installed.run("restore", "k1", "--quiet"))
    # The structured light with its level from the view: the speckle serves it too.
    ok(installed.run("restore", "k1", "--method", "structured-light-view", "--quiet"))
    k1 = installed.elsewhere / "k1"
    metrics = {n: json.loads((k1 / n / "metrics.json").read_text())
               for n in ("restore", "restore_schlieren", "restore_structured-light-view")}
    assert {n: m["method"] for n, m in metrics.items()} == {
        "restore": "structured-light", "restore_schlieren": "schlieren",
        "restore_structured-light-view": "structured-light-view"}
    view = metrics["restore_structured-light-view"]
    assert view["status"] == "ok" and view["anchor"]["method"] == "view"


def test_a_dataset(installed):
    ok(installed.run("dataset", "--frames", "2", "--out", "ds", "--quiet"))
    assert any((installed.elsewhere / "ds").glob("*.h5"))


BENCHES = [
    ["render", "--runs", "1"],
    ["restore", "--runs", "1", "--workers", "2"],
    ["sizes", "--runs", "1", "--out", "sizes"],
    ["accuracy", "--seeds", "1", "--out", "acc"],
    ["surfaces", "--out", "surfaces"],
    ["inputs", "--out", "inputs"],
    ["video", "--frames", "4", "--workers", "1", "--out", "video"],
    ["all", "--runs", "1", "--out", "bench"],
]


@pytest.mark.parametrize("args", BENCHES, ids=[b[0] for b in BENCHES])
def test_every_bench_runs(installed, args):
    assert ok(installed.run("bench", *args)).strip()


@pytest.mark.skipif(not CAPTURE.is_file(), reason="the CMU capture is not at ../shared/data")
def test_bench_capture_on_the_real_capture(installed):
    assert "grid" in ok(installed.run("bench", "capture", "--video", str(CAPTURE)))
