"""The coded pattern's symbols as a frame shows them (step 1 of :mod:`restoration.features.decode`):
each spot's green fraction ``G / (G + B)`` read at its centre and snapped to the nearest of the
four levels refined on the frame, with a confidence; and the symbol the code gives each node of
the reference lattice."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from restoration.features._types import FloatArray, IntArray
from restoration.features.reference import ReferenceGrid
from wai_core.config import SystemConfig
from wai_core.errors import WaiInputError
from wai_core.pattern import CODE_LEVELS, dot_codes

__all__ = ["MIN_DOT_FLUX", "MIN_SYMBOL_CONFIDENCE", "node_symbols", "spot_symbols"]

MIN_SYMBOL_CONFIDENCE = 0.4
"""A spot whose green fraction lies farther than 0.6 of the half-gap from its level (two
colours mixed) casts and receives no vote."""

MIN_DOT_FLUX = 0.03
"""A spot with less than this share of a typical spot's flux (the detector's flux-weighted
median) is a speck, not a dot's spot: it votes but takes no label. On the paper's rig 2 of
about 9200 dots' spots lie under it, and the Monte Carlo specks that the detector keeps (about
220 a frame) carry 0.005-0.02."""


def spot_symbols(
    image: NDArray, centres_px: FloatArray, sigma_px: float, levels: FloatArray | None = None
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray]:
    """Colour symbol of each spot from its green fraction ``G / (G + B)``.

    Parameters
    ----------
    image : (H, W, 3) ndarray
        Camera-s image, linear RGB.
    centres_px : (P, 2) ndarray
        Spot centres ``(col, row)``, pixels.
    sigma_px : float
        Spot standard deviation, pixels: the smoothing of the channels before sampling.
    levels : (L,) ndarray, optional
        Starting level centres (default :data:`~wai_core.pattern.CODE_LEVELS`), refined by
        three 1-D k-means steps on the spots whose colour is clear.

    Returns
    -------
    symbol : (P,) ndarray of int
        Index of the nearest level, -1 where the confidence is under
        :data:`MIN_SYMBOL_CONFIDENCE` or the spot is dark.
    confidence : (P,) ndarray
        ``1 - |g - level| / half-gap``, clipped to 0..1.
    green : (P,) ndarray
        The green fraction g (NaN where G + B is not positive).
    levels : (L,) ndarray
        The refined level centres.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] < 3:
        raise WaiInputError(
            "the coded pattern needs an RGB pattern image (H, W, 3), got shape "
            f"{np.shape(image)}"
        )
    s = max(float(sigma_px), 0.5)
    g_img = cv2.GaussianBlur(np.ascontiguousarray(img[..., 1], np.float32), (0, 0), s)
    b_img = cv2.GaussianBlur(np.ascontiguousarray(img[..., 2], np.float32), (0, 0), s)
    c = np.asarray(centres_px, np.float32).reshape(-1, 2)
    gs = cv2.remap(g_img, c[:, :1], c[:, 1:], cv2.INTER_LINEAR)[:, 0].astype(np.float64)
    bs = cv2.remap(b_img, c[:, :1], c[:, 1:], cv2.INTER_LINEAR)[:, 0].astype(np.float64)
    total = gs + bs
    green = np.where(total > 0, gs / np.where(total > 0, total, 1.0), np.nan)
    lev = np.asarray(CODE_LEVELS if levels is None else levels, np.float64).copy()
    finite = np.isfinite(green)

    def assign(lv: FloatArray) -> tuple[IntArray, FloatArray]:
        dist = np.abs(np.where(finite, green, -10.0)[:, None] - lv[None, :])
        sym = np.argmin(dist, axis=1)
        # Half the gap to the neighbouring level on the side the value lies.
        gaps = np.diff(lv)
        half = 0.5 * np.concatenate([[gaps[0]], np.minimum(gaps[:-1], gaps[1:]), [gaps[-1]]])
        conf = np.clip(1.0 - dist[np.arange(len(sym)), sym] / half[sym], 0.0, 1.0)
        return sym, np.where(finite, conf, 0.0)

    for _ in range(3):  # k-means on the clear spots; a level without any keeps its place
        sym, conf = assign(lev)
        clear = conf > 0.5
        sums = np.bincount(sym[clear], green[clear], len(lev))
        n = np.bincount(sym[clear], minlength=len(lev))
        lev = np.where(n > 0, sums / np.maximum(n, 1), lev)
    sym, conf = assign(lev)
    sym = np.where(conf >= MIN_SYMBOL_CONFIDENCE, sym, -1)
    return sym.astype(np.int64), conf, green, lev


def node_symbols(ref: ReferenceGrid, cfg: SystemConfig) -> IntArray:
    """Code symbol (G,) of every node of the reference lattice; -1 for virtual and unlit
    nodes (no spot can show their symbol)."""
    projector = cfg.rig.projector
    ij = cfg.rig.dot_ij
    codes = dot_codes(cfg.pattern, projector).astype(np.int64)
    lo = ij.min(axis=0)
    side = ij.max(axis=0) - lo + 1
    grid = np.full((side[1], side[0]), -1, np.int64)
    grid[ij[:, 1] - lo[1], ij[:, 0] - lo[0]] = codes
    q = ref.ij - lo
    inside = (q >= 0).all(axis=1) & (q[:, 0] < side[0]) & (q[:, 1] < side[1])
    out = np.full(len(ref.ij), -1, np.int64)
    out[inside] = grid[q[inside, 1], q[inside, 0]]
    return np.where(ref.lit, out, -1)
