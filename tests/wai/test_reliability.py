"""``wai render`` under bad input, signals and crashes: one line on stderr, exit code 2 (130 / 143
for SIGINT / SIGTERM), and the file system exactly as it was; valid input renders, replaces only
its own outputs and gives the same bytes for the same seed.

Renders use a small copy of the paper's scene (cameras 8x smaller, same optics) and 1-2 spp;
most cases fail before anything is rendered.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import PAPER_TOML, ROOT
from wai.cli import main
from wai_core.config import load_config
from wai_core.outputs import OUTPUT_MARKER, atomic_dir, output_marker

ALTERMAN_TOML = ROOT / "scenes" / "alterman.toml"


def snapshot(root: Path) -> dict[str, tuple]:
    """Every entry under ``root`` (hidden ones too): kind, content hash, mode."""
    state = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            path = Path(folder) / name
            rel = str(path.relative_to(root))
            if path.is_symlink():
                state[rel] = ("link", os.readlink(path))
            elif path.is_dir():
                state[rel] = ("dir", path.stat().st_mode)
            else:
                state[rel] = ("file", hashlib.sha256(path.read_bytes()).hexdigest(),
                              path.stat().st_mode)
    return state


def run(capfd, *argv) -> tuple[int, list[str], str]:
    """``wai ARGV`` in this process: exit code, stderr lines, stdout."""
    code = main([str(a) for a in argv])
    out, err = capfd.readouterr()
    return code, err.strip().splitlines(), out


def tiny_scene(folder: Path) -> Path:
    """The paper's scene with 100 x 75 cameras (the same fields of view)."""
    text = PAPER_TOML.read_text()
    text = text.replace("width_px = 800", "width_px = 100").replace("height_px = 600",
                                                                     "height_px = 75")
    path = folder / "tiny.toml"
    path.write_text(text)
    return path


@pytest.fixture
def inputs(tmp_path):
    """Inputs of every bad case, under ``tmp_path`` (whose state each case compares)."""
    x, y = np.linspace(-500.0, 900.0, 57), np.linspace(-500.0, 500.0, 41)
    flat = np.full((y.size, x.size), 150.0)
    files = {}
    for name, z in (("high", 5000.0), ("low", -50.0), ("mid", 30.0)):
        files[name] = tmp_path / f"{name}.npz"
        np.savez(files[name], x=x, y=y, z=np.full_like(flat, z))
    files["words"] = tmp_path / "words.npz"
    np.savez(files["words"], x=x.astype(str), y=y, z=flat)
    files["text"] = tmp_path / "text.npz"
    files["text"].write_text("x y z\n1 2 3\n")
    files["nan"] = tmp_path / "nan.npz"
    np.savez(files["nan"], x=x, y=y, z=np.where(flat > 0, np.nan, flat))
    files["shape"] = tmp_path / "shape.npz"
    np.savez(files["shape"], x=x, y=y, z=flat.T)
    files["small"] = tmp_path / "small.npz"
    np.savez(files["small"], x=np.linspace(0, 100, 11), y=np.linspace(-20, 20, 5),
             z=np.full((5, 11), 150.0))
    files["typo"] = tmp_path / "typo.toml"
    files["typo"].write_text(PAPER_TOML.read_text().replace("h0_mm = ", "h0_mmm = "))
    for name in ("__class__", "download_all", "lbp_frontal_face_cascade_filename"):
        files[name] = tmp_path / f"texture{name}.toml"  # not sample images: a traceback once
        files[name].write_text(PAPER_TOML.read_text().replace(
            'texture = "checkerboard"', f'texture = "skimage:{name}"'))
    for section in ("water", "diffuser"):  # the rig's level and screen: no silent default
        head, _, rest = PAPER_TOML.read_text().partition(f"[{section}]")
        files[f"no_{section}"] = tmp_path / f"no_{section}.toml"
        files[f"no_{section}"].write_text(head + rest[rest.index("\n["):])
    files["camera_s_5m"] = tmp_path / "camera_s_5m.toml"  # moved 5 m along x: t = -R c
    files["camera_s_5m"].write_text(PAPER_TOML.read_text().replace(
        "translation_mm = [-286.40, 0.0, 190.0]", "translation_mm = [-5286.40, 0.0, 190.0]"))
    files["foreign"] = tmp_path / "mine"
    files["foreign"].mkdir()
    (files["foreign"] / "notes.txt").write_text("keep me")
    files["file"] = tmp_path / "file.txt"
    files["file"].write_text("keep me too")
    files["tiny"] = tiny_scene(tmp_path)
    # One's own captures made the README's way: a render's scene.json beside one's images.
    files["captures"] = tmp_path / "captures"
    files["captures"].mkdir()
    (files["captures"] / "scene.json").write_text(
        json.dumps({"format": "wai-render/1", "config": {}}))
    for name in ("pattern.png", "pattern_flat.png", "view.png"):
        (files["captures"] / name).write_bytes(b"my capture")
    return files


