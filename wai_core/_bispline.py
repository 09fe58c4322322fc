"""A bicubic tensor-product B-spline's value and first derivatives in one compiled pass.

FITPACK's ``bispeu`` (behind ``RectBivariateSpline.ev``) evaluates one quantity per call, so a
ray's Newton step on a surface costs three calls (height and both slopes), each recomputing
the knot spans and basis functions. Here the span is found once per point (a lookup table,
:func:`span_table`) and the four cubic basis functions and their derivatives along each axis
give all three sums: on evenly spaced knots (every span of a gridded surface but the ends')
the uniform cubic B-spline's closed form, elsewhere Cox-de Boor's recursion (Piegl & Tiller,
*The NURBS Book*, algorithms A2.1-A2.3). The values agree with FITPACK's to rounding
(``tests/wai_core/test_heightfield.py``). :func:`intersect_rays` runs each ray's Newton steps
to the surface with the evaluations in place.

The helpers are inlined into the two kernels: a call between compiled functions that pass
arrays costs reference-count updates that, per point, took longer than the arithmetic.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["height_gradient", "intersect_rays", "span_table", "uniform_spans"]

_DEGREE = 3
_kernel = numba.njit(cache=True, nogil=True, error_model="numpy")
_inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")


def span_table(knots: NDArray) -> NDArray[np.int64]:
    """A lookup from the knots' range cut in ``m`` equal cells (none wider than the narrowest
    span) to the span holding each cell's start, for :func:`_span_of`.

    Examples
    --------
    >>> import numpy as np
    >>> knots = np.r_[0.0, 0.0, 0.0, 0.0, 2.0, 3.0, 4.0, 4.0, 4.0, 4.0]
    >>> span_table(knots).tolist()
    [3, 3, 4, 5, 5]
    """
    n_coef = knots.size - _DEGREE - 1
    lo, hi = knots[_DEGREE], knots[n_coef]
    gaps = np.diff(knots[_DEGREE:n_coef + 1])
    # Cells as wide as the narrowest span (less its rounding): on evenly spaced knots the
    # cells are the spans, and the lookup needs no correcting step.
    m = int(np.ceil((hi - lo) / gaps[gaps > 0].min() - 1e-6)) + 1
    starts = lo + (hi - lo) * np.arange(m) / (m - 1)
    spans = np.searchsorted(knots[:n_coef], starts, side="right") - 1
    return np.clip(spans, _DEGREE, n_coef - 1).astype(np.int64)


def uniform_spans(knots: NDArray) -> NDArray[np.bool_]:
    """For each knot span ``s``, True when the six knots its cubic basis reads
    (``knots[s - 2 : s + 4]``) are evenly spaced: there the basis has a closed form."""
    gaps = np.diff(knots)
    out = np.zeros(knots.size, dtype=np.bool_)
    s = np.arange(_DEGREE, knots.size - _DEGREE - 1)
    window = gaps[s[:, None] + np.arange(-2, 3)]  # the five gaps of span s's six knots
    first = window[:, :1]
    out[s] = (first[:, 0] > 0) & np.all(np.abs(window - first) <= 1e-9 * first, axis=1)
    return out


@_inline
def _span_of(knots: NDArray, table: NDArray, n_coef: int, u: float) -> int:
    """The knot span ``s`` with ``knots[s] <= u < knots[s + 1]`` (the last span holds the
    end; points outside the knots take the end spans): the table's cell, then at most a
    step either way."""
    lo, hi = knots[_DEGREE], knots[n_coef]
    m = table.size
    j = int((u - lo) * ((m - 1) / (hi - lo)))
    s = table[min(max(j, 0), m - 1)]
    while s < n_coef - 1 and u >= knots[s + 1]:
        s += 1
    while s > _DEGREE and u < knots[s]:
        s -= 1
    return s


@_inline
def _basis(knots: NDArray, uniform: NDArray, s: int, u: float,
           scratch: NDArray) -> tuple[float, float, float, float, float, float, float, float]:
    """The four nonzero cubic basis functions at ``u`` in span ``s`` and their derivatives
    (1/mm); ``scratch`` (5, 4) holds the recursion's terms where the knots are uneven."""
    if uniform[s]:
        inv = 1.0 / (knots[s + 1] - knots[s])
        tau = (u - knots[s]) * inv
        om = 1.0 - tau
        t2 = tau * tau
        t3 = t2 * tau
        sixth = 1.0 / 6.0
        return (om * om * om * sixth, (3.0 * t3 - 6.0 * t2 + 4.0) * sixth,
                (-3.0 * t3 + 3.0 * t2 + 3.0 * tau + 1.0) * sixth, t3 * sixth,
                -0.5 * om * om * inv, (1.5 * t2 - 2.0 * tau) * inv,
                (-1.5 * t2 + tau + 0.5) * inv, 0.5 * t2 * inv)
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
    d = scratch[4]
    for r in range(_DEGREE + 1):
        i = s - _DEGREE + r  # the basis function's index
        d[r] = 0.0
        if r >= 1:
            d[r] += lower[r - 1] / (knots[i + _DEGREE] - knots[i])
        if r <= _DEGREE - 1:
            d[r] -= lower[r] / (knots[i + _DEGREE + 1] - knots[i + 1])
    return (n[0], n[1], n[2], n[3],
            _DEGREE * d[0], _DEGREE * d[1], _DEGREE * d[2], _DEGREE * d[3])


