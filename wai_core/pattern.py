"""The structured-light pattern: a square grid of Gaussian dots on the projector panel.

Dot ``(i, j)`` sits at panel pixel ``(col, row) = (c0 + i D, r0 + j D)`` where ``(c0, r0)`` is the
panel centre and D the spacing (``PatternConfig.spacing_px``); ``i`` runs along panel columns, ``j``
along rows. Only dots at least three radii inside the panel are drawn. The renderer draws this
image; the restoration uses the same grid to know each feature's projector ray (calibration).
"""

from __future__ import annotations

import functools
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from wai_core.geometry import PinholeCamera


def dot_grid(pattern: Any, projector: PinholeCamera) -> tuple[NDArray, NDArray]:
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
    return ij, grid_panel_px(pattern, projector, ij)


def grid_panel_px(pattern: Any, projector: PinholeCamera, ij: NDArray) -> NDArray[np.float64]:
    """Panel position ``(col, row)`` (K, 2), px, of grid nodes ``ij`` (K, 2): the dots' own
    (:func:`dot_grid`) and, for nodes beyond the grid, where a dot would sit on the panel's
    plane (past its edge).

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> grid_panel_px(SimpleNamespace(spacing_px=10.0), SimpleNamespace(width_px=101,
    ...               height_px=51), np.array([[0, 0], [-6, 1]])).tolist()
    [[50.0, 25.0], [-10.0, 35.0]]
    """
    c0 = (projector.width_px - 1) / 2.0
    r0 = (projector.height_px - 1) / 2.0
    ij = np.asarray(ij, dtype=np.float64).reshape(-1, 2)
    return np.stack([c0 + ij[:, 0] * pattern.spacing_px, r0 + ij[:, 1] * pattern.spacing_px], 1)


def pattern_image(
    pattern: Any, projector: PinholeCamera, weights: NDArray | None = None
) -> NDArray[np.float32]:
    """Panel image (height, width, 3) in [0, 1]: the dots in ``pattern.color`` on black.

    Each dot is a Gaussian of standard deviation ``sigma_px``; dots are far enough apart
    (``spacing_px > 2 sigma``) that their tails barely overlap. ``weights`` (K,) in [0, 1], in
    :func:`dot_grid` order, scales each dot (0 leaves it dark); default: all at 1.
    """
    _, panel = dot_grid(pattern, projector)
    w0 = np.ones(len(panel)) if weights is None else np.asarray(weights, dtype=float)
    panel, w = panel[w0 > 0], w0[w0 > 0]
    cols = np.arange(projector.width_px, dtype=np.float64)
    rows = np.arange(projector.height_px, dtype=np.float64)
    s2 = 2.0 * pattern.sigma_px**2
    # Each dot is separable: a column profile times a row profile; sum their outer products.
    gx = w[:, None] * np.exp(-((cols[None, :] - panel[:, :1]) ** 2) / s2)
    gy = np.exp(-((rows[None, :] - panel[:, 1:]) ** 2) / s2)
    if pattern.code == "none":
        lum = np.clip(gy.T @ gx, 0.0, 1.0)
        return (lum[..., None] * np.asarray(pattern.color, dtype=np.float64)).astype(np.float32)
    # Coded: one such sum per channel, each dot weighted by its colour (dots do not overlap).
    colours = dot_colours(pattern, projector)[w0 > 0]
    rgb = np.stack([gy.T @ (gx * colours[:, c : c + 1]) for c in range(3)], axis=-1)
    return np.clip(rgb, 0.0, None).astype(np.float32)


