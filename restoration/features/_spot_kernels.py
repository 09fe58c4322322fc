"""The spot detector's compiled kernels (:func:`restoration.features.detect_spots`): the
segmented pixels' sums, the moments about each segment's peak, and the windowed centroids.

Compiled with numba (``cache=True``): the first run after an install compiles them."""

from __future__ import annotations

import math
from types import MappingProxyType

import numpy as np
from numba import njit

_JIT = MappingProxyType({"cache": True, "nogil": True, "error_model": "numpy"})


# --- spot detection ---------------------------------------------------------------------------


@njit(**_JIT)
def _accumulate(first, second, i, wk, xk, yk):  # pragma: no cover
    """Add pixel weight ``wk`` at offsets ``(xk, yk)`` to label ``i``'s sums of ``w``, ``w x``,
    ``w y`` (``first``) and ``w x^2``, ``w x y``, ``w y^2`` (``second``)."""
    first[i, 0] += wk * 1.0
    first[i, 1] += wk * xk
    first[i, 2] += wk * yk
    second[i, 0] += wk * (xk * xk)
    second[i, 1] += wk * (xk * yk)
    second[i, 2] += wk * (yk * yk)


@njit(**_JIT)
def segmented_pixels(labels, smooth, padded, pad, n, count, cx, cy):  # pragma: no cover
    """The labelled pixels (label > 0) of ``labels`` (h, w), ``count`` of them, and the sums
    of every label (n,) over them, in one pass in raster order.

    Returns the pixels' rows, columns and labels (int32), smoothed values (float64, from
    ``smooth``) and raw values (float32, from ``padded``, the image inside a frame of ``pad``
    pixels); then per label, with weights ``w = max(smooth, 0)`` at offsets ``(x, y) =
    (col - cx, row - cy)``: the sums of ``w``, ``w x``, ``w y`` (``first`` (n, 3)) and of ``w
    x^2``, ``w x y``, ``w y^2`` (``second`` (n, 3)), the peak of ``smooth`` (-inf without
    pixels), the sum of the raw values (float64) and the pixel count.
    """
    h, w = labels.shape
    rows, cols = np.empty(count, np.int32), np.empty(count, np.int32)
    lab, val, raw = np.empty(count, np.int32), np.empty(count), np.empty(count, np.float32)
    first, second = np.zeros((n, 3)), np.zeros((n, 3))
    peak, flux, area = np.full(n, -np.inf), np.zeros(n), np.zeros(n, np.int64)
    k = 0
    for r in range(h):
        label_row, smooth_row, raw_row = labels[r], smooth[r], padded[r + pad]
        for c in range(w):
            i = label_row[c]
            if i > 0 and k < count:  # count: the caller's, never written past
                sk, rk = np.float64(smooth_row[c]), raw_row[c + pad]
                rows[k], cols[k], lab[k], val[k], raw[k] = r, c, i, sk, rk
                _accumulate(first, second, i, max(sk, 0.0), np.float64(c) - cx,
                            np.float64(r) - cy)
                peak[i] = max(peak[i], sk)
                flux[i] += np.float64(rk)
                area[i] += 1
                k += 1
    return rows, cols, lab, val, raw, first, second, peak, flux, area


@njit(**_JIT)
def _above_peak(k, i, lab, smooth, cols, rows, peak, origin):  # pragma: no cover
    """Pixel ``k`` (of label ``i``) for the kurtosis: its weight ``max(smooth - 0.2 peak, 0)``
    and its offsets from the label's ``origin`` (n, 2) pixel, as exact small integers."""
    wk = max(smooth[k] - 0.2 * peak[i], 0.0)
    return wk, np.float64(cols[k] - origin[i, 0]), np.float64(rows[k] - origin[i, 1])


