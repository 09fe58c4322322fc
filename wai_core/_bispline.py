"""A bicubic tensor-product B-spline's value and first derivatives in one compiled pass.

FITPACK's ``bispeu`` (behind ``RectBivariateSpline.ev``) evaluates one quantity per call, so a
ray's Newton step on a surface costs three calls (height and both slopes), each recomputing
the knot spans and basis functions. Here the span is searched once per point and the four
cubic basis functions and their derivatives along each axis (Cox-de Boor, as in Piegl &
Tiller's *The NURBS Book*, algorithms A2.1-A2.3) give all three sums. The values agree with
FITPACK's to rounding (``tests/wai_core/test_heightfield.py``).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

_DEGREE = 3


@numba.njit(cache=True, nogil=True)
def _span(knots: NDArray, n_coef: int, u: float) -> int:
    """The knot interval ``[knots[s], knots[s + 1])`` holding ``u`` (the last one holds the end)."""
    lo, hi = _DEGREE, n_coef
    if u >= knots[n_coef]:
        return n_coef - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if u < knots[mid]:
            hi = mid
        else:
            lo = mid
    return lo


@numba.njit(cache=True, nogil=True)
def _basis(knots: NDArray, s: int, u: float, value: NDArray, slope: NDArray,
           scratch: NDArray) -> None:
    """The four nonzero cubic basis functions at ``u`` in span ``s`` into ``value``, their
    derivatives into ``slope``; ``scratch`` (4, 4) holds the recursion's terms."""
    left, right, n, lower = scratch[0], scratch[1], scratch[2], scratch[3]
    n[0] = 1.0
    for j in range(1, _DEGREE + 1):
        left[j] = u - knots[s + 1 - j]
        right[j] = knots[s + j] - u
        saved = 0.0
        for r in range(j):
            temp = n[r] / (right[r + 1] + left[j - r])
            n[r] = saved + right[r + 1] * temp
            saved = left[j - r] * temp
        n[j] = saved
        if j == _DEGREE - 1:  # the quadratic basis, whose differences are the slopes
            for r in range(_DEGREE):
                lower[r] = n[r]
    for r in range(_DEGREE + 1):
        value[r] = n[r]
        i = s - _DEGREE + r  # the basis function's index
        d = 0.0
        if r >= 1:
            d += lower[r - 1] / (knots[i + _DEGREE] - knots[i])
        if r <= _DEGREE - 1:
            d -= lower[r] / (knots[i + _DEGREE + 1] - knots[i + 1])
        slope[r] = _DEGREE * d


@numba.njit(cache=True, nogil=True)
def height_gradient(
    ty: NDArray, tx: NDArray, coef: NDArray, y: NDArray, x: NDArray,
    h: NDArray, gx: NDArray, gy: NDArray,
) -> None:
    """Fill ``h``, ``gx`` = dh/dx and ``gy`` = dh/dy at the points ``(x, y)`` (all (N,)) of the
    spline with knots ``ty`` (first axis), ``tx`` (second axis) and coefficients ``coef``
    (len(ty) - 4, len(tx) - 4): ``RectBivariateSpline(y, x, z).tck`` reshaped."""
    ny, nx = coef.shape
    by, dby = np.empty(4), np.empty(4)
    bx, dbx = np.empty(4), np.empty(4)
    scratch = np.zeros((4, 4))
    for k in range(x.size):
        sy = _span(ty, ny, y[k])
        sx = _span(tx, nx, x[k])
        _basis(ty, sy, y[k], by, dby, scratch)
        _basis(tx, sx, x[k], bx, dbx, scratch)
        v = 0.0
        vx = 0.0
        vy = 0.0
        for a in range(4):
            row = coef[sy - _DEGREE + a]
            cx = 0.0
            cdx = 0.0
            for b in range(4):
                c = row[sx - _DEGREE + b]
                cx += c * bx[b]
                cdx += c * dbx[b]
            v += by[a] * cx
            vx += by[a] * cdx
            vy += dby[a] * cx
        h[k] = v
        gx[k] = vx
        gy[k] = vy
