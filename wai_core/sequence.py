"""The layout of a sequence folder: frames of moving water that share one flat-water reference.

A rendered sequence folder holds ``sequence.json`` (the configuration, frame rate, each frame's
time and folder name, the seed and the versions), the flat-water reference images once
(``pattern_flat.exr``, ``view_truth.exr``: flat water looks the same at every instant), and
one subfolder per frame (``frame000``, ``frame001``, ...) in the single-frame layout of
``wai render``. Each frame folder links the shared reference images (hard links where the file
system allows, else copies), so every single-frame tool works on a frame as it is.

A folder of one's own captures is a sequence too (:func:`sequence_kind`): ``scene.json`` (the
rig's configuration, and optionally ``"fps"``, else 1), the flat-water reference
``pattern_flat.*`` (and optionally ``view_flat.*``) once, and either numbered images
(``pattern_000.png``, ``view_000.png``, ``pattern_001.png``, ...: numbers of any width, in
order of value; EXR, PNG or TIFF) or numbered frame folders (``frame_000/``, ``000/``,
``frame1/``, ...) each holding its frame's images. :func:`read_sequence` describes every
layout alike (:class:`SequenceRecord`).

Examples
--------
>>> frame_name(7)
'frame007'
>>> frame_times(10.0, 30.0, 3)
[10.0, 10.033333333333333, 10.066666666666666]
"""

from __future__ import annotations

import math
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from wai_core.errors import WaiInputError
from wai_core.images import IMAGE_SUFFIXES, copy_preview_records, locate_image
from wai_core.io import read_json

__all__ = [
    "DEFAULT_FPS",
    "FRAME_IMAGES",
    "REFERENCE_IMAGES",
    "SCENE_FILE",
    "SEQUENCE_FILE",
    "SequenceRecord",
    "frame_name",
    "frame_times",
    "is_sequence",
    "link_reference",
    "read_sequence",
    "sequence_kind",
]

SEQUENCE_FILE = "sequence.json"
DEFAULT_FPS = 30.0
"""Frames per second of a sequence unless one is given: what ``wai render --frames``, ``wai
bench video`` and ``wai experiment compare`` render (a machine-vision camera's common rate)."""
SCENE_FILE = "scene.json"
REFERENCE_IMAGES = ("pattern_flat", "view_truth")
"""Images of flat water, the same for every frame: stored once, linked into each frame."""
FRAME_IMAGES = ("pattern", "sunspots", "view")
"""Images that change from frame to frame: those a capture folder numbers (``view_000.png``)."""

_IMAGE_NUMBER = re.compile(rf"^(?P<prefix>(?:{'|'.join(FRAME_IMAGES)})_?)(?P<digits>\d+)$")
_FOLDER_NUMBER = re.compile(r"^(?P<prefix>(?:frame_?)?)(?P<digits>\d+)$")


def frame_name(index: int) -> str:
    """Folder name of frame ``index`` (0-based)."""
    return f"frame{index:03d}"


def frame_times(start_s: float, fps: float, n_frames: int) -> list[float]:
    """The instants ``start_s + k / fps`` of ``n_frames`` frames, s."""
    return [float(start_s) + k / float(fps) for k in range(int(n_frames))]


def sequence_kind(folder: str | Path) -> str | None:
    """Which sequence layout ``folder`` holds, or None when it holds none.

    ``"rendered"``: ``sequence.json`` and its frame folders (``wai render --frames``);
    ``"images"``: numbered images of :data:`FRAME_IMAGES` (``view_000.png``); ``"frames"``:
    numbered frame folders (``frame_000/``, ``000/``, ``frame1/``) holding a frame's images.
    A folder holding a frame's own images (``pattern.png``, ``view.png``) is a single frame.
    """
    folder = Path(folder)
    if (folder / SEQUENCE_FILE).is_file():
        return "rendered"
    if not folder.is_dir() or any(locate_image(folder, s) for s in FRAME_IMAGES):
        return None
    if _numbered(folder.iterdir(), _IMAGE_NUMBER, files=True):
        return "images"
    dirs = _numbered(folder.iterdir(), _FOLDER_NUMBER, files=False)
    if any(_holds_frame(d) for found in dirs.values() for d in found):
        return "frames"
    return None


def is_sequence(folder: str | Path) -> bool:
    """True for a folder of any sequence layout (:func:`sequence_kind`)."""
    return sequence_kind(folder) is not None


