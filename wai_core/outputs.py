"""The output policy: where an output may go, and how it gets there whole.

Outputs are written under a temporary sibling path and renamed into place when complete, so a
crash or a bad input never leaves a half-written result behind.

Output policy (:func:`atomic_dir` with ``command``, :func:`check_output_dir`)
---------------------------------------------------------------------------
- Every output folder holds a marker, :data:`OUTPUT_MARKER` (``.wai-output.json``), naming the
  command that wrote it and the files it wrote. It is the first file of the temporary folder,
  so even a killed run's leftover is recognisable as the tool's own.
- An existing folder is replaced (atomically: rename aside, rename the new one in, delete the
  old one) only when it is empty or a previous output of the same command holding nothing
  else (the tool's outputs nested in it, e.g. ``DIR/restore/``, and the figures other commands
  add, count as its own). Any other folder is refused
  (:class:`~wai_core.errors.WaiInputError`) unless ``overwrite`` is set; a regular file, a
  symbolic link, the current folder (or one above it) are always refused.
- The location is checked before any work starts: every existing part of the path must be a
  folder, and the folder the output goes in must be writable (probed with a temporary folder
  that is removed at once).
- Temporary folders are named ``.NAME.tmp-PID-XXXX`` (and ``.NAME.old-PID`` while swapping).
  They are removed on any exception, ``KeyboardInterrupt`` included; a later run removes the
  ones a killed run left (its process gone, the marker naming the same command), and only
  those.
- An output written in place (``wai dataset``'s store, continued by a rerun) is checked by
  :func:`check_output_dir` like the others and marked with :func:`mark_output` before its
  first file is written.
- :func:`wai_core.signals.catch_signals` (used by the ``wai`` command) turns SIGINT / SIGTERM
  into exceptions so that this clean-up also runs when the process is interrupted or
  terminated.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from wai_core.errors import WaiInputError
from wai_core.io import write_json
from wai_core.report import REPORT_FILE, write_report
from wai_core.signals import _signals_deferred, raise_if_interrupted

OUTPUT_MARKER = ".wai-output.json"
"""File inside every output folder written with a ``command``: who wrote the folder, and what."""

_MARKER_FORMAT = "wai-output/1"
_LEFTOVER = re.compile(r"^\.(?P<name>.+)\.(?:tmp|old)-(?P<pid>\d+)(?:-[A-Za-z0-9_]+)?$")
# Files other wai commands add to an output afterwards (the overview figures ``wai demo`` and
# ``wai experiment paper`` draw into a render folder, ``wai bench`` its report into the one it
# renders): the folder stays the tool's own. Code that adds others calls register_output_files.
_ADDED_LATER: dict[str, frozenset[str]] = {
    "render": frozenset({"fig10_surface.png", "pattern_flat_vs_wavy.png", "view_flat_vs_wavy.png",
                         "rig.png", "bench.json", "bench.png"}),
}


def output_marker(folder: str | Path) -> dict[str, Any] | None:
    """The marker of an output folder (command, files, pid, time), or None if it has none."""
    path = Path(folder) / OUTPUT_MARKER
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("format") == _MARKER_FORMAT else None


def _write_marker(folder: Path, command: str, files: list[str] | None) -> None:
    write_json(folder / OUTPUT_MARKER, {
        "format": _MARKER_FORMAT,
        "command": command,
        "complete": files is not None,
        "files": files,
        "pid": os.getpid(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    })


def mark_output(folder: str | Path, command: str, files: list[str]) -> None:
    """Mark ``folder`` as a complete output of ``command`` holding ``files``, for an output
    written in place rather than through :func:`atomic_dir` (a store a rerun continues, such as
    ``wai dataset``'s): :func:`check_output_dir` then accepts it for ``command`` as long as it
    holds nothing else."""
    _write_marker(Path(folder), command, sorted(files))


def _is_nested_output(path: Path) -> bool:
    """A folder inside an output that the tool wrote too (it holds a marker)."""
    if path.is_symlink() or not path.is_dir():
        return False
    marker = output_marker(path)
    return marker is not None and _holds_only(path, _marked_names(marker))


def _marked_names(marker: dict[str, Any]) -> frozenset[str]:
    added = _ADDED_LATER.get(str(marker.get("command")), frozenset())
    # The folder's page is the tool's own in every output, written or rewritten since.
    return frozenset(marker.get("files") or ()) | added | {OUTPUT_MARKER, REPORT_FILE}


def register_output_files(folder: str | Path, names: list[str]) -> None:
    """Record in an output folder's marker files added to it after it was written (so that a
    later run still recognises the folder as the tool's own and may replace it); a folder
    without a complete marker is left alone."""
    folder = Path(folder)
    marker = output_marker(folder)
    if marker is None or not marker.get("complete"):
        return
    files = sorted(set(marker.get("files") or ()) | set(names))
    write_json(folder / OUTPUT_MARKER, {**marker, "files": files})


def _holds_only(folder: Path, names: frozenset[str] | None) -> bool:
    """Every entry of ``folder`` is one of ``names`` (None: any regular file) or a nested
    output of the tool."""
    for entry in folder.iterdir():
        if entry.is_symlink():
            return False
        if entry.is_dir():
            if (names is None or entry.name not in names) and not _is_nested_output(entry):
                return False
        elif not entry.is_file() or (names is not None and entry.name not in names):
            return False
    return True


def is_output_of(folder: str | Path, command: str) -> bool:
    """True when ``folder`` is a complete previous output of ``command`` that holds nothing
    but what the tool wrote (its own files, nested outputs such as ``restore/``)."""
    folder = Path(folder)
    if folder.is_symlink() or not folder.is_dir():
        return False
    try:
        marker = output_marker(folder)
        # Only the marker says a folder is the tool's: an unmarked one that holds a render's
        # names (a user's captures beside a copied scene.json) is the user's.
        if marker is None:
            return False
        return (
            marker.get("command") == command
            and bool(marker.get("complete"))
            and _holds_only(folder, _marked_names(marker))
        )
    except OSError:
        return False


def _is_empty(folder: Path) -> bool:
    return next(folder.iterdir(), None) is None


def _foreign_entries(folder: Path, limit: int = 3) -> str:
    """``, holding A, B, C`` of ``folder``'s entries, those the tool did not write first (they
    are why the folder is not its own)."""
    try:
        marker = output_marker(folder)
        own = _marked_names(marker) if marker is not None else frozenset()
        names = sorted((p.name for p in folder.iterdir()), key=lambda n: (n in own, n))
    except OSError:
        return ""
    more = f", ... ({len(names)} entries)" if len(names) > limit else ""
    return ", holding " + ", ".join(names[:limit]) + more


def check_output_dir(
    final: str | Path,
    command: str,
    overwrite: bool = False,
    label: str | None = None,
    remedy: str = "choose a new folder or pass --overwrite",
) -> Path:
    """Check, before any work, that a new output of ``command`` may be written at ``final``.

    Parameters
    ----------
    final : path
        The output folder.
    command : str
        The command that writes it (``"render"``, ``"restore"``): a folder is replaced without
        ``overwrite`` only if it is a previous output of this command.
    overwrite : bool
        Allow replacing an existing folder that is not such an output (never a file).
    label : str, optional
        How the message names the location (default ``output folder FINAL``), e.g.
        ``--out renders/f1``.
    remedy : str
        What the message for a foreign folder tells the user to do (a command without
        ``--overwrite`` says something else).

    Returns
    -------
    Path
        ``final`` made absolute (``.`` and ``..`` resolved, symbolic links kept).

    Raises
    ------
    WaiInputError
        In one line, naming ``label``: the path is the current folder or above it, a part of
        it is a file, it is a file or a symbolic link, it is a folder that is not a previous
        output (without ``overwrite``), or its folder is not writable.
    """
    label = label or f"output folder {final}"
    path = Path(os.path.abspath(final))
    try:
        cwd = Path(os.path.realpath(Path.cwd()))
        real = Path(os.path.realpath(path))
        if real == cwd or real in cwd.parents:
            raise WaiInputError(f"{label}: is the current folder or contains it; name a new "
                                "folder for the output")
        anchor = _existing_folder(path, label)
        if path.is_symlink():
            raise WaiInputError(f"{label}: is a symbolic link; name the folder itself")
        _check_name_length(path, anchor, label)
        if path.exists():
            if not path.is_dir():
                raise WaiInputError(f"{label}: is an existing file; an output is a folder")
            if _rename_blocked(path):
                raise WaiInputError(f"{label}: is immutable or append-only (chattr), so a new "
                                    "output cannot replace it")
            if not overwrite and not _is_empty(path) and not is_output_of(path, command):
                raise WaiInputError(
                    f"{label}: exists and is not a previous 'wai {command}' output"
                    f"{_foreign_entries(path)}; {remedy}"
                )
    except OSError as exc:
        raise WaiInputError(f"{label}: {exc.strerror or exc}") from None
    _probe_writable(anchor, label)
    return path


def check_output_file(final: str | Path, label: str, is_own: Callable[[Path], bool],
                      remedy: str) -> Path:
    """Check, before any work, that a file may be written at ``final`` (atomically, through a
    temporary file beside it): every existing part of its path a folder, its folder writable,
    and an existing ``final`` a regular file that the tool wrote (``is_own``), never a folder,
    a symbolic link or a file of the user's.

    Parameters
    ----------
    final : path
        The file.
    label : str
        How the message names it (``--out rig.json``).
    is_own : callable
        Whether an existing file is one the tool wrote (and may replace).
    remedy : str
        What the message for a file of the user's tells them to do.

    Returns
    -------
    Path
        ``final`` made absolute.

    Raises
    ------
    WaiInputError
        In one line naming ``label``.
    """
    path = Path(os.path.abspath(final))
    try:
        anchor = _existing_folder(path, label)
        if path.is_symlink() or (path.exists() and not path.is_file()):
            raise WaiInputError(f"{label}: exists and is not a regular file")
        if path.exists() and not is_own(path):
            raise WaiInputError(f"{label}: exists and was not written by wai; {remedy}")
    except OSError as exc:
        raise WaiInputError(f"{label}: {exc.strerror or exc}") from None
    _probe_writable(anchor, label)
    return path


def _existing_folder(path: Path, label: str) -> Path:
    """The nearest existing folder above ``path``; a file there is refused."""
    anchor = path.parent
    while not anchor.exists() and anchor != anchor.parent:
        anchor = anchor.parent
    if not anchor.is_dir():
        raise WaiInputError(f"{label}: {anchor} is a file, not a folder")
    return anchor


def _probe_writable(folder: Path, label: str) -> None:
    """Refuse a folder in which nothing can be created (probed with a temporary folder)."""
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".wai-probe-", dir=folder))
    except OSError as exc:
        raise WaiInputError(f"{label}: cannot write in {folder}: {exc.strerror or exc}") from None


# Longest suffix atomic_dir adds to a name: ".NAME.tmp-PID-XXXXXXXX" (PIDs up to 2^22).
_TEMP_NAME_EXTRA = len(".") + len(".tmp-4194304-") + 8
_FS_IOC_GETFLAGS = 0x80086601  # Linux: the inode flags chattr sets
_RENAME_BLOCKING_FLAGS = 0x10 | 0x20  # FS_IMMUTABLE_FL, FS_APPEND_FL


def _check_name_length(path: Path, anchor: Path, label: str) -> None:
    """Refuse a name too long for the temporary folder beside it (checked before the work,
    not when ``mkdtemp`` fails after it)."""
    try:
        name_max = os.pathconf(anchor, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    size = len(os.fsencode(path.name))
    if size + _TEMP_NAME_EXTRA > name_max:
        raise WaiInputError(f"{label}: its name is {size} bytes long; at most "
                            f"{name_max - _TEMP_NAME_EXTRA} fit (the output is first written "
                            "beside it under a longer temporary name)")


def _rename_blocked(path: Path) -> bool:
    """Whether the folder's inode flags forbid renaming it (Linux; False where unknown)."""
    import array
    import fcntl

    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return False
    try:
        flags = array.array("l", [0])
        fcntl.ioctl(fd, _FS_IOC_GETFLAGS, flags, True)
        return bool(flags[0] & _RENAME_BLOCKING_FLAGS)
    except OSError:
        return False
    finally:
        os.close(fd)


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def remove_leftovers(final: str | Path, command: str) -> list[Path]:
    """Remove the temporary folders that killed runs of ``command`` left beside ``final``.

    Only folders named as :func:`atomic_dir` names them (``.NAME.tmp-PID-*``,
    ``.NAME.old-PID``) whose process is gone and whose marker names ``command``.

    Returns
    -------
    list of Path
        The folders removed.
    """
    final = Path(os.path.abspath(final))
    removed = []
    with contextlib.suppress(OSError):
        for entry in final.parent.iterdir():
            m = _LEFTOVER.match(entry.name)
            if not m or m["name"] != final.name or entry.is_symlink() or not entry.is_dir():
                continue
            marker = output_marker(entry)
            if marker is None or marker.get("command") != command or _pid_alive(int(m["pid"])):
                continue
            _remove_output(entry)
            removed.append(entry)
    return removed