@njit(**_JIT)
def peak_moments(lab, smooth, cols, rows, peak, origin, n):  # pragma: no cover
    """``first`` and ``second`` as :func:`segmented_pixels` gives them, of the part of each
    segment above 0.2 x its peak, offsets from ``origin`` (:func:`_above_peak`), made pixel by
    pixel (no pixel-sized temporaries)."""
    first = np.zeros((n, 3))
    second = np.zeros((n, 3))
    for k in range(lab.size):
        i = lab[k]
        wk, xk, yk = _above_peak(k, i, lab, smooth, cols, rows, peak, origin)
        _accumulate(first, second, i, wk, xk, yk)
    return first, second


@njit(**_JIT)
def peak_axis_moments(lab, smooth, cols, rows, peak, origin, mean, cos, sin,
                      n):  # pragma: no cover
    """Per label (n,): sums of ``w p^2`` and ``w p^4`` with ``p = (x - mean_x) cos + (y -
    mean_y) sin`` the offset along the label's axis, over the part of each segment above 0.2 x
    its peak (weights ``w`` and offsets ``(x, y)`` as :func:`peak_moments`)."""
    m2 = np.zeros(n)
    m4 = np.zeros(n)
    for k in range(lab.size):
        i = lab[k]
        wk, xk, yk = _above_peak(k, i, lab, smooth, cols, rows, peak, origin)
        p = (xk - mean[i, 0]) * cos[i] + (yk - mean[i, 1]) * sin[i]
        p2 = p * p
        m2[i] += wk * p2
        m4[i] += wk * (p2 * p2)
    return m2, m4


@njit(inline="always", **_JIT)
def _kept(img, lab, spot_of, spot, col):  # pragma: no cover
    """Pixel ``col`` of a row ``img`` of the raw image, 0 where ``lab`` marks another kept
    segment than ``spot``."""
    o = spot_of[lab[col]]
    return img[col] if o < 0 or o == spot else 0.0


@njit(inline="always", **_JIT)
def _weigh_row(img, lab, spot_of, spot, col0, hx, out, j0, e0, right, left, decay,
               fy):  # pragma: no cover
    """One row of :func:`_weigh`: the raw pixels (of row ``img``, labels ``lab``) times the
    window, walking out from column ``j0`` where the window is ``e0``; ``right`` and ``left``
    are the ratios of the weights next to it to ``e0``, and each step further multiplies the
    ratio by ``decay``. Writes the row into ``out`` and returns its ``sum``, ``sum fx`` and
    ``sum fy``."""
    tot, mx, my = 0.0, 0.0, 0.0
    e = e0
    for fx in range(j0, hx + 1):
        v = e * _kept(img, lab, spot_of, spot, col0 + fx + hx)
        out[fx + hx] = v
        tot += v
        mx += v * fx
        my += v * fy
        e *= right
        right *= decay
    e = e0 * left
    for fx in range(j0 - 1, -hx - 1, -1):
        v = e * _kept(img, lab, spot_of, spot, col0 + fx + hx)
        out[fx + hx] = v
        tot += v
        mx += v * fx
        my += v * fy
        left *= decay
        e *= left
    return tot, mx, my


# Largest |exponent| the row recurrences of _weigh start from: exp(-0.5 x 1200) is far inside
# float64, so no row's first weight underflows and no ratio overflows.
_MAX_EXPONENT = 1200.0


