"""``wai restore`` on a folder of one's own numbered captures: restored as a sequence (level
tracked, frames.csv, movies, no truth), the same surfaces as the rendered layout of the same
frames, the input folder untouched, and a broken numbering named in one line."""

import csv
import json
import shutil

import cv2
import numpy as np
import pytest

from tests.conftest import paper_toml_with
from wai.cli import main
from wai_core.errors import WaiInputError
from wai_core.sequence import read_sequence, sequence_kind

FRAMES = 3


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Three rendered frames of the paper's scene at 1 sample per pixel, restored as rendered."""
    text = paper_toml_with(render={"spp_pattern": 1, "spp_view": 1})
    root = tmp_path_factory.mktemp("own")
    (root / "quick.toml").write_text(text)
    out = root / "seq"
    assert main(["render", str(root / "quick.toml"), "--frames", str(FRAMES), "--out", str(out),
                 "--quiet"]) == 0
    assert main(["restore", str(out), "--quiet"]) == 0
    return out


def capture_scene(rendered, folder):
    """What a capture folder holds besides its frames: the rig's configuration (no renderer
    records) and the flat-water reference."""
    folder.mkdir()
    record = json.loads((rendered / "frame000" / "scene.json").read_text())
    (folder / "scene.json").write_text(json.dumps({"config": record["config"], "fps": 30}))
    shutil.copy(rendered / "pattern_flat.exr", folder / "pattern_flat.exr")


def listing(folder):
    return sorted((p.relative_to(folder), p.stat().st_mtime_ns) for p in folder.rglob("*"))


def test_numbered_images_restore_as_a_sequence_with_the_rendered_surfaces(rendered, tmp_path,
                                                                         monkeypatch):
    from restoration import StructuredLight

    own = tmp_path / "capture"
    capture_scene(rendered, own)
    for k in range(FRAMES):  # patterns as rendered, views as a camera's 8-bit PNG
        shutil.copy(rendered / f"frame{k:03d}" / "pattern.exr", own / f"pattern_{k:03d}.exr")
        shutil.copy(rendered / f"frame{k:03d}" / "view.png", own / f"view_{k:03d}.png")
    before = listing(own)
    starts = []
    real = StructuredLight.__call__

    def spy(self, images, cal, track=None):
        starts.append(None if track is None else track.start_mm)
        return real(self, images, cal, track)

    monkeypatch.setattr(StructuredLight, "__call__", spy)
    assert main(["restore", str(own), "--quiet"]) == 0

    out = own / "restore"
    assert [p for p in listing(own) if p[0].parts[0] != "restore"] == before  # input untouched
    rows = list(csv.DictReader((out / "frames.csv").open()))
    assert [r["status"] for r in rows] == ["ok"] * FRAMES
    assert all(r["wai_rmse_mm"] == "" and r["restored_ssim"] == "" for r in rows)  # no truth
    # The level is tracked: each frame's search starts where the previous frame's level was.
    anchors = [json.loads((out / f"frame_{k:03d}" / "metrics.json").read_text())["anchor"]
               for k in range(FRAMES)]
    assert all(a["method"] == "integrability" for a in anchors)
    assert starts == [None] + [a["anchor_mm"] for a in anchors[:-1]]
    assert [float(r["anchor_mm"]) for r in rows] == [a["anchor_mm"] for a in anchors]
    for movie in ("restored", "side_by_side"):
        assert any((out / f"{movie}{ext}").is_file() for ext in (".mp4", ".gif"))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["fps"] == 30 and summary["wai_rmse_mm"] is None
    for k in range(FRAMES):
        metrics = json.loads((out / f"frame_{k:03d}" / "metrics.json").read_text())
        assert metrics["scored"] is False and "no truth" in metrics["scores_skipped"]
        ours = np.load(out / f"frame_{k:03d}" / "heightfield_est.npz")["z"]
        theirs = np.load(rendered / f"frame{k:03d}" / "restore" / "heightfield_est.npz")["z"]
        assert np.array_equal(ours, theirs, equal_nan=True)


def test_numbered_frame_folders_restore_in_order_of_their_numbers(rendered, tmp_path):
    from restoration import restore_sequence

    own = tmp_path / "capture"
    capture_scene(rendered, own)
    names = ["frame_8", "9", "frame10"]  # any prefix and width, in order of value
    for k, name in enumerate(names):
        (own / name).mkdir()
        for stem in ("pattern", "view"):
            shutil.copy(rendered / f"frame{k:03d}" / f"{stem}.exr", own / name / f"{stem}.exr")
    seq = read_sequence(own)
    assert (seq.kind, seq.frames, seq.fps) == ("frames", names, 30.0)
    done = restore_sequence(own, movie=False)
    rendered_rows = list(csv.DictReader((rendered / "restore" / "frames.csv").open()))
    assert [r["anchor_mm"] for r in done.rows] == [float(r["anchor_mm"]) for r in rendered_rows]
    for k, name in enumerate(names):
        ours = np.load(own / "restore" / name / "heightfield_est.npz")["z"]
        theirs = np.load(rendered / f"frame{k:03d}" / "restore" / "heightfield_est.npz")["z"]
        assert np.array_equal(ours, theirs, equal_nan=True)
        assert not (own / name / "restore").exists()