# --- Coded pattern ([pattern] code = "colour") -----------------------------------------------
# Four symbols, all in the blue-green window of seawater (section 2.2): the green fraction
# g = G / (G + B) of a dot's colour. A ratio of channels is what survives the path: the Fresnel
# reflection (n does not vary over 450-550 nm here) and the white diffuser scale both channels
# alike, and focusing by the waves changes a spot's brightness and size but not its hue.
CODE_LEVELS = (0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)
"""Green fraction ``G / (G + B)`` of each symbol's colour."""
CODE_WINDOW = 3
"""Side of the window (dots) whose symbols make a dot's code word."""
CODE_REACH = 8
"""Lattice offsets (Chebyshev distance, dots) within which every two windows must differ."""
CODE_MIN_DISTANCE = 3
"""Fewest differing symbols between two windows within :data:`CODE_REACH` (where both dots are
in the grid): one misread symbol still leaves the true window closest, and a window shifted by
any offset within reach agrees with the true one on at most ``9 - 3`` dots."""


@numba.njit(cache=True)
def _pair_penalty(s: NDArray, r0: int, c0: int, r1: int, c1: int, need: int) -> int:
    """``max(0, need - d)``, d the symbols that differ between the windows centred at
    ``(r0, c0)`` and ``(r1, c1)`` where both cells are on the grid."""
    nr, nc = s.shape
    d = 0
    for a in range(-1, 2):
        for b in range(-1, 2):
            ra, ca, rb, cb = r0 + a, c0 + b, r1 + a, c1 + b
            if 0 <= ra < nr and 0 <= ca < nc and 0 <= rb < nr and 0 <= cb < nc:
                if s[ra, ca] != s[rb, cb]:
                    d += 1
    return max(0, need - d)


@numba.njit(cache=True)
def _centre_cost(s: NDArray, r: int, c: int, reach: int, need: int) -> int:
    """Summed penalty of the full window at ``(r, c)`` against every full window within
    ``reach`` (0 for a window that leaves the grid)."""
    nr, nc = s.shape
    cost = 0
    if not (1 <= r < nr - 1 and 1 <= c < nc - 1):
        return 0
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            r1, c1 = r + dr, c + dc
            if (dr != 0 or dc != 0) and 1 <= r1 < nr - 1 and 1 <= c1 < nc - 1:
                cost += _pair_penalty(s, r, c, r1, c1, need)
    return cost


@numba.njit(cache=True)
def _repair(s: NDArray, n_symbols: int, reach: int, need: int, seed: int, sweeps: int) -> int:
    """Local search on the symbols ``s`` (in place): every sweep visits the windows that break
    the distance rule and gives one of their dots the symbol that breaks the fewest; returns
    the total penalty left (0: the array satisfies the rule)."""
    np.random.seed(seed)  # noqa: NPY002  (numba knows only the legacy generator)
    nr, nc = s.shape
    total = 0
    for _ in range(sweeps):
        total = 0
        for r in range(nr):
            for c in range(nc):
                if _centre_cost(s, r, c, reach, need) == 0:
                    continue
                total += 1
                rr = min(max(r + np.random.randint(-1, 2), 0), nr - 1)  # noqa: NPY002
                cc = min(max(c + np.random.randint(-1, 2), 0), nc - 1)  # noqa: NPY002
                best, best_cost = s[rr, cc], -1
                start = np.random.randint(n_symbols)  # noqa: NPY002
                for k in range(n_symbols):
                    sym = (start + k) % n_symbols
                    s[rr, cc] = sym
                    cost = 0  # the windows that hold the changed dot
                    for a in range(-1, 2):
                        for b in range(-1, 2):
                            if 0 <= rr + a < nr and 0 <= cc + b < nc:
                                cost += _centre_cost(s, rr + a, cc + b, reach, need)
                    if best_cost < 0 or cost < best_cost:
                        best, best_cost = sym, cost
                s[rr, cc] = best
        if total == 0:
            return 0
    return total