@_inline
def _eval_point(ty: NDArray, tx: NDArray, uy: NDArray, ux: NDArray, ly: NDArray, lx: NDArray,
                coef: NDArray, y: float, x: float,
                scratch: NDArray) -> tuple[float, float, float]:
    """The spline's height and slopes ``(d/dx, d/dy)`` at one point ``(x, y)``."""
    ny, nx = coef.shape
    sy = _span_of(ty, ly, ny, y)
    sx = _span_of(tx, lx, nx, x)
    by0, by1, by2, by3, dy0, dy1, dy2, dy3 = _basis(ty, uy, sy, y, scratch)
    bx0, bx1, bx2, bx3, dx0, dx1, dx2, dx3 = _basis(tx, ux, sx, x, scratch)
    # The 4 x 4 sums written out: the products and their order of a loop over the rows,
    # which, indexing tuples of the basis, compiles 7 % slower.
    r, c = sy - _DEGREE, sx - _DEGREE
    c00, c01, c02, c03 = coef[r, c], coef[r, c + 1], coef[r, c + 2], coef[r, c + 3]
    c10, c11, c12, c13 = coef[r + 1, c], coef[r + 1, c + 1], coef[r + 1, c + 2], coef[r + 1, c + 3]
    c20, c21, c22, c23 = coef[r + 2, c], coef[r + 2, c + 1], coef[r + 2, c + 2], coef[r + 2, c + 3]
    c30, c31, c32, c33 = coef[r + 3, c], coef[r + 3, c + 1], coef[r + 3, c + 2], coef[r + 3, c + 3]
    cx0 = c00 * bx0 + c01 * bx1 + c02 * bx2 + c03 * bx3
    cx1 = c10 * bx0 + c11 * bx1 + c12 * bx2 + c13 * bx3
    cx2 = c20 * bx0 + c21 * bx1 + c22 * bx2 + c23 * bx3
    cx3 = c30 * bx0 + c31 * bx1 + c32 * bx2 + c33 * bx3
    cd0 = c00 * dx0 + c01 * dx1 + c02 * dx2 + c03 * dx3
    cd1 = c10 * dx0 + c11 * dx1 + c12 * dx2 + c13 * dx3
    cd2 = c20 * dx0 + c21 * dx1 + c22 * dx2 + c23 * dx3
    cd3 = c30 * dx0 + c31 * dx1 + c32 * dx2 + c33 * dx3
    v = by0 * cx0 + by1 * cx1 + by2 * cx2 + by3 * cx3
    vx = by0 * cd0 + by1 * cd1 + by2 * cd2 + by3 * cd3
    vy = dy0 * cx0 + dy1 * cx1 + dy2 * cx2 + dy3 * cx3
    return v, vx, vy


