"""Sequences: ``wai render --frames`` and ``wai restore`` on moving water, through the CLI."""

import csv
import json

import numpy as np
import pytest

from wai.cli import main
from wai_core.io import read_exr
from wai_core.sequence import read_sequence

FRAMES, FPS = 3, 30.0


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("seq") / "seq"
    args = ["render", "paper", "--out", str(out), "--frames", str(FRAMES), "--fps", str(FPS),
            "--spp", "2", "--quiet"]
    assert main(args) == 0
    return out


def test_a_sequence_shares_one_flat_water_reference(sequence_dir):
    seq = read_sequence(sequence_dir)
    assert seq.frames == ["frame000", "frame001", "frame002"]
    np.testing.assert_allclose(np.diff(seq.times_s), 1.0 / FPS)
    for k, frame in enumerate(seq.frame_dirs):
        # Each frame is a single-frame render folder, its reference the sequence's own file.
        assert (frame / "pattern_flat.exr").samefile(sequence_dir / "pattern_flat.exr") or (
            read_exr(frame / "pattern_flat.exr") == read_exr(sequence_dir / "pattern_flat.exr")
        ).all()
        record = json.loads((frame / "scene.json").read_text())
        assert record["config"]["waves"]["time_s"] == pytest.approx(seq.times_s[k])
    # The water moves between frames; the rig does not.
    a, b = (read_exr(f / "pattern.exr") for f in seq.frame_dirs[:2])
    assert np.abs(a - b).max() > 0


def test_restoring_a_sequence_writes_the_table_the_movies_and_temporal_scores(sequence_dir,
                                                                            capsys):
    assert main(["restore", str(sequence_dir), "--quiet"]) == 0
    out = sequence_dir / "restore"
    rows = list(csv.DictReader((out / "frames.csv").open()))
    assert [int(r["frame"]) for r in rows] == list(range(FRAMES))
    assert all(r["status"] == "ok" and float(r["wai_rmse_mm"]) < 1.0 for r in rows)
    for movie in ("restored", "side_by_side"):
        assert any((out / f"{movie}{ext}").is_file() for ext in (".mp4", ".gif"))
    summary = json.loads((out / "summary.json").read_text())
    # A still checkerboard: the restored frames move far less than the distorted ones.
    assert summary["change_restored"] < 0.5 * summary["change_distorted"]
    # Every frame got its own restore folder, as a single-frame restore would write.
    assert (sequence_dir / "frame001" / "restore" / "metrics.json").is_file()
    assert "3 frames at 30 fps" in capsys.readouterr().out


def test_a_single_frame_of_the_sequence_restores_as_before(sequence_dir, capsys):
    assert main(["restore", str(sequence_dir / "frame002"), "--quiet"]) == 0
    assert "surface RMSE" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, needle",
    [(["--frames", "0"], "--frames"), (["--fps", "0"], "--fps"), (["--fps", "nan"], "--fps"),
     (["--workers", "-1"], "--workers")],
)
def test_bad_sequence_options_are_one_line(tmp_path, capsys, extra, needle):
    args = ["render", "paper", "--out", str(tmp_path / "s"), "--frames", "2", *extra]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]
    assert not (tmp_path / "s").exists()


@pytest.fixture
def sequence_copy(sequence_dir, tmp_path):
    """A copy of the test sequence to change (its files copied, not linked)."""
    import shutil

    copy = tmp_path / "seq"
    shutil.copytree(sequence_dir, copy, ignore=shutil.ignore_patterns("restore"))
    return copy


def test_a_turned_view_in_a_sequence_is_a_view_mismatch(sequence_copy):
    from restoration import restore_sequence
    from wai_core.io import write_exr

    frame = sequence_copy / "frame001"
    write_exr(frame / "view.exr", read_exr(frame / "view.exr")[::-1, ::-1])
    (frame / "view.png").unlink()  # else the preview disagrees: ambiguous_input
    done = restore_sequence(sequence_copy, write=False)
    # A still checkerboard: the other frames' restored views agree, this one does not.
    assert [r["status"] for r in done.rows] == ["ok", "view_mismatch", "ok"]
    assert done.rows[0]["view_ncc"] > 0.9 > done.rows[1]["view_ncc"]


def test_an_interrupted_sequence_restore_keeps_every_old_output(sequence_copy, monkeypatch):
    from restoration import StructuredLight, StructuredLightOptions, restore_sequence

    restore_sequence(sequence_copy, movie=False)
    outputs = sorted(sequence_copy.rglob("restore/*"))
    before = {p: p.read_bytes() for p in outputs if p.is_file()}
    calls = []
    real = StructuredLight.__call__

    def interrupted(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == FRAMES:
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(StructuredLight, "__call__", interrupted)
    with pytest.raises(KeyboardInterrupt):
        restore_sequence(sequence_copy, options=StructuredLightOptions(integrator="trapezoid"),
                         movie=False)
    after = {p: p.read_bytes() for p in sorted(sequence_copy.rglob("restore/*")) if p.is_file()}
    assert after == before
    assert not [p for p in sequence_copy.rglob(".*") if ".tmp-" in p.name or ".old-" in p.name]


def test_a_sequences_first_frame_restores_as_its_folder_alone(sequence_copy):
    """Before any level is tracked, a sequence's frame is the single-frame restore: same
    surface, view and metrics (timings aside), no figures."""
    from restoration import restore_folder, restore_sequence

    frame = sequence_copy / "frame000"
    alone = restore_folder(frame, write=False)
    restore_sequence(sequence_copy, movie=False)
    written = json.loads((frame / "restore" / "metrics.json").read_text())
    for m in (written, alone.metrics):
        m.pop("timings_ms")
    assert json.dumps(written, sort_keys=True) == json.dumps(alone.metrics, sort_keys=True)
    est = np.load(frame / "restore" / "heightfield_est.npz")
    assert np.array_equal(est["z"], alone.result.surface.heightfield.z, equal_nan=True)
    assert np.array_equal(read_exr(frame / "restore" / "restored.exr"),
                          alone.result.view.image.astype(np.float32), equal_nan=True)
    assert not (frame / "restore" / "distorted_vs_restored.png").exists()