def window_distances(symbols: NDArray, reach: int = CODE_REACH) -> NDArray:
    """Smallest number of differing symbols between the full window at each cell and any
    other full window within ``reach`` (the verification of :func:`code_array`), vectorised.

    Parameters
    ----------
    symbols : (nj, ni) ndarray of int
        Symbol of each grid cell (rows: grid j, columns: grid i).
    reach : int
        Largest lattice offset (Chebyshev) compared, dots.

    Returns
    -------
    (nj, ni) ndarray of int
        Per window, the distance to its nearest other window (9 on the grid's border, whose
        windows leave the grid and are not compared: a border dot is decoded through its
        inner neighbours' windows).
    """
    s = np.asarray(symbols, dtype=np.int64)
    nr, nc = s.shape
    pad = reach + 1
    big = np.full((nr + 2 * pad, nc + 2 * pad), -1, np.int64)
    big[pad : pad + nr, pad : pad + nc] = s
    out = np.full((nr, nc), 9, np.int64)
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            if dr == 0 and dc == 0:
                continue
            d = np.zeros((nr, nc), np.int64)
            for a in (-1, 0, 1):
                for b in (-1, 0, 1):
                    x = big[pad + a : pad + a + nr, pad + b : pad + b + nc]
                    y = big[pad + a + dr : pad + a + dr + nr, pad + b + dc : pad + b + dc + nc]
                    d += (x >= 0) & (y >= 0) & (x != y)
            # Only pairs of full windows (both centres at least one dot inside the grid).
            inside = np.zeros((nr, nc), bool)
            inside[1 + max(0, -dr) : nr - 1 - max(0, dr), 1 + max(0, -dc) : nc - 1 - max(0, dc)] = 1
            out = np.where(inside, np.minimum(out, d), out)
    out[[0, -1], :] = 9
    out[:, [0, -1]] = 9
    return out


@functools.lru_cache(maxsize=8)
def code_array(
    nj: int, ni: int, seed: int = 0, n_symbols: int = len(CODE_LEVELS),
    reach: int = CODE_REACH, min_distance: int = CODE_MIN_DISTANCE,
) -> NDArray[np.int8]:
    """Symbols (nj, ni) of a grid whose 3 x 3 windows are locally unique, deterministic in
    ``seed``: a seeded random array repaired by local search until every two full windows within
    ``reach`` dots differ in at least ``min_distance`` symbols, then verified
    (:func:`window_distances`).

    Raises
    ------
    ValueError
        When the search leaves windows that break the rule (too many symbols asked of too few).
    """
    rng = np.random.default_rng(seed)
    s = rng.integers(0, n_symbols, size=(nj, ni)).astype(np.int64)
    left = _repair(s, n_symbols, reach, min_distance, seed, 200)
    if left or window_distances(s, reach).min() < min_distance:
        raise ValueError(
            f"no {nj} x {ni} code with {n_symbols} symbols and window distance {min_distance} "
            f"within {reach} dots was found (seed {seed})"
        )
    out = s.astype(np.int8)
    out.flags.writeable = False
    return out


def dot_codes(pattern: Any, projector: PinholeCamera) -> NDArray[np.int8]:
    """Symbol (K,) of each dot in :func:`dot_grid` order (an index into :data:`CODE_LEVELS`);
    all 0 for ``code = "none"``."""
    ij, _ = dot_grid(pattern, projector)
    if pattern.code == "none":
        return np.zeros(len(ij), np.int8)
    lo = ij.min(axis=0)
    ni, nj = ij.max(axis=0) - lo + 1
    grid = code_array(int(nj), int(ni), int(pattern.code_seed))
    return grid[ij[:, 1] - lo[1], ij[:, 0] - lo[0]]


def dot_colours(pattern: Any, projector: PinholeCamera) -> NDArray:
    """Projector RGB (K, 3) of each dot: ``pattern.color`` for every dot with ``code = "none"``;
    with ``"colour"``, ``(0, g, 1 - g)`` times the G + B of ``pattern.color`` (g: the symbol's
    :data:`CODE_LEVELS`), so every dot carries the plain pattern's G + B, the luminance that
    the detection sums."""
    colour = np.asarray(pattern.color, dtype=np.float64)
    sym = dot_codes(pattern, projector)
    if pattern.code == "none":
        return np.broadcast_to(colour, (len(sym), 3)).copy()
    g = np.asarray(CODE_LEVELS)[sym]
    return (colour[1] + colour[2]) * np.stack([np.zeros_like(g), g, 1.0 - g], axis=1)
