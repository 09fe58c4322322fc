"""Where a spot's light centre lies off its dot's centre ray, and the correction for it.

Structured light takes each detected spot's centre as the point where its dot's centre ray
lands. The detector measures the centre of the spot's light, and the water does not reflect
a dot's light evenly:

- Fresnel's reflectance from below rises steeply towards the critical angle (2 % at normal
  incidence, 100 % at 48.6 degrees for n = 4/3), so the side of a dot that meets the surface
  more obliquely is brighter;
- on rough water (GGX microfacets of width alpha, the scene's ``[water] roughness``) each
  point of the dot is reflected about a spread of facet normals, and that same slope of the
  reflectance weights the facets tilted towards grazing incidence: the whole spot moves,
  by about a pixel of camera s at alpha = 0.01 on the paper's rig, and by how much depends on
  the surface's slope under the dot;
- a curved surface maps the dot's Gaussian onto the diffuser unevenly.

The flat-water reference (``flat_referenced``, the default) removes the part that flat water
has too; this module models the rest. Each dot is a set of Gauss-Hermite points of its
Gaussian (:class:`~restoration.pattern_model.DotParticles`), reflected at the surface about
its normal, or about each of a fixed set of GGX facet slopes, weighted by the light each
carries (Fresnel's reflectance at its facet, the facet's share of the projected area) onto the
diffuser. The spot's bias is that weighted centroid less the centre ray's spot, in camera s's
pixels, and the correction subtracts from each detected spot its bias on the surface less its
bias on flat water at the gauge's level: :func:`spot_bias_px`.

The model is of a spot alone. On rough water every spot's halo lies to the same side, so with
every dot lit a neighbour's halo lights the opposite flank of each spot and takes part of its
shift back; on smooth water there is no halo and nothing is taken back. The flat reference
says how much: its spots' shifts from their calibrated places against the model's flat-water
bias have a least-squares slope of 0.98 along x on smooth water and 0.40-0.64 at GGX
alpha 0.01 (docs/results.md). On rough water the correction is scaled by that slope, per axis
(:func:`flat_gain`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from restoration.fit import SMOOTHNESS, BSplineSurface, hits, knot_step, spline_through
from restoration.pattern_model import dot_quadrature, facet_light, ggx_facet_slopes
from wai_core.light_paths import dot_rays, real_spot_px, spots_from_hits
from wai_core.optics import pattern_index

__all__ = ["MIN_GAIN_SPOTS", "SpotBiasModel", "flat_gain", "shown_share", "spot_bias_px",
           "spot_correction_px"]

Array = NDArray[np.float64]

MIN_GAIN_SPOTS = 50
"""Flat-water spots :func:`shown_share` needs to fit the share; with fewer the correction
takes the model's shift whole."""


@dataclass(frozen=True)
class SpotBiasModel:
    """What the spots' bias depends on besides the surface.

    Attributes
    ----------
    roughness : float
        The water's micro-roughness, GGX alpha (0: smooth).
    n_water : float
        The water's index (the reflectance's).
    order : int
        Gauss-Hermite points per axis of each dot.
    facets : int
        GGX facet slopes per point (rough water only).
    window : float
        The detector's centroid window, as a multiple of the spot's covariance (0: the plain
        centroid of the spot's light).
    """

    roughness: float = 0.0
    n_water: float = 4.0 / 3.0
    order: int = 4
    facets: int = 32
    window: float = 1.75

    @classmethod
    def of_scene(cls, cfg: Any) -> SpotBiasModel:
        """The model of a scene: its water's roughness, and the index the pattern's light
        meets at the surface (:func:`wai_core.optics.pattern_index`: ``[water] n_water``, or
        sea water's at the pattern's colour).

        Examples
        --------
        >>> from wai_core import load_system
        >>> SpotBiasModel.of_scene(load_system("paper")).roughness
        0.0
        """
        return cls(roughness=float(cfg.water.roughness), n_water=pattern_index(cfg))


