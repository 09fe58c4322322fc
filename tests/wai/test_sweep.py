"""The sweep runner: rows stream into one table, reruns skip finished points, errors are rows."""

from __future__ import annotations

import argparse
import csv
import json
import os
import threading
import time

import pytest

from wai.sweep import (
    SweepOptions,
    SweepTable,
    add_sweep_arguments,
    point_id,
    read_table,
    run_sweep,
)
from wai_core.errors import WaiInputError

FAILING = {3}  # the values of x for which square() raises; tests change it in this process


def square(point: dict) -> dict:
    """The toy experiment: y = x², an error for the x in FAILING, a few ms of work."""
    time.sleep(0.005)
    if point["x"] in FAILING:
        raise ValueError(f"no square for\n{point['x']}")
    return {"y": point["x"] ** 2}


def square_and_threads(point: dict) -> dict:
    """square() plus the worker's OpenMP thread count (to check the worker environment); for
    x = 5 a result that does not pickle (to check that a Dask failure is a row too)."""
    if point["x"] == 5:
        return {"y": threading.Lock()}
    return {**square(point), "omp": os.environ.get("OMP_NUM_THREADS")}


def points(n: int, start: int = 0) -> list[dict]:
    return [{"x": x, "label": f"p{x}"} for x in range(start, start + n)]


def summary(rows: list[dict]) -> set[tuple]:
    """Rows as a set (completion order does not matter)."""
    return {(r["x"], r["y"], r["status"].split(":")[0]) for r in rows}


def last_run(table) -> dict:
    return json.loads(table.with_suffix(".json").read_text())["runs"][-1]


def test_in_process_writes_every_row(tmp_path):
    table = tmp_path / "t.csv"
    rows = run_sweep(points(5), square, table, workers=0, progress=False)

    expected = {(0, 0, "ok"), (1, 1, "ok"), (2, 4, "ok"), (3, None, "error"), (4, 16, "ok")}
    assert summary(rows) == expected
    assert [r["x"] for r in rows] == [0, 1, 2, 3, 4]  # in the order of the points
    assert summary(read_table(table)) == expected
    with table.open() as f:
        header = next(csv.reader(f))
    assert header == ["x", "label", "y", "point_id", "status", "elapsed_s", "worker"]
    assert {r["point_id"] for r in rows} == {point_id(p) for p in points(5)}
    assert all(r["worker"] == "in-process" and r["elapsed_s"] >= 0.0 for r in rows)
    run = last_run(table)
    assert (run["points"], run["ran"], run["failed"], run["skipped"]) == (5, 5, 1, 0)
    assert run["scheduler"] == "in-process" and run["outcome"] == "complete"


