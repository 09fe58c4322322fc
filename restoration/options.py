"""The restoration's choices, and their defaults in one place."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from restoration.integrate import GRIDDERS, INTEGRATORS
from wai_core.errors import WaiInputError

__all__ = ["ANCHORS", "RestoreOptions"]

ANCHORS = ("integrability", "gauge")
"""How the absolute level is set: from the slopes' integrability, or the gauge's h0."""


@dataclass(frozen=True)
class RestoreOptions:
    """Choices of the restoration (defaults: the most accurate at real-time speed).

    ``integrator='paper'``, ``n_refine=0``, ``gridder='clough_tocher'`` and ``anchor='gauge'``
    is the paper's method as published (q_k on z = h0, central differences, bicubic-type
    interpolation, mean height = h0). ``anchor='integrability'`` finds the absolute height
    from the data instead (:mod:`restoration.anchor`); when the data do not pin it (standard
    error above ``anchor_max_sigma_mm``, e.g. over calm water) the gauge's h0 is used and the
    estimate says so (``SurfaceEstimate.anchor["method"] == "gauge_fallback"``).

    Attributes
    ----------
    integrator : str
        A name in :data:`restoration.integrate.INTEGRATORS` (``fourth_order``, ``trapezoid``,
        ``paper``, ``spline``, ``frankot_chellappa``, ``dct_poisson``).
    n_refine : int
        Most refinement passes of the reflection points after the paper's pass (0: the
        paper); they stop once a pass moves no height by more than ``refine_tol_mm``.
    refine_tol_mm : float
        The refinement's convergence, mm. An unconverged refinement biases the level search
        (three fixed passes left seed 4 of the accuracy bench 0.2 mm off; converged, 0.05 mm),
        while 0.01 mm gives the same level as 1e-4 mm in 4-5 passes instead of 6-8
        (docs/results.md).
    gridder : str
        A name in :data:`restoration.integrate.GRIDDERS`.
    grid_spacing_mm : float
        Node spacing of the reconstructed heightfield, mm.
    warp_step_px : int
        Spacing of the reverse trace's solved nodes in camera v, px (pixels between are
        interpolated).
    anchor : str
        One of :data:`ANCHORS`.
    anchor_max_sigma_mm : float
        Largest standard error of the integrability level that is trusted, mm.
    converge_mm : float
        When the last of the ``n_refine`` passes still moves a height by more than this (mm),
        the fixed point has not converged (a diffuser close to the water contracts slowly)
        and the level search is run again with up to ``max_refine`` passes per probe.
    max_refine : int
        Most refinement passes of that second search (it stops earlier once converged).
    fit_spots : bool
        After the reconstruction, fit a smooth surface and its level to the detected spots
        through the exact reflection model (:func:`restoration.fit.fit_level`), at ~0.3-1 s
        per frame, so off by default (real time). Since the secant level search the default
        is as accurate on the mean (0.020 against 0.024 mm over ten seeds); docs/results.md.

    Examples
    --------
    >>> from restoration import RestoreOptions
    >>> RestoreOptions().integrator
    'fourth_order'
    >>> RestoreOptions(integrator="paper", n_refine=0, anchor="gauge").n_refine
    0
    """

    integrator: str = "fourth_order"
    n_refine: int = 8
    refine_tol_mm: float = 0.01
    gridder: str = "tangent_blend"
    grid_spacing_mm: float = 2.0
    warp_step_px: int = 8
    anchor: str = "integrability"
    anchor_max_sigma_mm: float = 1.0
    converge_mm: float = 1.0
    max_refine: int = 40
    fit_spots: bool = False

    def __post_init__(self) -> None:
        for name, value, known in (
            ("integrator", self.integrator, tuple(INTEGRATORS)),
            ("gridder", self.gridder, GRIDDERS),
            ("anchor", self.anchor, ANCHORS),
        ):
            if value not in known:
                raise WaiInputError(f"unknown {name} {value!r} (known: {', '.join(known)})")
        if int(self.n_refine) < 0 or int(self.max_refine) < int(self.n_refine):
            raise WaiInputError(
                f"refinement passes must be >= 0 and max_refine >= n_refine, not "
                f"{self.n_refine} and {self.max_refine}"
            )
        if not self.refine_tol_mm > 0:
            raise WaiInputError(f"refine_tol_mm must be > 0, not {self.refine_tol_mm}")
        if not self.grid_spacing_mm > 0 or int(self.warp_step_px) < 1:
            raise WaiInputError("grid spacing must be > 0 mm and the warp step >= 1 px")

    def to_dict(self) -> dict[str, Any]:
        """The options as plain values (what ``metrics.json`` records)."""
        return asdict(self)

