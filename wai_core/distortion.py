"""Brown-Conrady lens distortion as OpenCV defines it: the map, its Jacobian, its inverse and
where it stops being one to one.

An undistorted normalised point ``(x, y) = (X / Z, Y / Z)`` (``cam`` frame) maps to the
distorted ``(x_d, y_d)`` by ``(k1, k2, p1, p2, k3)`` (:func:`distort`; the formula in
:mod:`wai_core.lens`). The maps are written in arithmetic that works on NumPy arrays and on
Dr.Jit arrays alike, so the renderer (:mod:`mitsuba_wai.lens`) and the restoration share them;
:class:`wai_core.lens.DeviceOptics` puts them together with the principal point and a port.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

__all__ = [
    "NEWTON_STEPS",
    "distort",
    "distortion_fold_r2",
    "distortion_jacobian",
    "distortion_one_to_one",
    "undistort",
]

# Newton steps of the iterative inversions in float64 (both converge quadratically from their
# starting points; 12 steps reach machine precision for any distortion that stays invertible).
NEWTON_STEPS = 12


def distort(x: Any, y: Any, k: tuple[float, ...]) -> tuple[Any, Any]:
    """Brown-Conrady distortion of undistorted normalised points (OpenCV's definition).

    Parameters
    ----------
    x, y : array (NumPy or Dr.Jit), (...,)
        Undistorted normalised coordinates ``X / Z``, ``Y / Z`` (``cam`` frame).
    k : (5,) tuple of float
        ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    x_d, y_d : array, (...,)
        Distorted normalised coordinates (the image point minus the principal point, over the
        focal length in pixels).
    """
    k1, k2, p1, p2, k3 = k
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = x * y
    return (x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy)


def distortion_jacobian(x: Any, y: Any, k: tuple[float, ...]) -> tuple[Any, Any, Any]:
    """Jacobian of :func:`distort`: ``(dx_d/dx, dx_d/dy = dy_d/dx, dy_d/dy)``, (...,) each
    (the map's Jacobian is symmetric)."""
    k1, k2, p1, p2, k3 = k
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    q = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))  # d(radial)/d(r^2), doubled
    a = radial + q * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    b = q * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + q * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, d


@lru_cache(maxsize=64)
def distortion_fold_r2(k: tuple[float, ...]) -> float:
    """The squared undistorted radius ``r^2`` at which the radial distortion folds, inf where it
    never does.

    The radial map ``r_d = r (1 + k_1 r^2 + k_2 r^4 + k_3 r^6)`` grows with ``r`` up to the
    first positive root of ``d r_d / d r = 1 + 3 k_1 r^2 + 5 k_2 r^4 + 7 k_3 r^6``; past it the
    model bends back (barrel distortion, ``k_1 < 0``: at ``r^2 = 1 / (3 |k_1|)``) and, past
    ``1 + k_1 r^2 + ... = 0``, crosses to the image's other side with a positive Jacobian again.
    A real lens is the model up to the fold only: rays beyond it are not the lens's.

    Parameters
    ----------
    k : (5,) tuple of float
        ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    float
        ``r^2`` of the fold (``x^2 + y^2`` in normalised coordinates), or ``inf``.

    Examples
    --------
    >>> round(distortion_fold_r2((-0.05, 0.0, 0.0, 0.0, 0.0)), 4)  # 1 / (3 x 0.05)
    6.6667
    >>> distortion_fold_r2((0.1, 0.0, 0.0, 0.0, 0.0))
    inf
    """
    k1, k2, _, _, k3 = (float(v) for v in k)
    roots = np.roots(np.trim_zeros([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0], "f"))
    real = roots[(np.abs(roots.imag) < 1e-12) & (roots.real > 0)].real
    return float(real.min()) if real.size else float("inf")


def distortion_one_to_one(x: Any, y: Any, k: tuple[float, ...]) -> Any:
    """Where the distortion maps undistorted normalised points one to one onto the image:
    inside the fold (:func:`distortion_fold_r2`) and with a positive Jacobian
    (:func:`distortion_jacobian`; the tangential terms can fold it first).

    Parameters
    ----------
    x, y : array (NumPy or Dr.Jit), (...,)
        Undistorted normalised coordinates.
    k : (5,) tuple of float
        ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    array of bool, (...,)

    Examples
    --------
    >>> k = (-0.05, 0.0, 0.0, 0.0, 0.0)
    >>> distortion_one_to_one(np.array([2.0, 3.0, 5.0]), np.zeros(3), k)  # fold at r = 2.58
    array([ True, False, False])
    """
    a, b, d = distortion_jacobian(x, y, k)
    return (x * x + y * y < distortion_fold_r2(tuple(k))) & (a * d - b * b > 0.0)


def undistort(
    x_d: Any, y_d: Any, k: tuple[float, ...], steps: int = NEWTON_STEPS
) -> tuple[Any, Any]:
    """Invert :func:`distort` by Newton's method from ``(x_d, y_d)``.

    Parameters
    ----------
    x_d, y_d : array (NumPy or Dr.Jit), (...,)
        Distorted normalised coordinates.
    k : (5,) tuple of float
        ``(k1, k2, p1, p2, k3)``.
    steps : int
        Newton steps (a fixed count: the same work for every point, as a kernel needs).

    Returns
    -------
    x, y : array, (...,)
        Undistorted normalised coordinates; where the map is not invertible they do not
        satisfy ``distort(x, y) == (x_d, y_d)`` (callers check the residual).
    """
    x, y = x_d, y_d
    for _ in range(steps):
        fx, fy = distort(x, y, k)
        fx, fy = fx - x_d, fy - y_d
        a, b, d = distortion_jacobian(x, y, k)
        inv_det = 1.0 / (a * d - b * b)
        x = x - (d * fx - b * fy) * inv_det
        y = y - (a * fy - b * fx) * inv_det
    return x, y