def tiny(path):
    cv2.imwrite(str(path), np.zeros((4, 4), np.uint8))


def test_layouts_are_told_apart_and_numbers_sorted_by_value(tmp_path, rendered):
    assert sequence_kind(rendered) == "rendered"
    assert sequence_kind(rendered / "frame001") is None  # a single frame stays one
    own = tmp_path / "own"
    own.mkdir()
    (own / "scene.json").write_text(json.dumps({"config": {}}))
    for n in (9, 10, 11):
        tiny(own / f"pattern_{n}.png")
        tiny(own / f"view_{n}.tif")
    seq = read_sequence(own)
    assert (seq.kind, seq.frames, seq.fps) == ("images", ["frame_9", "frame_10", "frame_11"], 1.0)
    assert seq.image_path(1, "view") == own / "view_10.tif"
    with pytest.raises(WaiInputError, match="pattern_flat"):
        seq.image_path(1, "pattern_flat")
    tiny(own / "pattern_flat.png")  # the shared reference, one for every frame
    assert seq.image_path(2, "pattern_flat") == own / "pattern_flat.png"
    tiny(own / "view.png")  # a frame's own view: the folder is a single frame
    assert sequence_kind(own) is None


@pytest.mark.parametrize(
    "files, named",
    [(["pattern_000.png", "view_000.png", "pattern_002.png", "view_002.png"], "pattern_001.*"),
     (["pattern_000.png", "view_000.png", "pattern_001.png"], "view_001.*"),
     (["pattern_1.png", "view_1.png", "pattern_01.png", "view_01.png"], "pattern_01.png"),
     (["frame_0/pattern.png", "frame_0/view.png", "frame_2/pattern.png", "frame_2/view.png"],
      "frame_1/"),
     (["000/pattern.png", "000/view.png", "001/pattern.png"], "001/view.*")],
)
def test_a_broken_capture_numbering_is_one_line_naming_the_file(tmp_path, capsys, files,
                                                                named):
    own = tmp_path / "own"
    own.mkdir()
    (own / "scene.json").write_text(json.dumps({"config": {}}))
    for name in files:
        (own / name).parent.mkdir(exist_ok=True)
        tiny(own / name)
    before = listing(own)
    assert main(["restore", str(own), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and named in err[0], err
    assert listing(own) == before


def test_a_rig_file_s_keys_reach_the_sequence_s_calibration(rendered):
    from restoration import restore_sequence

    with pytest.raises(WaiInputError, match="camera_v.no_such_key"):
        restore_sequence(rendered, write=False, rig={"camera_v.no_such_key": 1})


def test_grey_captures_restore_with_their_figures_and_movies(rendered, tmp_path, capsys):
    # A monochrome camera's 8-bit PNGs: (H, W) images, drawn in the figures and movies as RGB.
    def grey(src, dst):
        cv2.imwrite(str(dst), cv2.imread(str(src), cv2.IMREAD_GRAYSCALE))

    single = tmp_path / "single"
    capture_scene(rendered, single)
    for name in ("pattern", "view"):
        grey(rendered / "frame000" / f"{name}.png", single / f"{name}.png")
    own = tmp_path / "capture"
    capture_scene(rendered, own)
    for k in range(FRAMES):
        for name in ("pattern", "view"):
            grey(rendered / f"frame{k:03d}" / f"{name}.png", own / f"{name}_{k:03d}.png")
    capsys.readouterr()
    for folder in (single, own):
        assert main(["restore", str(folder), "--quiet"]) == 0
        # 8-bit grey spots loosen the level: a frame may say so, and nothing else.
        err = capsys.readouterr().err.splitlines()
        assert all("uncertain_level" in line for line in err), err
    assert cv2.imread(str(single / "restore" / "distorted_vs_restored.png")) is not None
    from wai_core.io import read_exr

    assert read_exr(single / "restore" / "restored.exr").ndim == 2  # the view stays grey
    for movie in ("restored", "side_by_side"):
        assert any((own / "restore" / f"{movie}{ext}").is_file() for ext in (".mp4", ".gif"))
    assert (own / "restore" / "temporal.png").is_file()
