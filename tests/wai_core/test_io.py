"""The output policy of wai_core.outputs: what may be replaced, what is refused, what is cleaned
up."""

import errno
import json
import os
import signal
import subprocess
import sys
import tempfile

import pytest

from wai_core import outputs, signals
from wai_core.errors import WaiInputError
from wai_core.outputs import (
    OUTPUT_MARKER,
    atomic_dir,
    check_output_dir,
    is_output_of,
    output_marker,
    register_output_files,
    remove_leftovers,
)
from wai_core.signals import catch_signals, raise_if_interrupted


def _write(folder, command="render", files=("a.txt",)):
    with atomic_dir(folder, command=command) as tmp:
        for name in files:
            (tmp / name).write_text(name)


def _dead_pid() -> int:
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    return int(proc.stdout)


def test_marked_output_is_replaced_atomically(tmp_path):
    out = tmp_path / "out"
    _write(out, files=("a.txt", "b.txt"))
    marker = output_marker(out)
    # the files written, and the run's page (wai_core.report)
    assert marker["command"] == "render" and marker["files"] == ["a.txt", "b.txt", "index.html"]
    assert is_output_of(out, "render") and not is_output_of(out, "restore")
    _write(out, files=("c.txt",))
    assert sorted(p.name for p in out.iterdir()) == [OUTPUT_MARKER, "c.txt", "index.html"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing left beside it


def test_foreign_folder_file_and_cwd_are_refused(tmp_path, monkeypatch):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    with pytest.raises(WaiInputError, match="not a previous 'wai render' output.*notes.txt"):
        _write(foreign)
    assert (foreign / "notes.txt").read_text() == "keep me"
    with atomic_dir(foreign, command="render", overwrite=True) as tmp:
        (tmp / "x").write_text("x")
    assert sorted(p.name for p in foreign.iterdir()) == [OUTPUT_MARKER, "index.html", "x"]
    a_file = tmp_path / "file.txt"
    a_file.write_text("data")
    for overwrite in (False, True):
        with pytest.raises(WaiInputError, match="existing file"):
            check_output_dir(a_file, "render", overwrite)
    with pytest.raises(WaiInputError, match="is a file, not a folder"):
        check_output_dir(a_file / "sub" / "out", "render")
    monkeypatch.chdir(foreign)
    for where in (".", "..", str(tmp_path)):
        with pytest.raises(WaiInputError, match="current folder"):
            check_output_dir(where, "render", overwrite=True)
    assert a_file.read_text() == "data"


def test_output_with_foreign_file_inside_is_refused(tmp_path):
    out = tmp_path / "out"
    _write(out)
    (out / "notes.txt").write_text("mine")
    assert not is_output_of(out, "render")
    with pytest.raises(WaiInputError, match="notes.txt"):
        _write(out)
    register_output_files(out, ["notes.txt"])  # a wai command that added it says so
    assert is_output_of(out, "render")


def test_nested_outputs_are_the_tools_own_and_unmarked_look_alikes_are_not(tmp_path):
    out = tmp_path / "out"
    _write(out)
    _write(out / "restore", command="restore", files=("metrics.json",))
    (out / "fig10_surface.png").write_bytes(b"png")  # drawn by wai demo afterwards
    assert is_output_of(out, "render")
    # One's own captures beside a render's scene.json, made the README's way: the user's.
    own = tmp_path / "own"
    (own / "restore").mkdir(parents=True)
    (own / "scene.json").write_text(json.dumps({"format": "wai-render/1"}))
    for name in ("pattern.png", "pattern_flat.png", "view.png"):
        (own / name).write_bytes(b"png")
    (own / "restore" / "metrics.json").write_text("{}")
    assert not is_output_of(own, "render")
    assert not is_output_of(own / "restore", "restore")
    with pytest.raises(WaiInputError, match="--overwrite"):
        _write(own)


def test_unwritable_location_is_refused_before_work(tmp_path, monkeypatch):
    real = tempfile.mkdtemp

    def read_only(*args, **kwargs):
        if kwargs.get("prefix") == ".wai-probe-":
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real(*args, **kwargs)

    monkeypatch.setattr(outputs.tempfile, "mkdtemp", read_only)
    with pytest.raises(WaiInputError, match="cannot write in .*Read-only file system"):
        check_output_dir(tmp_path / "new" / "out", "render", label="--out X")
    assert list(tmp_path.iterdir()) == []


def test_error_and_interrupt_leave_nothing(tmp_path):
    out = tmp_path / "out"
    _write(out)
    before = sorted(p.name for p in out.iterdir())
    for exc in (RuntimeError("boom"), KeyboardInterrupt(), signals.Terminated()):
        with pytest.raises(type(exc)):
            with atomic_dir(out, command="render") as tmp:
                (tmp / "half.txt").write_text("half")
                raise exc
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert sorted(p.name for p in out.iterdir()) == before


def test_killed_runs_leftovers_are_removed_and_only_those(tmp_path):
    out = tmp_path / "out"
    dead = _dead_pid()

    def leftover(name, command="render", marker=True):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "pattern.exr").write_bytes(b"x")
        if marker:
            outputs._write_marker(folder, command, None)
        return folder

    ours = [leftover(f".out.tmp-{dead}-abc"), leftover(f".out.old-{dead}")]
    kept = [
        leftover(f".out.tmp-{os.getpid()}-live"),  # a live process's
        leftover(f".out.tmp-{dead}-nomark", marker=False),  # not recognisably ours
        leftover(f".out.tmp-{dead}-other", command="restore"),  # another command's
        leftover(f".other.tmp-{dead}-abc"),  # another output's
    ]
    removed = remove_leftovers(out, "render")
    assert sorted(removed) == sorted(ours)
    assert all(k.is_dir() for k in kept) and not any(o.exists() for o in ours)


def test_signals_become_exceptions_and_are_remembered():
    before = signal.getsignal(signal.SIGTERM)
    with catch_signals() as caught:
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs between bytecodes
                pass
        except signals.Terminated:
            pass
        assert caught.signum == signal.SIGTERM and caught.exit_code == 143
        with pytest.raises(signals.Terminated):  # e.g. after a library swallowed the exception
            raise_if_interrupted()
    raise_if_interrupted()  # outside: nothing caught
    assert signal.getsignal(signal.SIGTERM) == before
