"""The integrator registry and dispatcher: every integrator shares one interface
(:data:`Integrator`) and is registered by name in :data:`INTEGRATORS`, so new ones can be added
and compared by name; :func:`integrate` runs the one named."""

from __future__ import annotations

from collections.abc import Callable

from numpy.typing import ArrayLike

from restoration.integrate._common import Array
from restoration.integrate.fourier import integrate_dct_poisson, integrate_frankot_chellappa
from restoration.integrate.lattice import (
    integrate_fourth_order,
    integrate_paper,
    integrate_trapezoid,
)
from restoration.integrate.plans import IntegrationPlans
from restoration.integrate.spline import integrate_spline
from wai_core.errors import WaiInputError

Integrator = Callable[[ArrayLike, ArrayLike, ArrayLike], Array]
"""The interface every integrator shares (the built-in ones also take an optional
``weight_xy_mm``, see :func:`integrate`):

``integrator(ij, xy_mm, slopes) -> heights_mm``

``ij`` (K, 2) int
    Grid index ``(i, j)`` of each sample (its dot in the pattern); 4-neighbours in ``(i, j)`` are
    neighbours on the surface. Missing nodes (undetected dots) are simply absent.
``xy_mm`` (K, 2) float
    Horizontal sample positions, mm (irregular: the projector's keystone plus the waves).
``slopes`` (K, 2) float
    ``(dz/dx, dz/dy)`` at the samples, dimensionless.
``heights_mm`` (K,) float
    Heights up to a constant, mm, with zero mean; NaN for samples that the integrator cannot tie
    to the others (outside the largest connected piece of the sample grid).
"""

INTEGRATORS: dict[str, Integrator] = {
    "fourth_order": integrate_fourth_order,
    "paper": integrate_paper,
    "trapezoid": integrate_trapezoid,
    "spline": integrate_spline,
    "frankot_chellappa": integrate_frankot_chellappa,
    "dct_poisson": integrate_dct_poisson,
}
"""Registered integrators by name; add an entry to make a new one selectable.

Integrators
-----------
``"paper"``
    Eq. 10-13: central differences on the ``(i, j)`` grid, one-sided at borders and holes, solved
    by least squares. Eq. 10 divides by ``x`` spacings, which assumes rows of samples run along
    ``x``; the projector's samples form a keystone, so each difference is taken along the actual
    displacement, ``h(c+) - h(c-) = g(c) . (xy(c+) - xy(c-))``, weighted to a residual in slope
    units as in eq. 13. On a rectilinear grid this is eq. 10 exactly.
``"trapezoid"``
    Least squares over the edges of the 4-neighbour graph with the trapezoid rule,
    ``h(b) - h(a) = (g(a) + g(b)) / 2 . (xy(b) - xy(a))``: exact for quadratic surfaces on any
    irregular grid, and free of the odd-even decoupling that central differences suffer.
``"fourth_order"`` (the default)
    The trapezoid integrator's edges and least squares, each step from the slopes at the edge's
    ends and at the samples just before and after it on the same lattice line: the slope along
    the edge interpolated by their cubic and integrated exactly (quadratic with one neighbour,
    the trapezoid rule with none; :mod:`restoration.integrate.rules`). Exact for quartic
    surfaces along straight, evenly sampled lattice lines; on the paper's rig its steps err
    ~13x less than the trapezoid's, which the level search needs (docs/results.md).
``"spline"``
    A bicubic B-spline on a regular control grid fitted by sparse least squares straight to the
    slopes, with a weak penalty on third differences of its coefficients (it leaves planes and
    quadratics untouched and only steers coefficients that the data leave free).
``"frankot_chellappa"``
    Frankot & Chellappa (1988) on a regular grid: the slopes are resampled onto nodes half the
    median sample spacing apart (linear on the samples' Delaunay triangles, extended beyond
    their hull by nearest values plus the mean curvature), projected onto the grid's integrable
    Fourier modes (heights mirrored evenly at the borders, so the periodic wrap adds no step),
    and the heights are read back at the samples. Exact for planes; the mirror's slope kinks
    cost accuracy near the grid's borders.
``"dct_poisson"``
    The same resampling, then least squares over the grid's edges with the trapezoid rule: the
    Poisson equation with Neumann borders, solved by DCT (Simchony, Chellappa & Shao 1990).
    Exact for quadratic surfaces.

    Both grid integrators ignore ``weight_xy_mm``. They integrate the interpolated slopes, so
    where the samples leave wide gaps inside their hull (the far field's holes), and near its
    edge, they err more than the lattice integrators; they cost a fixed ~10 ms per call.
"""

LATTICE_INTEGRATORS = ("fourth_order", "paper", "trapezoid")
"""Integrators on the dot lattice, which take ``plans`` (:func:`integrate`)."""

COMPARISON_INTEGRATORS = ("frankot_chellappa", "dct_poisson")
"""Integrators kept for comparison (sweeps, benchmarks) but not offered by ``wai restore``: on
the paper's scene every frame they restore is ``inconsistent`` (surface RMSE 0.15-0.32 mm where
the lattice integrators reach 0.02 mm in ``wai experiment tradeoffs --quick``): resampling the
dots' slopes onto a grid costs more than the level search and the forward check allow."""


def integrate(
    ij: ArrayLike,
    xy_mm: ArrayLike,
    slopes: ArrayLike,
    method: str = "fourth_order",
    weight_xy_mm: ArrayLike | None = None,
    plans: IntegrationPlans | None = None,
) -> Array:
    """Heights (K,) in mm, zero mean, from slopes with the integrator named ``method``.

    ``weight_xy_mm`` (K, 2) mm, optional: positions that set the difference weights of
    the lattice integrators (default ``xy_mm``; see :func:`integrate_paper`). ``plans``,
    optional: where the lattice integrators keep their edges and factorisations for later
    calls on the same samples (:class:`~restoration.integrate.plans.IntegrationPlans`).
    """
    try:
        integrator = INTEGRATORS[method]
    except KeyError:
        raise WaiInputError(
            f"integrate: unknown integrator {method!r} (known: {', '.join(INTEGRATORS)})"
        ) from None
    kwargs: dict = {} if weight_xy_mm is None else {"weight_xy_mm": weight_xy_mm}
    if plans is not None and method in LATTICE_INTEGRATORS:
        kwargs["plans"] = plans
    return integrator(ij, xy_mm, slopes, **kwargs)