def _remove_output(folder: Path) -> None:
    """Delete a folder the tool wrote, its marker last (a removal cut short stays
    recognisable as the tool's own)."""
    with _signals_deferred():
        with contextlib.suppress(OSError):
            for entry in folder.iterdir():
                if entry.name == OUTPUT_MARKER:
                    continue
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    entry.unlink(missing_ok=True)
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def atomic_dir(
    final: str | Path,
    replace: bool = True,
    *,
    command: str | None = None,
    overwrite: bool = False,
    remedy: str = "choose a new folder or pass --overwrite",
) -> Iterator[Path]:
    """Yield a temporary folder that becomes ``final`` when the block ends without error.

    On an exception (``KeyboardInterrupt`` and :class:`Terminated` included) the temporary
    folder is removed and ``final`` is left as it was.

    Parameters
    ----------
    final : path
        The output folder.
    replace : bool
        Without ``command``: replace whatever is at ``final`` (the behaviour before the output
        policy), else refuse when it exists.
    command : str, optional
        Apply the output policy (module notes) for this command: check ``final`` first
        (:func:`check_output_dir`), remove killed runs' leftovers, mark the folder, and replace
        an existing one only if it is a previous output of ``command`` (or ``overwrite``).
    overwrite : bool
        With ``command``: also replace an existing folder that is not such an output.
    remedy : str
        As :func:`check_output_dir`.
    """
    final = Path(final)
    if command is not None:
        final = check_output_dir(final, command, overwrite, remedy=remedy)
        remove_leftovers(final, command)
    final.parent.mkdir(parents=True, exist_ok=True)
    with _signals_deferred():  # no signal between creating the folder and marking it
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-{os.getpid()}-", dir=final.parent))
        try:
            tmp.chmod(0o755)  # mkdtemp makes it private; results are for everyone to read
            if command is not None:
                _write_marker(tmp, command, None)
        except BaseException:
            _remove_output(tmp)
            raise
    try:
        yield tmp
        raise_if_interrupted()
        if command is not None:
            write_report(tmp, title=f"{final.name}: wai {command}")
            names = sorted(p.name for p in tmp.iterdir() if p.name != OUTPUT_MARKER)
            _write_marker(tmp, command, names)
            check_output_dir(final, command, overwrite, remedy=remedy)  # it may have changed
        try:
            _swap_in(tmp, final, replace)
        except PermissionError as exc:
            raise WaiInputError(f"cannot put the output at {final}: {exc.strerror or exc} "
                                "(the new output was not kept)") from None
    except BaseException:
        _remove_output(tmp)
        raise


def _swap_in(tmp: Path, final: Path, replace: bool) -> None:
    """Rename ``tmp`` to ``final``, first moving an existing ``final`` aside (and deleting it
    once the new one is in place); signals wait until both renames are done."""
    if not (final.exists() or final.is_symlink()):
        tmp.rename(final)
        return
    if not replace:
        raise WaiInputError(f"output exists: {final}")
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    with _signals_deferred():
        final.rename(old)
        try:
            tmp.rename(final)
        except BaseException:
            old.rename(final)
            raise
        if old.is_dir() and not old.is_symlink():
            _remove_output(old)