def _cuda_works() -> bool:
    from mitsuba_wai.variant import _cuda_works

    return _cuda_works()


# (id, arguments after "render" given the inputs and tmp_path, text the one line must hold)
BAD = [
    ("out-foreign-folder", lambda f, t: [f["tiny"], "--out", f["foreign"]],
     "not a previous 'wai render' output, holding notes.txt"),
    ("out-own-captures", lambda f, t: [f["tiny"], "--out", f["captures"]],
     "not a previous 'wai render' output, holding pattern.png"),
    ("out-name-too-long", lambda f, t: [f["tiny"], "--out", t / ("n" * 240)],
     "bytes long; at most"),
    ("out-file", lambda f, t: [f["tiny"], "--out", f["file"]], "is an existing file"),
    ("out-file-overwrite", lambda f, t: [f["tiny"], "--out", f["file"], "--overwrite"],
     "is an existing file"),
    ("out-under-file", lambda f, t: [f["tiny"], "--out", f["file"] / "a" / "b"],
     "file.txt is a file, not a folder"),
    ("out-dot", lambda f, t: [f["tiny"], "--out", "."], "--out .: is the current folder"),
    ("out-dot-overwrite", lambda f, t: [f["tiny"], "--out", ".", "--overwrite"],
     "is the current folder"),
    ("out-parent", lambda f, t: [f["tiny"], "--out", t.parent], "current folder or contains"),
    ("variant-bogus", lambda f, t: [f["tiny"], "--variant", "bogus", "--out", t / "o"],
     "--variant bogus: not a variant"),
    ("variant-scalar", lambda f, t: [f["tiny"], "--variant", "scalar_rgb", "--out", t / "o"],
     "--variant scalar_rgb"),
    ("wind-inf", lambda f, t: [f["tiny"], "--wind", "inf", "--out", t / "o"],
     "--wind must be a finite number"),
    ("wind-nan", lambda f, t: [f["tiny"], "--wind", "nan", "--out", t / "o"],
     "--wind must be a finite number"),
    ("wind-negative", lambda f, t: [f["tiny"], "--wind", "-1", "--out", t / "o"],
     "--wind must be >= 0"),
    ("time-nan", lambda f, t: [f["tiny"], "--time", "nan", "--out", t / "o"],
     "--time must be a finite number"),
    ("time-inf", lambda f, t: [f["tiny"], "--time", "inf", "--out", t / "o"],
     "--time must be a finite number"),
    ("seed-negative", lambda f, t: [f["tiny"], "--seed", "-1", "--out", t / "o"], "--seed"),
    ("seed-huge", lambda f, t: [f["tiny"], "--seed", str(2**40), "--out", t / "o"], "--seed"),
    ("spp-zero", lambda f, t: [f["tiny"], "--spp", "0", "--out", t / "o"], "--spp"),
    ("surface-above-rig", lambda f, t: [f["tiny"], "--heightfield", f["high"], "--out", t / "o"],
     "high.npz: the surface reaches z = 5000.0 mm"),
    ("surface-below-projector",
     lambda f, t: [f["tiny"], "--heightfield", f["low"], "--out", t / "o"],
     "low.npz: the surface dips to z = -50.0 mm"),
    ("surface-below-diffuser",
     lambda f, t: [f["tiny"], "--heightfield", f["mid"], "--out", t / "o"],
     "below the diffuser at 60.0 mm"),
    ("wind-huge", lambda f, t: [f["tiny"], "--wind", "1e6", "--out", t / "o"],
     "--wind 1e+06: the surface"),
    ("wind-tiny", lambda f, t: [f["tiny"], "--wind", "0.01", "--out", t / "o"],
     "--wind 0.01: wind 0.01 m/s makes waves as short as"),
    ("surface-words", lambda f, t: [f["tiny"], "--heightfield", f["words"], "--out", t / "o"],
     "words.npz: array 'x' is not numeric"),
    ("surface-text", lambda f, t: [f["tiny"], "--heightfield", f["text"], "--out", t / "o"],
     "text.npz is not an .npz archive"),
    ("surface-nan", lambda f, t: [f["tiny"], "--heightfield", f["nan"], "--out", t / "o"],
     "nan.npz: z holds NaN"),
    ("surface-shape", lambda f, t: [f["tiny"], "--heightfield", f["shape"], "--out", t / "o"],
     "shape.npz: z must have shape"),
    ("surface-uncovered",
     lambda f, t: [f["tiny"], "--heightfield", f["small"], "--out", t / "o"],
     "small.npz: does not cover the observed patch"),
    ("surface-missing",
     lambda f, t: [f["tiny"], "--heightfield", t / "nowhere" / "h.npz", "--out", t / "o"],
     "heightfield file not found"),
    ("config-typo", lambda f, t: [f["typo"], "--out", t / "o"], "unknown key [water].h0_mmm"),
    *[(f"texture-skimage-{name}", lambda f, t, name=name: [f[name], "--out", t / "o"],
       f"[object].texture 'skimage:{name}' is not a scikit-image sample image")
      for name in ("__class__", "download_all", "lbp_frontal_face_cascade_filename")],
    ("config-no-water", lambda f, t: [f["no_water"], "--out", t / "o"],
     "missing section [water] (the sections that describe the rig"),
    ("config-no-diffuser", lambda f, t: [f["no_diffuser"], "--out", t / "o"],
     "missing section [diffuser]"),
    ("rig-camera-s-sees-no-dot", lambda f, t: [f["camera_s_5m"], "--out", t / "o"],
     "camera_s_5m.toml: camera s sees none of the projector's dots on the diffuser"),
    ("config-missing", lambda f, t: [t / "nowhere" / "scene.toml", "--out", t / "o"],
     "not found"),
    ("scene-name-unknown", lambda f, t: ["papper", "--out", t / "o"], "papper"),
    ("sun-sensor-surface-above-rig",
     lambda f, t: [ALTERMAN_TOML, "--heightfield", f["high"], "--out", t / "o"],
     "high.npz: the surface reaches z = 5000.0 mm"),
]


