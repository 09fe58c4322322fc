"""The fit's level search (:func:`fit_level`): the surface refitted to its spots at probe levels
around its start, the level where the spots' residual is least (a vertex of the profile), and
its standard error from the profile's curvature. Level and shape trade against each other along
the depth-normal ambiguity, a valley too flat for the Gauss-Newton fit alone to move along
(:func:`restoration.fit.fit_surface`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from restoration.fit import (
    _MEDIAN_NORM,
    _ONE_BLAS_THREAD,
    CAUCHY_SCALE,
    MAX_PROBES,
    POLISH_MM,
    PROBE_STEPS,
    PROBE_TOL_MM,
    SMOOTHNESS,
    Array,
    BSplineSurface,
    FitResult,
    _cost,
    _Fit,
    _gauss_newton,
    _Rays,
    _result,
    knot_step,
    spline_through,
)
from restoration.level import N_SETS, anchor_sigma_mm
from restoration.observations import Observations
from wai_core.heightfield import Heightfield
from wai_core.timings import Timings

__all__ = ["LevelFit", "fit_level"]


@dataclass
class LevelFit:
    """:func:`fit_level`'s result: the fit at the chosen level and the level's profile.

    Attributes
    ----------
    fit : FitResult
        The fit at the chosen level.
    offsets_mm : (P,) ndarray
        The probes' levels (the spline's mean height at the samples) against the warm start's,
        sorted, mm.
    cost_mm2 : (P,) ndarray
        Each probe's summed Cauchy loss of the spot residuals over the rays every probe
        keeps, mm^2 (the profile).
    iterations : (P,) ndarray of int
        Gauss-Newton steps each probe took.
    converged : (P,) ndarray of bool
        Whether each probe met the step tolerance within its steps.
    offset_mm : float
        The chosen level against the warm start's, mm (0 when the start's level was kept).
    sigma_mm : float
        The minimum's standard error, mm, from the spread of interleaved subsets' own minima
        (noise only: the remaining error can be several times larger; docs/results.md).
    kept_start : bool
        True when the profile did not pin a minimum and the warm start's level was kept.
    reason : str
        Why the start's level was kept ("" when the profile's minimum was used).
    """

    fit: FitResult
    offsets_mm: Array
    cost_mm2: Array
    iterations: NDArray
    converged: NDArray
    offset_mm: float
    sigma_mm: float
    kept_start: bool
    reason: str


def _level_weights(spline: BSplineSurface, xy: Array) -> Array:
    """``a`` such that ``a . c`` is the spline's mean height at the points ``xy`` (K, 2)."""
    index, w, inside = spline.rows(xy[:, 0], xy[:, 1])
    a = np.bincount(index[inside].ravel(), w[0][inside].ravel(), spline.coeffs.size)
    return a / max(int(inside.sum()), 1)


