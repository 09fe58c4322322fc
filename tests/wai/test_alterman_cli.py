"""The sun sensor on the command line: an overcast frame is valid input the method cannot use
(exit 0, a status, no surface); a wrong anchor or method is bad input (exit 2, one line); the
experiment's tables carry every number."""

import json

import numpy as np
import pytest

from tests.conftest import PAPER_TOML, ROOT
from wai.cli import main
from wai.experiments.alterman import COLUMNS, csv_text, report_markdown, row
from wai_core.alterman import load_alterman


@pytest.fixture(scope="module")
def overcast_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("overcast")
    toml = folder / "overcast.toml"
    text = (ROOT / "scenes" / "alterman.toml").read_text()
    text = text.replace('config = "paper.toml"', f'config = "{PAPER_TOML}"')
    toml.write_text(text.replace("enabled = true", "enabled = false"))
    out = folder / "frame"
    assert main(["render", str(toml), "--out", str(out), "--quiet"]) == 0
    return out


def test_overcast_frame_reports_no_sun_and_writes_no_surface(overcast_dir, capsys):
    assert main(["restore", str(overcast_dir), "--method", "alterman", "--quiet"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1 and "no_sun" in lines[0]
    metrics = json.loads((overcast_dir / "restore" / "metrics.json").read_text())
    assert metrics["status"] == "no_sun" and metrics["method"] == "alterman"
    written = sorted(p.name for p in (overcast_dir / "restore").iterdir())
    # the output marker, the run's page, and no surface
    assert written == [".wai-output.json", "index.html", "metrics.json"]


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--method", "alterman", "--anchor", "integrability"], "gauge"),
        (["--method", "sonar"], "--method"),
        (["--method", "structured-light"], "pattern.exr"),
    ],
)
def test_bad_restore_input_is_one_line(overcast_dir, capsys, extra, needle):
    assert main(["restore", str(overcast_dir), "--quiet", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


def test_experiment_tables_hold_every_number():
    system = load_alterman(ROOT / "scenes" / "alterman.toml")
    metrics = {
        "wai_rmse_mm": 3.0, "wai_rmse_demeaned_mm": 0.1, "wai_max_abs_mm": 3.5,
        "wai_mean_offset_mm": 3.0, "wai_points": 100, "features_used": 1000,
        "features_rejected": 2, "corner_std_distorted_px": 7.0, "corner_std_restored_px": 0.5,
        "view_restored_fraction": 0.9, "timings_ms": {"end_to_end": 120.0},
        "distorted": {"ssim": 0.55, "mse": 0.17, "psnr_db": 7.6},
        "restored": {"ssim": 0.95, "mse": 0.005, "psnr_db": 23.0},
    }
    rows = [row(0, "structured-light", v, None, metrics, 7.0) for v in ("integrability", "gauge")]
    for theta in (15.0, 60.0):
        rows += [row(0, "alterman", v, theta, metrics, 3.0) for v in ("refined", "h0")]
    rows.append(row(0, "alterman", "overcast", 30.0, {"status": "no_sun"}))
    text = csv_text(rows)
    header, *body = text.strip().splitlines()
    assert header.split(",") == list(COLUMNS) and len(body) == len(rows)
    assert "no_sun" in body[-1]
    md = report_markdown("wai experiment alterman --quick", system, rows, [0], (15.0, 60.0), [])
    assert "3.4603" in md and "1.7845" in md and "0.6814" in md  # the paper's numbers
    assert "results.csv" in md and "`no_sun`" in md
    assert np.isnan(rows[-1]["wai_rmse_mm"])
