"""Reading and writing images and JSON, each file whole: written to a temporary name and renamed
into place (the output folders' policy is :mod:`wai_core.outputs`)."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wai_core.errors import WaiInputError

# Anything else stays aside, as before the output policy (callers with a command
        # never get here with a file: check_output_dir refuses it).


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_json(path: str | Path, data: Any) -> None:
    """Write indented JSON atomically (numpy arrays and scalars allowed; NaN becomes null)."""
    text = json.dumps(_nan_to_none(data), indent=2, default=_jsonable, allow_nan=False)
    atomic_write_bytes(path, (text + "\n").encode())


def _nan_to_none(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_nan_to_none(v) for v in obj]
    if isinstance(obj, float | np.floating) and not np.isfinite(obj):
        return None
    return obj


def read_json(path: str | Path) -> Any:
    """Read JSON, raising :class:`WaiInputError` for a missing or corrupt file."""
    path = Path(path)
    if not path.is_file():
        raise WaiInputError(f"file not found: {path}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise WaiInputError(f"{path} is not valid JSON: {exc}") from None


def write_exr(path: str | Path, image: NDArray) -> None:
    """Write a float image of shape (h, w) or (h, w, 3) as a ZIP-compressed float32 OpenEXR
    (a failed write, a full disk, raises ``OSError``)."""
    import OpenEXR

    img = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    channels = {"Y": img} if img.ndim == 2 else {"RGB": img}
    header = {"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION}
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))
    except RuntimeError as exc:  # OpenEXR's way of saying the file could not be written
        tmp.unlink(missing_ok=True)
        raise OSError(f"cannot write {path}: {exc}") from None
    os.replace(tmp, path)


def read_exr(path: str | Path) -> NDArray[np.float32]:
    """Read an OpenEXR image as float32 (h, w, 3) or (h, w); checks for NaN."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise WaiInputError(f"image not found: {path}")
    try:
        with OpenEXR.File(str(path)) as f:
            ch = f.channels()
            if "RGB" in ch:
                img = np.asarray(ch["RGB"].pixels, dtype=np.float32)
            elif {"R", "G", "B"} <= set(ch):
                img = np.stack([np.asarray(ch[c].pixels, np.float32) for c in "RGB"], -1)
            elif "Y" in ch:
                img = np.asarray(ch["Y"].pixels, dtype=np.float32)
            else:
                raise WaiInputError(f"{path}: no RGB or Y channel")
    except WaiInputError:
        raise
    except Exception as exc:
        raise WaiInputError(f"{path} is not a readable OpenEXR image: {exc}") from None
    if not np.all(np.isfinite(img)):
        raise WaiInputError(f"{path}: image holds NaN or inf")
    return img


def to_srgb8(image: NDArray, exposure: float | None = None) -> NDArray[np.uint8]:
    """Tone-map a linear image to 8-bit sRGB; ``exposure`` scales it (default: 99.5th percentile
    to white)."""
    img = np.asarray(image, dtype=np.float64)
    if exposure is None:
        top = np.percentile(img, 99.5)
        exposure = 1.0 / top if top > 0 else 1.0
    x = np.clip(img * exposure, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (srgb * 255 + 0.5).astype(np.uint8)


def write_png(path: str | Path, image: NDArray, exposure: float | None = None) -> None:
    """Write a preview PNG of a linear float image (or an 8-bit image as is)."""
    from skimage.io import imsave

    img = np.asarray(image)
    out = img if img.dtype == np.uint8 else to_srgb8(img, exposure)
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp.png")
    imsave(tmp, out, check_contrast=False)
    os.replace(tmp, path)
