"""Reading a frame's images whatever their format: rendered EXR or a camera's PNG/TIFF.

Renders are float OpenEXR (linear radiance). Captures from outside the testbed are 8- or 16-bit
PNG or TIFF; their integer values are taken as linear sensor counts and scaled to [0, 1] by the
type's full scale (no sRGB decoding: machine-vision cameras write linear data). A colour image
keeps its three channels in RGB order; a grey image is (H, W).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from wai_core.errors import WaiInputError
from wai_core.io import read_exr

__all__ = ["IMAGE_SUFFIXES", "find_image", "locate_image", "read_image"]

IMAGE_SUFFIXES = (".exr", ".png", ".tif", ".tiff")
"""Suffixes tried, in order, for an image named by its stem (``pattern`` -> ``pattern.exr``)."""


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

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise WaiInputError(f"{path} is not a readable {path.suffix.lstrip('.').upper()} image")
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
