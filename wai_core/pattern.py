"""The structured-light pattern: a square grid of Gaussian dots on the projector panel.

Dot ``(i, j)`` sits at panel pixel ``(col, row) = (c0 + i D, r0 + j D)`` where ``(c0, r0)`` is the
panel centre and D the spacing (``PatternConfig.spacing_px``); ``i`` runs along panel columns, ``j``
along rows. Only dots at least three radii inside the panel are drawn. The renderer draws this
image; the restoration uses the same grid to know each feature's projector ray (calibration).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from wai_core.config import PatternConfig
from wai_core.geometry import PinholeCamera


def dot_grid(pattern: PatternConfig, projector: PinholeCamera) -> tuple[NDArray, NDArray]:
    """Grid indices and panel positions of every dot.

    Returns
    -------
    ij : (K, 2) ndarray of int
        Grid index ``(i, j)`` of each dot; ``(0, 0)`` is the dot at the panel centre.
    panel_px : (K, 2) ndarray of float
        Continuous panel pixel coordinates ``(col, row)`` of each dot centre.
    """
    c0 = (projector.width_px - 1) / 2.0
    r0 = (projector.height_px - 1) / 2.0
    margin = 3.0 * pattern.sigma_px
    ni = int(np.floor((c0 - margin) / pattern.spacing_px))
    nj = int(np.floor((r0 - margin) / pattern.spacing_px))
    jj, ii = np.mgrid[-nj : nj + 1, -ni : ni + 1]
    ij = np.stack([ii.ravel(), jj.ravel()], axis=1)
    panel = np.stack([c0 + ij[:, 0] * pattern.spacing_px, r0 + ij[:, 1] * pattern.spacing_px], 1)
    return ij, panel


def pattern_image(
    pattern: PatternConfig, projector: PinholeCamera, weights: NDArray | None = None
) -> NDArray[np.float32]:
    """Panel image (height, width, 3) in [0, 1]: the dots in ``pattern.color`` on black.

    Each dot is a Gaussian of standard deviation ``sigma_px``; dots are far enough apart
    (``spacing_px > 2 sigma``) that their tails barely overlap. ``weights`` (K,) in [0, 1], in
    :func:`dot_grid` order, scales each dot (0 leaves it dark); default: all at 1.
    """
    _, panel = dot_grid(pattern, projector)
    w = np.ones(len(panel)) if weights is None else np.asarray(weights, dtype=float)
    panel, w = panel[w > 0], w[w > 0]
    cols = np.arange(projector.width_px, dtype=np.float64)
    rows = np.arange(projector.height_px, dtype=np.float64)
    s2 = 2.0 * pattern.sigma_px**2
    # Each dot is separable: a column profile times a row profile; sum their outer products.
    gx = w[:, None] * np.exp(-((cols[None, :] - panel[:, :1]) ** 2) / s2)
    gy = np.exp(-((rows[None, :] - panel[:, 1:]) ** 2) / s2)
    lum = np.clip(gy.T @ gx, 0.0, 1.0)
    return (lum[..., None] * np.asarray(pattern.color, dtype=np.float64)).astype(np.float32)
