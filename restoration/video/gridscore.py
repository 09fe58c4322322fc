"""A regular grid seen through flat water: the smooth map a checkerboard's corners follow.

A camera under still water that looks up at a horizontal board in air does not see it by a
homography: each ray bends at the surface (Snell's law), by more the further it leans from
the vertical, so the board's image is squeezed radially about the nadir and ends at the edge
of Snell's window. In the camera's direction tangents ``p`` (the water-side ray's horizontal
over vertical components, a homography of the image), a board point at horizontal offset
``q`` from the nadir, in units of the board's height above the water, satisfies

    |q| = T + a * rho(T),   rho(T) = T / sqrt(n^2 + (n^2 - 1) T^2),   p = q * rho(T) / |q|,

with ``T`` the air-side ray's tangent, ``a`` the camera's depth over the board's height and
``n`` the water's refractive index. The flat-water grid model is this radial map between a
square grid placed about the nadir (scale, offset: 3 parameters) and a homography (8): 12
parameters in all, fitted to the corners by least squares. It is exact for flat water, so
the residual of a view's corners measures what the water's waves (or a restoration) left.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

__all__ = ["FLAT_WATER_MIN_CORNERS", "flat_water_residuals_px"]

FLAT_WATER_MIN_CORNERS = 16
"""Corners the flat-water model needs at least (12 parameters, two equations a corner)."""

_NEWTON_STEPS = 6
_START_DEPTH = (0.05, 0.3)
"""Camera depth over board height tried as starts (a shallow camera, a deep one)."""
_START_SCALE = (0.03, 0.1, 0.3, 1.0)
"""Grid spacing over board height tried as starts."""
_START_OFFSETS = np.linspace(-1.0, 1.0, 5)
"""Grid centre from the nadir tried as starts, in units of the grid's extent."""


def _to_direction_tangents(q: NDArray, depth: float, n: float) -> NDArray:
    """Board offsets ``q`` (M, 2) (units of board height) -> water-side direction tangents."""
    r = np.hypot(q[:, 0], q[:, 1])
    t = r / (1.0 + depth / n)  # a lower bound of the root; Newton rises to it monotonically
    for _ in range(_NEWTON_STEPS):
        s = np.sqrt(n * n + (n * n - 1.0) * t * t)
        t = t - (t + depth * t / s - r) / (1.0 + depth * n * n / s**3)
    rho = t / np.sqrt(n * n + (n * n - 1.0) * t * t)
    scale = np.where(r > 1e-12, rho / np.maximum(r, 1e-12), 1.0 / (n + depth))
    return q * scale[:, None]


def _apply_homography(h8: NDArray, p: NDArray) -> NDArray:
    hom = np.append(h8, 1.0).reshape(3, 3)
    x = p @ hom[:, :2].T + hom[:, 2]
    return x[:, :2] / x[:, 2:]


def _start(x: NDArray, g: NDArray, n: float) -> NDArray | None:
    """The best of a small set of grid placements, each with its linear homography fit."""
    extent = float(np.abs(g).max()) or 1.0
    best: tuple[float, NDArray] | None = None
    for depth in _START_DEPTH:
        for spacing in _START_SCALE:
            for ox in _START_OFFSETS * spacing * extent * 2.0:
                for oy in _START_OFFSETS * spacing * extent * 2.0:
                    p = _to_direction_tangents(spacing * g + [ox, oy], depth, n)
                    hom, _ = cv2.findHomography(p, x, 0)
                    if hom is None or abs(hom[2, 2]) < 1e-12:
                        continue
                    h8 = (hom / hom[2, 2]).ravel()[:8]
                    err = float(np.mean(np.sum((_apply_homography(h8, p) - x) ** 2, axis=1)))
                    if best is None or err < best[0]:
                        best = (err, np.r_[np.sqrt(depth), np.log(spacing), ox, oy, h8])
    return None if best is None else best[1]


def _model(z: NDArray, g: NDArray, n: float) -> NDArray:
    # z: sqrt(depth ratio), log(spacing), grid offset (2), homography (8).
    return _apply_homography(z[4:], _to_direction_tangents(np.exp(z[1]) * g + z[2:4],
                                                           z[0] ** 2, n))


def flat_water_residuals_px(
    corners: NDArray, grid: NDArray, n_water: float = 4.0 / 3.0, trim: float = 0.0
) -> NDArray[np.float64]:
    """Distances (px) of corners from the best flat-water image of a regular square grid.

    The fit starts from the best of a small set of grid placements (a linear homography fit
    for each) and refines all 12 parameters by least squares (Levenberg-Marquardt). With
    ``trim``, it is then fitted again without that share of the corners furthest from it
    (trimmed least squares), so that a few corners the detector misplaced do not bend it.

    Parameters
    ----------
    corners : (M, 2) ndarray
        Corner positions (x, y) in px, finite; M >= :data:`FLAT_WATER_MIN_CORNERS`.
    grid : (M, 2) ndarray
        Each corner's (column, row) index on the board.
    n_water : float
        Refractive index of the water.
    trim : float in [0, 0.5]
        Share of the corners left out of the second fit.

    Returns
    -------
    (M,) ndarray of float64
        Each corner's distance from the fitted model, px (NaN when no start could be fitted).

    Examples
    --------
    A camera just under the surface looking straight up (focal length 400 px) sees a board
    point at tangent ``q`` from the zenith at direction tangent ``q / sqrt(n^2 + (n^2 - 1)
    |q|^2)`` (Snell's law); such corners fit with no residual:

    >>> import numpy as np
    >>> j, i = np.mgrid[0:6, 0:7]
    >>> g = np.c_[i.ravel(), j.ravel()].astype(float)
    >>> q = 0.4 * (g - [2.0, 3.0])
    >>> n = 4.0 / 3.0
    >>> p = q / np.sqrt(n**2 + (n**2 - 1) * np.sum(q**2, axis=1, keepdims=True))
    >>> bool(flat_water_residuals_px(400.0 * p + [320.0, 240.0], g).max() < 1e-3)
    True
    """
    pts = np.asarray(corners, np.float64).reshape(-1, 2)
    g = np.asarray(grid, np.float64).reshape(-1, 2)
    g = g - (g.max(axis=0) + g.min(axis=0)) / 2.0
    centre = pts.mean(axis=0)
    unit = float(np.sqrt(np.mean(np.sum((pts - centre) ** 2, axis=1)))) or 1.0
    x = (pts - centre) / unit  # conditioned image coordinates
    z = _start(x, g, n_water)
    if z is None:
        return np.full(len(pts), np.nan)
    keep = np.ones(len(pts), bool)
    for _ in range(2 if trim > 0 else 1):
        def residual(zz: NDArray, keep: NDArray = keep) -> NDArray:
            return (_model(zz, g[keep], n_water) - x[keep]).ravel()

        z = least_squares(residual, z, method="lm").x
        dist = np.linalg.norm(_model(z, g, n_water) - x, axis=1)
        keep = dist <= np.quantile(dist, 1.0 - trim)
    return dist * unit