@pytest.mark.parametrize("argv, needle", [c[1:] for c in BAD], ids=[c[0] for c in BAD])
def test_bad_input_is_one_line_exit_2_and_changes_nothing(
    capfd, tmp_path, monkeypatch, inputs, argv, needle
):
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    code, err, out = run(capfd, "render", *argv(inputs, tmp_path), "--quiet")
    assert (code, len(err)) == (2, 1), err
    assert err[0].startswith("wai: error: ") and needle in err[0], err[0]
    assert snapshot(tmp_path) == before and out == ""


@pytest.mark.skipif(_cuda_works(), reason="this machine has a working GPU")
def test_cuda_variant_without_gpu(capfd, tmp_path, inputs):
    before = snapshot(tmp_path)
    code, err, _ = run(capfd, "render", inputs["tiny"], "--variant", "cuda_ad_rgb",
                       "--out", tmp_path / "o")
    assert (code, len(err)) == (2, 1) and "--variant cuda_ad_rgb: needs a CUDA GPU" in err[0]
    assert snapshot(tmp_path) == before


def test_read_only_location_is_refused_before_rendering(capfd, tmp_path, monkeypatch, inputs):
    # A read-only file system (checked on a real read-only mount when writing this test) makes
    # mkdtemp fail with EROFS: simulated here for the probe of the output's folder only.
    import errno
    import tempfile

    from wai_core import outputs

    real = tempfile.mkdtemp

    def read_only(*args, **kwargs):
        if kwargs.get("prefix") == ".wai-probe-":
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real(*args, **kwargs)

    monkeypatch.setattr(outputs.tempfile, "mkdtemp", read_only)
    before = snapshot(tmp_path)
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", tmp_path / "ro" / "out")
    assert (code, len(err)) == (2, 1) and "Read-only file system" in err[0]
    assert "--out " in err[0] and snapshot(tmp_path) == before


