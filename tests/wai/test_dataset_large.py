"""``wai dataset --frames 100`` through the CLI: a hundred sea states, each as its seed draws it.

The scene is the paper's with a coarse mesh (8 vertices per shortest wavelength instead of 48)
and small cameras: a frame's cost is then the renderer's fixed cost per image, not its pixels or
its mesh (docs/dataset.md, Throughput).
"""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests.conftest import paper_toml_with
from wai.cli import main
from wai.dataset import (
    ARRAYS,
    DATASET_FILE,
    MANIFEST_FILE,
    FrameParams,
    Ranges,
    read_frame,
    read_manifest,
    read_runs,
    sample_params,
)

pytestmark = pytest.mark.slow  # 100 frames rendered; CI runs it (scripts/test.sh --all)

FRAMES = 100
SEED = 7


@pytest.fixture(scope="module")
def hundred(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[str]]:
    tmp = tmp_path_factory.mktemp("ds100")
    scene = tmp / "coarse.toml"
    scene.write_text(paper_toml_with(waves={"mesh_points_per_wavelength": 8}))
    args = ["--size", "64x48", "--spp", "1", "--seed", str(SEED), "--config", str(scene),
            "--quiet"]
    out = tmp / "d"
    assert main(["dataset", "--frames", str(FRAMES), "--out", str(out), *args]) == 0
    return out, args


def test_every_frame_is_its_seeds_draw(hundred: tuple[Path, list[str]]) -> None:
    out, _ = hundred
    want = [sample_params(SEED, i) for i in range(FRAMES)]
    assert read_manifest(out) == want
    with open(out / MANIFEST_FILE) as fh:
        rows = list(csv.DictReader(fh))
    # The manifest's text holds the same values (repr of each float: exact).
    assert [FrameParams(int(r["frame"]), float(r["wind_speed_m_s"]),
                        float(r["wind_direction_deg"]), float(r["time_s"]), int(r["wave_seed"]),
                        float(r["signal_level"]), float(r["read_noise_e"])) for r in rows] == want
    # Uniform draws over the default ranges: a hundred of them reach near both ends.
    r = Ranges()
    wind = np.array([p.wind_speed_m_s for p in want])
    assert wind.min() >= r.wind_speed_m_s[0] and wind.max() <= r.wind_speed_m_s[1]
    assert wind.min() < 0.7 and wind.max() > 1.8
    assert len({p.wave_seed for p in want}) == FRAMES


def test_frames_are_distinct_sea_states_finite_where_valid(
    hundred: tuple[Path, list[str]],
) -> None:
    out, _ = hundred
    with h5py.File(out / DATASET_FILE, "r") as f:
        assert int(f.attrs["frames"]) == FRAMES
        for name in ARRAYS:
            assert f[name].shape[0] == FRAMES
        assert f["view"].shape[1:] == (48, 64, 3) and f["pattern"].shape[1:] == (48, 64)
        h0 = json.loads(f.attrs["config_json"])["water"]["h0_mm"]
    digests = set()
    for i in range(FRAMES):
        rec = read_frame(out, i)
        for name in ("view", "view_truth", "pattern", "pattern_flat", "height_mm", "normals"):
            a = getattr(rec, name)
            assert np.all(np.isfinite(a)), (i, name)
        for name in ("view", "view_truth", "pattern", "pattern_flat"):
            assert getattr(rec, name).min() >= 0, (i, name)
        assert rec.view_truth.astype(np.float32).std() > 0.05  # the checkerboard, seen
        np.testing.assert_allclose(np.linalg.norm(rec.normals, axis=-1), 1.0, atol=1e-3)
        assert rec.normals[..., 2].min() > 0
        # A sea state about the still water: within 6 sigma of it (Pierson-Moskowitz:
        # Hs = 4 sigma = 0.21 U^2 / g), and not flat.
        hs_mm = 0.21 * rec.params.wind_speed_m_s**2 / 9.81 * 1e3
        z = rec.height_mm.astype(float)
        assert np.abs(z - h0).max() < 1.5 * hs_mm and np.ptp(z) > 1.0
        ok = np.isfinite(rec.warp_px[..., 0])
        assert 0.5 < ok.mean() < 1.0  # camera v's top rows see the totally reflected band
        assert np.array_equal(ok, np.isfinite(rec.warp_px[..., 1]))
        digests.add(hashlib.sha256(rec.height_mm.tobytes()).hexdigest())
    assert len(digests) == FRAMES


def test_the_run_is_recorded(hundred: tuple[Path, list[str]]) -> None:
    out, _ = hundred
    (run,) = read_runs(out)
    assert run["first_frame"] == 0 and run["frames"] == FRAMES
    assert run["frames_per_s"] == pytest.approx(FRAMES / run["seconds"], rel=1e-3)
    assert run["renderers"] == "this process" and run["reference_ms"] > 0


def test_complete_store_is_kept_and_another_refused(
    hundred: tuple[Path, list[str]], capsys: pytest.CaptureFixture[str]
) -> None:
    out, args = hundred
    last = read_frame(out, FRAMES - 1)
    for frames in (FRAMES, FRAMES // 2):
        assert main(["dataset", "--frames", str(frames), "--out", str(out), *args]) == 0
    assert "none made" in capsys.readouterr().out
    assert len(read_runs(out)) == 1 and len(read_manifest(out)) == FRAMES
    other = [a if a != str(SEED) else str(SEED + 1) for a in args]
    assert main(["dataset", "--frames", str(FRAMES), "--out", str(out), *other]) == 2
    assert "seed" in capsys.readouterr().err
    smaller = [a if a != "64x48" else "48x36" for a in args]
    assert main(["dataset", "--frames", str(FRAMES), "--out", str(out), *smaller]) == 2
    assert "size_px" in capsys.readouterr().err
    assert len(read_manifest(out)) == FRAMES
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(read_frame(out, FRAMES - 1), name),
                                      getattr(last, name))