@dataclass(frozen=True)
class SequenceRecord:
    """A sequence folder's frames, in order: what ``sequence.json`` says, or what a scan of
    one's own captures found.

    Attributes
    ----------
    folder : Path
    fps : float
        Frames per second.
    times_s : list of float
        Each frame's instant, s (``k / fps`` for captures).
    frames : list of str
        Each frame's name, in order: its folder's (``frame000``, ``frame_000``, ``000``), or
        ``frame_`` and its images' number (``frame_000`` for ``view_000.png``).
    record : dict
        The whole record: ``sequence.json`` (configuration, seed, versions), or a capture's
        ``scene.json``.
    kind : str
        The layout (:func:`sequence_kind`).
    files : tuple of dict of str to Path
        Per frame, its numbered images by name (``{"pattern": .../pattern_000.png, ...}``);
        empty where frames are folders.
    scene : Path or None
        A capture's ``scene.json``; None for a render, whose frame folders hold their own.
    """

    folder: Path
    fps: float
    times_s: list[float]
    frames: list[str]
    record: dict[str, Any]
    kind: str = "rendered"
    files: tuple[dict[str, Path], ...] = ()
    scene: Path | None = None

    @property
    def captured(self) -> bool:
        """One's own captures: no truth, and every output under ``folder/restore/``."""
        return self.kind != "rendered"

    @property
    def frame_dirs(self) -> list[Path]:
        """The folder holding each frame's own files, in order: its frame folder, or the
        sequence folder itself for numbered images."""
        if self.kind == "images":
            return [self.folder] * len(self.frames)
        return [self.folder / name for name in self.frames]

    @property
    def scene_dir(self) -> Path:
        """The folder whose ``scene.json`` holds the rig (the first frame's for a render)."""
        return self.scene.parent if self.scene is not None else self.frame_dirs[0]

    def image_path(self, k: int, stem: str) -> Path:
        """The file of image ``stem`` (``pattern``, ``pattern_flat``, ``view``, ...) of frame
        ``k``: its numbered image, else the first ``stem.*`` in its frame folder, else in the
        sequence folder (the shared flat-water reference).

        Raises
        ------
        WaiInputError
            When there is none (the message names the frame and the folders searched).
        """
        numbered = self.files[k].get(stem) if self.files else None
        if numbered is not None:
            return numbered
        where = list(dict.fromkeys((self.frame_dirs[k], self.folder)))
        for folder in where:
            path = locate_image(folder, stem)
            if path is not None:
                return path
        if self.kind == "images" and stem in FRAME_IMAGES:
            number = self.frames[k].removeprefix("frame_")
            raise WaiInputError(f"{self.folder / f'{stem}_{number}'}.*: missing (frame {k})")
        searched = " or ".join(str(w) for w in where)
        raise WaiInputError(f"frame {self.frames[k]}: no {stem} image ({stem}.* in {searched})")


def read_sequence(folder: str | Path) -> SequenceRecord:
    """Describe the sequence in ``folder``, any layout (:func:`sequence_kind`), checked: every
    frame folder ``sequence.json`` names must exist; a capture's numbering must have no gap,
    every numbered pattern its view.

    Raises
    ------
    WaiInputError
        One line naming the file or folder at fault.
    """
    folder = Path(folder)
    kind = sequence_kind(folder)
    if kind == "images":
        return _scan_images(folder)
    if kind == "frames":
        return _scan_frames(folder)
    if kind is None:
        raise WaiInputError(
            f"{folder}: not a sequence (no {SEQUENCE_FILE}, numbered images such as "
            "view_000.png, or numbered frame folders such as frame_000/)"
        )
    rec = read_json(folder / SEQUENCE_FILE)
    frames = rec.get("frames") if isinstance(rec, dict) else None
    if not isinstance(frames, list) or not frames or not all(
        isinstance(f, dict) and isinstance(f.get("name"), str) for f in frames
    ):
        raise WaiInputError(f"{folder / SEQUENCE_FILE}: needs a non-empty 'frames' list")
    missing = [f["name"] for f in frames if not (folder / f["name"]).is_dir()]
    if missing:
        raise WaiInputError(f"{folder}: frame folder {missing[0]} is missing")
    fps = rec.get("fps")
    if not _positive(fps):
        raise WaiInputError(f"{folder / SEQUENCE_FILE}: 'fps' must be a positive number")
    return SequenceRecord(
        folder, float(fps), [float(f.get("time_s", 0.0)) for f in frames],
        [f["name"] for f in frames], rec,
    )


def _positive(value: Any) -> bool:
    return (isinstance(value, int | float) and not isinstance(value, bool)
            and math.isfinite(value) and value > 0)


def _numbered(paths: Any, pattern: re.Pattern, *, files: bool) -> dict[int, list[Path]]:
    """The image files (``files``) or folders among ``paths`` whose name (a file's without
    its suffix) matches ``pattern``, by number."""
    found: dict[int, list[Path]] = {}
    for path in paths:
        if files and not (path.suffix.lower() in IMAGE_SUFFIXES and path.is_file()):
            continue
        if not files and not path.is_dir():
            continue
        match = pattern.match(path.stem if files else path.name)
        if match is not None:
            found.setdefault(int(match["digits"]), []).append(path)
    return found


def _holds_frame(folder: Path) -> bool:
    return any(locate_image(folder, s) for s in FRAME_IMAGES)


def _parts(path: Path, pattern: re.Pattern) -> tuple[str, str]:
    """``(prefix, digits)`` of a numbered file or folder name."""
    match = pattern.match(path.stem if path.is_file() else path.name)
    assert match is not None  # only numbered paths get here
    return match["prefix"], match["digits"]