@njit(**_JIT)
def _weigh(padded, labels, spot_of, spot, row0, col0, box, hx, hy, a, b, c, sx, sy,
           decay):  # pragma: no cover
    """Write the raw box of spot ``spot`` (2 hy + 1, 2 hx + 1), rows from ``row0`` and columns
    from ``col0`` of ``padded`` (pixels of the other kept segments blanked: see
    :func:`centroid_chunk`), times the window ``w = exp(-q / 2)``, ``q = (f - s)^T [[a, b],
    [b, c]] (f - s)`` of pixel offsets ``f = (fx, fy)`` from the box's centre, into ``box``,
    and return its ``sum``, ``sum fx`` and ``sum fy``.

    No exponential per pixel (``decay = exp(-a)``): each row walks out from the window's
    centre column, its weight there and the ratios to the next pixels passed from row to row
    by constant factors (seven exponentials per box, to ~1e-14 relative). A window so
    elongated that a row's start would leave float64's range walks each row out from its own
    maximum instead, with three exponentials per row.
    """
    tot, mx, my = 0.0, 0.0, 0.0
    js = min(max(int(math.floor(sx + 0.5)), -hx), hx)
    dx = js - sx
    top, bottom = -hy - sy, hy - sy  # the first and last rows' offsets
    # q at column js, and the exponents of the right and left ratios there, on the first and
    # last rows (all linear or convex in the row: these bound every row's).
    q_top = a * dx * dx + 2.0 * b * dx * top + c * top * top
    q_bottom = a * dx * dx + 2.0 * b * dx * bottom + c * bottom * bottom
    r_top, r_bottom = a * (2.0 * dx + 1.0) + 2.0 * b * top, a * (2.0 * dx + 1.0) + 2.0 * b * bottom
    l_top, l_bottom = a * (1.0 - 2.0 * dx) - 2.0 * b * top, a * (1.0 - 2.0 * dx) - 2.0 * b * bottom
    if max(q_top, q_bottom, abs(r_top), abs(r_bottom), abs(l_top), abs(l_bottom)) < _MAX_EXPONENT:
        e0 = math.exp(-0.5 * q_top)
        down = math.exp(-0.5 * (2.0 * b * dx + c * (2.0 * top + 1.0)))  # e0's next-row factor
        down_step = math.exp(-c)
        right, left = math.exp(-0.5 * r_top), math.exp(-0.5 * l_top)
        right_step, left_step = math.exp(-b), math.exp(b)
        for row in range(2 * hy + 1):
            t, x, y = _weigh_row(padded[row0 + row], labels[row0 + row], spot_of, spot, col0,
                                 hx, box[row], js, e0, right, left, decay, row - hy)
            tot += t
            mx += x
            my += y
            e0 *= down
            down *= down_step
            right *= right_step
            left *= left_step
        return tot, mx, my
    for row in range(2 * hy + 1):
        fy = row - hy
        dy = fy - sy
        # The row's maximum, q'(fx) = 0: fx = sx - b dy / a.
        j0 = min(max(int(math.floor(sx - b * dy / a + 0.5)), -hx), hx)
        dx = j0 - sx
        e0 = math.exp(-0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy))
        right = math.exp(-0.5 * (a * (2.0 * dx + 1.0) + 2.0 * b * dy))
        left = math.exp(-0.5 * (a * (1.0 - 2.0 * dx) - 2.0 * b * dy))
        t, x, y = _weigh_row(padded[row0 + row], labels[row0 + row], spot_of, spot, col0, hx,
                             box[row], j0, e0, right, left, decay, fy)
        tot += t
        mx += x
        my += y
    return tot, mx, my


@njit(**_JIT, fastmath={"reassoc", "contract"})
def _shifted_sums(box, hx, hy, ux, uy, ex):  # pragma: no cover
    """``sum``, ``sum fx`` and ``sum fy`` of ``box`` (2 hy + 1, 2 hx + 1) times ``exp(ux fx +
    uy fy)``: a window written by :func:`_weigh` moved by ``d``, with ``u = A d``, up to a
    constant factor (``q(f - s - d) = q(f - s) - 2 (f - s)^T A d + q(d)``). The factor is
    separable, so a pixel costs two multiply-adds; its values come by products from the
    centre column out and from row to row (``|ux| hx`` and ``|uy| hy`` stay under 600: see
    :func:`centroid_chunk`). ``ex`` (2 hx + 1) is scratch space."""
    step = math.exp(ux)
    back = 1.0 / step
    ex[hx] = 1.0
    for k in range(1, hx + 1):
        ex[hx + k] = ex[hx + k - 1] * step
        ex[hx - k] = ex[hx - k + 1] * back
    g, g_step = math.exp(-uy * hy), math.exp(uy)  # exp(uy fy), from fy = -hy
    tot, mx, my = 0.0, 0.0, 0.0
    for row in range(2 * hy + 1):
        s0, s1 = 0.0, 0.0
        for j in range(2 * hx + 1):
            v = box[row, j] * ex[j]
            s0 += v
            s1 += v * (j - hx)
        fy = row - hy
        tot += g * s0
        mx += g * s1
        my += g * fy * s0
        g *= g_step
    return tot, mx, my


