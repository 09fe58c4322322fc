"""Sweep experiments: one frame per point, failures reported, summaries that never average a
failed frame in."""

import pytest

from wai.experiments.frame_eval import evaluate_frame
from wai.experiments.stability import sweep_summary
from wai.experiments.tradeoffs import chart_series

PAPER = "scenes/paper.toml"


@pytest.fixture(scope="module")
def calm_row():
    return evaluate_frame({"config": PAPER, "seed": 0, "spp_pattern": 4, "repeats": 1})


def test_a_frame_within_the_bound_is_restored(calm_row):
    # U = 1 m/s, D = 28 px: the waves' slope amplitude is near eq. 35's bound, most dots keep
    # their labels and the surface comes back far below the paper's 1.78 mm.
    assert calm_row["frame_status"] == "ok"
    assert calm_row["fraction_correct"] > 0.6
    assert calm_row["n_wrong"] <= 0.05 * calm_row["n_matched"]
    assert calm_row["wai_rmse_mm"] < 0.5
    assert calm_row["restored_ssim"] > calm_row["distorted_ssim"]


def test_a_frame_far_beyond_the_bound_is_reported_as_failed():
    # The same waves 6x steeper: Φ is several times eq. 35's limit, so ordering-based
    # correspondence must break, and the row must say so rather than carry scores.
    row = evaluate_frame(
        {"config": PAPER, "seed": 0, "spp_pattern": 4, "repeats": 1, "amplitude": 6.0}
    )
    assert row["phi_deg"] > 3 * row["phi_max_deg"]
    assert row["frame_status"] != "ok"
    assert row["fraction_correct"] < 0.5


def test_summaries_count_failures_apart():
    rows = [
        {"sweep": "wind", "wind_mps": 1.0, "status": "ok", "frame_status": "ok",
         "fraction_correct": 0.8, "wai_rmse_mm": 0.1, "restored_ssim": 0.98, "phi_deg": 1.0,
         "phi_max_deg": 1.0},
        {"sweep": "wind", "wind_mps": 1.0, "status": "ok", "frame_status": "failed: too few",
         "fraction_correct": 0.0, "phi_deg": 3.0, "phi_max_deg": 1.0},
        {"sweep": "wind", "wind_mps": 1.0, "status": "error: ValueError: x"},
    ]
    (entry,) = sweep_summary(rows)["wind"]
    assert entry["frames"] == 3 and entry["ok"] == 1
    assert entry["statuses"] == {"ok": 1, "failed": 1, "error": 1}
    assert entry["wai_rmse_mm"] == pytest.approx(0.1)  # the failed frames carry no score
    assert entry["fraction_correct"] == pytest.approx(0.4)  # but do count as not correct

    series = chart_series([
        {"chart": "spacing", "spacing_px": 28, "status": "ok", "frame_status": "ok",
         "ms_end_to_end": 50.0, "wai_rmse_mm": 0.2},
        {"chart": "spacing", "spacing_px": 28, "status": "ok", "frame_status": "wrong_labels",
         "ms_end_to_end": 90.0, "wai_rmse_mm": 9.0},
    ])
    (spacing,) = series["spacing"]
    assert (spacing["ok"], spacing["n"], spacing["rmse_mm"]) == (1, 2, 0.2)
