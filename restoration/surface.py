"""Water-surface reconstruction from one structured-light frame (section 3.2 of the paper).

Pipeline per frame: spots on the diffuser (camera-s pixels back-projected to ``z = z_h``) and
projector rays give normals by the law of reflection (eq. 3-7); the normals' slopes are
integrated to heights (eq. 8-13) and gridded to a :class:`~wai_core.heightfield.Heightfield`.

Iteration 0 is the paper's method: every reflection point ``q_k`` is put on the mean level
``z = h0`` (eq. 3). Refinement removes that approximation: the integrated heights move each
``q_k`` along its projector ray to the reconstructed surface, normals and slopes are recomputed
there and re-integrated, until the heights change by less than ``tol_mm``. This fixed-point
iteration contracts by roughly 0.2 to 0.6 per pass on the paper's rig; Anderson mixing (on by
default) reaches the same fixed point in about half the passes. Every pass weights the
height differences (eq. 13) by the sample spacing of pass 0: the passes then share one sparse
factorisation (the samples move by millimetres along their rays, which changes the weights but
not what a consistent slope field integrates to; on the demo frame heights change by < 1e-3 mm).

Anchor and remaining bias
-------------------------
One spot per projector ray fixes the surface only up to a one-parameter family (raise or lower
the surface and slightly different normals explain the same spots: the depth-normal ambiguity
of deflectometry); slopes fix nothing about the constant either. Like the paper, the
reconstruction takes the mean level ``h0`` (from a depth gauge) as known and sets the **mean of
the sample heights** to ``h0`` at every iteration. Where the true mean height of the sampled
points differs from ``h0`` (waves longer than the sampled patch, or a patch whose samples
cluster on crests), the whole estimate sits on the wrong member of the family: a height offset
plus a smooth normal error that no refinement can recover without extra information (a
second camera, a second spot per ray, or a calibrated reference). On the paper's rig a 1 mm
anchor error costs about 5e-3 rad (rms) in the normals and 0.25 mm (rms) in the shape.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from restoration.integrate import (
    GRIDDERS,
    INTEGRATORS,
    to_heightfield,
)
from restoration.level import Anchor
from restoration.normals import (
    points_on_rays,
)
from restoration.observations import Observations
from restoration.options import StructuredLightOptions
from restoration.refine import _compiled_refinement, _refinement
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera
from wai_core.heightfield import Heightfield
from wai_core.timings import Timings

Array = NDArray[np.float64]

_DEFAULT = StructuredLightOptions()

COMPILED_INTEGRATORS = ("fourth_order", "trapezoid")
"""Integrators whose refinement passes run in one compiled call (:func:`_compiled_refinement`)."""


@dataclass(frozen=True)
class SurfaceEstimate:
    """A reconstructed water surface and the samples it was built from.

    Attributes
    ----------
    ij : (K, 2) ndarray of int
        Grid indices of the samples kept (those the integrator could tie together).
    points_mm : (K, 3) ndarray
        Surface samples: ``(x, y)`` where the last normals were evaluated (the reflection
        points ``q_k`` on the projector rays) and the reconstructed height ``z``, mm.
    normals : (K, 3) ndarray
        Unit normals at the samples, pointing up.
    slopes : (K, 2) ndarray
        ``(dz/dx, dz/dy)`` at the samples.
    iterations : int
        Refinement passes run after the paper's pass (0 reproduces the paper).
    height_change_mm : float
        Largest height change of the last refinement pass, mm (NaN when none ran).
    timings_ms : dict of str to float
        Wall time per stage, ms: ``normals``, ``integrate`` (summed over passes) and
        ``total``; ``grid`` is added (and counted in
        ``total``) when :attr:`heightfield` is first read. With the integrators of
        :data:`COMPILED_INTEGRATORS` the passes run in one compiled call: ``integrate`` then
        holds the normals too and ``normals`` is 0.
    grid_spacing_mm : float
        Node spacing of :attr:`heightfield`, mm.
    gridder : str
        ``method`` of :func:`restoration.integrate.to_heightfield` that builds it.
    anchor : Anchor
        How the absolute level was set (filled by the caller, e.g.
        :func:`restoration.structured_light.estimate_surface`).
    integrator : str
        The integrator that made the heights (its rule also measures their integrability,
        :func:`restoration.anchor.edge_residuals_mm`).
    """

    ij: NDArray[np.int64]
    points_mm: Array
    normals: Array
    slopes: Array
    iterations: int
    height_change_mm: float
    timings_ms: dict[str, float] = field(default_factory=dict)
    grid_spacing_mm: float = _DEFAULT.grid_spacing_mm
    gridder: str = _DEFAULT.gridder
    anchor: Anchor = field(default_factory=Anchor)
    integrator: str = _DEFAULT.integrator
    _heightfield: Heightfield | None = field(default=None, init=False, repr=False, compare=False)

    def refitted(self, heightfield: Heightfield, points_mm: Array, slopes: Array,
                 **timings_ms: float) -> SurfaceEstimate:
        """This estimate with its surface replaced by ``heightfield`` (e.g. a fit to the
        spots, :mod:`restoration.fit`), its samples moved to ``points_mm`` (K, 3) with
        ``slopes`` (K, 2), and ``timings_ms`` added."""
        normals = np.column_stack([-slopes, np.ones(len(slopes))])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        new = replace(self, points_mm=points_mm, slopes=slopes, normals=normals,
                      timings_ms={**self.timings_ms, **timings_ms}, anchor=replace(self.anchor))
        object.__setattr__(new, "_heightfield", heightfield)
        return new

    def unknown_near(self, rejected_xy_mm: Array) -> SurfaceEstimate:
        """This estimate with its surface left unknown (NaN) at the grid nodes nearer to one of
        ``rejected_xy_mm`` (R, 2), samples left out as wrong, than to any sample kept: what
        the surface there would be is a guess from the samples around.

        Examples
        --------
        >>> import numpy as np
        >>> xy = np.array([[x, y] for y in range(0, 30, 10) for x in range(0, 30, 10)], float)
        >>> est = SurfaceEstimate(np.zeros((9, 2), np.int64), np.column_stack([xy, np.zeros(9)]),
        ...                       np.tile([0.0, 0.0, 1.0], (9, 1)), np.zeros((9, 2)), 0, np.nan,
        ...                       grid_spacing_mm=1.0)
        >>> z = est.unknown_near(np.array([[17.0, 17.0]])).heightfield.z  # nodes 1 mm apart
        >>> bool(np.isnan(z[17, 17])), bool(np.isnan(z[0, 0]))
        (True, False)
        """
        from scipy.spatial import cKDTree

        hf = self.heightfield
        rejected = np.asarray(rejected_xy_mm, dtype=float).reshape(-1, 2)
        known = np.isfinite(hf.z)
        if not len(rejected) or not known.any():
            return self
        xx, yy = np.meshgrid(hf.x, hf.y)
        nodes = np.column_stack([xx[known], yy[known]])
        d_kept, _ = cKDTree(self.points_mm[:, :2]).query(nodes)
        d_rejected, _ = cKDTree(rejected).query(nodes)
        z = hf.z.copy()
        z.ravel()[np.flatnonzero(known.ravel())[d_rejected < d_kept]] = np.nan
        new = replace(self, anchor=replace(self.anchor))
        object.__setattr__(new, "_heightfield", replace(hf, z=z))
        return new

    @property
    def heightfield(self) -> Heightfield:
        """Absolute heights on a regular grid, mm; NaN outside the samples' convex hull and over
        gaps between them, by distance and on the dot lattice (see
        :func:`restoration.integrate.to_heightfield`).

        Built on first access and kept: only the estimate that is used for reverse tracing needs
        it, while a search over anchors (:mod:`restoration.anchor`) makes several and reads only
        their samples.
        """
        if self._heightfield is None:
            timings = Timings()
            with timings("grid"):
                xy, z = self.points_mm[:, :2], self.points_mm[:, 2]
                grid = to_heightfield(xy, z, self.slopes, self.grid_spacing_mm,
                                      method=self.gridder, lattice_ij=self.ij)
                object.__setattr__(self, "_heightfield", grid)  # a cache: frozen otherwise
            self.timings_ms["grid"] = timings.ms["grid"]
            self.timings_ms["total"] = self.timings_ms.get("total", 0.0) + timings.ms["grid"]
        return self._heightfield


def _check_choices(
    obs: Observations,
    h0_mm: float,
    integrator: str,
    n_refine: int,
    gridder: str,
    grid_spacing_mm: float,
) -> None:
    """Validate the choices of :func:`reconstruct` (the arrays were checked when ``obs`` was
    built)."""
    if not h0_mm > obs.z_h_mm:
        raise WaiInputError("reconstruct_surface: the water level h0 must lie above the diffuser")
    if integrator not in INTEGRATORS:
        raise WaiInputError(
            f"reconstruct_surface: unknown integrator {integrator!r} "
            f"(known: {', '.join(INTEGRATORS)})"
        )
    if int(n_refine) != n_refine or n_refine < 0:
        raise WaiInputError("reconstruct_surface: n_refine must be a non-negative integer")
    if gridder not in GRIDDERS:
        raise WaiInputError(
            f"reconstruct_surface: unknown gridder {gridder!r} (known: {', '.join(GRIDDERS)})"
        )
    if not grid_spacing_mm > 0:
        raise WaiInputError("reconstruct_surface: grid_spacing_mm must be positive")


def reconstruct_surface(
    ij: ArrayLike,
    panel_px: ArrayLike,
    spot_px: ArrayLike,
    projector: PinholeCamera,
    camera_s: PinholeCamera,
    z_h_mm: float,
    h0_mm: float,
    integrator: str = _DEFAULT.integrator,
    n_refine: int = _DEFAULT.n_refine,
    grid_spacing_mm: float = _DEFAULT.grid_spacing_mm,
    gridder: str = _DEFAULT.gridder,
    tol_mm: float = _DEFAULT.refine_tol_mm,
    accelerate: bool = True,
    weight_xy_mm: ArrayLike | None = None,
) -> SurfaceEstimate:
    """Reconstruct the water surface from matched structured-light features.

    Parameters
    ----------
    ij : (K, 2) array_like of int
        Grid index of each feature's dot.
    panel_px : (K, 2) array_like
        Projector panel position ``(col, row)`` of each dot, pixels.
    spot_px : (K, 2) array_like
        Detected spot ``(col, row)`` of each dot in camera s, pixels.
    projector, camera_s : PinholeCamera
        Calibrated projector and diffuser camera.
    z_h_mm : float
        Height of the diffuser plane, mm.
    h0_mm : float
        Mean water level, mm (the anchor; see the module docstring).
    integrator, n_refine, grid_spacing_mm, gridder, tol_mm, accelerate
        As :func:`reconstruct` (defaults: :class:`~restoration.options.SurfaceOptions`).
    weight_xy_mm : (K, 2) array_like, optional
        Sample positions that set the integration weights of every pass, mm (default: the
        first pass's reflection points).

    Returns
    -------
    SurfaceEstimate

    See Also
    --------
    reconstruct : the same from :class:`~restoration.observations.Observations`, which a
        frame's repeated reconstructions share.
    """
    obs = Observations.build(
        ij, panel_px, spot_px, projector, camera_s, z_h_mm, weight_xy_mm=weight_xy_mm
    )
    return reconstruct(
        obs, h0_mm, integrator=integrator, n_refine=n_refine, grid_spacing_mm=grid_spacing_mm,
        gridder=gridder, tol_mm=tol_mm, accelerate=accelerate,
    )


def reconstruct(
    obs: Observations,
    h0_mm: float,
    *,
    integrator: str = _DEFAULT.integrator,
    n_refine: int = _DEFAULT.n_refine,
    grid_spacing_mm: float = _DEFAULT.grid_spacing_mm,
    gridder: str = _DEFAULT.gridder,
    tol_mm: float = _DEFAULT.refine_tol_mm,
    accelerate: bool = True,
) -> SurfaceEstimate:
    """Reconstruct the water surface from one frame's observations, its samples' mean height
    pinned at ``h0_mm``.

    Parameters
    ----------
    obs : Observations
        The features with their rays; its :attr:`~Observations.weight_xy_mm` weigh the
        differences of every pass, and its :attr:`~Observations.plans` keep the integration
        structures for the next reconstruction of the same features (the level search runs
        several).
    h0_mm : float
        Mean water level, mm (the anchor; see the module docstring).
    integrator : str
        Name in :data:`restoration.integrate.INTEGRATORS`.
    n_refine : int
        Most refinement passes after the paper's ``q = h0`` pass; 0 is the paper's method.
    grid_spacing_mm : float
        Node spacing of the output heightfield, mm.
    gridder : str
        ``method`` of :func:`restoration.integrate.to_heightfield`; the paper's pipeline is
        ``integrator="paper", n_refine=0, gridder="clough_tocher"``. The heightfield is
        gridded when :attr:`SurfaceEstimate.heightfield` is first read.
    tol_mm : float
        Refinement stops once a pass changes no height by more than this, mm.
    accelerate : bool
        Mix each refinement step with the previous one (Anderson acceleration, depth 1): the
        same fixed point in about half the passes. False gives the plain iteration
        ``h <- integrate(normals(q(h)))``.

    Returns
    -------
    SurfaceEstimate
    """
    timings = Timings()
    with timings("total"):
        _check_choices(obs, h0_mm, integrator, n_refine, gridder, grid_spacing_mm)
        timings.add("normals", 0.0)  # the compiled passes time both steps as one
        timings.add("integrate", 0.0)
        args = (obs.ij, obs.origin_mm, obs.dirs, obs.spots_mm, h0_mm, int(n_refine), tol_mm,
                accelerate)
        weight_xy = obs.weight_xy_mm
        if integrator in COMPILED_INTEGRATORS:  # the level search's: all passes in one call
            with timings("integrate"):
                # Default weights: the first pass's reflection points (q on z = h0), as the loop's.
                if weight_xy is None:
                    weight_xy = points_on_rays(obs.origin_mm, obs.dirs, h0_mm)[:, :2]
                ij_arr, q, normals, slopes, integrated, it, change = _compiled_refinement(
                    *args, weight_xy, integrator == "fourth_order", obs.plans
                )
        else:
            ij_arr, q, normals, slopes, integrated, it, change = _refinement(
                *args, weight_xy, integrator, timings, obs.plans
            )
    return SurfaceEstimate(
        ij=ij_arr,
        points_mm=np.column_stack([q[:, :2], integrated]),
        normals=normals,
        slopes=slopes,
        iterations=it,
        height_change_mm=change,
        timings_ms=timings.to_dict(),
        grid_spacing_mm=float(grid_spacing_mm),
        gridder=gridder,
        integrator=integrator,
    )
