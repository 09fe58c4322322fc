"""The command line: bad input gives one line and exit code 2, and writes nothing."""

import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import PAPER_TOML
from wai.cli import main
from wai_core.errors import WaiInputError


def _run(capsys, *argv):
    code = main(list(argv))
    err = capsys.readouterr().err.strip().splitlines()
    return code, err


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["render", "missing.toml"], "not found"),
        (["render", str(PAPER_TOML), "--wind", "-1"], "--wind"),
        (["render", str(PAPER_TOML), "--spp", "0"], "--spp"),
    ],
)
def test_bad_render_input(capsys, tmp_path, argv, needle):
    code, err = _run(capsys, *argv, "--out", str(tmp_path / "out"))
    assert code == 2 and len(err) == 1 and needle in err[0]
    assert not (tmp_path / "out").exists()


def test_heightfield_with_nans(capsys, tmp_path):
    path = tmp_path / "h.npz"
    z = np.full((5, 6), 150.0)
    z[2, 2] = np.nan
    np.savez(path, x=np.arange(6.0), y=np.arange(5.0), z=z)
    code, err = _run(
        capsys, "render", str(PAPER_TOML), "--heightfield", str(path), "--out", str(tmp_path / "o")
    )
    assert code == 2 and "NaN" in err[0] and not (tmp_path / "o").exists()


def test_console_script_exit_code(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "wai.cli", "render", str(tmp_path / "nope.toml")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0


def test_unset_restore_flags_leave_each_methods_defaults():
    """The CLI holds no defaults of its own: unset flags give what a script gets from the
    method's options, and a flag the method has no use for is refused."""
    from restoration import AltermanOptions, StructuredLightOptions
    from wai.cli import build_parser
    from wai.restore_cli import method_options

    parse = build_parser().parse_args
    assert method_options(parse(["restore", "d"])) == StructuredLightOptions()
    alterman = parse(["restore", "d", "--method", "alterman", "--refine", "0"])
    assert method_options(alterman) == AltermanOptions(n_refine=0)
    with pytest.raises(WaiInputError, match="--fit"):
        method_options(parse(["restore", "d", "--method", "alterman", "--fit"]))
    as_detected = method_options(parse(["restore", "d", "--as-detected"]))
    assert as_detected == StructuredLightOptions(flat_referenced=False)
    with pytest.raises(WaiInputError, match="--as-detected"):
        method_options(parse(["restore", "d", "--method", "alterman", "--as-detected"]))
    assert method_options(parse(["restore", "d", "--spot-bias"])) == StructuredLightOptions(
        spot_bias=True)
    assert method_options(parse(["restore", "d", "--no-spot-bias"])) == StructuredLightOptions(
        spot_bias=False)
    assert StructuredLightOptions().spot_bias is None  # left to the scene's water
    with pytest.raises(WaiInputError, match="--spot-bias"):
        method_options(parse(["restore", "d", "--method", "alterman", "--spot-bias"]))


def test_negative_refine_names_the_option(capsys, tmp_path):
    assert main(["restore", str(tmp_path), "--refine", "-1"]) == 2
    err = capsys.readouterr().err
    assert "--refine" in err and len(err.strip().splitlines()) == 1


def test_video_methods_restore_a_folder_of_frames(tmp_path, capsys):
    """A folder of numbered frames, no scene.json: the registration baseline writes its
    restored view and metrics; per-frame methods refuse the video options."""
    import cv2
    import numpy as np

    frames = tmp_path / "frames"
    frames.mkdir()
    rng = np.random.default_rng(3)
    board = np.kron((np.indices((6, 8)).sum(axis=0) % 2), np.ones((16, 16))) * 200 + 20
    for k in range(4):
        shift = rng.normal(0, 1.0, 2)
        m = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
        img = cv2.warpAffine(board.astype(np.uint8), m, board.shape[::-1],
                             borderMode=cv2.BORDER_REFLECT)
        cv2.imwrite(str(frames / f"frame_{k:02d}.png"), img)
    out = tmp_path / "out"
    assert main(["restore", str(frames), "--method", "registration", "--out", str(out)]) == 0
    assert {p.name for p in out.iterdir()} >= {"restored.png", "metrics.json"}
    assert "4 frames fused" in capsys.readouterr().out
    assert main(["restore", str(frames), "--out", str(out)]) == 2
    assert "--out and --board are for the video methods" in capsys.readouterr().err


def _clip(path, frames: int, size=(64, 48)):
    """A video of ``frames`` frames of a board that moves by a pixel or two."""
    import cv2

    w, h = size
    board = (np.kron(np.indices((h // 8, w // 8)).sum(axis=0) % 2, np.ones((8, 8))) * 200 + 20)
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    for k in range(frames):
        moved = np.roll(board, k % 3 - 1, axis=1).astype(np.uint8)
        out.write(np.repeat(moved[..., None], 3, axis=2))
    out.release()
    return path


def test_a_video_too_long_for_the_memory_is_refused_before_reading(tmp_path, capsys,
                                                                   monkeypatch):
    # 1 KiB available: registering 12 frames of 64 x 48 px needs more, the mean streams.
    import json

    from restoration.video import read_frames
    from wai_core import memory

    clip = _clip(tmp_path / "clip.avi", 12)
    monkeypatch.setattr(memory, "available_bytes", lambda: 1024)
    for method in ("registration", "lucky"):
        code, err = _run(capsys, "restore", str(clip), "--method", method, "--out",
                         str(tmp_path / method))
        assert (code, len(err)) == (2, 1), err
        assert err[0].startswith(f"wai: error: {clip} (12 frames of 64 x 48 px): --method "
                                 f"{method}") and "GiB of memory" in err[0]
        # At least the frames themselves, float32 RGB.
        assert float(err[0].split("about ")[1].split(" GiB")[0]) * 2**30 >= 12 * 64 * 48 * 12 * 0.9
        assert not (tmp_path / method).exists()
    assert main(["restore", str(clip), "--method", "mean", "--out", str(tmp_path / "m")]) == 0
    metrics = json.loads((tmp_path / "m" / "metrics.json").read_text())
    assert metrics["frames"] == 12
    from wai_core.io import read_exr

    np.testing.assert_allclose(read_exr(tmp_path / "m" / "restored.exr"),
                               read_frames(clip).mean(axis=0), atol=1e-6)
    # The before/after figure and the folder's page, which shows it.
    assert (tmp_path / "m" / "before_after.png").read_bytes()[:4] == b"\x89PNG"
    assert 'src="before_after.png"' in (tmp_path / "m" / "index.html").read_text()


def test_an_unknown_method_lists_every_method_a_user_can_name(capsys, tmp_path):
    from restoration import method_names
    from wai.restore_video_cli import VIDEO_METHODS

    code, err = _run(capsys, "restore", str(tmp_path), "--method", "nope")
    assert code == 2 and len(err) == 1 and "'nope'" in err[0]
    for name in (*method_names(), *VIDEO_METHODS, "module:Class"):
        assert name in err[0], name


def test_the_guide_lists_its_pages_and_prints_one(capsys):
    from wai.guide_cli import guide_folder

    assert main(["guide"]) == 0
    listing = capsys.readouterr().out
    assert "rig  " in listing and "A rig of one's own" in listing
    assert main(["guide", "rig"]) == 0
    assert capsys.readouterr().out == (guide_folder() / "rig.md").read_text()
    assert main(["guide", "outputs", "--path"]) == 0
    assert capsys.readouterr().out.strip() == str(guide_folder() / "outputs.md")
    assert main(["guide", "nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no page 'nope'" in err[0] and "rig" in err[0]
