"""From sampled surface slopes to heights (section 3.2.2), and from scattered heights to a grid.

The integrators turn slopes at the detected dots into heights up to a constant; all share one
interface (:data:`Integrator`) and are chosen by name from :data:`INTEGRATORS` through
:func:`integrate`. :func:`to_heightfield` then grids the scattered heights (and slopes) onto a
regular :class:`~wai_core.heightfield.Heightfield`.

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
``_common``
    Array aliases and the input limits shared by the modules above.
"""

from restoration.integrate._common import MIN_SAMPLES
from restoration.integrate.dispatch import (
    COMPARISON_INTEGRATORS,
    INTEGRATORS,
    Integrator,
    integrate,
)
from restoration.integrate.fourier import (
    SlopeGrid,
    frankot_chellappa,
    integrate_dct_poisson,
    integrate_frankot_chellappa,
    poisson_dct,
    resample_slopes,
    sample_heights,
)
from restoration.integrate.gridding import (
    GRIDDERS,
    MAX_LATTICE_STEP,
    gap_free_triangles,
    lattice_bridges,
    to_heightfield,
)
from restoration.integrate.lattice import (
    DifferenceGraph,
    check_samples,
    grid_neighbours,
    integrate_fourth_order,
    integrate_paper,
    integrate_trapezoid,
    largest_grid_piece,
    largest_piece,
    line_neighbours,
    solve_differences,
    spd_solve,
)
from restoration.integrate.rules import edge_step, edge_steps
from restoration.integrate.spline import SplineGrid, integrate_spline

__all__ = [
    "COMPARISON_INTEGRATORS",
    "GRIDDERS",
    "INTEGRATORS",
    "MAX_LATTICE_STEP",
    "MIN_SAMPLES",
    "DifferenceGraph",
    "Integrator",
    "SlopeGrid",
    "SplineGrid",
    "check_samples",
    "edge_step",
    "edge_steps",
    "frankot_chellappa",
    "gap_free_triangles",
    "grid_neighbours",
    "integrate",
    "integrate_dct_poisson",
    "integrate_fourth_order",
    "integrate_frankot_chellappa",
    "integrate_paper",
    "integrate_spline",
    "integrate_trapezoid",
    "largest_grid_piece",
    "largest_piece",
    "lattice_bridges",
    "line_neighbours",
    "poisson_dct",
    "resample_slopes",
    "sample_heights",
    "solve_differences",
    "spd_solve",
    "to_heightfield",
]
