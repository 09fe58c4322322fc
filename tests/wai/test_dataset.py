"""``wai dataset``: the store, its resumption, its refusals and the warp against the renders."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from wai.cli import main
from wai.dataset import (
    ARRAYS,
    DATASET_FILE,
    MANIFEST_FILE,
    read_frame,
    read_manifest,
    read_runs,
    sample_params,
)
from wai_core import load_system
from wai_core.light_paths import flat_pixel_of
from wai_core.optics import trace_to_object

SIZE = "120x90"
# Seed 4 draws windy frames first: coarse meshes, quick renders.
ARGS = ["--size", SIZE, "--spp", "2", "--seed", "4", "--quiet"]


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "d"
    assert main(["dataset", "--frames", "2", "--out", str(out), *ARGS]) == 0
    return out


def test_store_holds_the_datasets_and_the_manifest(store: Path) -> None:
    with h5py.File(store / DATASET_FILE, "r") as f:
        assert int(f.attrs["frames"]) == 2
        assert f.attrs["seed"] == 4
        assert "numpy" in f.attrs["versions"]
        for name in ARRAYS:
            assert f[name].shape[0] == 2 and f[name].chunks[0] == 1
        assert f["view"].shape[1:] == (90, 120, 3)
        assert f["height_mm"].shape[1:] == (f["y_mm"].size, f["x_mm"].size)
        assert f["normals"].shape[1:] == (*f["height_mm"].shape[1:], 3)
    with open(store / MANIFEST_FILE) as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["frame"]) for r in rows] == [0, 1]
    for r, p in zip(rows, (sample_params(4, 0), sample_params(4, 1)), strict=True):
        assert float(r["wind_speed_m_s"]) == p.wind_speed_m_s
        assert int(r["wave_seed"]) == p.wave_seed
    rec = read_frame(store, 1)
    assert rec.params == sample_params(4, 1)
    # The normals are the stored heights' own: (-dz/dx, -dz/dy, 1), normalised.
    with h5py.File(store / DATASET_FILE, "r") as f:
        x, y = f["x_mm"][:], f["y_mm"][:]
    gy, gx = np.gradient(rec.height_mm.astype(float), y, x)
    n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    np.testing.assert_allclose(rec.normals[2:-2, 2:-2], n[2:-2, 2:-2], atol=2e-3)
    assert np.ptp(rec.height_mm) > 1.0  # a sea state, not flat water
    assert 0.5 <= rec.params.wind_speed_m_s <= 2.0


def test_the_store_holds_the_frames_as_made(store: Path) -> None:
    # The chunks compressed in the maker's process and written as they are: each array read
    # back is the frame as FrameMaker made it, bit for bit.
    from wai.dataset import DatasetSpec, FrameMaker

    w, h = (int(v) for v in SIZE.split("x"))
    made = FrameMaker(DatasetSpec(seed=4, spp=2, size_px=(w, h))).make(1)
    stored = read_frame(store, 1)
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(stored, name), getattr(made, name), err_msg=name)
    with h5py.File(store / DATASET_FILE, "r") as f:  # Blosc (32001): LZ4 after a byte shuffle
        opts = f["normals"]._filters["32001"]
        assert opts[4:7] == (5, 1, 1)  # level 5, shuffle, LZ4
        stored_bytes = f["normals"].id.get_storage_size()
        assert stored_bytes < 0.9 * f["normals"].shape[0] * made.normals.nbytes


def test_waves_summed_on_the_device_give_the_same_truth(store: Path) -> None:
    # A GPU's worker sums the waves on the device (Dr.Jit), a CPU's by BLAS: here both on
    # this machine's backend, against the frame the store holds.
    from wai.dataset import DatasetSpec, FrameMaker

    w, h = (int(v) for v in SIZE.split("x"))
    made = FrameMaker(DatasetSpec(seed=4, spp=2, size_px=(w, h)), waves_on_device=True).make(1)
    stored = read_frame(store, 1)
    assert np.ptp(stored.height_mm) > 1.0
    np.testing.assert_allclose(made.height_mm, stored.height_mm, atol=1e-4)  # float32's step
    np.testing.assert_allclose(made.normals, stored.normals, atol=1e-6)
    valid = np.isfinite(stored.warp_px)
    np.testing.assert_array_equal(np.isfinite(made.warp_px), valid)
    assert np.max(np.abs(made.warp_px[valid] - stored.warp_px[valid])) < 0.01


def test_the_frames_share_one_flat_water_render(store: Path, tmp_path: Path) -> None:
    # Flat water is the rig's, not the frame's: one render serves every frame, while the
    # waves' renders are each frame's own. With the sensor on, each frame reads it afresh:
    # the same light, its own noise.
    a, b = read_frame(store, 0), read_frame(store, 1)
    np.testing.assert_array_equal(a.view_truth, b.view_truth)
    np.testing.assert_array_equal(a.pattern_flat, b.pattern_flat)
    assert not np.array_equal(a.view, b.view) and not np.array_equal(a.pattern, b.pattern)
    out = tmp_path / "noisy"
    assert main(["dataset", "--frames", "2", "--out", str(out), "--degrade", *ARGS]) == 0
    a, b = read_frame(out, 0), read_frame(out, 1)
    ta, tb = a.view_truth.astype(float), b.view_truth.astype(float)
    assert not np.array_equal(ta, tb)
    # Exposed for each frame's own signal level: the same image up to scale and noise.
    k = ta.mean() / tb.mean()
    assert np.corrcoef(ta.ravel(), tb.ravel())[0, 1] > 0.9 and 0.1 < k < 10


def test_resume_adds_frames_and_keeps_the_first(
    store: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = [read_frame(store, i) for i in range(2)]
    assert main(["dataset", "--frames", "3", "--out", str(store), *ARGS]) == 0
    # The run's throughput, printed and recorded after the first run's.
    printed = capsys.readouterr().out
    first, run = read_runs(store)[-2:]
    assert (first["first_frame"], first["frames"], run["first_frame"], run["frames"]) == (
        0, 2, 2, 1)
    assert "3 frames; made 1 (from frame 2)" in printed and "by this process" in printed
    assert f"{run['frames_per_s']:.3g} frames/s" in printed
    assert [p.frame for p in read_manifest(store)] == [0, 1, 2]
    for i, rec in enumerate(before):
        again = read_frame(store, i)
        assert again.params == rec.params
        for name in ARRAYS:
            np.testing.assert_array_equal(getattr(again, name), getattr(rec, name))
    # Frame 2 is a new sea state, not a copy.
    assert read_frame(store, 2).params == sample_params(4, 2)
    assert not np.array_equal(read_frame(store, 2).height_mm, before[1].height_mm)


def test_warp_reproduces_the_distorted_view(store: Path) -> None:
    for i in range(2):
        rec = read_frame(store, i)
        truth = rec.view_truth.astype(np.float32)
        view = rec.view.astype(np.float32)
        warp = rec.warp_px
        ok = np.isfinite(warp[..., 0])
        assert ok.mean() > 0.5  # camera v's top rows see the TIR band
        mapped = cv2.remap(truth, np.where(ok, warp[..., 0], -10), np.where(ok, warp[..., 1], -10),
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
        good = ok & np.all(np.isfinite(mapped), axis=-1)
        assert good.mean() > 0.4
        err_warped = np.abs(mapped - view)[good].mean()
        err_unwarped = np.abs(truth - view)[good].mean()
        # The waves displace the checkerboard by pixels: undone, the views agree up to noise
        # and interpolation at the squares' edges.
        assert err_warped < 0.4 * err_unwarped
        m = good[..., None]
        ssim = structural_similarity(np.where(m, mapped, 0), np.where(m, view, 0),
                                     channel_axis=-1, data_range=1.0)
        assert ssim > 0.85


def test_stored_warp_is_the_trace_through_the_true_surface(store: Path) -> None:
    # Independent of the writer's tracing: each frame's sea state synthesised again from its
    # parameters on the stored grid, each pixel traced through it (trace_to_object) and taken
    # back through flat water (flat_pixel_of, checked against trace_to_object below).
    from mitsuba_wai.waves import sea_surface
    from wai.dataset import frame_config

    base = load_system("paper").replace("camera_v", width_px=120, height_px=90)
    cam, w = base.rig.camera_v, base.water
    cols, rows = cam.pixel_grid()
    with h5py.File(store / DATASET_FILE, "r") as f:
        x, y = f["x_mm"][:], f["y_mm"][:]
    for i in range(2):
        rec = read_frame(store, i)
        cfg = frame_config(base, rec.params)
        surf = sea_surface(cfg.waves).grid(x, y, cfg.waves.time_s, mean_level_mm=w.h0_mm)
        # The stored heights are that surface (float32: about 1e-5 mm at the water level).
        np.testing.assert_allclose(rec.height_mm, surf.z, rtol=0, atol=1e-4)
        points = trace_to_object(cam, surf, w.h0_mm, w.n_water, cfg.object_z_mm, cols,
                                 rows).object_mm
        want = np.stack(flat_pixel_of(cfg.rig, points), axis=-1)
        ok = np.isfinite(want[..., 0])
        assert ok.mean() > 0.5
        np.testing.assert_array_equal(np.isfinite(rec.warp_px[..., 0]), ok)
        np.testing.assert_allclose(rec.warp_px[ok], want[ok], rtol=0, atol=1e-3)
        moved = np.hypot(*(want[ok] - np.stack([cols, rows], axis=-1)[ok]).T)
        assert np.percentile(moved, 90) > 0.5  # the waves move the pixels: not the identity


def test_flat_pixel_of_inverts_the_flat_forward_map() -> None:
    cfg = load_system("paper")
    cam = cfg.rig.camera_v
    rng = np.random.default_rng(3)
    cols, rows = rng.uniform(0, 799, 500), rng.uniform(300, 599, 500)
    pts = trace_to_object(cam, None, cfg.water.h0_mm, cfg.water.n_water, cfg.object_z_mm,
                          cols, rows).object_mm
    ok = np.all(np.isfinite(pts), axis=-1)
    assert ok.mean() > 0.5  # the rest is totally reflected
    c, r = flat_pixel_of(cfg.rig, pts[ok])
    np.testing.assert_allclose(c, cols[ok], atol=1e-6)
    np.testing.assert_allclose(r, rows[ok], atol=1e-6)


def test_the_warp_is_trace_to_object_then_flat_pixel_of() -> None:
    # Both compressed passes (the CPU's compiled kernels, and Dr.Jit's lanes that the dataset
    # uses) against the vectorised steps they fuse, on a calm, a windy and a steep sea.
    from mitsuba_wai import ViewWarpTracer, wave_surface
    from wai.dataset import true_view_warp

    base = load_system("paper").replace("camera_v", width_px=120, height_px=90)
    tracer = ViewWarpTracer(base.rig)
    for wind, scale in ((0.6, 1.0), (2.0, 1.0), (1.0, 3.0)):
        cfg = base.replace("waves", wind_speed_m_s=wind, time_s=3.0, seed=11, height_scale=scale)
        surf = wave_surface(cfg)
        cam = cfg.rig.camera_v
        points = trace_to_object(cam, surf, cfg.water.h0_mm, cfg.water.n_water,
                                 cfg.object_z_mm, *cam.pixel_grid()).object_mm
        want = np.stack(flat_pixel_of(cfg.rig, points), axis=-1)
        ok = np.isfinite(want[..., 0])
        assert ok.mean() > 0.5
        got = true_view_warp(cfg, surf)
        np.testing.assert_array_equal(np.isfinite(got[..., 0]), ok)
        np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-3)
        # Dr.Jit starts every ray from the mean plane, the CPU from its neighbour's hit: a ray
        # that crosses the surface twice may settle elsewhere; none else may differ.
        traced = tracer(cfg.rig, surf)
        differ = np.isfinite(traced[..., 0]) != ok
        assert differ.mean() < 1e-3
        both = ok & ~differ
        assert np.mean(np.abs(traced[both] - want[both]).max(axis=-1) < 1e-3) > 0.999
        cols, rows = cam.pixel_grid()  # the waves move the pixels: not a flat sea's agreement
        assert np.percentile(np.hypot(want[..., 0] - cols, want[..., 1] - rows)[ok], 90) > 0.5


def test_bad_out_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    assert main(["dataset", "--frames", "1", "--out", str(a_file), *ARGS]) == 2
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    with h5py.File(foreign / DATASET_FILE, "w") as f:
        f.attrs["owner"] = "someone else"
    assert main(["dataset", "--frames", "1", "--out", str(foreign), *ARGS]) == 2
    with h5py.File(foreign / DATASET_FILE, "r") as f:
        assert dict(f.attrs) == {"owner": "someone else"}
    not_h5 = tmp_path / "not_h5"
    not_h5.mkdir()
    (not_h5 / DATASET_FILE).write_bytes(b"plain bytes")
    assert main(["dataset", "--frames", "1", "--out", str(not_h5), *ARGS]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("wai: error: --out ") for line in err)


def test_other_seed_is_refused(store: Path) -> None:
    args = [a if a != "4" else "5" for a in ARGS]
    assert main(["dataset", "--frames", "4", "--out", str(store), *args]) == 2
    assert int(h5py.File(store / DATASET_FILE, "r").attrs["frames"]) >= 2


def test_dask_workers_render_the_same_frames(store: Path, tmp_path: Path) -> None:
    import logging

    from distributed import LocalCluster

    from wai.dataset import DatasetSpec, write_dataset

    spec = DatasetSpec(seed=4, spp=2, size_px=(120, 90))
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None, silence_logs=logging.ERROR) as cluster:
        write_dataset(tmp_path / "d", 1, spec, scheduler=cluster.scheduler_address,
                      progress=False)
    for i in range(1):
        a, b = read_frame(tmp_path / "d", i), read_frame(store, i)
        assert a.params == b.params
        for name in ARRAYS:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_frames_go_to_the_workers_that_hold_a_gpu(store: Path, tmp_path: Path) -> None:
    # A worker started with --resources GPU=1 (here a CPU standing in for it): the frames
    # ask for one GPU each, render there, and come out as without.
    import logging

    from distributed import LocalCluster
    from distributed.diagnostics.plugin import SchedulerPlugin

    from wai.dataset import DatasetSpec, write_dataset

    class Asked(SchedulerPlugin):  # what each task asked of its worker when it ran
        def __init__(self, scheduler):
            self.scheduler, self.asked = scheduler, []

        def transition(self, key, start, finish, *args, **kwargs):
            if finish == "processing":
                self.asked.append(self.scheduler.tasks[key].resource_restrictions)

    spec = DatasetSpec(seed=4, spp=2, size_px=(120, 90))
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      resources={"GPU": 1}, dashboard_address=None,
                      silence_logs=logging.ERROR) as cluster:
        plugin = Asked(cluster.scheduler)
        cluster.scheduler.add_plugin(plugin)
        write_dataset(tmp_path / "g", 1, spec, scheduler=cluster.scheduler_address,
                      progress=False)
    assert plugin.asked == [{"GPU": 1}]
    a, b = read_frame(tmp_path / "g", 0), read_frame(store, 0)
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def _listing(root: Path) -> dict[str, bytes | None]:
    return {str(p.relative_to(root)): p.read_bytes() if p.is_file() else None
            for p in sorted(root.rglob("*"))}


def test_a_folder_of_the_users_is_never_written_into(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / MANIFEST_FILE).write_text("my own manifest\n")
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    before = _listing(tmp_path)
    for out in (mine, a_file / "d"):
        assert main(["dataset", "--frames", "1", "--out", str(out), *ARGS]) == 2
    assert _listing(tmp_path) == before
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and f"--out {mine}" in err[0] and "manifest.csv" in err[0]
    assert "file.txt is a file" in err[1]


def test_an_unwritable_folder_is_refused_before_rendering(tmp_path: Path, monkeypatch,
                                                          capsys: pytest.CaptureFixture[str]):
    # A read-only mount makes creating a file fail with EROFS (root ignores the mode bits).
    import errno
    import os
    import tempfile

    import wai.dataset.write as writer

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    monkeypatch.setattr(writer, "FrameMaker", None)  # rendering would raise TypeError
    (tmp_path / "empty").mkdir()
    for out in (tmp_path / "new", tmp_path / "empty"):
        assert main(["dataset", "--frames", "1", "--out", str(out), *ARGS]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("Read-only file system" in e and "--out" in e for e in err)


def test_a_dataset_too_large_for_the_memory_is_refused_first(tmp_path: Path, monkeypatch,
                                                             capsys) -> None:
    from wai_core import memory

    monkeypatch.setattr(memory, "available_bytes", lambda: 2**30)
    code = main(["dataset", "--frames", "1", "--out", str(tmp_path / "d"), "--size",
                 "20000x20000", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert (code, len(err)) == (2, 1)
    assert err[0].startswith("wai: error: --size 20000x20000: rendering a frame needs about ")
    # Both cameras' 4e8 pixels at the renderer's measured ~170 bytes each, at least.
    need_gib = float(err[0].split("about ")[1].split(" GiB")[0])
    assert 4e8 * 170 / 2**30 < need_gib and "1 GiB is available" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_stops_between_frames_and_the_rerun_continues(
    tmp_path: Path, monkeypatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # The disk fills after the first frame: the second frame's space cannot be allocated.
    import errno
    import os

    import wai.dataset.store as store

    real, calls = os.posix_fallocate, []

    def fills_up(fd, offset, length):
        calls.append(length)
        if len(calls) > 2:  # the store's creation, then frame 0
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd, offset, length)

    monkeypatch.setattr(store.os, "posix_fallocate", fills_up)
    out = tmp_path / "d"
    assert main(["dataset", "--frames", "2", "--out", str(out), *ARGS]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no room for frame 1" in err[0] and "No space left" in err[0]
    assert [p.frame for p in read_manifest(out)] == [0]
    assert read_frame(out, 0).params == sample_params(4, 0)
    monkeypatch.setattr(store.os, "posix_fallocate", real)
    assert main(["dataset", "--frames", "2", "--out", str(out), *ARGS]) == 0
    assert [p.frame for p in read_manifest(out)] == [0, 1]
    assert read_frame(out, 1).params == sample_params(4, 1)


def test_a_store_written_before_folders_were_marked_continues(store: Path, tmp_path: Path):
    import shutil

    from wai_core.outputs import OUTPUT_MARKER, output_marker

    old = tmp_path / "old"
    shutil.copytree(store, old)
    (old / OUTPUT_MARKER).unlink()
    frames = int(h5py.File(old / DATASET_FILE, "r").attrs["frames"])
    assert main(["dataset", "--frames", str(frames + 1), "--out", str(old), *ARGS]) == 0
    assert len(read_manifest(old)) == frames + 1 and output_marker(old)["command"] == "dataset"


def test_a_store_of_the_older_format_is_not_continued(
        store: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    old = tmp_path / "v1"
    shutil.copytree(store, old)
    with h5py.File(old / DATASET_FILE, "a") as f:
        f.attrs["format"] = "wai-dataset/1"
    before = (old / DATASET_FILE).read_bytes()
    capsys.readouterr()
    assert main(["dataset", "--frames", "3", "--out", str(old), *ARGS]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0] and "wai-dataset/1" in err[0]
    assert (old / DATASET_FILE).read_bytes() == before


def test_a_real_full_disk_ends_in_one_line_not_a_crash(tmp_path: Path) -> None:
    # HDF5 crashes (segmentation fault, exit 139) closing a store whose write met a full disk;
    # on a 2 MiB file system the space for the first frame is refused before any write.
    import os
    import subprocess
    import sys

    from tests.conftest import ROOT

    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)],
                             capture_output=True)
    if mounted.returncode != 0:
        pytest.skip("mounting a small tmpfs needs root")
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "wai", "dataset", "--frames", "2", "--out",
             str(disk / "d"), *ARGS], capture_output=True, text=True, cwd=ROOT, timeout=300,
            env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert proc.returncode == 2, proc.stderr[-2000:]
        err = proc.stderr.strip().splitlines()
        assert len(err) == 1 and "no room for frame 0" in err[0], err
        with h5py.File(disk / "d" / DATASET_FILE, "r") as f:
            assert int(f.attrs["frames"]) == 0
    finally:
        subprocess.run(["umount", str(disk)], check=True)


def test_a_store_has_its_preview_and_its_page(store: Path) -> None:
    import re

    from wai_core.outputs import output_marker

    names = {p.name for p in store.iterdir()}
    assert {"preview.png", "index.html", DATASET_FILE} <= names
    assert (store / "preview.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    page = (store / "index.html").read_text()
    assert re.findall(r'<img[^>]+src="([^"]+)"', page) == ["preview.png"]
    assert set(output_marker(store)["files"]) >= {"preview.png", "index.html"}