def test_parquet_copy_matches_the_table(tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    table = tmp_path / "t.csv"
    run_sweep(points(4), square, table, workers=0, progress=False)
    copy = pq.read_table(table.with_suffix(".parquet")).to_pylist()
    assert sorted(copy, key=lambda r: r["x"]) == sorted(read_table(table), key=lambda r: r["x"])


def test_rerun_skips_finished_points(tmp_path, capsys):
    table = tmp_path / "t.csv"
    first = run_sweep(points(3), square, table, workers=0, progress=False)

    rows = run_sweep(points(5), square, table, workers=0)

    assert "3 already in the table, 2 to run" in capsys.readouterr().err
    run = last_run(table)
    assert (run["skipped"], run["ran"]) == (3, 2)
    assert len(read_table(table)) == 5
    assert rows[:3] == first  # the old rows are kept as they were
    assert summary(rows[3:]) == {(3, None, "error"), (4, 16, "ok")}


def test_errors_are_not_retried_unless_asked(tmp_path, monkeypatch):
    table = tmp_path / "t.csv"
    run_sweep(points(5), square, table, workers=0, progress=False)
    error = next(r for r in read_table(table) if r["x"] == 3)
    assert error["status"] == "error: ValueError: no square for 3"  # one line

    monkeypatch.setattr("tests.wai.test_sweep.FAILING", set())
    run_sweep(points(5), square, table, workers=0, progress=False)
    assert last_run(table)["ran"] == 0

    rows = run_sweep(points(5), square, table, workers=0, progress=False, retry_errors=True)
    assert last_run(table)["ran"] == 1
    assert len(read_table(table)) == 5  # the error row was replaced, not duplicated
    assert next(r for r in rows if r["x"] == 3)["status"] == "ok"


def test_truncated_last_line_is_dropped(tmp_path, capsys):
    table = tmp_path / "t.csv"
    run_sweep(points(3), square, table, workers=0, progress=False)
    with table.open("a") as f:
        f.write("9,p9,81,abc")  # a killed sweep was writing this row

    rows = run_sweep(points(4), square, table, workers=0, progress=False)

    assert "truncated" in capsys.readouterr().err
    assert table.read_text().endswith("\n") and "abc" not in table.read_text()
    assert summary(rows) == {(0, 0, "ok"), (1, 1, "ok"), (2, 4, "ok"), (3, None, "error")}


def test_new_result_columns_widen_the_table(tmp_path, monkeypatch):
    table = tmp_path / "t.csv"
    run_sweep(points(2), square, table, workers=0, progress=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")

    run_sweep(points(2, start=10), square_and_threads, table, workers=0, progress=False)

    rows = read_table(table)
    assert list(rows[0]) == ["x", "label", "y", "omp", "point_id", "status", "elapsed_s", "worker"]
    assert [(r["x"], r["omp"]) for r in rows] == [(0, None), (1, None), (10, 3), (11, 3)]


def test_bad_results_are_error_rows(tmp_path):
    table = tmp_path / "t.csv"
    rows = run_sweep([{"x": 1}], _returns_x, table, workers=0, progress=False)
    assert rows[0]["status"].startswith("error: ValueError: result keys ['x']")


def _returns_x(point: dict) -> dict:
    return {"x": 2}


def test_point_ids():
    assert point_id({"a": 1, "b": "s"}) == point_id({"b": "s", "a": 1})
    assert point_id({"a": 3.0}) == point_id({"a": 3})
    assert point_id({"a": 1, "seed": 2}, key=["a"]) == point_id({"a": 1, "seed": 5}, key=["a"])
    assert point_id({"a": 1}) != point_id({"a": 2})
    with pytest.raises(ValueError, match="same key fields"):
        run_sweep([{"a": 1, "s": 1}, {"a": 1, "s": 2}], square, "t.csv", key=["a"], workers=0)
    with pytest.raises(ValueError, match="reserved"):
        run_sweep([{"status": 1}], square, "t.csv", workers=0)


def test_one_sweep_per_table(tmp_path):
    table = tmp_path / "t.csv"
    with SweepTable(table), pytest.raises(WaiInputError, match="another sweep"):
        run_sweep(points(2), square, table, workers=0, progress=False)


def test_command_line_options():
    parser = argparse.ArgumentParser()
    add_sweep_arguments(parser)
    args = parser.parse_args(["--workers", "0", "--retry-errors", "--no-progress"])
    assert SweepOptions.from_args(args) == SweepOptions(workers=0, retry_errors=True,
                                                        progress=False)
    assert SweepOptions.from_args(args).kwargs() == {
        "scheduler": None,
        "workers": 0,
        "threads_per_worker": 1,
        "retry_errors": True,
        "progress": False,
    }
    args = parser.parse_args(["--scheduler", "tcp://h:8786", "--threads-per-worker", "2"])
    assert SweepOptions.from_args(args) == SweepOptions("tcp://h:8786", threads_per_worker=2)
    assert SweepOptions.from_args(parser.parse_args([])) == SweepOptions()
    with pytest.raises(SystemExit):
        parser.parse_args(["--workers", "-1"])


def test_local_cluster_of_two_workers(tmp_path):
    pytest.importorskip("distributed")
    table = tmp_path / "t.csv"
    run_sweep(points(2), square, table, workers=0, progress=False)

    rows = run_sweep(points(6), square_and_threads, table, workers=2, progress=False)

    new = [r for r in rows if r["x"] >= 2]
    assert summary(new) == {(2, 4, "ok"), (3, None, "error"), (4, 16, "ok"), (5, None, "error")}
    assert "error: ValueError: no square for 3" in {r["status"] for r in new}
    assert all(r["worker"].startswith("tcp://") for r in new if r["x"] != 5)
    assert {r["omp"] for r in new if r["status"] == "ok"} == {1}  # one native thread per worker
    run = last_run(table)
    assert (run["scheduler"], run["workers"], run["threads_per_worker"]) == ("local", 2, 1)
    assert (run["skipped"], run["ran"], run["failed"]) == (2, 4, 2)


def die_once(point: dict) -> dict:
    """Kill this worker process the first time a point runs (a marker file remembers)."""
    marker = f"{point['dir']}/{point['x']}.tried"
    if point["x"] == 1 and not os.path.exists(marker):
        open(marker, "w").close()
        os._exit(1)
    if point["x"] == 2:
        os._exit(1)  # every time
    return {"y": point["x"]}


def test_a_dead_worker_is_said_and_its_point_retried(tmp_path):
    # One point per sweep: a dying worker takes down whatever else it holds, which is what
    # the scheduler's retries are for, but would make the counts below a race. Two tries
    # (the scheduler's default is four) keep the worker restarts few.
    import dask

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        rows = _die_sweeps(tmp_path)
    assert rows[0]["status"] == "ok"  # ran again on the restarted worker
    assert rows[1]["status"].startswith("error: worker died (2 tries)")
    assert last_run(tmp_path / "b.csv")["failed"] == 1
    assert not list(tmp_path.glob(".*.lock"))


def _die_sweeps(tmp_path) -> list[dict]:
    once = run_sweep([{"x": 1, "dir": str(tmp_path)}], die_once, tmp_path / "a.csv", workers=1,
                     progress=False)
    always = run_sweep([{"x": 2, "dir": str(tmp_path)}], die_once, tmp_path / "b.csv",
                       workers=1, progress=False)
    return [once[0], always[0]]
