"""Reading a frame's images whatever their format: rendered EXR or a camera's PNG/TIFF.

Renders are float OpenEXR (linear radiance). Captures from outside the testbed are 8- or 16-bit
PNG or TIFF; their integer values are taken as linear sensor counts and scaled to [0, 1] by the
type's full scale (no sRGB decoding: machine-vision cameras write linear data). A colour image
keeps its three channels in RGB order; a grey image is (H, W).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sys
import tempfile
import threading
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from wai_core.errors import WaiInputError
from wai_core.io import read_exr

__all__ = [
    "IMAGE_SUFFIXES", "PREVIEWS_FILE", "copy_preview_records", "find_image", "image_conflict",
    "image_digest", "locate_image", "read_image", "record_previews",
]

IMAGE_SUFFIXES = (".exr", ".png", ".tif", ".tiff")
"""Suffixes tried, in order, for an image named by its stem (``pattern`` -> ``pattern.exr``)."""

SAME_IMAGE_CORRELATION = 0.98
"""Two files of one stem hold the same image when their correlation, under the encodings a
preview may use (linear; sRGB; sRGB clipped at the 99.5th percentile), reaches this. A render's
own previews reach 0.996-1.0; another frame of the same rig 0.09 (patterns) to 0.69 (views)."""


def read_image(path: str | Path) -> NDArray[np.float32]:
    """Read an EXR, PNG or TIFF image as float32 (H, W) or (H, W, 3).

    Parameters
    ----------
    path : str or Path
        The image file. EXR: linear float values as stored. PNG/TIFF, 8 or 16 bit, grey or
        colour (an alpha channel is dropped): values divided by 255 or 65535.

    Returns
    -------
    (H, W) or (H, W, 3) ndarray of float32

    Raises
    ------
    WaiInputError
        Missing, unreadable or non-finite image, or an unsupported pixel type; the message
        names the file.

    Examples
    --------
    >>> import numpy as np, tempfile, cv2, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "grey.png"
    >>> _ = cv2.imwrite(str(p), np.full((4, 6), 65535, np.uint16))
    >>> img = read_image(p)
    >>> img.shape, float(img.max())
    ((4, 6), 1.0)
    """
    path = Path(path)
    if path.suffix.lower() == ".exr":
        return read_exr(path)
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise WaiInputError(f"{path}: unsupported image type (use {', '.join(IMAGE_SUFFIXES)})")
    if not path.is_file():
        raise WaiInputError(f"image not found: {path}")
    import cv2

    with _native_stderr() as said:  # libpng and libtiff print their errors themselves
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        why = f" ({'; '.join(said)})" if said else ""
        raise WaiInputError(f"{path} is not a readable {path.suffix.lstrip('.').upper()} "
                            f"image{why}")
    if raw.dtype == np.uint8:
        img = raw.astype(np.float32) / 255.0
    elif raw.dtype == np.uint16:
        img = raw.astype(np.float32) / 65535.0
    elif raw.dtype.kind == "f":
        img = raw.astype(np.float32)
    else:
        raise WaiInputError(f"{path}: pixel type {raw.dtype} is not supported (8/16-bit or float)")
    if img.ndim == 3:
        img = img[..., :3][..., ::-1] if img.shape[2] >= 3 else img[..., 0]  # BGR(A) -> RGB
        img = np.ascontiguousarray(img)
    if not np.all(np.isfinite(img)):
        raise WaiInputError(f"{path}: image holds NaN or inf")
    return img


_STDERR_LOCK = threading.Lock()  # file descriptor 2 is the process's: one redirection at a time


@contextlib.contextmanager
def _native_stderr() -> Iterator[list[str]]:
    """Within the block, what native libraries write to the process's stderr (file
    descriptor 2: libpng's and libtiff's messages, OpenCV's log) is captured, not shown; the
    list holds its lines at the end (the decoders' reasons for a one-line message). Threads
    take turns (a lock), so that each restores the descriptor it found."""
    lines: list[str] = []
    try:
        sink = tempfile.TemporaryFile()
    except OSError:  # no room for it: the messages go to the terminal, as before
        yield lines
        return
    with _STDERR_LOCK, sink:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(sink.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode(errors="replace")
            lines.extend(line.strip() for line in text.splitlines() if line.strip())


def locate_image(folder: str | Path, stem: str) -> Path | None:
    """The file of image ``stem`` in ``folder`` (``stem`` + the first of
    :data:`IMAGE_SUFFIXES` that exists), or None."""
    for suffix in IMAGE_SUFFIXES:
        path = Path(folder) / f"{stem}{suffix}"
        if path.is_file():
            return path
    return None


def find_image(folder: str | Path, stem: str) -> Path:
    """The file of image ``stem`` in ``folder``: the first of ``stem`` + :data:`IMAGE_SUFFIXES`
    that exists.

    Raises
    ------
    WaiInputError
        When none exists (the message lists what was looked for).
    """
    path = locate_image(folder, stem)
    if path is not None:
        return path
    tried = ", ".join(f"{stem}{s}" for s in IMAGE_SUFFIXES)
    raise WaiInputError(f"image not found in {folder}: tried {tried}")


PREVIEWS_FILE = ".wai-previews.json"
"""The record, in a folder the tool wrote images into, of the previews it wrote beside them:
for each preview file its SHA-256 and the image it shows (file name and
:func:`image_digest`). A preview recorded there, unchanged, of the very image beside it is
never taken for a second, differing file of that image (:func:`image_conflict`)."""


def image_digest(image: NDArray) -> str:
    """A digest of an image's values as float32 (every 4th row and column, and the shape):
    the same for an image and its float32 EXR read back, different for another frame.

    Examples
    --------
    >>> import numpy as np
    >>> a = np.arange(48, dtype=np.float32).reshape(4, 4, 3)
    >>> same = image_digest(a) == image_digest(a.astype(np.float64))
    >>> same, image_digest(a) == image_digest(a + 1)
    (True, False)
    """
    img = np.asarray(image, np.float32)
    h = hashlib.sha256(repr(img.shape).encode())
    h.update(np.ascontiguousarray(img[::4, ::4]).tobytes())
    return h.hexdigest()


def _file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _read_previews(folder: Path) -> dict:
    try:
        record = json.loads((folder / PREVIEWS_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def _write_previews(folder: Path, record: dict) -> None:
    from wai_core.io import atomic_write_bytes

    atomic_write_bytes(folder / PREVIEWS_FILE, json.dumps(record, indent=1).encode())


def record_previews(folder: str | Path, previews: Mapping[str, tuple[str, NDArray]]) -> None:
    """Record previews just written into ``folder`` (:data:`PREVIEWS_FILE`, merged with the
    folder's record).

    Parameters
    ----------
    folder : str or Path
    previews : mapping of str to (str, ndarray)
        Preview file name: (the image file it shows, that image's values as written).
    """
    folder = Path(folder)
    record = _read_previews(folder)
    for name, (image_name, image) in previews.items():
        record[name] = {"sha256": _file_sha256(folder / name), "image": image_name,
                        "image_digest": image_digest(image)}
    _write_previews(folder, record)


def copy_preview_records(src: str | Path, dst: str | Path, names: Iterable[str]) -> None:
    """Carry the records of previews ``names`` from folder ``src`` to ``dst`` (files linked or
    copied from one to the other)."""
    found = _read_previews(Path(src))
    entries = {n: found[n] for n in names if n in found}
    if entries:
        record = _read_previews(Path(dst))
        record.update(entries)
        _write_previews(Path(dst), record)


def _own_preview(other: Path, chosen: Path, image: NDArray, record: dict) -> bool:
    """Whether ``other`` is a preview the tool recorded, unchanged, of ``chosen``'s image."""
    entry = record.get(other.name)
    if not isinstance(entry, dict) or entry.get("image") != chosen.name:
        return False
    try:
        same_file = entry.get("sha256") == _file_sha256(other)
    except OSError:
        return False
    return same_file and entry.get("image_digest") == image_digest(image)


def _correlation(a: NDArray, b: NDArray) -> float:
    a, b = a - a.mean(), b - b.mean()
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else 0.0


def _srgb_to_linear(x: NDArray) -> NDArray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def image_conflict(folder: str | Path, stem: str, image: NDArray) -> str | None:
    """Say so when ``folder`` holds another file of image ``stem`` whose content differs from
    ``image`` (the one :func:`find_image` chose), e.g. ``pattern.exr`` beside a
    ``pattern.png`` of another frame.

    A preview the tool wrote of this very image (recorded in :data:`PREVIEWS_FILE`, unchanged)
    is never a conflict. Another file is compared by content: a preview of the same image (sRGB
    at its own exposure, or a sensor's integer counts) is not a conflict; see
    :data:`SAME_IMAGE_CORRELATION`.

    Parameters
    ----------
    folder : str or Path
        The frame's folder.
    stem : str
        The image's name without suffix.
    image : (H, W) or (H, W, 3) ndarray
        The image read from the chosen file.

    Returns
    -------
    str or None
        One line naming both files, or None when there is no other file or it agrees.

    Examples
    --------
    >>> import numpy as np, tempfile, cv2, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> ramp = np.tile(np.arange(0, 256, 4, dtype=np.uint8), (8, 1))
    >>> _ = cv2.imwrite(str(d / "view.png"), ramp)
    >>> _ = cv2.imwrite(str(d / "view.tif"), ramp[:, ::-1])
    >>> image_conflict(d, "view", read_image(d / "view.png")) is not None
    True
    """
    chosen = find_image(folder, stem)
    others = [p for s in IMAGE_SUFFIXES if (p := Path(folder) / f"{stem}{s}").is_file()
              and p != chosen]
    if not others:
        return None
    record = _read_previews(Path(folder))
    others = [p for p in others if not _own_preview(p, chosen, image, record)]
    if not others:
        return None
    used = np.asarray(image, np.float64)
    used = (used.mean(axis=-1) if used.ndim == 3 else used)[::4, ::4]
    top = float(np.percentile(used, 99.5))
    clipped = np.clip(used / top, 0.0, 1.0) if top > 0 else used
    for other in others:
        img = read_image(other)
        if img.shape[:2] != np.shape(image)[:2]:
            return (f"{chosen.name} and {other.name} in {folder} are different images "
                    f"({np.shape(image)[1]}x{np.shape(image)[0]} and {img.shape[1]}x"
                    f"{img.shape[0]}); {chosen.name} was used")
        alt = np.asarray(img, np.float64)
        alt = (alt.mean(axis=-1) if alt.ndim == 3 else alt)[::4, ::4]
        lin = _srgb_to_linear(alt)
        r = max(_correlation(alt, used), _correlation(lin, used), _correlation(lin, clipped))
        if r < SAME_IMAGE_CORRELATION:
            return (f"{chosen.name} and {other.name} in {folder} hold different images "
                    f"(correlation {r:.2f}); {chosen.name} was used: remove the one that is "
                    "not this frame's")
    return None
