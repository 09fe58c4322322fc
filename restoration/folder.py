"""Restore a folder of images (a render, or one's own captures) and write ``FOLDER/restore/``.

Reads ``scene.json`` (the calibration) and the frame's images (EXR, PNG or TIFF); when the
folder also holds truth (``heightfield.npz``, ``view_truth.exr``) the restoration is scored,
otherwise ``metrics.json`` says that scores were skipped. Everything is written to a temporary
folder and renamed into place when complete.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from restoration.calibration import LevelTrack, read_scene_record
from restoration.frame import (
    RESTORE_REMEDY,
    FolderRestore,
    check_files,
    check_inputs,
    check_rig_geometry,
    default_out,
    restore_frame,
    with_rig,
)
from restoration.methods import as_method
from restoration.options import SurfaceOptions
from restoration.protocol import Method
from wai_core.outputs import atomic_dir, check_output_dir

__all__ = [
    "FolderRestore", "check_files", "check_inputs", "check_rig_geometry", "default_out",
    "restore_folder",
    "restore_frame", "with_rig",
]


def restore_folder(
    folder: str | Path,
    method: str | Method = "structured-light",
    options: SurfaceOptions | None = None,
    *,
    out: str | Path | None = None,
    scored: bool = True,
    write: bool = True,
    track: LevelTrack | None = None,
    progress: bool = False,
    rig: Mapping[str, Any] | str | Path | None = None,
) -> FolderRestore:
    """Restore the frame in ``folder``, score it where truth exists, write the outputs.

    Parameters
    ----------
    folder : str or Path
        Holds ``scene.json`` and the method's images (structured light: ``pattern``,
        ``pattern_flat``, ``view``; Alterman: ``sunspots``, ``sunspots_flat``, ``view``), each
        ``.exr``, ``.png``, ``.tif`` or ``.tiff``.
    method : str or Method
        ``"structured-light"`` (default), ``"alterman"``, or a configured method object.
    options : SurfaceOptions, optional
        With a method name: its options (default: the method's own).
    out : str or Path, optional
        Output folder (default :func:`default_out`: ``folder/restore`` for the folder's own
        method, ``folder/restore_METHOD`` for another, so that no method's results replace
        another's).
    scored : bool
        Score against the folder's truth when it has some (default True).
    write : bool
        Write the outputs (default True); False only restores and scores.
    track : LevelTrack, optional
        A sequence's level (see :class:`~restoration.calibration.LevelTrack`).
    progress : bool
        Show a progress bar.
    rig : mapping of str to value, or str or Path, optional
        Configuration keys (``"camera_v.distortion"``: value) that replace the folder's, or the
        path of a rig file holding them (``wai calibrate``'s; :func:`with_rig`); recorded in
        ``metrics.json`` under ``rig``.

    Returns
    -------
    FolderRestore

    Examples
    --------
    >>> from restoration import restore_folder
    >>> done = restore_folder("renders/demo")               # doctest: +SKIP
    >>> print("\\n".join(done.summary_lines()))              # doctest: +SKIP
    """
    from tqdm import tqdm

    folder = Path(folder)
    meth = as_method(method, options)
    bar = tqdm(total=3, desc="restore", disable=not progress, leave=False, unit="step")
    bar.set_postfix_str("surface and view")

    def step(name: str) -> None:
        bar.set_postfix_str(name, refresh=False)
        bar.update(1)

    record = read_scene_record(folder)
    target = (Path(out) if out is not None else folder / default_out(record, meth.name)
              ) if write else None
    if target is not None:  # refused before any work
        check_output_dir(target, "restore", remedy=RESTORE_REMEDY)
    cal = with_rig(meth.calibration_type.from_record(record), rig)
    check_rig_geometry(cal, folder / "scene.json")
    done = restore_frame(folder, cal, meth, track, scored=scored, seed=record.get("seed"),
                         step=step)
    step("write" if write else "write (skipped)")
    if target is not None:
        with atomic_dir(target, command="restore", remedy=RESTORE_REMEDY) as tmp:
            done.write_files(tmp)
        done.out = target
    step("done")
    bar.close()
    return done
