"""From sampled surface slopes to heights (section 3.2.2), and from scattered heights to a grid.

The integrators turn slopes at the detected dots into heights up to a constant; all share one
interface (:data:`Integrator`) and are chosen by name from :data:`INTEGRATORS` through
:func:`integrate`. :func:`to_heightfield` then grids the scattered heights (and slopes) onto a
regular :class:`~wai_core.heightfield.Heightfield`. The package's API is these; each
integrator and its helpers are in its module.

Modules
-------
:mod:`~restoration.integrate.lattice`
    Integrators on the dot lattice (``"paper"``, ``"trapezoid"``, ``"fourth_order"``): input
    checks, grid neighbours, connected pieces, sparse least squares over height differences.
:mod:`~restoration.integrate.rules`
    The compiled fourth-order rule for one edge's height step (:func:`edge_step`).
:mod:`~restoration.integrate.spline`
    The ``"spline"`` integrator and its uniform bicubic B-spline (:class:`SplineGrid`).
:mod:`~restoration.integrate.fourier`
    Grid integrators (``"frankot_chellappa"``, ``"dct_poisson"``): slopes resampled onto a
    regular grid and integrated there.
:mod:`~restoration.integrate.gridding`
    Scattered heights to a :class:`~wai_core.heightfield.Heightfield` (:data:`GRIDDERS`).
:mod:`~restoration.integrate.dispatch`
    The :data:`INTEGRATORS` registry and the :func:`integrate` dispatcher.
:mod:`~restoration.integrate.plans`
    What repeated integrations of one sample set share (:class:`IntegrationPlans`).
``_common``
    Array aliases and the input limits shared by the modules above.
"""

from restoration.integrate._common import MIN_SAMPLES
from restoration.integrate.dispatch import (
    COMPARISON_INTEGRATORS,
    INTEGRATORS,
    LATTICE_INTEGRATORS,
    Integrator,
    integrate,
)
from restoration.integrate.gridding import GRIDDERS, to_heightfield
from restoration.integrate.lattice import DifferenceGraph, check_samples, grid_neighbours
from restoration.integrate.plans import IntegrationPlans

__all__ = [
    "COMPARISON_INTEGRATORS",
    "GRIDDERS",
    "INTEGRATORS",
    "LATTICE_INTEGRATORS",
    "MIN_SAMPLES",
    "DifferenceGraph",
    "IntegrationPlans",
    "Integrator",
    "check_samples",
    "grid_neighbours",
    "integrate",
    "to_heightfield",
]