@njit(**_JIT)
def centroid_chunk(chunk, n_chunks, padded, labels, pad, spot_of, base, half, inv_win, start,
                   gain, n_iter, out):  # pragma: no cover
    """Gaussian-windowed centroids of spots ``chunk, chunk + n_chunks, ...`` of P into ``out``
    (P, 2) px; see :func:`restoration.features.detect._refine_centres` for the method. The
    spots are independent: any thread may run any chunk.

    The first step weighs the box once (:func:`_weigh`); the later ones move that window by a
    separable factor (:func:`_shifted_sums`) while it has moved at most a pixel along each
    axis and neither factor's exponent can pass 600 (well inside float64), and weigh it afresh
    otherwise.

    Parameters
    ----------
    chunk, n_chunks : int
        This chunk, and how many there are.
    padded : (H + 2 pad, W + 2 pad) ndarray of float32
        The raw image in a frame of zeros.
    labels : (H + 2 pad, W + 2 pad) ndarray of int32
        The segment label of each pixel of ``padded`` (0: none, and in the frame).
    pad : int
        Frame width, px (at least the largest half width).
    spot_of : (n,) ndarray of int
        The spot of each label (-1: not a kept segment).
    base, half : (P, 2) ndarray of int
        Box centre ``(col, row)`` and half widths ``(hx, hy)`` of each spot, px.
    inv_win : (P, 3) ndarray
        The window's inverse covariance ``a, b, c`` (``[[a, b], [b, c]]``), 1/px^2.
    start : (P, 2) ndarray
        First centres, px.
    gain : float
        Step gain ``1 + 1 / k^2``.
    n_iter : int
        Window steps.
    out : (P, 2) ndarray
        Out: the centres, px.
    """
    box = np.empty((2 * pad + 1, 2 * pad + 1))
    ex = np.empty(2 * pad + 1)
    for s in range(chunk, start.shape[0], n_chunks):
        hx, hy = half[s, 0], half[s, 1]
        bx, by = base[s, 0], base[s, 1]
        # The raw image around the spot, the other kept segments blanked, read by _weigh.
        top, left = by - hy + pad, bx - hx + pad
        a, b, c = inv_win[s, 0], inv_win[s, 1], inv_win[s, 2]
        decay = math.exp(-a)
        sx, sy = start[s, 0] - bx, start[s, 1] - by
        wx, wy = sx, sy  # where the weighed box's window is centred
        for k in range(n_iter):
            dx, dy = sx - wx, sy - wy
            ux, uy = a * dx + b * dy, b * dx + c * dy
            if k == 0 or abs(dx) > 1.0 or abs(dy) > 1.0 or max(abs(ux) * hx, abs(uy) * hy) > 600.0:
                tot, mx, my = _weigh(padded, labels, spot_of, s, top, left, box, hx, hy, a, b,
                                     c, sx, sy, decay)
                wx, wy = sx, sy
            else:
                tot, mx, my = _shifted_sums(box, hx, hy, ux, uy, ex)
            if tot > 0.0:
                # A step longer than a pixel means noise dominates the window.
                sx += min(max(gain * (mx / tot - sx), -1.0), 1.0)
                sy += min(max(gain * (my / tot - sy), -1.0), 1.0)
        out[s, 0], out[s, 1] = sx + bx, sy + by
