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
    # k2 is the lens's, so the views determine it; its tangential terms are not there.
    assert "k2" not in fit.held_zero and abs(fit.distortion[1] - 0.05) < 3 * fit.sigma["k2"]
    assert set(fit.held_zero) == {"p1", "p2"} and fit.distortion[2:4].tolist() == [0.0, 0.0]
    assert fit.rms_px <= 0.1
    keys = fit.to_config_keys("camera_v", dev)
    calibrated = with_keys(load_system("paper"), keys).camera_v
    assert calibrated.focal_mm == pytest.approx(dev.focal_mm, rel=0.002)
    np.testing.assert_allclose(calibrated.principal_offset_px, [15.0, -10.0], atol=1.0)


def _lens_error_px(fit, dev, pixels):
    """How far ``fit`` puts the true lens's image of each of ``pixels`` (K, 2) off them, px."""
    import cv2

    f = dev.focal_mm * dev.width_px / dev.sensor_width_mm
    c = np.array([(dev.width_px - 1) / 2, (dev.height_px - 1) / 2]) + dev.principal_offset_px
    k_true = np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1]])
    rays = cv2.undistortPoints(pixels.reshape(-1, 1, 2), k_true, np.asarray(dev.distortion))
    rays = np.concatenate([rays.reshape(-1, 2), np.ones((len(pixels), 1))], axis=1)
    k_fit = np.array([[fit.fx_px, 0, fit.cx_px], [0, fit.fy_px, fit.cy_px], [0, 0, 1]])
    seen = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), k_fit, fit.distortion)[0]
    return np.linalg.norm(seen.reshape(-1, 2) - pixels, axis=1)


@pytest.mark.slow
def test_terms_the_views_do_not_determine_are_held_at_zero_and_the_corners_stay_right():
    # A lens of k1 alone: a free fit gives k2 and p1, p2 values the boards barely see, traded
    # against k1 where the boards are; at the image's corners, where the boards seldom reach,
    # that trade moves the lens. Held at zero, the lens stays closer to the true one there.
    cfg = with_keys(load_system("paper"), {"camera_v.distortion": [-0.1, 0.0, 0.0, 0.0, 0.0],
                                           "camera_v.principal_offset_px": [5.0, 5.0]})
    dev = cfg.camera_v
    images = render_checkerboards(cfg, "camera_v", 12, seed=3)
    free = calibrate_device(images, Board(), (dev.height_px, dev.width_px), select_terms=False)
    fit = calibrate_device(images, Board(), (dev.height_px, dev.width_px))
    assert not free.held_zero and set(fit.held_zero) == {"k2", "p1", "p2"}
    assert fit.distortion[1:].tolist() == [0.0] * 4 and fit.sigma["k2"] == 0.0
    assert fit.held_zero["k2"] == free.sigma["k2"]
    assert abs(fit.distortion[0] + 0.1) < 3 * fit.sigma["k1"] + 1e-3
    rows, cols = np.mgrid[0:dev.height_px:20, 0:dev.width_px:20]
    pixels = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(float)
    reach = np.percentile(np.linalg.norm(np.concatenate(fit.corners_px) - (400, 300), axis=1),
                          95)
    beyond = np.linalg.norm(pixels - (400, 300), axis=1) > reach
    assert beyond.mean() > 0.3  # the boards leave the corners out
    held, free_px = (_lens_error_px(f, dev, pixels[beyond]).max() for f in (fit, free))
    assert held < free_px and held < 1.0, (held, free_px)


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
    capsys.readouterr()
    assert main(["calibrate", str(out / "checkerboards"), "--out", str(rig), "--quiet"]) == 0
    printed = capsys.readouterr().out
    record = json.loads(rig.read_text())
    for camera in ("camera_v", "camera_s"):
        assert record["devices"][camera]["fx_px"] == pytest.approx(truth[camera]["fx_px"],
                                                                   rel=0.002)
        # The paper's ideal lenses: k1 alone is fitted where nothing else shows in 6 views
        # (each term held at zero is said so, in the file and on the terminal).
        held = record["devices"][camera]["held_at_zero"]
        assert set(held) <= {"k2", "p1", "p2"}
        assert all(record["devices"][camera]["sigma"][t] == 0.0 for t in held)
        line = next(x for x in printed.splitlines() if x.startswith(f"{camera}: fx"))
        assert ("held at 0" in line) == bool(held), line
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


@pytest.fixture(scope="module")
def boards(tmp_path_factory):
    """Six rendered board views per camera of the paper's rig (``DIR/checkerboards``)."""
    out = tmp_path_factory.mktemp("boards") / "boards"
    assert main(["render", "paper", "--checkerboards", "6", "--out", str(out), "--quiet"]) == 0
    return out / "checkerboards"


def _calibrate(capfd, *argv):
    code = main(["calibrate", *map(str, argv), "--quiet"])
    out, err = capfd.readouterr()
    return code, err.strip().splitlines(), out


