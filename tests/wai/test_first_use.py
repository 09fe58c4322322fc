"""First use: sweeps on a plain install (a worker that dies, a cluster that does not start) and
the notice of the first restoration's compile."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from wai.sweep import WORKER_DIED, is_error, run_sweep

ROOT = Path(__file__).resolve().parents[2]


def die_on_first_try(point: dict) -> dict:
    """Kill this worker process the first time point ``x`` runs (a marker file remembers it);
    ``x`` = 2 kills it every time."""
    marker = Path(point["dir"]) / f"{point['x']}.tried"
    if point["x"] == 2 or (point["x"] == 1 and not marker.exists()):
        marker.touch()
        os._exit(1)
    return {"y": point["x"] * 10}


def test_a_point_whose_worker_died_runs_once_more_and_says_so(tmp_path, capsys):
    table = tmp_path / "t.csv"
    pts = [{"x": x, "dir": str(tmp_path)} for x in range(4)]
    rows = run_sweep(pts, die_on_first_try, table, workers=1)

    by_x = {r["x"]: r for r in rows}
    assert [by_x[x]["status"] for x in (0, 1, 3)] == ["ok"] * 3  # 1 ran again, and then ok
    assert [by_x[x]["y"] for x in (0, 1, 3)] == [0, 10, 30]
    assert by_x[2]["status"].startswith(f"error: {WORKER_DIED} (2 tries): tcp://")
    assert is_error(by_x[2]["status"])
    run = json.loads(table.with_suffix(".json").read_text())["runs"][-1]
    assert (run["ran"], run["failed"]) == (4, 1)
    # 1 once, 2 twice; a finished point whose result died with its worker runs once more too
    assert run["worker_deaths"] >= 3
    assert "ran 4 (1 failed)" in capsys.readouterr().err
    assert not list(tmp_path.glob(".*.lock"))


def test_a_sweep_that_cannot_start_leaves_nothing_of_its_own(tmp_path, monkeypatch):
    import wai.sweep

    def broken(*args, **kwargs):
        raise RuntimeError("no cluster today")

    monkeypatch.setattr(wai.sweep, "_dask_client", broken)
    mine = tmp_path / "notes.txt"
    mine.write_text("the user's")
    with pytest.raises(RuntimeError, match="no cluster today"):
        run_sweep([{"x": 1}], die_on_first_try, tmp_path / "t.csv", workers=2, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_a_table_that_is_not_a_sweeps_leaves_no_lock(tmp_path):
    from wai_core.errors import WaiInputError

    table = tmp_path / "t.csv"
    table.write_text("a,b\n1,2\n")
    with pytest.raises(WaiInputError, match="not a sweep table"):
        run_sweep([{"x": 1}], die_on_first_try, table, workers=0, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv"]


def test_numba_threads_are_sized_without_changing_its_environment_under_it():
    # A worker that loaded numba (unpickling the point's function imports it) with another
    # NUMBA_NUM_THREADS than the sweep's, e.g. one the nanny restarted: numba rereads the
    # variable whenever it compiles and raises if it changed after its threads started.
    probe = (
        "import numba, os\n"
        "numba.set_num_threads(1)\n"  # starts numba's threads with the inherited count
        "from wai.sweep import limit_native_threads\n"
        "limit_native_threads(1)\n"
        "assert numba.get_num_threads() == 1\n"
        "numba.njit(lambda x: x + 1)(1)\n"  # a compile after the sizing
        "print('compiled')\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    env["NUMBA_NUM_THREADS"] = "2"
    done = subprocess.run([sys.executable, "-c", probe], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "compiled"