def test_an_immutable_output_is_refused_before_rendering(capfd, tmp_path, inputs):
    out = tmp_path / "frozen"
    out.mkdir()
    if subprocess.run(["chattr", "+i", str(out)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not allowed here")
    try:
        before = snapshot(tmp_path)
        code, err, _ = run(capfd, "render", inputs["tiny"], "--out", out, "--quiet")
        assert (code, len(err)) == (2, 1) and "immutable" in err[0]
        assert snapshot(tmp_path) == before
    finally:
        subprocess.run(["chattr", "-i", str(out)], check=True)


def test_a_rename_refused_at_the_end_is_one_line_and_keeps_nothing(capfd, tmp_path, inputs,
                                                                monkeypatch):
    from wai_core import outputs

    def refused(tmp, final, replace):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(outputs, "_swap_in", refused)
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", tmp_path / "o", "--spp", "1",
                       "--quiet")
    assert (code, len(err)) == (2, 1) and "Operation not permitted" in err[0]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_restore_refusing_a_foreign_restore_folder_names_no_missing_option(capfd, tmp_path,
                                                                          inputs):
    out = tmp_path / "frame"
    assert run(capfd, "render", inputs["tiny"], "--out", out, "--spp", "1", "--quiet")[0] == 0
    (out / "restore").mkdir()
    (out / "restore" / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    code, err, _ = run(capfd, "restore", out, "--quiet")
    assert (code, len(err)) == (2, 1) and "notes.txt" in err[0]
    assert "--overwrite" not in err[0] and snapshot(tmp_path) == before


def test_outputs_replace_only_their_own(capfd, tmp_path, inputs):
    out = tmp_path / "frame"
    code, err, stdout = run(capfd, "render", inputs["tiny"], "--out", out, "--spp", "1",
                            "--seed", "3", "--quiet")
    assert (code, err) == (0, []) and stdout.startswith("rendered")
    marker = output_marker(out)
    assert marker["command"] == "render" and "pattern.exr" in marker["files"]
    # A previous output of the same command (with a nested restore output) is replaced.
    with atomic_dir(out / "restore", command="restore") as tmp:
        (tmp / "metrics.json").write_text("{}")
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", out, "--spp", "1", "--quiet")
    assert (code, err) == (0, []) and not (out / "restore").exists()
    assert '"seed": 0' in (out / "scene.json").read_text()
    # The user's file inside makes it no longer only the tool's: refused, nothing touched...
    (out / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", out, "--spp", "1", "--quiet")
    assert (code, len(err)) == (2, 1) and "notes.txt" in err[0] and "--overwrite" in err[0]
    assert snapshot(tmp_path) == before
    # ... unless --overwrite, which may replace a folder (never a file).
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", inputs["foreign"], "--spp", "1",
                       "--quiet", "--overwrite")
    assert (code, err) == (0, []) and not (inputs["foreign"] / "notes.txt").exists()
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert leftovers == []


def test_same_seed_same_bytes(capfd, tmp_path):
    # The paper's scene at 2 spp: views and patterns (particle tracer) bit for bit.
    folders = [tmp_path / "a", tmp_path / "b"]
    for folder in folders:
        code, err, _ = run(capfd, "render", PAPER_TOML, "--out", folder, "--spp", "2",
                           "--quiet")
        assert (code, err) == (0, [])
    for name in ("pattern.exr", "pattern_flat.exr", "view.exr", "view_truth.exr"):
        assert (folders[0] / name).read_bytes() == (folders[1] / name).read_bytes(), name


def test_any_spp_renders_in_passes(capfd, tmp_path, monkeypatch, inputs):
    # Mitsuba refuses a wavefront over 2^32 samples unless its own split divides spp (e.g.
    # 8951 spp at 800 x 600); the renders split first. Shown with the limits lowered so that
    # 7 spp of this film need passes of 3, 2 and 2.
    from mitsuba_wai import particles
    from mitsuba_wai import render as render_mod
    from wai_core.io import read_exr

    monkeypatch.setattr(render_mod, "MAX_WAVEFRONT", 3 * 100 * 75)
    monkeypatch.setattr(particles, "MAX_PASS_SAMPLES", 3 * 100 * 75)
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", tmp_path / "o", "--spp", "7",
                       "--quiet")
    assert (code, err) == (0, [])
    assert read_exr(tmp_path / "o" / "pattern.exr").max() > 0
    assert read_exr(tmp_path / "o" / "view.exr").max() > 0


def test_swallowed_interrupt_still_stops(capfd, tmp_path, monkeypatch, inputs):
    # trimesh wraps imports in 'except BaseException': a Ctrl-C there is lost unless the
    # handler remembers it. Simulated with a step that swallows it.
    from mitsuba_wai import render as render_mod

    real = render_mod.FrameRenderer

    def swallowing(*args, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):  # the handler runs between bytecodes
                pass
        except BaseException:
            pass
        return real(*args, **kwargs)

    monkeypatch.setattr(render_mod, "FrameRenderer", swallowing)
    before = snapshot(tmp_path)
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", tmp_path / "o", "--spp", "1",
                       "--quiet")
    assert (code, err) == (130, ["wai: interrupted"])
    assert snapshot(tmp_path) == before


