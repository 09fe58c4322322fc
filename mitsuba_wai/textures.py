"""Images shown on the object plane above the water.

Orientation: texture column ``c`` grows with lab +x and row ``r`` with lab +y, and the image spans
the object rectangle exactly (``ObjectConfig.size_mm``), stretched if its aspect ratio differs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from wai_core.config import SKIMAGE_TEXTURES, ObjectConfig
from wai_core.errors import WaiInputError

# Checkerboard levels: dark and light squares stay off 0 and 1 so tone mapping never clips them.
CHECKER_LEVELS = (0.05, 0.95)


def checkerboard(squares: tuple[int, int], px_per_square: int = 64) -> NDArray[np.float32]:
    """Grey checkerboard (h, w, 3) in [0, 1] with ``squares = (n_x, n_y)`` squares; the square at
    the first row and column is dark."""
    nx, ny = squares
    jj, ii = np.mgrid[0 : ny * px_per_square, 0 : nx * px_per_square] // px_per_square
    lo, hi = CHECKER_LEVELS
    board = np.where((ii + jj) % 2 == 0, lo, hi).astype(np.float32)
    return np.repeat(board[..., None], 3, axis=2)


def speckle(size_mm: tuple[float, float], feature_mm: float, seed: int = 0
            ) -> NDArray[np.float32]:
    """A random grey pattern (h, w, 3) in [0, 1] over an object of ``size_mm`` (width,
    height): white noise smoothed by a Gaussian of standard deviation ``feature_mm / 2``,
    sampled at a quarter of ``feature_mm`` and stretched to fill the checkerboard's levels
    (1st and 99th percentiles); what a lab tank's synthetic Schlieren looks through.

    Examples
    --------
    >>> img = speckle((400.0, 200.0), 8.0)
    >>> img.shape, bool(img.min() >= 0.0 and img.max() <= 1.0)
    ((100, 200, 3), True)
    """
    from scipy.ndimage import gaussian_filter

    texel_mm = feature_mm / 4.0
    w, h = (max(int(round(s / texel_mm)), 8) for s in size_mm)
    noise = np.random.default_rng(int(seed)).standard_normal((h, w))
    field = gaussian_filter(noise, sigma=2.0, mode="wrap")  # feature_mm / 2 in texels
    lo_q, hi_q = np.percentile(field, [1.0, 99.0])
    lo, hi = CHECKER_LEVELS
    img = np.clip(lo + (hi - lo) * (field - lo_q) / (hi_q - lo_q), lo, hi).astype(np.float32)
    return np.repeat(img[..., None], 3, axis=2)


def _skimage_image(name: str) -> NDArray:
    from skimage import data

    if name not in SKIMAGE_TEXTURES:
        raise WaiInputError(f"texture: {name!r} is not a scikit-image sample image (one of "
                            f"{', '.join(SKIMAGE_TEXTURES)})")
    return getattr(data, name)()


def _file_image(path: Path) -> NDArray:
    from skimage.io import imread

    if not path.is_file():
        raise WaiInputError(f"texture file not found: {path}")
    try:
        return imread(path)
    except Exception as exc:
        raise WaiInputError(f"texture file {path} cannot be read: {exc}") from None


def to_rgb_float(img: NDArray) -> NDArray[np.float32]:
    """Any grey/RGB/RGBA image as float32 RGB in [0, 1]."""
    img = np.asarray(img)
    out = img.astype(np.float32)
    if np.issubdtype(img.dtype, np.integer):
        out /= float(np.iinfo(img.dtype).max)
    if out.ndim == 2:
        out = np.repeat(out[..., None], 3, axis=2)
    if out.ndim != 3 or out.shape[2] not in (3, 4):
        raise WaiInputError(f"texture: expected a grey or RGB image, got shape {img.shape}")
    return np.clip(out[..., :3], 0.0, 1.0)


def object_texture(obj: ObjectConfig, base_dir: Path | None = None) -> NDArray[np.float32]:
    """The object plane's image (h, w, 3) in [0, 1] for ``ObjectConfig.texture``:
    ``checkerboard``, ``speckle`` (:func:`speckle`), ``skimage:<name>`` (one of
    :data:`wai_core.sections.SKIMAGE_TEXTURES`, e.g. ``skimage:astronaut``) or an image file
    path (relative paths resolve against ``base_dir``)."""
    spec = obj.texture
    if spec == "checkerboard":
        return checkerboard(obj.squares)
    if spec == "speckle":
        return speckle(obj.size_mm, obj.speckle_mm, obj.speckle_seed)
    if spec.startswith("skimage:"):
        return to_rgb_float(_skimage_image(spec.split(":", 1)[1]))
    path = Path(spec)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    return to_rgb_float(_file_image(path))
