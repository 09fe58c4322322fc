"""A dataset folder's checks before the work, and the disk space of its writes (:mod:`wai.dataset`).

A dataset is written in place, frame by frame, and a rerun continues it, so its folder does not
go through :func:`wai_core.outputs.atomic_dir`; it follows the output policy otherwise
(:func:`wai_core.outputs.check_output_dir`): a new or empty folder, or one that ``wai dataset``
marked as its own (``.wai-output.json``) holding nothing but its store and manifest. Any other
folder, one holding a file of the user's (their own ``manifest.csv``), a regular file, a folder
that cannot be written, is refused before any frame is rendered; nothing the tool did not write
is ever written over.

HDF5 cannot survive a failed write: once a write of the store fails (a full disk), closing the
file crashes the process (a segmentation fault in the library). So the space a frame needs is
allocated at the end of the store before the frame is written (:func:`reserve_space`); where
there is none, the run stops with one line before touching the store, which keeps every frame
complete before it and is continued by a rerun once there is room.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError

__all__ = ["COMMAND", "DATASET_FILE", "FOLDER_FILES", "FORMAT", "FORMAT_FAMILY", "MANIFEST_FILE",
           "PREVIEW_FILE",
           "check_dataset_folder", "check_dataset_memory", "close_store", "create_store",
           "mark_dataset_folder", "reserve_space", "write_manifest"]

COMMAND = "dataset"
"""The command a dataset folder's marker names."""
DATASET_FILE = "dataset.h5"
"""The store, in the dataset folder."""
MANIFEST_FILE = "manifest.csv"
"""The frames' parameters as a table, beside the store."""
PREVIEW_FILE = "preview.png"
"""A look at the store's first frames (:func:`wai.dataset.write.write_preview`)."""
FOLDER_FILES = (DATASET_FILE, MANIFEST_FILE, PREVIEW_FILE, "index.html")
"""Everything ``wai dataset`` writes in its folder."""
FORMAT = "wai-dataset/3"
"""The ``format`` attribute of a store ``wai dataset`` writes (what a rerun looks for). Stores
of ``wai-dataset/1`` rendered flat water for every frame and compressed the float32 arrays
without the shuffle, those of ``wai-dataset/2`` compressed with LZF: they are read alike, but
not continued."""
FORMAT_FAMILY = "wai-dataset/"
"""The prefix of every store format ``wai dataset`` has written."""
WARP_BYTES_PER_PX = 70
"""Peak bytes per camera-v pixel beyond the render's while a frame's warp is traced and its
record assembled (a dataset frame at 3200 x 2400 px peaked at 271 bytes per pixel, the render
of the same cameras at 218, with the warp on the CPU's compiled kernels; traced by Dr.Jit, which
keeps camera v's rays on the device, the process's peak is 16 bytes per pixel higher: 3.01
against 2.89 GB for two frames)."""
METADATA_BYTES = 1 << 20
"""Room reserved beyond a frame's arrays for the store's own records (chunk index, attributes,
the runs' log)."""


def _unmarked_store(out: Path) -> bool:
    """A dataset folder without its marker (written before folders were marked): a store of
    ``wai dataset`` and the files it writes beside it, nothing else."""
    import h5py

    from wai_core.outputs import output_marker

    if not out.is_dir() or out.is_symlink() or output_marker(out) is not None:
        return False
    names = {p.name for p in out.iterdir()}
    if DATASET_FILE not in names or not names <= set(FOLDER_FILES):
        return False
    try:
        with h5py.File(out / DATASET_FILE, "r") as f:
            return str(f.attrs.get("format", "")).startswith(FORMAT_FAMILY)
    except OSError:
        return False


def check_dataset_folder(out: str | Path) -> Path:
    """Check, before any work, that a dataset may be written into ``out`` (module notes).

    Returns
    -------
    Path
        ``out`` made absolute.

    Raises
    ------
    WaiInputError
        Naming ``--out``: a file or a folder that is not ``wai dataset``'s own, a location
        under a file, a folder that cannot be written.
    """
    from wai_core.outputs import check_output_dir

    out = Path(out)
    label = f"--out {out}"
    if not _unmarked_store(out):
        check_output_dir(out, COMMAND, label=label,
                         remedy="choose another --out (a dataset folder holds only what "
                         "'wai dataset' wrote)")
    if out.is_dir():  # the frames are written inside it, not beside it
        try:
            fd, probe = tempfile.mkstemp(prefix=".wai-probe-", dir=out)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise WaiInputError(f"{label}: cannot write in it: {exc.strerror or exc}") from None
    return Path(os.path.abspath(out))


