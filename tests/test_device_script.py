"""scripts/device_bench.sh: without a CUDA device it says so in one line and exits 0 (the GPU's
figures themselves are measured where a GPU is lent: docs/results.md, "On a GPU")."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _has_cuda() -> bool:
    try:
        import drjit as dr
    except ImportError:
        return False
    return bool(dr.has_backend(dr.JitBackend.CUDA))


@pytest.mark.skipif(_has_cuda(), reason="a CUDA device is present: the script measures it")
def test_device_script_says_no_gpu_and_measures_nothing(tmp_path):
    out = tmp_path / "bench"
    run = subprocess.run(["bash", str(ROOT / "scripts" / "device_bench.sh"), str(out)],
                         capture_output=True, text=True, timeout=120,
                         env={"PYTHON": sys.executable, "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr
    lines = run.stdout.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("no GPU: ")
    assert not out.exists()  # nothing written where nothing was measured


def test_device_script_without_drjit_says_why(tmp_path):
    # A Python that cannot load Dr.Jit (a bare machine before the packages are carried).
    fake = tmp_path / "python"
    fake.write_text(f"#!/bin/sh\nexec {sys.executable} -S -I \"$@\"\n")
    fake.chmod(0o755)
    run = subprocess.run(["bash", str(ROOT / "scripts" / "device_bench.sh"), str(tmp_path / "b")],
                         capture_output=True, text=True, timeout=120,
                         env={"PYTHON": str(fake), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("no GPU: Dr.Jit does not load (ModuleNotFoundError")


def test_the_table_reads_each_steps_figure_from_its_log(tmp_path):
    # The script's last part, run on logs as the steps write them (no GPU needed): each
    # step's figure lands in the JSON and the table.
    import json

    script = (ROOT / "scripts" / "device_bench.sh").read_text()
    table = script[script.rindex("<<'PY'\n") + len("<<'PY'\n"):script.rindex("\nPY")]
    logs = {
        "tests": "12 passed, 3 skipped in 40.0s",
        "dataset_800x600": "datasets/d: 200 frames; made 200 in 1.6 s, 125.0 frames/s",
        "inverse_rendering": ("fit to the pattern image (cuda): 67 loss evaluations, 8.4 ms "
                              "each in its descents (the model's image and its gradient)"),
    }
    (tmp_path / "steps.txt").write_text("".join(f"{n} 0 5\n" for n in logs))
    for name, text in logs.items():
        (tmp_path / f"{name}.log").write_text(text)
    run = subprocess.run([sys.executable, "-", str(tmp_path)], input=table,
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    rows = json.loads((tmp_path / "device_bench.json").read_text())
    assert rows["tests"]["passed"] == 12
    assert rows["dataset_800x600"]["frames_per_s"] == 125.0
    assert rows["inverse_rendering"]["ms_per_evaluation"] == 8.4
    assert rows["inverse_rendering"]["backend"] == "cuda"
    assert "8.4 ms an evaluation (cuda" in run.stdout and "125.0 frames/s" in run.stdout
