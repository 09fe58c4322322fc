"""Height steps along lattice edges from the slopes at the samples: the rules that turn the
slopes at a dot and at its lattice neighbours into the height difference across an edge.

The trapezoid rule averages the slopes at an edge's two ends; its error is ``L^3 h_3 / 12``
along an edge of length ``L`` (``h_3`` the third derivative along it). Small as it is (~2 um
rms on the paper's rig at U = 1 m/s), it is systematic, and the level search
(:mod:`restoration.anchor`) amplifies it: the residual's valley along the level is so flat that
a ~2 um bias in the steps moves its minimum by ~0.1 mm. The fourth-order rule also reads the
samples before and after the edge on the same lattice line, interpolates the slope along the
edge by the cubic through the four, and integrates that exactly (:func:`edge_step`): ~0.13 um
rms there, and the level follows (docs/results.md, "Accuracy").
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

__all__ = ["edge_step", "edge_steps"]

_GAUSS_LO = 0.5 - 0.5 / np.sqrt(3.0)
_GAUSS_HI = 0.5 + 0.5 / np.sqrt(3.0)


@njit(cache=True, nogil=True, inline="always")
def _mean_of_cubic(t0, t1, t2, t3, g0, g1, g2, g3):  # pragma: no cover
    """Mean over [0, 1] of the cubic through ``(t_k, g_k)``: two-point Gauss-Legendre, exact
    for it."""
    total = 0.0
    for tau in (_GAUSS_LO, _GAUSS_HI):
        total += (
            g0 * (tau - t1) * (tau - t2) * (tau - t3) / ((t0 - t1) * (t0 - t2) * (t0 - t3))
            + g1 * (tau - t0) * (tau - t2) * (tau - t3) / ((t1 - t0) * (t1 - t2) * (t1 - t3))
            + g2 * (tau - t0) * (tau - t1) * (tau - t3) / ((t2 - t0) * (t2 - t1) * (t2 - t3))
            + g3 * (tau - t0) * (tau - t1) * (tau - t2) / ((t3 - t0) * (t3 - t1) * (t3 - t2))
        )
    return 0.5 * total


@njit(cache=True, nogil=True, inline="always")
def _mean_of_quadratic(t0, t1, t2, g0, g1, g2):  # pragma: no cover
    """Mean over [0, 1] of the parabola through ``(t_k, g_k)`` (Gauss-Legendre, exact)."""
    total = 0.0
    for tau in (_GAUSS_LO, _GAUSS_HI):
        total += (
            g0 * (tau - t1) * (tau - t2) / ((t0 - t1) * (t0 - t2))
            + g1 * (tau - t0) * (tau - t2) / ((t1 - t0) * (t1 - t2))
            + g2 * (tau - t0) * (tau - t1) / ((t2 - t0) * (t2 - t1))
        )
    return 0.5 * total


@njit(cache=True, nogil=True, inline="always")
def _on_line(xy, slopes, k, i, dx, dy, d2, hx, hy):  # pragma: no cover
    """Position ``t`` of sample ``k`` projected on the edge from ``i`` (in edge lengths) and
    the slope along the edge there: ``slopes[k] . d`` less what the sample's offset ``u``
    across the edge adds, ``u . (H d)``, with ``H d = (hx, hy)`` the change of the slope
    vector along the edge (exact for quadratic heights, whose Hessian ``H`` is constant)."""
    ox = xy[k, 0] - xy[i, 0]
    oy = xy[k, 1] - xy[i, 1]
    t = (ox * dx + oy * dy) / d2
    g = slopes[k, 0] * dx + slopes[k, 1] * dy - ((ox - t * dx) * hx + (oy - t * dy) * hy)
    return t, g


@njit(cache=True, nogil=True, inline="always")
def edge_step(xy, slopes, p, i, j, n):  # pragma: no cover
    """Height difference ``h[j] - h[i]`` (mm) along the straight edge ``i -> j`` from the
    slopes at the samples ``xy`` (K, 2) mm.

    The slope along the edge is interpolated through its ends and the samples ``p`` (before
    ``i``) and ``n`` (after ``j``) on the same lattice line (-1: absent), placed at their
    projections on the edge (their slopes corrected for their offset across it, see
    :func:`_on_line`), and integrated exactly. Both absent: the trapezoid rule, the same
    arithmetic. One: exact for cubic heights along a straight line. Both: exact for quartic
    ones (``(-g_p + 13 g_i + 13 g_j - g_n) / 24`` on even spacing). Every case is exact for
    quadratic surfaces on any irregular samples. A neighbour that does not lie beyond its end
    of the edge by a quarter of it is not used.
    """
    dx = xy[j, 0] - xy[i, 0]
    dy = xy[j, 1] - xy[i, 1]
    d2 = dx * dx + dy * dy
    hx = slopes[j, 0] - slopes[i, 0]
    hy = slopes[j, 1] - slopes[i, 1]
    tp, gp, tn, gn = 0.0, 0.0, 0.0, 0.0
    if p >= 0:
        tp, gp = _on_line(xy, slopes, p, i, dx, dy, d2, hx, hy)
    if n >= 0:
        tn, gn = _on_line(xy, slopes, n, i, dx, dy, d2, hx, hy)
    use_p, use_n = p >= 0 and tp < -0.25, n >= 0 and tn > 1.25
    if not (use_p or use_n):
        gx = 0.5 * (slopes[i, 0] + slopes[j, 0])
        gy = 0.5 * (slopes[i, 1] + slopes[j, 1])
        return gx * dx + gy * dy
    gi = slopes[i, 0] * dx + slopes[i, 1] * dy
    gj = slopes[j, 0] * dx + slopes[j, 1] * dy
    if use_p and use_n:
        return _mean_of_cubic(tp, 0.0, 1.0, tn, gp, gi, gj, gn)
    if use_p:
        return _mean_of_quadratic(tp, 0.0, 1.0, gp, gi, gj)
    return _mean_of_quadratic(0.0, 1.0, tn, gi, gj, gn)


@njit(cache=True, nogil=True)
def _edge_steps_kernel(xy, slopes, a, b, before, after, out):  # pragma: no cover
    for e in range(a.size):
        out[e] = edge_step(xy, slopes, before[e], a[e], b[e], after[e])


def edge_steps(
    xy_mm: NDArray[np.float64], slopes: NDArray[np.float64], a: NDArray[np.int64],
    b: NDArray[np.int64], before: NDArray[np.int64], after: NDArray[np.int64],
) -> NDArray[np.float64]:
    """Height steps (E,) mm along edges ``a -> b`` (E,) by :func:`edge_step`.

    Parameters
    ----------
    xy_mm : (K, 2) ndarray
        Sample positions, mm.
    slopes : (K, 2) ndarray
        ``(dz/dx, dz/dy)`` at the samples.
    a, b : (E,) ndarray of int
        Edge ends.
    before, after : (E,) ndarray of int
        The sample before ``a`` and the one after ``b`` on the edge's lattice line, -1 where
        none (:func:`restoration.integrate.lattice.line_neighbours`); all -1 gives the
        trapezoid rule.

    Returns
    -------
    (E,) ndarray
        ``h[b] - h[a]``, mm.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.arange(4.0)  # h = x^4 / 4, slope x^3: the rule is exact for it
    >>> xy = np.column_stack([x, 0 * x]); g = np.column_stack([x**3, 0 * x])
    >>> one = np.array([1]); step = edge_steps(xy, g, one, one + 1, one - 1, one + 2)
    >>> round(float(step[0]), 12), (2.0**4 - 1.0) / 4
    (3.75, 3.75)
    """
    out = np.empty(a.size)
    _edge_steps_kernel(
        np.ascontiguousarray(xy_mm, dtype=float), np.ascontiguousarray(slopes, dtype=float),
        a, b, before, after, out,
    )
    return out
