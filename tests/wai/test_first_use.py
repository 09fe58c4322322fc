"""First use: sweeps on a plain install (a worker that dies, a cluster that does not start) and
the notice of the first restoration's compile."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from wai.sweep import WORKER_DIED, is_error, parse_cell, run_sweep

ROOT = Path(__file__).resolve().parents[2]


def die_on_first_try(point: dict) -> dict:
    """Kill this worker process the first time point ``x`` runs (a marker file remembers it);
    ``x`` = 2 kills it every time."""
    marker = Path(point["dir"]) / f"{point['x']}.tried"
    if point["x"] == 2 or (point["x"] == 1 and not marker.exists()):
        marker.touch()
        # Die a moment later, as a real crash seldom comes at once: the client has by then
        # gathered the results the worker finished before. (A result still in the worker's
        # memory dies with it and runs again; on a loaded machine that rerun could meet the
        # next death too, and the test would count a point it did not mean to kill.)
        time.sleep(1.0)
        os._exit(1)
    env = {name: os.environ.get(name) for name in ("OMP_NUM_THREADS", "MALLOC_TRIM_THRESHOLD_")}
    return {"y": point["x"] * 10, "omp": env["OMP_NUM_THREADS"],
            "trim": env["MALLOC_TRIM_THRESHOLD_"]}


def test_a_point_whose_worker_died_runs_once_more_and_says_so(tmp_path, capsys):
    table = tmp_path / "t.csv"
    pts = [{"x": x, "dir": str(tmp_path)} for x in range(4)]
    rows = run_sweep(pts, die_on_first_try, table, workers=1)

    by_x = {r["x"]: r for r in rows}
    assert [by_x[x]["status"] for x in (0, 1, 3)] == ["ok"] * 3  # 1 ran again, and then ok
    assert [by_x[x]["y"] for x in (0, 1, 3)] == [0, 10, 30]
    # Workers, restarted ones too, keep one native thread, and glibc's own trim threshold
    # (dask's 64 KiB one page-faults every array in anew: 1.3x slower restorations).
    assert {by_x[x]["omp"] for x in (0, 1, 3)} == {1}
    mine = os.environ.get("MALLOC_TRIM_THRESHOLD_")  # one the user set is theirs to keep
    assert {by_x[x]["trim"] for x in (0, 1, 3)} == {None if mine is None else parse_cell(mine)}
    assert by_x[2]["status"].startswith(f"error: {WORKER_DIED} (2 tries): tcp://")
    assert is_error(by_x[2]["status"])
    run = json.loads(table.with_suffix(".json").read_text())["runs"][-1]
    assert (run["ran"], run["failed"]) == (4, 1)
    # 1 once, 2 twice; a finished point whose result died with its worker runs once more too
    assert run["worker_deaths"] >= 3
    assert "ran 4 (1 failed)" in capsys.readouterr().err
    assert not list(tmp_path.glob(".*.lock"))


def test_a_sweep_that_cannot_start_leaves_nothing_of_its_own(tmp_path, monkeypatch):
    import wai.sweep.backend

    def broken(*args, **kwargs):
        raise RuntimeError("no cluster today")

    monkeypatch.setattr(wai.sweep.backend, "_dask_client", broken)
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
        "from wai.threads import limit_native_threads\n"
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


def test_kernel_activity_tells_a_cold_call_from_a_warm_one():
    import numba

    from restoration._compile import kernel_activity

    kernel = numba.njit(lambda x: x * 2 + 1)
    with kernel_activity() as cold:
        assert kernel(3) == 7
    with kernel_activity() as warm:
        assert kernel(4) == 9
    assert cold.compiles >= 1 and cold.loads >= 1 and not cold.warm
    assert warm.warm


def test_a_sweep_timing_that_ran_a_new_kernel_is_taken_again(monkeypatch):
    # The variant's first frame ran untimed, but the first timed restore still compiles (a
    # code path that frame did not take): its time must not be the one reported.
    from types import SimpleNamespace

    import numba

    from wai.experiments import frame_eval

    calls: list[bool] = []

    class Restore:
        def __init__(self, options):
            pass

        def __call__(self, images, cal):
            cold = len(calls) < 2  # the untimed warm-up and the first timed restore
            if cold:
                numba.njit(lambda x: x + 1)(1)  # a new kernel, compiled now
            calls.append(cold)
            return SimpleNamespace(restored=True, surface=SimpleNamespace(timings_ms={}),
                                   timings_ms={"end_to_end": 500.0 if cold else 5.0})

    monkeypatch.setattr(frame_eval, "_WARMED", set())
    _, ms = frame_eval._timed_restore({}, None, Restore("variant"), repeats=1)
    assert ms == {"end_to_end": 5.0}
    assert calls == [True, True, False]


PROBE = """
import importlib, json
from restoration._compile import _KERNEL_MODULES, kernels_cached
index = []
for name in _KERNEL_MODULES:
    for value in vars(importlib.import_module(name)).values():
        path = getattr(getattr(getattr(value, "_cache", None), "_cache_file", None),
                       "_index_path", None)
        if path:
            index.append(path)
            break
print(json.dumps({"cached": kernels_cached(), "index": index}))
"""


def _probe(cache_dir: Path) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    done = subprocess.run([sys.executable, "-c", PROBE], env=env, cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def test_the_compile_notice_is_due_until_the_kernels_are_cached(tmp_path):
    # Only imports, no compile: an empty cache folder means the next restore compiles (the
    # notice is due); once a kernel of each module is cached there, it is not.
    cold = _probe(tmp_path)
    assert cold["cached"] is False
    assert cold["index"] and all(Path(p).is_relative_to(tmp_path) for p in cold["index"])
    for path in cold["index"]:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).touch()  # what numba writes beside a cached kernel
    assert _probe(tmp_path)["cached"] is True