def spot_bias_px(rig: Any, panel_px: Array, surface: BSplineSurface | None, level_mm: float,
                 model: SpotBiasModel) -> Array:
    """The light centroid of the dots at ``panel_px`` (K, 2) less their centre rays' spots,
    camera s pixels (K, 2), on ``surface`` (None: flat water at ``level_mm``); NaN where a
    dot's light leaves the surface or the diffuser.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system
    >>> rig = load_system("paper").rig
    >>> smooth = spot_bias_px(rig, rig.dot_panel_px[:3], None, rig.cfg.water.h0_mm,
    ...                       SpotBiasModel())
    >>> rough = spot_bias_px(rig, rig.dot_panel_px[:3], None, rig.cfg.water.h0_mm,
    ...                      SpotBiasModel(roughness=0.01))
    >>> bool(np.abs(smooth).max() < np.abs(rough).max())
    True
    """
    panel_px = np.asarray(panel_px, float)
    k = len(panel_px)
    offsets, weights = dot_quadrature(rig, model.order)
    offsets, weights = np.vstack([[0.0, 0.0], offsets]), np.r_[0.0, weights]
    m = len(offsets)  # the centre ray first (no weight), then the quadrature points
    origin, dirs = dot_rays(rig, (panel_px[:, None, :] + offsets[None]).reshape(-1, 2))
    t = (level_mm - origin[..., 2]) / dirs[:, 2]
    if surface is None:
        surface = BSplineSurface.covering((origin + t[:, None] * dirs)[:, :2], 10.0, level_mm)
    t = hits(surface, origin, dirs, t, n_iter=3)
    hit = origin + t[:, None] * dirs
    _, gx, gy = surface.evaluate(hit[:, 0], hit[:, 1])[:3]
    n_water = float(model.n_water)
    centre = slice(0, None, m)
    normal, _ = facet_light(dirs[centre], gx[centre], gy[centre], None, n_water)
    centre_px = real_spot_px(rig, spots_from_hits(rig, hit[centre], dirs[centre], normal).px)
    slopes = (ggx_facet_slopes(model.roughness, model.facets) if model.roughness > 0
              else np.zeros((1, 2)))
    f = len(slopes)
    d = np.repeat(dirs, f, axis=0)
    normal, light = facet_light(d, np.repeat(gx, f), np.repeat(gy, f),
                                np.tile(slopes, (k * m, 1)), n_water)
    weight = (np.tile(np.repeat(weights, f), k) / f * light).reshape(k, m * f)
    px = real_spot_px(rig, spots_from_hits(rig, np.repeat(hit, f, axis=0), d, normal).px)
    px = px.reshape(k, m * f, 2)
    good = (np.isfinite(px).all(axis=2).all(axis=1) & np.isfinite(weight).all(axis=1)
            & (np.nansum(weight, axis=1) > 0))
    px = np.where(good[:, None, None], px, 0.0)
    weight = np.where(good[:, None], weight, 0.0)
    bias = _windowed_centroid(px, weight, model.window) - centre_px
    bias[~good] = np.nan
    return bias


def _windowed_centroid(px: Array, weight: Array, window: float, n_iter: int = 3) -> Array:
    """Each spot's centre (K, 2) from its particles ``px`` (K, P, 2) of ``weight`` (K, P), as
    the detector finds it: a Gaussian-windowed centroid (window covariance ``window`` times the
    spot's, plus a pixel's box, iterated with the detector's gain); the plain centroid for
    ``window`` 0."""
    total = np.where(weight.sum(axis=1) > 0, weight.sum(axis=1), 1.0)
    x = np.einsum("kp,kpc->kc", weight, px) / total[:, None]
    if window <= 0:
        return x
    d = px - x[:, None, :]
    cov = np.einsum("kp,kpa,kpb->kab", weight, d, d) / total[:, None, None]
    cov = cov + np.eye(2) / 12.0  # the pixel's box
    inv = np.linalg.inv(window * cov + np.eye(2) / 12.0)
    gain = 1.0 + 1.0 / window
    for _ in range(n_iter):
        d = px - x[:, None, :]
        w = weight * np.exp(-0.5 * np.einsum("kpa,kab,kpb->kp", d, inv, d))
        s = np.where(w.sum(axis=1) > 0, w.sum(axis=1), 1.0)
        x = x + gain * np.einsum("kp,kpc->kc", w, d) / s[:, None]
    return x