@_ONE_BLAS_THREAD
def fit_level(
    points_mm: Array,
    slopes: Array,
    obs: Observations,
    like: Heightfield,
    *,
    probe_mm: float = 0.15,
    iterations: int = PROBE_STEPS,
    max_probes: int = MAX_PROBES,
) -> LevelFit:
    """:func:`fit_surface` with the level found by a search along the fit's flat direction.

    Raising the surface and re-bending it sends every ray to nearly the same spot (the
    depth-normal ambiguity): the spot residual changes by microns per 0.1 mm of level, far
    less than Gauss-Newton's damping lets one step move along it, so a free fit keeps the
    level it starts from (and creeps along the valley, which makes its residual depend on how
    many steps it took). Each probe therefore fits the shape with the level held fixed (the
    spline's mean height at the samples), from the same start (the fit at the warm start's
    level, shifted) and with the same bounded steps, so that the profile (the spot
    residuals' summed Cauchy loss over the level) is a smooth function of the level alone.
    The search brackets the profile's minimum (walking downhill from three probes around the
    start) and refines it by successive parabolas through the lowest probe and its two
    neighbours. With the renders' exact spots the minimum is the true level within 0.01 mm
    where the integrability level is off by 0.1-0.3 mm (docs/results.md). Where the walk
    finds no minimum within ``max_probes``, the start's level is kept and the result says so.

    Parameters
    ----------
    points_mm, slopes, obs, like
        As :func:`~restoration.fit.fit_surface`.
    probe_mm : float
        Spacing of the first three probes around the warm start's level and of the walk, mm.
    iterations : int
        Most Gauss-Newton steps per probe (each stops earlier once converged).
    max_probes : int
        Most probes (the start's included).

    Returns
    -------
    LevelFit
    """
    timings = Timings()
    with timings("gauss_newton"):  # the whole search over levels
        xy = points_mm[:, :2]
        # One knot layout for every probe, or their residuals would not compare.
        start = spline_through(xy, points_mm[:, 2], slopes, knot_step(xy), SMOOTHNESS)
        rays = _Rays.of(obs)
        a = _level_weights(start, xy)
        level0 = float(a @ start.coeffs.ravel())
        gn = {"iterations": iterations, "tol_mm": PROBE_TOL_MM, "smoothness": SMOOTHNESS}
        base = _gauss_newton(start, rays, rays.t_at(points_mm[:, 2]), level=(a, level0), **gn)
        # A few spots far off the rest (a detection error, a crest the spline cannot follow)
        # can outweigh every other ray's preference for a level: the profile is of the Cauchy
        # loss, its scale fixed from the plain fit's median residual so all probes compare.
        r = np.linalg.norm(base.prediction.residual_mm, axis=1)
        scale = CAUCHY_SCALE * max(float(np.nanmedian(r)), 1e-6) / _MEDIAN_NORM  # exact spots
        gn["scale_mm"] = scale
        base = _gauss_newton(base.spline, rays, base.prediction.t, level=(a, level0), **gn)
        fits = {0.0: base}

        def probe(offset: float) -> None:
            # The same start for every probe: the base moved by the offset (a's weights sum to
            # one, so adding the offset to every coefficient moves the level by exactly that).
            shifted = BSplineSurface(start.x0_mm, start.y0_mm, start.step_mm,
                                     base.spline.coeffs + offset)
            t = base.prediction.t + offset / rays.d[:, 2]
            fits[offset] = _gauss_newton(shifted, rays, t, level=(a, level0 + offset), **gn)

        for offset in (-probe_mm, probe_mm):
            probe(offset)
        reason = ""
        while True:
            offsets, cost, _ = _profile(fits, scale)
            low = int(np.argmin(cost))
            if 0 < low < len(offsets) - 1:  # bracketed: refine by the parabola through three
                vertex = _vertex3(offsets[low - 1:low + 2], cost[low - 1:low + 2])
                if np.min(np.abs(offsets - vertex)) < POLISH_MM or len(fits) >= max_probes:
                    break
                probe(vertex)
            elif len(fits) >= max_probes:
                reason = (f"the level's profile has no minimum within {offsets[0]:+.2f} to "
                          f"{offsets[-1]:+.2f} mm of the start")
                break
            else:  # walk downhill
                probe(float(offsets[low] + (probe_mm if low else -probe_mm)))
        chosen = 0.0 if reason else float(offsets[low])
    sigma = _profile_sigma(fits, scale)
    return LevelFit(
        _result(fits[chosen], like, timings), offsets, cost,
        np.array([fits[o].iterations for o in offsets]),
        np.array([fits[o].converged for o in offsets]),
        chosen, sigma, bool(reason), reason,
    )


def _vertex3(x: Array, y: Array) -> float:
    """Abscissa of the vertex of the parabola through three points whose middle is lowest."""
    d0, d1 = (y[1] - y[0]) / (x[1] - x[0]), (y[2] - y[1]) / (x[2] - x[1])
    curvature = (d1 - d0) / (x[2] - x[0])
    return float(0.5 * (x[0] + x[1]) - d0 / (2 * curvature)) if curvature > 0 else float(x[1])


def _profile(fits: dict[float, _Fit], scale: float | None) -> tuple[Array, Array, int]:
    """Probe levels (sorted, mm), their summed :func:`_cost` over the rays all of them keep
    (mm^2), and how many rays that is."""
    offsets = np.array(sorted(fits))
    residuals = np.stack([_cost(np.sum(fits[o].prediction.residual_mm ** 2, axis=1), scale)
                          for o in offsets])
    common = np.isfinite(residuals).all(axis=0)
    return offsets, np.sum(residuals[:, common], axis=1), int(common.sum())


def _profile_sigma(fits: dict[float, _Fit], scale: float | None) -> float:
    """Standard error of the profile's minimum, mm: :func:`restoration.anchor.anchor_sigma_mm`
    on the summed :func:`_cost` of interleaved subsets of the rays (inf when a subset finds no
    minimum within the probed span of the probes)."""
    offsets = np.array(sorted(fits))
    residuals = np.stack([_cost(np.sum(fits[o].prediction.residual_mm ** 2, axis=1), scale)
                          for o in offsets])
    common = np.isfinite(residuals).all(axis=0)
    sets = np.arange(residuals.shape[1]) % N_SETS
    set_ss = np.stack([np.sum(residuals[:, common & (sets == k)], axis=1)
                       for k in range(N_SETS)], axis=1)
    return anchor_sigma_mm(offsets, set_ss, float(np.ptp(offsets)))