def test_a_rig_file_of_ones_own_is_never_replaced_but_calibrates_own_is(boards, tmp_path,
                                                                        capfd):
    mine = tmp_path / "my_rig.json"
    mine.write_text(json.dumps({"config_keys": {"camera_v.focal_mm": 4.0}}))
    code, err, _ = _calibrate(capfd, boards, "--out", mine)
    assert (code, len(err)) == (2, 1) and f"--out {mine}" in err[0]
    assert "not written by wai" in err[0]
    assert json.loads(mine.read_text()) == {"config_keys": {"camera_v.focal_mm": 4.0}}
    assert read_rig(mine) == {"camera_v.focal_mm": 4.0}  # still a rig file to restore with
    ours = tmp_path / "rig.json"
    for _ in range(2):  # written, then replaced by the next calibration
        code, err, _ = _calibrate(capfd, boards, "--out", ours)
        assert (code, err) == (0, [])
    assert json.loads(ours.read_text())["format"] == "wai-rig/1"


def test_an_output_that_cannot_be_written_is_refused_before_calibrating(boards, tmp_path,
                                                                        capfd, monkeypatch):
    import errno
    import os
    import tempfile

    import restoration as rc  # wai calibrate reads the face's calibrate_device

    def never(*args, **kwargs):
        raise AssertionError("calibrated before the output was checked")

    monkeypatch.setattr(rc, "calibrate_device", never)
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    (tmp_path / "folder.json").mkdir()
    cases = {a_file / "rig.json": "file.txt is a file", tmp_path / "folder.json":
             "not a regular file"}
    for out, says in cases.items():
        code, err, _ = _calibrate(capfd, boards, "--out", out)
        assert (code, len(err)) == (2, 1) and says in err[0] and f"--out {out}" in err[0]
    real = tempfile.mkdtemp

    def read_only(*args, **kwargs):  # a read-only mount (root ignores the mode bits)
        if kwargs.get("prefix") == ".wai-probe-":
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real(*args, **kwargs)

    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    code, err, _ = _calibrate(capfd, boards, "--out", tmp_path / "ro" / "rig.json")
    assert (code, len(err)) == (2, 1) and "Read-only file system" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt", "folder.json"]


@pytest.mark.parametrize("board", [
    {"cols": -8, "rows": 6, "square_mm": 20.0},
    {"cols": 0, "rows": 6, "square_mm": 20.0},
    {"cols": 8, "rows": 6, "square_mm": float("nan")},
    {"cols": 8, "rows": 6, "square_mm": -1},
    {"cols": 7.5, "rows": 6, "square_mm": 20.0},
    {"cols": True, "rows": 6, "square_mm": 20.0},
    {"cols": "8", "rows": 6, "square_mm": 20.0},
    [8, 6, 20.0],
])
def test_a_board_file_that_describes_no_board_is_named_in_one_line(tmp_path, capfd, board):
    (tmp_path / "camera_v").mkdir()
    (tmp_path / "board.json").write_text(json.dumps(board))  # NaN as JSON's NaN
    code, err, _ = _calibrate(capfd, tmp_path, "--out", tmp_path / "rig.json")
    assert (code, len(err)) == (2, 1) and str(tmp_path / "board.json") in err[0], err


def test_an_unreadable_flat_image_is_one_line_without_the_decoders_noise(boards, tmp_path,
                                                                         capfd):
    png = (boards / "camera_s").iterdir().__next__().read_bytes()
    broken = bytearray(png)
    broken[20:24] = b"\xff\xff\xff\xff"  # the header's checksum: libpng prints an error
    flat = tmp_path / "corrupt.png"
    flat.write_bytes(bytes(broken))
    code, err, _ = _calibrate(capfd, boards, "--flat", flat, "--out", tmp_path / "rig.json")
    assert (code, len(err)) == (2, 1), err
    assert err[0].startswith(f"wai: error: --flat {flat} is not a readable PNG image")
    assert not (tmp_path / "rig.json").exists()


def test_calibrate_draws_each_cameras_corners_and_errors_beside_the_rig_file(boards, tmp_path,
                                                                            capfd):
    from html.parser import HTMLParser

    rig = tmp_path / "rig.json"
    code, err, out = _calibrate(capfd, boards, "--out", rig)
    assert (code, err) == (0, [])
    figures = tmp_path / "rig_figures"
    assert sorted(p.name for p in figures.iterdir()) == [
        ".wai-output.json", "camera_s.png", "camera_v.png", "index.html"]
    assert f"figures: {figures}" in out

    class Images(HTMLParser):
        found: list = []

        def handle_starttag(self, tag, attrs):
            if tag == "img":
                self.found.append(dict(attrs)["src"])

    page = Images()
    page.feed((figures / "index.html").read_text())
    assert sorted(page.found) == ["camera_s.png", "camera_v.png"]
    again = tmp_path / "again.json"
    code, err, _ = _calibrate(capfd, boards, "--out", again, "--no-figures")
    assert (code, err) == (0, []) and not (tmp_path / "again_figures").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    code, err, _ = _calibrate(capfd, boards, "--out", tmp_path / "third.json", "--figures", mine)
    assert code == 2 and len(err) == 1 and "--figures" in err[0]
    assert not (tmp_path / "third.json").exists()  # refused before any work


def test_flat_tilt_needs_the_flat_image_and_a_projector_port(boards, tmp_path, capfd):
    flat = next((boards / "camera_s").iterdir())
    for args, says in (([], "--flat-tilt fits the projector port's tilt on --flat"),
                       (["--flat", flat], "--flat-tilt: --config's projector has no port")):
        code, err, _ = _calibrate(capfd, boards, "--flat-tilt", *args,
                                  "--out", tmp_path / "rig.json")
        assert (code, len(err)) == (2, 1) and says in err[0], err
    assert not (tmp_path / "rig.json").exists()