# A child process that runs 'wai' with one hook: HOOK is Python run before main().
CHILD = """
import os, signal, sys
{hook}
from wai.cli import main
sys.exit(main(sys.argv[1:]))
"""
# SIGTERM / SIGINT to itself in the write step, after the surface files are written.
KILL_IN_WRITE = """
import mitsuba_wai.render as r
_write = r.write_surface
def write_surface(folder, surface):
    _write(folder, surface)
    os.kill(os.getpid(), signal.{sig})
r.write_surface = write_surface
"""
# SIGINT while 'import mitsuba' runs (the start-up).
INT_AT_IMPORT = """
class Finder:
    @staticmethod
    def find_spec(name, path=None, target=None):
        if name == "mitsuba":
            os.kill(os.getpid(), signal.SIGINT)
        return None
sys.meta_path.insert(0, Finder)
"""
# A crash (no clean-up possible) while scene.json is written.
CRASH_IN_WRITE = """
import mitsuba_wai.render as r
_json = r.write_json
def write_json(path, data):
    if str(path).endswith("scene.json"):
        os._exit(9)
    _json(path, data)
r.write_json = write_json
"""


def child(hook: str, *argv) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-c", CHILD.format(hook=hook), *map(str, argv)],
        capture_output=True, text=True, env=env, cwd=ROOT, timeout=120,
    )


@pytest.mark.parametrize("sig, code, word", [("SIGTERM", 143, "terminated"),
                                             ("SIGINT", 130, "interrupted")])
def test_signal_in_write_step_leaves_the_previous_output(tmp_path, inputs, sig, code, word):
    out = tmp_path / "frame"
    with atomic_dir(out, command="render") as tmp:  # a previous output, to be kept
        (tmp / "scene.json").write_text('{"format": "wai-render/1"}')
    before = snapshot(tmp_path)
    proc = child(KILL_IN_WRITE.format(sig=sig), "render", inputs["tiny"], "--out", out,
                 "--spp", "1", "--quiet")
    assert proc.returncode == code and proc.stderr.strip() == f"wai: {word}", proc.stderr
    assert snapshot(tmp_path) == before