def mark_dataset_folder(out: Path) -> None:
    """Create ``out`` if needed and mark it as ``wai dataset``'s own, before its first file."""
    from wai_core.outputs import mark_output, output_marker

    try:
        out.mkdir(parents=True, exist_ok=True)
        if output_marker(out) is None:
            mark_output(out, COMMAND, list(FOLDER_FILES))
    except OSError as exc:
        raise WaiInputError(f"--out {out}: {exc.strerror or exc}") from None


def check_dataset_memory(spec: Any, cfg: SystemConfig, renderers: int) -> None:
    """Refuse a dataset whose frames, rendered by ``renderers`` processes at once on this
    machine, would need more memory than is available (:mod:`mitsuba_wai.memory`)."""
    from mitsuba_wai import describe_devices, render_bytes
    from wai_core.memory import check_memory

    pixels_v = cfg.camera_v.width_px * cfg.camera_v.height_px
    need = renderers * (render_bytes(cfg) + WARP_BYTES_PER_PX * pixels_v)
    if spec.size_px is not None:
        what = f"--size {spec.size_px[0]}x{spec.size_px[1]}"
    else:
        what = f"--config {spec.config}: {describe_devices(cfg)}"
    work = "rendering a frame" if renderers == 1 else f"rendering {renderers} frames at once"
    check_memory(need, what, work)


def reserve_space(f: Any, nbytes: int, stored: int) -> None:
    """Allocate the disk space for ``nbytes`` (plus :data:`METADATA_BYTES`) past the end of
    what the open store ``f`` uses, before a frame is written into it, so that HDF5 never meets
    a full disk (module notes).

    Parameters
    ----------
    f : h5py.File
        The store, open to append.
    nbytes : int
        The frame's bytes, uncompressed (Blosc keeps a block that would not shrink as it is,
        behind a header of a few bytes; :data:`METADATA_BYTES` covers that).
    stored : int
        The frames the store holds, for the message.

    Raises
    ------
    WaiInputError
        The disk (or quota) has no room for the frame: the store is left as it was.
    """
    path = Path(f.filename)
    need = int(nbytes) + METADATA_BYTES
    fd = os.open(path, os.O_WRONLY)
    try:  # HDF5 allocates from its end of address, which the file's size may exceed
        os.posix_fallocate(fd, f.id.get_filesize(), need)
    except OSError as exc:
        full = exc.errno in (errno.ENOSPC, errno.EDQUOT)
        if not full and shutil.disk_usage(path.parent).free >= need:
            return  # a file system without fallocate: its free space is the best check
        why = exc.strerror if full else os.strerror(errno.ENOSPC)
        raise WaiInputError(
            f"--out {path.parent}: no room for frame {stored} (about {need / 2**20:.1f} MiB: "
            f"{why}); the store keeps its {stored} frames, and the same command run again "
            "once there is room continues it") from None
    finally:
        os.close(fd)


def close_store(f: Any) -> None:
    """Close the store and give back the space reserved past its end that it did not use."""
    import h5py

    path = Path(f.filename)
    f.close()
    with h5py.File(path, "r") as done:
        used = done.id.get_filesize()
    if path.stat().st_size > used:
        os.truncate(path, used)


def create_store(path: Path, attrs: dict[str, Any]) -> Any:
    """A new store at ``path`` with ``attrs``, opened to append; where the disk has no room for
    it, none (a partly created file removed) and one line."""
    import h5py

    try:
        f = h5py.File(path, "w")
    except OSError as exc:
        path.unlink(missing_ok=True)
        raise WaiInputError(f"--out {path.parent}: cannot create {path.name}: "
                            f"{exc.strerror or exc}") from None
    try:
        reserve_space(f, 0, 0)
    except WaiInputError:
        f.close()
        path.unlink(missing_ok=True)
        raise
    f.attrs.update(attrs)
    return f


def write_manifest(path: Path, text: str) -> None:
    """Write the manifest (atomically); a disk without room for it stops the run in one line,
    the previous manifest and the store as they were."""
    from wai_core.io import atomic_write_bytes

    try:
        atomic_write_bytes(path, text.encode())
    except OSError as exc:
        raise WaiInputError(f"--out {path.parent}: cannot write {path.name}: "
                            f"{exc.strerror or exc}; the store keeps its frames, and the same "
                            "command run again continues it") from None