def _check_numbering(folder: Path, numbers: list[int], first: dict[int, Path],
                     pattern: re.Pattern) -> None:
    """No gap in ``numbers`` (sorted): a missing one is named after its neighbour."""
    for a, b in zip(numbers, numbers[1:], strict=False):
        if b != a + 1:
            prefix, digits = _parts(first[a], pattern)
            name = f"{prefix}{a + 1:0{len(digits)}d}"
            kind = ".*" if first[a].is_file() else "/"
            raise WaiInputError(f"{folder / name}{kind}: missing (the numbering goes from "
                                f"{first[a].name} to {first[b].name})")


def _capture_record(folder: Path, scene: Path) -> tuple[dict[str, Any], float]:
    """A capture's ``scene.json`` and its frame rate (``"fps"``, default 1)."""
    if not scene.is_file():
        raise WaiInputError(f"{scene}: missing (a capture sequence needs the rig's "
                            "configuration, the single-frame scene.json)")
    rec = read_json(scene)
    if not isinstance(rec, dict):
        raise WaiInputError(f"{scene}: needs a 'config' table (the system configuration)")
    fps = rec.get("fps", 1.0)
    if not _positive(fps):
        raise WaiInputError(f"{scene}: 'fps' must be a positive number, not {fps!r}")
    return rec, float(fps)


def _scan_images(folder: Path) -> SequenceRecord:
    """A capture folder of numbered images (``pattern_000.png``, ``view_000.png``, ...)."""
    by_stem: dict[str, dict[int, Path]] = {}
    for number, paths in _numbered(sorted(folder.iterdir()), _IMAGE_NUMBER, files=True).items():
        for path in paths:
            prefix, digits = _parts(path, _IMAGE_NUMBER)
            stem = prefix.rstrip("_")
            held = by_stem.setdefault(stem, {}).get(number)
            if held is not None and _parts(held, _IMAGE_NUMBER)[1] != digits:
                raise WaiInputError(f"{folder}: {held.name} and {path.name} both number "
                                    f"{stem} {number}: keep one")
            if held is None or _rank(path) < _rank(held):  # find_image's choice of suffix
                by_stem[stem][number] = path
    numbers = sorted({n for found in by_stem.values() for n in found})
    first = {n: next(by_stem[s][n] for s in FRAME_IMAGES if n in by_stem.get(s, {}))
             for n in numbers}
    _check_numbering(folder, numbers, first, _IMAGE_NUMBER)
    for n in numbers:
        for stem in FRAME_IMAGES:
            if (stem in by_stem or stem == "view") and n not in by_stem.get(stem, {}):
                prefix, digits = _parts(first[n], _IMAGE_NUMBER)
                sep = "_" if prefix.endswith("_") else ""
                raise WaiInputError(f"{folder / f'{stem}{sep}{digits}'}.*: missing "
                                    f"({first[n].name} has no {stem})")
    rec, fps = _capture_record(folder, folder / SCENE_FILE)
    names = [f"frame_{_parts(first[n], _IMAGE_NUMBER)[1]}" for n in numbers]
    files = tuple({s: found[n] for s, found in by_stem.items()} for n in numbers)
    return SequenceRecord(folder, fps, frame_times(0.0, fps, len(names)), names, rec,
                          "images", files, folder / SCENE_FILE)


def _rank(path: Path) -> int:
    return IMAGE_SUFFIXES.index(path.suffix.lower())


def _scan_frames(folder: Path) -> SequenceRecord:
    """A capture folder of numbered frame folders (``frame_000/``, ``000/``, ...)."""
    found = _numbered(sorted(folder.iterdir()), _FOLDER_NUMBER, files=False)
    for number, dirs in found.items():
        if len(dirs) > 1:
            raise WaiInputError(f"{folder}: {dirs[0].name}/ and {dirs[1].name}/ are both "
                                f"frame {number}: keep one")
    numbers = sorted(found)
    first = {n: found[n][0] for n in numbers}
    _check_numbering(folder, numbers, first, _FOLDER_NUMBER)
    for n in numbers:
        if locate_image(first[n], "view") is None:
            raise WaiInputError(f"{first[n] / 'view'}.*: missing (each frame folder holds its "
                                "frame's images)")
    scene = folder / SCENE_FILE
    if not scene.is_file() and (first[numbers[0]] / SCENE_FILE).is_file():
        scene = first[numbers[0]] / SCENE_FILE
    rec, fps = _capture_record(folder, scene)
    names = [first[n].name for n in numbers]
    return SequenceRecord(folder, fps, frame_times(0.0, fps, len(names)), names, rec,
                          "frames", (), scene)


def link_reference(sequence_dir: Path, frame_dir: Path) -> None:
    """Put the shared reference images of ``sequence_dir`` into ``frame_dir`` (hard links,
    copies where links are not allowed), with their PNG previews when present."""
    for stem in REFERENCE_IMAGES:
        for suffix in (".exr", ".png"):
            src = sequence_dir / f"{stem}{suffix}"
            if not src.is_file():
                continue
            dst = frame_dir / src.name
            try:
                os.link(src, dst)
            except OSError:  # another file system, or links not allowed
                shutil.copy2(src, dst)
    copy_preview_records(sequence_dir, frame_dir, (f"{stem}.png" for stem in REFERENCE_IMAGES))
