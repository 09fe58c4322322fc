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
