"""The layout of a sequence folder: frames of moving water that share one flat-water reference.

A sequence folder holds ``sequence.json`` (the configuration, frame rate, each frame's time
and folder name, the seed and the versions), the flat-water reference images once
(``pattern_flat.exr``, ``view_truth.exr``: flat water looks the same at every instant), and
one subfolder per frame (``frame000``, ``frame001``, ...) in the single-frame layout of
``wai render``. Each frame folder links the shared reference images (hard links where the file
system allows, else copies), so every single-frame tool works on a frame as it is.

Examples
--------
>>> frame_name(7)
'frame007'
>>> frame_times(10.0, 30.0, 3)
[10.0, 10.033333333333333, 10.066666666666666]
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from wai_core.errors import WaiInputError
from wai_core.io import read_json

__all__ = [
    "REFERENCE_IMAGES",
    "SEQUENCE_FILE",
    "SequenceRecord",
    "frame_name",
    "frame_times",
    "is_sequence",
    "link_reference",
    "read_sequence",
]

SEQUENCE_FILE = "sequence.json"
REFERENCE_IMAGES = ("pattern_flat", "view_truth")
"""Images of flat water, the same for every frame: stored once, linked into each frame."""


def frame_name(index: int) -> str:
    """Folder name of frame ``index`` (0-based)."""
    return f"frame{index:03d}"


def frame_times(start_s: float, fps: float, n_frames: int) -> list[float]:
    """The instants ``start_s + k / fps`` of ``n_frames`` frames, s."""
    return [float(start_s) + k / float(fps) for k in range(int(n_frames))]


def is_sequence(folder: str | Path) -> bool:
    """True for a folder written as a sequence (it holds ``sequence.json``)."""
    return (Path(folder) / SEQUENCE_FILE).is_file()


@dataclass(frozen=True)
class SequenceRecord:
    """What ``sequence.json`` says.

    Attributes
    ----------
    folder : Path
    fps : float
        Frames per second.
    times_s : list of float
        Each frame's instant, s.
    frames : list of str
        Each frame's folder name, in order.
    record : dict
        The whole record (configuration, seed, versions).
    """

    folder: Path
    fps: float
    times_s: list[float]
    frames: list[str]
    record: dict[str, Any]

    @property
    def frame_dirs(self) -> list[Path]:
        """The frame folders, in order."""
        return [self.folder / name for name in self.frames]


def read_sequence(folder: str | Path) -> SequenceRecord:
    """Read and check ``folder/sequence.json``: every frame folder it names must exist."""
    folder = Path(folder)
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
    if not isinstance(fps, int | float) or not fps > 0:
        raise WaiInputError(f"{folder / SEQUENCE_FILE}: 'fps' must be a positive number")
    return SequenceRecord(
        folder, float(fps), [float(f.get("time_s", 0.0)) for f in frames],
        [f["name"] for f in frames], rec,
    )


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