@_kernel
def height_gradient(
    ty: NDArray, tx: NDArray, uy: NDArray, ux: NDArray, ly: NDArray, lx: NDArray,
    coef: NDArray, y: NDArray, x: NDArray, h: NDArray, gx: NDArray, gy: NDArray,
) -> None:
    """Fill ``h``, ``gx`` = dh/dx and ``gy`` = dh/dy at the points ``(x, y)`` (all (N,)) of the
    spline with knots ``ty`` (first axis), ``tx`` (second axis) and coefficients ``coef``
    (len(ty) - 4, len(tx) - 4): ``RectBivariateSpline(y, x, z).tck`` reshaped; ``uy``, ``ux``
    are :func:`uniform_spans` of the knots and ``ly``, ``lx`` their :func:`span_table`."""
    scratch = np.zeros((5, 4))
    for k in range(x.size):
        h[k], gx[k], gy[k] = _eval_point(ty, tx, uy, ux, ly, lx, coef, y[k], x[k], scratch)


# A hit's height residual, mm, below which Newton's steps stop: the next step would move it by
# the square of this, far below the float64 rounding of lab coordinates in mm.
_CONVERGED_MM = 1e-9


@_kernel
def intersect_rays(
    ty: NDArray, tx: NDArray, uy: NDArray, ux: NDArray, ly: NDArray, lx: NDArray,
    coef: NDArray, origins: NDArray, dirs: NDArray, z_ref: float, n_iter: int, tol: float,
    points: NDArray, normals: NDArray, valid: NDArray,
) -> None:
    """Newton's steps on ``f(t) = o_z + t d_z - z(o + t d)`` for each ray (the spline as
    :func:`height_gradient`'s), at most ``n_iter`` and none once ``|f|`` is below
    :data:`_CONVERGED_MM`: ``points`` (N, 3) and unit ``normals`` (N, 3) at the hits, ``valid``
    (N,) where ``|f| < tol`` mm and ``t > 0``. ``origins`` is (N, 3) or (1, 3); ``dirs`` (N, 3).
    A ray that leaves the knots' rectangle at any step is invalid (NaN).

    A ray starts from the plane ``z = z_ref``; with one origin for all (a camera's pixels in
    order), from the previous ray's hit distance when that one converged, and again from the
    plane if that start does not converge."""
    x_lo, x_hi, y_lo, y_hi = tx[0], tx[-1], ty[0], ty[-1]
    scratch = np.zeros((5, 4))
    one_origin = origins.shape[0] == 1
    nan = np.nan
    t_last = nan
    for k in range(dirs.shape[0]):
        j = 0 if one_origin else k
        ox, oy, oz = origins[j, 0], origins[j, 1], origins[j, 2]
        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        h = gx = gy = 0.0
        px = py = pz = t = nan
        ok = False
        warm = one_origin and t_last == t_last  # the previous ray converged
        for attempt in range(2):
            if attempt == 0 and not warm:
                continue
            t = t_last if attempt == 0 else (z_ref - oz) / dz if dz != 0.0 else nan
            ok = False
            for step in range(n_iter + 1):
                px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
                if not (x_lo <= px <= x_hi and y_lo <= py <= y_hi):
                    break
                h, gx, gy = _eval_point(ty, tx, uy, ux, ly, lx, coef, py, px, scratch)
                f = pz - h
                if abs(f) < _CONVERGED_MM or step == n_iter:
                    ok = abs(f) < tol and t > 0.0
                    break
                t -= f / (dz - gx * dx - gy * dy)
            if ok:
                break
        if ok:
            points[k, 0], points[k, 1], points[k, 2] = px, py, pz
            norm = np.sqrt(gx * gx + gy * gy + 1.0)
            normals[k, 0], normals[k, 1], normals[k, 2] = -gx / norm, -gy / norm, 1.0 / norm
            t_last = t
        else:
            for c in range(3):
                points[k, c] = nan
                normals[k, c] = nan
            t_last = nan
        valid[k] = ok
