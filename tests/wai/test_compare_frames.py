"""Compare's frames by condition: statuses and surface errors frame by frame, each frame
against the same frame without the condition's effect."""

from __future__ import annotations

import pytest

from wai.experiments.compare import DEGRADATIONS, report
from wai.experiments.compare_frames import ADDED_MM, by_condition, frame_columns


def _row(degradation, statuses, rmse, method="sl", seed=0, **extra):
    return {"wind": 1.0, "seed": seed, "method": method, "degradation": degradation,
            "case_frames": len(statuses), **frame_columns(statuses, rmse), **extra}


def test_a_frame_counts_within_the_bar_only_against_its_own_baseline_frame():
    """Frame k under roughness is judged against frame k of the speckle case of the same seed
    and method: ok and within ADDED_MM of it counts, ok past it or not ok does not, and a
    frame whose baseline has no surface is not compared."""
    base = [0.010, 0.200, 0.010, None]
    rough = [0.010 + ADDED_MM * 0.9,   # ok, within: counts
             0.200 + ADDED_MM * 0.5,   # ok, within its own (large) baseline: counts
             0.010 + ADDED_MM * 1.1,   # ok, past the bar
             0.030]                    # ok, but its baseline frame has no surface
    rows = [_row("speckle", ["ok", "ok", "ok", "failed"], base),
            _row("rough_0.01", ["ok", "ok", "ok", "ok"], rough),
            # Another seed's baseline is not this seed's: its frames are all far off.
            _row("speckle", ["ok"] * 4, [5.0] * 4, seed=1),
            _row("rough_0.01", ["ok", "sparse", "ok", "ok"], [5.01, 9.0, 5.2, 5.0], seed=1)]
    got = {(e["condition"], e["method"]): e for e in by_condition(rows, DEGRADATIONS)}
    rough_entry = got["rough_0.01", "sl"]
    assert rough_entry["baseline"] == "speckle"
    assert (rough_entry["frames"], rough_entry["ok"]) == (8, 7)
    assert rough_entry["compared"] == 3 + 4
    assert rough_entry["ok_within"] == 2 + 2  # seed 1: frames 0 and 3
    assert rough_entry["ok_share"] == pytest.approx(7 / 8)
    speckle = got["speckle", "sl"]
    assert speckle["baseline"] is None and speckle["ok_within"] is None
    assert (speckle["frames"], speckle["ok"]) == (8, 7)


def test_conditions_that_change_the_waves_or_have_no_surface_are_not_compared():
    rows = [_row("speckle", ["ok", "ok"], [0.01, 0.01]),
            _row("capillary_5", ["ok", "ok"], [0.02, 0.02]),
            _row("sensor", ["ok", "ok"], [0.02, 0.02]),
            _row("none", ["ok", "ok"], [0.01, 0.3]),
            # A video method's row: no frames of its own; a table written before the columns.
            {"wind": 1.0, "seed": 0, "method": "mean", "degradation": "speckle"},
            {"wind": "1.0", "seed": "0", "method": "old", "degradation": "speckle",
             "frame_statuses": "", "frame_rmse_mm": ""}]
    got = {(e["condition"], e["method"]): e for e in by_condition(rows, DEGRADATIONS)}
    assert set(got) == {("speckle", "sl"), ("capillary_5", "sl"), ("sensor", "sl"),
                        ("none", "sl")}
    assert got["capillary_5", "sl"]["baseline"] is None
    # Sensor noise is seen on the checkerboard: its baseline is the plain scene.
    assert got["sensor", "sl"]["baseline"] == "none"
    assert (got["sensor", "sl"]["compared"], got["sensor", "sl"]["ok_within"]) == (2, 2)
    # Read back from a CSV the keys are strings: the same frames match.
    as_text = [{k: str(v) for k, v in r.items()} for r in rows[2:4]]
    again = {e["condition"]: e for e in by_condition(as_text, DEGRADATIONS)}
    assert again["sensor"]["ok_within"] == 2


def test_the_report_gives_the_frames_by_condition():
    rows = [_row("speckle", ["ok", "ok"], [0.01, 0.01]),
            _row("rough_0.01", ["ok", "sparse"], [0.02, 0.5])]
    text = report([], "wai experiment compare", None, by_condition(rows, DEGRADATIONS))
    line = next(x for x in text.splitlines() if x.startswith("| rough_0.01 | sl |"))
    assert "| 1 / 2 | 50% | 1 / 2 | speckle |" in line
    assert "## Frames by condition" in text
    assert "Frames by condition" not in report([], "wai experiment compare")


