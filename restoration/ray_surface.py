"""A surface from slopes sampled where known rays cross it, at the gauge's level.

Two methods measure a slope per ray without knowing where along the ray the surface lies:
Alterman's sun sensor (a pinhole's refracted sunlight) and synthetic Schlieren (a camera
pixel's line of sight). Both place the samples at the gauge's level ``h0`` first, integrate
the slopes there, move each sample along its ray to the height the integration gives, and
repeat until the heights settle (the structured light's refinement, without its level search:
the slopes do not pin the level, the gauge's ``h0`` is the samples' mean height).
:func:`integrate_along_rays` is that loop; the slopes may depend on the sample's position
(Schlieren's do, Alterman's do not).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from restoration.integrate import integrate, to_heightfield
from restoration.level import Anchor
from restoration.options import SurfaceOptions
from wai_core.heightfield import Heightfield
from wai_core.timings import Timings

__all__ = ["RaySurface", "integrate_along_rays", "points_on_lines"]

Array = NDArray[np.float64]

SlopesAt = Callable[[Array, NDArray[np.int64]], tuple[Array, Array]]
"""``slopes_at(points_mm, index)``: the unit normals (K, 3) and slopes ``(dz/dx, dz/dy)``
(K, 2) of the samples ``index`` (K,) (of the rays given) when they lie at ``points_mm``
(K, 3)."""


@dataclass(frozen=True)
class RaySurface:
    """A surface reconstructed from slopes on rays, with the samples it was built from (the
    same public attributes as the structured light's
    :class:`restoration.surface.SurfaceEstimate`, so scoring and reporting treat all alike).

    Attributes
    ----------
    heightfield : Heightfield
        Absolute heights on a regular grid, mm; NaN outside the samples.
    ij : (K, 2) ndarray of int
        Lattice indices of the samples kept (4-neighbours are neighbours on the surface).
    points_mm : (K, 3) ndarray
        Samples: where each ray crossed the surface (last pass) and its height.
    normals : (K, 3) ndarray
        Unit normals at the samples, pointing up.
    slopes : (K, 2) ndarray
        ``(dz/dx, dz/dy)`` at the samples.
    iterations : int
        Refinement passes after the samples-at-h0 pass.
    height_change_mm : float
        Largest height change of the last refinement pass, mm (NaN when none ran).
    kept : (K,) ndarray of int
        Index of each sample among the rays given (samples the integrator could not tie to the
        rest are left out).
    timings_ms : dict of str to float
        ``normals``, ``integrate`` (all passes), ``grid`` and ``total``, ms.
    anchor : Anchor
        How the absolute level was set: the gauge's h0.
    """

    heightfield: Heightfield
    ij: NDArray[np.int64]
    points_mm: Array
    normals: Array
    slopes: Array
    iterations: int
    height_change_mm: float
    kept: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    timings_ms: dict[str, float] = field(default_factory=dict)
    anchor: Anchor = field(default_factory=lambda: Anchor("gauge"))

    def refitted(self, heightfield: Heightfield, points_mm: Array, slopes: Array,
                 **timings_ms: float) -> RaySurface:
        """This surface replaced by ``heightfield`` (e.g. a fit to the pattern image), its
        samples moved to ``points_mm`` (K, 3) with ``slopes`` (K, 2), and ``timings_ms``
        added (:meth:`restoration.surface.SurfaceEstimate.refitted`'s counterpart)."""
        normals = np.column_stack([-slopes, np.ones(len(slopes))])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return replace(self, heightfield=heightfield, points_mm=points_mm, slopes=slopes,
                       normals=normals, timings_ms={**self.timings_ms, **timings_ms},
                       anchor=replace(self.anchor))


def points_on_lines(origins_mm: Array, dirs: Array, heights_mm: ArrayLike) -> Array:
    """Points at the given heights (K,) on the lines through ``origins_mm`` (K, 3) along
    ``dirs`` (K, 3), mm.

    Examples
    --------
    >>> import numpy as np
    >>> points_on_lines(np.zeros((1, 3)), np.array([[0.6, 0.0, 0.8]]), [8.0]).tolist()
    [[6.0, 0.0, 8.0]]
    """
    h = np.broadcast_to(np.asarray(heights_mm, dtype=float), origins_mm.shape[:1])
    return origins_mm + ((h - origins_mm[:, 2]) / dirs[:, 2])[:, None] * dirs


def integrate_along_rays(
    ij: NDArray[np.int64],
    origins_mm: Array,
    dirs: Array,
    slopes_at: SlopesAt,
    h0_mm: float,
    options: SurfaceOptions,
    refine_tol_mm: float,
) -> RaySurface:
    """Slopes on rays integrated at the gauge's level, the samples moved along their rays
    to the integrated heights until they settle, then gridded.

    Parameters
    ----------
    ij : (K, 2) ndarray of int
        Lattice indices of the samples (``options.integrator``'s neighbours).
    origins_mm, dirs : (K, 3) ndarray
        The rays, mm, and their directions (not horizontal).
    slopes_at : callable
        The samples' normals and slopes at given points (:data:`SlopesAt`).
    h0_mm : float
        The gauge's level: the samples' mean height, mm.
    options : SurfaceOptions
        ``integrator``, ``n_refine`` (0: the samples stay on ``z = h0``), ``gridder``,
        ``grid_spacing_mm``.
    refine_tol_mm : float
        The passes stop once none moves a height by more than this, mm.

    Raises
    ------
    RestorationFailed
        From the integrator, when the samples fix no surface.
    """
    timings = Timings()
    kept = np.arange(len(ij))
    heights = np.full(len(ij), float(h0_mm))
    change, it = np.nan, 0
    for it in range(int(options.n_refine) + 1):
        q = points_on_lines(origins_mm, dirs, heights)
        with timings("normals"):
            normals, slopes = slopes_at(q, kept)
        with timings("integrate"):
            rel = integrate(ij, q[:, :2], slopes, options.integrator)
        new = rel - np.nanmean(rel) + h0_mm
        # Samples the integrator cannot tie to the rest leave for good.
        keep = np.isfinite(new)
        ij, origins_mm, dirs, normals, slopes, q, kept = (
            a[keep] for a in (ij, origins_mm, dirs, normals, slopes, q, kept)
        )
        new, heights = new[keep], heights[keep]
        change = float(np.max(np.abs(new - heights))) if it > 0 else np.nan
        heights = new
        if it > 0 and change < refine_tol_mm:
            break
    q = points_on_lines(origins_mm, dirs, heights)
    with timings("grid"):
        surface = to_heightfield(
            q[:, :2], heights, slopes, options.grid_spacing_mm, method=options.gridder
        )
    timings.add("total", timings.total())
    return RaySurface(
        heightfield=surface,
        ij=ij,
        points_mm=np.column_stack([q[:, :2], heights]),
        normals=normals,
        slopes=slopes,
        iterations=it,
        height_change_mm=change,
        kept=kept,
        timings_ms=timings.to_dict(),
    )
