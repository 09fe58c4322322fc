"""Every ``wai experiment`` at ``--quick`` (and one seed where it has seeds), as a user runs it:
from a plain install (a wheel of the checkout in a folder of its own), in another folder. The
slow tier."""

from __future__ import annotations

import json

import pytest

from wai.experiments import EXPERIMENTS

pytestmark = pytest.mark.slow


def _args(name: str) -> list[str]:
    exp = EXPERIMENTS[name]
    args = ["experiment", name, "--quick", "--out", name]
    if exp.seeds is not None:
        args += ["--seeds", "1"]
    if exp.sweep:
        args += ["--workers", "2", "--no-progress"]
    if exp.frames is not None:
        args += ["--frames", "3"]
    if exp.conditions:
        args += ["--first-seed", "1", "--condition", "speckle"]
    return args


WRITES = {"validate": "validate.json", "paper": "report.md", "alterman": "report.md",
          "tradeoffs": "tradeoffs.md", "stability": "stability.md", "budget": "budget.md",
          "calibration": "calibration.md", "compare": "compare.md",
          "seawater": "seawater_snr.json"}
"""A file each experiment's help says it writes."""


def test_every_experiment_is_run_here():
    assert set(WRITES) == set(EXPERIMENTS)


@pytest.mark.parametrize("name", list(EXPERIMENTS))
def test_every_experiment_runs_quick_from_a_plain_install(installed, name):
    done = installed.run(*_args(name), timeout=900)
    assert done.returncode == 0, (name, done.stderr[-3000:])
    assert WRITES[name] in EXPERIMENTS[name].description
    report = installed.elsewhere / name / WRITES[name]
    assert report.is_file() and report.stat().st_size > 0
    if name == "compare":  # the method of one's own it compares by default, by module name
        assert "as-seen" in (installed.elsewhere / name / "compare.csv").read_text()
        # --frames: each case a sequence of that many frames, and the report says so
        cases = sorted((installed.elsewhere / name / "cases").iterdir())
        assert cases and all(c.name.endswith("_3f") for c in cases)
        assert all(len(list(c.glob("frame*"))) == 3 for c in cases)
        assert "--frames 3" in report.read_text()
        # --first-seed and --condition: only seed 1's speckle case, and the report says so
        assert [c.name for c in cases] == ["U1_seed001_speckle_3f"]
        assert "--first-seed 1 --condition speckle" in report.read_text()
        # Frames by condition: counted from each frame's status, they agree with the
        # methods' ok counts; the speckle object is a baseline, compared with nothing.
        summary = json.loads((installed.elsewhere / name / "compare_summary.json").read_text())
        counted = {e["method"]: e for e in summary["conditions"]}
        surfaces = [m for m in summary["methods"] if m.get("rmse_mm") is not None]
        assert surfaces and all(counted[m["method"]]["ok"] == m["frames_ok"]
                                and counted[m["method"]]["frames"] == m["frames"] == 3
                                and counted[m["method"]]["ok_within"] is None
                                for m in surfaces)
        assert "## Frames by condition" in report.read_text()