def test_a_frame_whose_view_is_not_scored_keeps_its_surface_error() -> None:
    # A steep frame can restore its surface while camera v sees almost none of the object
    # through it: the view has no scores, and the surface's error must still reach the row
    # (and with it the "ok but wrong" count).
    from types import SimpleNamespace

    from wai.experiments.compare import WRONG_OK_MM, _ok_but_wrong, frame_row

    result = SimpleNamespace(ok=True, status="ok", timings_ms={"end_to_end": 12.0},
                             has_view=False)
    wrong = WRONG_OK_MM + 0.1
    done = SimpleNamespace(result=result, scores=SimpleNamespace(restored=None),
                           metrics={"wai_rmse_mm": wrong, "wai_rmse_demeaned_mm": 0.05})
    row = frame_row(done, cal=None)
    assert row["rmse_mm"] == wrong and row["rmse_demeaned_mm"] == 0.05
    assert "ssim" not in row
    assert _ok_but_wrong([row]) == 1
    unscored = SimpleNamespace(result=result, scores=None, metrics={})
    assert frame_row(unscored, cal=None)["rmse_mm"] is None


def test_a_method_rescues_only_the_structured_lights_weak_frames_of_the_same_case():
    from wai.experiments.compare_frames import RIGHT_MM, WRONG_OK_MM, rescues

    sl = "structured-light"
    rows = [
        # The reference: frame 0 right, 1 ok but past RIGHT_MM, 2 not ok, 3 no surface.
        _row("rough_0.01", ["ok", "ok", "sparse", "failed"],
             [0.01, RIGHT_MM + 0.05, 0.02, None], method=sl),
        # The method: right on frame 0 (not weak, not counted), right on 1 and 3, ok but
        # far off on 2.
        _row("rough_0.01", ["ok", "ok", "ok", "ok"],
             [0.01, RIGHT_MM * 0.5, WRONG_OK_MM + 0.1, RIGHT_MM * 0.9], method="m"),
        # Another seed: the reference is right everywhere, so nothing is weak there, and the
        # method's wrong frames on it are not counted here.
        _row("rough_0.01", ["ok", "ok"], [0.01, 0.02], method=sl, seed=1),
        _row("rough_0.01", ["ok", "ok"], [1.0, 1.0], method="m", seed=1),
        # A condition where the method misses what the reference also misses.
        _row("steep_2", ["inconsistent"], [5.0], method=sl),
        _row("steep_2", ["inconsistent"], [0.01], method="m"),
    ]
    got = {(e["condition"], e["method"]): e for e in rescues(rows)}
    assert set(got) == {("rough_0.01", "m"), ("steep_2", "m"), ("all", "m")}
    rough = got["rough_0.01", "m"]
    assert (rough["weak"], rough["rescued"], rough["ok_wrong"]) == (3, 2, 1)
    steep = got["steep_2", "m"]
    assert (steep["weak"], steep["rescued"], steep["ok_wrong"]) == (1, 0, 0)
    total = got["all", "m"]
    assert (total["weak"], total["rescued"]) == (4, 2) and total["rescued_share"] == 0.5
    text = report([], "wai experiment compare", rescued=rescues(rows))
    assert "## Where structured-light is weak" in text
    assert "| all | m | 4 | 2 | 50% | 1 |" in text
    assert "is weak" not in report([], "wai experiment compare")


def test_the_frame_tables_name_a_method_as_the_summary_does():
    # A method of one's own is given by its spec (a file path or module:Class) and names
    # itself; the frame tables show its name, as compare's summary table does.
    from wai.experiments.compare_frames import rescues

    spec = "/somewhere/mine.py:Mine"
    rows = [_row("rough_0.01", ["sparse"], [1.0], method="structured-light",
                 method_name="structured-light"),
            _row("rough_0.01", ["ok"], [0.02], method=spec, method_name="mine")]
    assert {e["method"] for e in rescues(rows)} == {"mine"}
    assert "mine" in {e["method"] for e in by_condition(rows, DEGRADATIONS)}


def test_the_chart_names_every_method_whichever_panels_it_has_a_point_in(tmp_path):
    # On a speckle object most methods find no corners: a legend read off the corner panel
    # alone named only the methods that did. Every method with a time is named.
    from wai.experiments.compare import _figure

    def entry(name, corner_std_px=None, ssim=None, rmse=None):
        return {"name": name, "ms_per_frame": 10.0, "corner_std_px": corner_std_px,
                "ssim": ssim, "rmse_demeaned_mm": rmse}

    summary = [entry("a", ssim=0.8, rmse=0.02), entry("b", corner_std_px=0.5, ssim=0.7),
               entry("c", rmse=0.01), {**entry("d", ssim=0.9), "ms_per_frame": None}]
    assert _figure(summary, tmp_path / "compare.png") == ["a", "b", "c"]
    assert (tmp_path / "compare.png").stat().st_size > 0
