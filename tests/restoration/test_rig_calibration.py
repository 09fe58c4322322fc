"""Calibrating cameras from checkerboards (OpenCV) against the lenses the boards were rendered
with: the truth comes from the scene's configuration, not from the calibration."""

import json

import numpy as np
import pytest

from mitsuba_wai.checkerboards import Board, render_checkerboards
from restoration.rig_calibration import calibrate_device, read_rig
from wai.cli import main
from wai_core import load_system, with_keys
from wai_core.errors import WaiInputError

LENS = {"camera_v.distortion": [-0.2, 0.05, 0.0, 0.0, 0.0],
        "camera_v.principal_offset_px": [15.0, -10.0]}


@pytest.mark.slow
def test_a_distorted_lens_off_centre_is_recovered():
    cfg = with_keys(load_system("paper"), LENS)
    dev = cfg.camera_v
    fit = calibrate_device(render_checkerboards(cfg, "camera_v", 12, seed=3), Board(),
                           (dev.height_px, dev.width_px))
    fx = dev.focal_mm * dev.width_px / dev.sensor_width_mm
    assert fit.n_used == 12 and fit.n_rejected == 0
    assert abs(fit.fx_px / fx - 1) < 0.002
    assert abs(fit.cx_px - ((dev.width_px - 1) / 2 + 15.0)) < 1.0
    assert abs(fit.cy_px - ((dev.height_px - 1) / 2 - 10.0)) < 1.0
    assert abs(fit.distortion[0] + 0.2) < 0.01
    assert fit.rms_px <= 0.1
    keys = fit.to_config_keys("camera_v", dev)
    calibrated = with_keys(load_system("paper"), keys).camera_v
    assert calibrated.focal_mm == pytest.approx(dev.focal_mm, rel=0.002)
    np.testing.assert_allclose(calibrated.principal_offset_px, [15.0, -10.0], atol=1.0)


def test_boards_not_found_are_counted_and_too_few_refused():
    cfg = load_system("paper")
    images = render_checkerboards(cfg, "camera_v", 5, seed=1)
    blank = [np.full((600, 800), 0.5, np.float32)] * 2
    fit = calibrate_device(images + blank, Board(), (600, 800))
    assert fit.n_used == 5 and fit.n_rejected == 2
    assert np.abs(fit.distortion[:2]).max() < 0.01  # an ideal lens
    with pytest.raises(WaiInputError, match="found in 0 of 2"):
        calibrate_device(blank, Board(), (600, 800))


def test_render_calibrate_and_restore_options_from_the_command_line(tmp_path, capsys):
    out = tmp_path / "boards"
    assert main(["render", "paper", "--checkerboards", "6", "--out", str(out), "--quiet"]) == 0
    truth = json.loads((out / "scene.json").read_text())["checkerboards"]["truth"]
    rig = tmp_path / "rig.json"
    assert main(["calibrate", str(out / "checkerboards"), "--out", str(rig), "--quiet"]) == 0
    record = json.loads(rig.read_text())
    for camera in ("camera_v", "camera_s"):
        assert record["devices"][camera]["fx_px"] == pytest.approx(truth[camera]["fx_px"],
                                                                   rel=0.002)
    keys = read_rig(rig)
    assert set(keys) >= {"camera_v.focal_mm", "camera_s.distortion"}
    capsys.readouterr()
    (tmp_path / "mine.json").write_text("{}")
    assert main(["calibrate", str(out / "checkerboards"), "--out",
                 str(tmp_path / "mine.json")]) == 2  # not ours: never overwritten
    assert (tmp_path / "mine.json").read_text() == "{}"
    assert main(["calibrate", str(tmp_path / "none")]) == 2
    assert main(["restore", str(out), "--rig", str(tmp_path / "mine.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("wai: error:") for line in err)