def test_interrupt_at_start_up(tmp_path, inputs):
    before = snapshot(tmp_path)
    proc = child(INT_AT_IMPORT, "render", inputs["tiny"], "--out", tmp_path / "o", "--quiet")
    assert proc.returncode == 130 and proc.stderr.strip() == "wai: interrupted", proc.stderr
    assert snapshot(tmp_path) == before


def test_killed_runs_leftover_is_removed_by_the_next_run(capfd, tmp_path, inputs):
    out = tmp_path / "frame"
    proc = child(CRASH_IN_WRITE, "render", inputs["tiny"], "--out", out, "--spp", "1",
                 "--quiet")
    assert proc.returncode == 9
    left = [p for p in tmp_path.iterdir() if p.name.startswith(".frame.tmp-")]
    assert len(left) == 1 and (left[0] / OUTPUT_MARKER).is_file()
    assert (left[0] / "pattern.exr").is_file() and not out.exists()
    # Not the tool's: a look-alike without a marker (same dead pid), beside it, stays.
    pid = left[0].name.split("-")[1]
    stranger = tmp_path / f".frame.tmp-{pid}-notours"
    stranger.mkdir()
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", out, "--spp", "1", "--quiet")
    assert (code, err) == (0, [])
    hidden = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("."))
    assert hidden == [stranger.name] and (out / "scene.json").is_file()


def test_a_tiny_render_restores_or_says_why_in_one_line(capfd, tmp_path, inputs):
    # Cameras 8x smaller than the paper's: dots under a pixel, once a ZeroDivisionError.
    out = tmp_path / "frame"
    assert run(capfd, "render", inputs["tiny"], "--out", out, "--spp", "1", "--quiet")[0] == 0
    code, err, _ = run(capfd, "restore", out, "--quiet")
    assert code in (0, 2) and len(err) <= 1 and not any("Traceback" in e for e in err)


def test_a_cold_kernel_cache_is_noticed(tmp_path):
    # Only imports: numba finds its cache (NUMBA_CACHE_DIR first) when a kernel is defined;
    # an empty one means this run compiles, and `wai restore` says so first.
    probe = "from restoration._compile import kernels_cached; print(kernels_cached())"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    cold = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                          text=True, check=True, cwd=ROOT)
    assert cold.stdout.strip() == "False"


def _sized_scene(folder: Path, section: str, width: int, height: int) -> Path:
    """The paper's scene with one device's panel resized (same field of view)."""
    import re

    text = PAPER_TOML.read_text()
    head, _, rest = text.partition(f"[{section}]")
    rest = re.sub(r"width_px = \d+", f"width_px = {width}", rest, count=1)
    rest = re.sub(r"height_px = \d+", f"height_px = {height}", rest, count=1)
    path = folder / f"{section}_{width}.toml"
    path.write_text(f"{head}[{section}]{rest}")
    return path


BOARDS = ["--checkerboards", "3"]  # seen by the cameras alone


@pytest.mark.parametrize("section, extra", [
    ("camera_s", []), ("camera_v", []), ("projector", []), ("camera_s", BOARDS),
    ("camera_v", BOARDS)])
def test_a_render_too_large_for_the_memory_is_refused_first(capfd, tmp_path, monkeypatch,
                                                            section, extra):
    from wai_core import memory

    monkeypatch.setattr(memory, "available_bytes", lambda: 2**30)
    scene = _sized_scene(tmp_path, section, 20000, 20000)
    before = snapshot(tmp_path)
    code, err, _ = run(capfd, "render", scene, "--out", tmp_path / "o", "--quiet", *extra)
    assert (code, len(err)) == (2, 1), err
    assert err[0].startswith(f"wai: error: {scene}: [{section}] 20000 x 20000 px")
    # 4e8 pixels: at least a float32 RGB image of each (12 bytes a pixel), far above 1 GiB.
    need_gib = float(err[0].split("about ")[1].split(" GiB")[0])
    assert need_gib > 4e8 * 12 / 2**30 and "1 GiB is available" in err[0]
    assert snapshot(tmp_path) == before


def test_the_paper_sized_render_fits_where_the_large_one_does_not(capfd, tmp_path, monkeypatch,
                                                                 inputs):
    from wai_core import memory

    monkeypatch.setattr(memory, "available_bytes", lambda: 2**30)
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", tmp_path / "o", "--spp", "1",
                       "--quiet")
    assert (code, err) == (0, [])