def shown_share(shift_px: Array, model_px: Array) -> Array:
    """The least-squares slope (with an intercept), per axis (2,), of measured spot shifts
    ``shift_px`` (K, 2) (a flat reference's spots less their calibrated places) on the
    model's flat-water bias ``model_px`` (K, 2) at the same dots: the share of the modelled
    shift the spots show. NaN on an axis the model does not vary along, or with fewer than
    :data:`MIN_GAIN_SPOTS` dots where both are known.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> model = rng.normal(0.0, 0.3, (400, 2))
    >>> shift = 0.55 * model + 0.02 + rng.normal(0.0, 0.05, (400, 2))
    >>> np.round(shown_share(shift, model), 1)
    array([0.6, 0.6])
    """
    share = np.full(2, np.nan)
    known = np.isfinite(shift_px).all(axis=1) & np.isfinite(model_px).all(axis=1)
    if known.sum() < MIN_GAIN_SPOTS:
        return share
    for axis in (0, 1):
        m = model_px[known, axis] - model_px[known, axis].mean()
        spread = float(m @ m)
        if spread > 0:
            share[axis] = float(m @ shift_px[known, axis]) / spread
    return share


def flat_gain(shift_px: Array, model_px: Array, roughness: float) -> Array:
    """The share of the modelled bias a correction takes off, per axis (2,): on rough water
    what the flat reference shows (:func:`shown_share` of its measured shifts ``shift_px`` on
    the model's flat-water bias ``model_px``, each (K, 2)), clipped to [0, 1]; 1 on smooth
    water (``roughness`` 0: no halo, nothing taken back) and where the share is unknown.

    Examples
    --------
    >>> import numpy as np
    >>> model = np.random.default_rng(1).normal(0.0, 0.3, (400, 2))
    >>> flat_gain(0.5 * model, model, 0.01), flat_gain(0.5 * model, model, 0.0)
    (array([0.5, 0.5]), array([1., 1.]))
    """
    if roughness <= 0:
        return np.ones(2)
    share = shown_share(shift_px, model_px)
    return np.clip(np.where(np.isfinite(share), share, 1.0), 0.0, 1.0)


def spot_correction_px(cal: Any, ij: NDArray, surface: Any, model: SpotBiasModel) -> Array:
    """What to subtract from the detected spots of the dots ``ij`` (K, 2) before they are
    observed (K, 2), camera s pixels: each dot's bias on ``surface`` (a
    :class:`~restoration.surface.SurfaceEstimate`, as a spline through its heights and slopes)
    less its bias on flat water (which the flat reference holds too), times the share of it
    the flat reference shows (:meth:`restoration.Calibration.spot_bias_gain`, 1 on smooth
    water); zero where either bias is unknown."""
    rig = cal.cfg.rig
    dots = rig.dot_index(ij)
    xy = surface.points_mm[:, :2]
    spline = spline_through(xy, surface.points_mm[:, 2], surface.slopes, knot_step(xy),
                            SMOOTHNESS)
    level = float(surface.anchor.anchor_mm)
    on_surface = spot_bias_px(rig, rig.dot_panel_px[dots], spline, level, model)
    correction = (on_surface - cal.flat_spot_bias_px(model)[dots]) * cal.spot_bias_gain(model)
    return np.where(np.isfinite(correction), correction, 0.0)