_PEAK = ("import resource, subprocess, sys\n"
         "done = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL)\n"
         "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
         "sys.exit(done.returncode)\n")


def _peak_rss_mib(*argv) -> float:
    """The peak resident memory of ``wai ARGV`` in a child process, MiB. The child is started
    by a fresh, small launcher: a process forked from this one (a test worker holding a
    renderer) would count this one's memory in its peak (Linux keeps the peak across exec)."""
    done = subprocess.run([sys.executable, "-c", _PEAK, sys.executable, "-m", "wai",
                           *map(str, argv)], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr[-2000:]
    return int(done.stdout.split()[-1]) / 1024


@pytest.mark.slow
def test_the_render_memory_estimate_follows_the_measured_peak(tmp_path, inputs):
    # The estimate is of the work's memory, the imports' left out: the peak of a render at
    # 4800 x 3600 px less that of a 100 x 75 one, against the estimates' difference (large
    # enough, 2.7 GiB, that no fixed peak of the process, such as compiling the renderer's
    # kernels, hides it).
    from mitsuba_wai.memory import render_bytes

    big = _sized_scene(tmp_path, "camera_s", 4800, 3600)

    def peak(scene, out):
        return _peak_rss_mib("render", scene, "--out", tmp_path / out, "--spp", "1", "--quiet")

    # A first render compiles the renderer's kernels (cached on disk): a peak of its own, and a
    # machine's other work can make it larger. Measured once they are cached.
    peak(big, "warm-up")
    peaks = [peak(inputs["tiny"], "tiny"), peak(big, "big")]
    estimates = [render_bytes(load_config(scene)) / 2**20 for scene in (inputs["tiny"], big)]
    ratio = (estimates[1] - estimates[0]) / (peaks[1] - peaks[0])
    assert 0.75 < ratio < 1.33, (peaks, estimates)


def test_a_folder_whose_rig_sees_nothing_is_refused_before_restoring(capfd, tmp_path, inputs):
    # The README promises exit code 2 for impossible geometry: camera s moved 5 m in the
    # folder's scene.json sees none of the dots (it restored to a `failed` frame, exit 0).
    out = tmp_path / "frame"
    assert run(capfd, "render", inputs["tiny"], "--out", out, "--spp", "1", "--quiet")[0] == 0
    record = json.loads((out / "scene.json").read_text())
    t = record["config"]["camera_s"]["translation_mm"]
    record["config"]["camera_s"]["translation_mm"] = [t[0] - 5000.0, t[1], t[2]]
    (out / "scene.json").write_text(json.dumps(record))
    before = snapshot(tmp_path)
    code, err, _ = run(capfd, "restore", out, "--quiet")
    assert (code, len(err)) == (2, 1), err
    assert err[0].startswith(f"wai: error: {out / 'scene.json'}: camera s sees none of the "
                             "projector's dots")
    assert snapshot(tmp_path) == before


def test_a_disk_that_fills_while_writing_is_one_line_and_keeps_nothing(capfd, tmp_path, inputs,
                                                                       monkeypatch):
    # The renders done, writing the previews meets a full disk (PIL's OSError; OpenEXR's own
    # RuntimeError is turned into one): one line, exit 2, the temporary folder removed.
    import errno

    from mitsuba_wai import render_files

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(render_files, "write_png", full)
    before = snapshot(tmp_path)
    code, err, _ = run(capfd, "render", inputs["tiny"], "--out", tmp_path / "o", "--spp", "1",
                       "--quiet")
    assert (code, err) == (2, ["wai: error: No space left on device"])
    assert snapshot(tmp_path) == before


def test_an_exr_that_cannot_be_written_raises_an_os_error(tmp_path):
    from wai_core.io import write_exr

    with pytest.raises(OSError, match="cannot write"):
        write_exr(tmp_path / "no_such_folder" / "a.exr", np.zeros((4, 4, 3), np.float32))
    assert list(tmp_path.iterdir()) == []
