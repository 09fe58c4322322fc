"""Camera s's pattern image as a differentiable function of the water surface.

The projector's dots are Gaussians on its panel (``[pattern] sigma_px``). Each dot is carried
by a fixed set of particles: Gauss-Hermite points of its Gaussian (their centroid and spread
exactly the dot's), whose rays leave the projector through its optics
(:func:`wai_core.light_paths.dot_rays`), reflect off the surface (a B-spline,
:class:`~restoration.fit.BSplineSurface`) about its normal, or about a microfacet's when the
water is rough (a fixed set of GGX slopes, ``alpha`` the scene's roughness), meet the
diffuser plane and are imaged by camera s (its lens and port included). The model image is

    M(x) = b + sum_j A_j sum_{p in j} w_p (G_sigma * splat(q_p))(x)

``q_p`` the particle's pixel, ``splat`` its bilinear footprint, ``G_sigma`` a Gaussian blur
(the scale of the fit), ``A_j`` each dot's brightness (fitted by linear least squares: the
dots' brightness depends on the Fresnel reflectance, the diffuser's profile and camera s's
vignetting, none of which the fit needs to know) and ``b`` the background.

Its derivative in the spline's coefficients is the exact adjoint: the residual image blurred
by ``G_sigma`` (symmetric, its own adjoint), its bilinear gradient at each particle (the
splat's adjoint) and the particle's pixel Jacobian in the coefficients
(:func:`restoration.fit.linearise` and camera s's projection). ``tests/restoration/
test_pattern_model.py`` checks it against finite differences of the loss.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter, gaussian_filter1d

from restoration.fit import BSplineSurface, hits, linearise
from wai_core.geometry import fresnel_reflectance
from wai_core.light_paths import dot_rays, real_spot_px

__all__ = ["DotParticles", "PatternModel", "Raster", "Traced", "dot_quadrature", "facet_light",
           "ggx_facet_slopes"]

Array = NDArray[np.float64]

BLUR_TRUNCATE = 3.0
"""The model image's Gaussian blur ends this many standard deviations out."""

_FD_MM = 1e-3  # finite-difference step of camera s's projection on the diffuser, mm
GGX_CAP = 0.9
"""Microfacet slopes are drawn from GGX's distribution up to this quantile of their radius
(the tail beyond it spreads its light over many spots: the background takes it)."""


def ggx_facet_slopes(roughness: float, facets: int) -> Array:
    """A fixed set of ``facets`` microfacet slopes (F, 2) of GGX's distribution of width
    ``roughness`` (alpha): rings at its radius quantiles up to :data:`GGX_CAP`, evenly spaced
    angles turned ring to ring, their mean zero.

    Examples
    --------
    >>> s = ggx_facet_slopes(0.01, 32)
    >>> s.shape, bool(abs(s.mean(axis=0)).max() < 1e-15)
    ((32, 2), True)
    """
    facet = np.arange(int(facets))
    rings = max(1, int(round(np.sqrt(facets / 2))))
    q = ((facet % rings) + 0.5) / rings * GGX_CAP
    radius = roughness * np.sqrt(q / (1.0 - q))  # GGX: P(|slope| < r) = r^2/(a^2+r^2)
    phi = 2 * np.pi * (facet / facets + (facet % rings) / (2.0 * facets))
    slopes = np.column_stack([radius * np.cos(phi), radius * np.sin(phi)])
    return slopes - slopes.mean(axis=0)


def dot_quadrature(rig: Any, order: int) -> tuple[Array, Array]:
    """Gauss-Hermite points of a dot's Gaussian (``[pattern] sigma_px``), ``order`` per axis:
    their offsets from the dot's centre (M, 2), panel pixels, and weights (M,) summing to 1
    (their centroid and spread exactly the dot's).

    Examples
    --------
    >>> from wai_core import load_system
    >>> offsets, weights = dot_quadrature(load_system("paper").rig, 3)
    >>> offsets.shape, round(float(weights.sum()), 12)
    ((9, 2), 1.0)
    """
    nodes, w = np.polynomial.hermite_e.hermegauss(int(order))
    w = w / w.sum()
    sigma = float(rig.cfg.pattern.sigma_px)
    ox, oy = np.meshgrid(sigma * nodes, sigma * nodes)
    return np.column_stack([ox.ravel(), oy.ravel()]), np.outer(w, w).ravel()


def facet_light(dirs: Array, gx: Array, gy: Array, slope_offset: Array | None,
                n_water: float) -> tuple[Array, Array]:
    """Where rays of unit directions ``dirs`` (P, 3) meet a surface of slopes ``gx``, ``gy``
    (P,), each about a microfacet of slope ``slope_offset`` (P, 2) more (None: the surface's
    own normal): the facets' unit normals (P, 3), and the share of each ray's light the facet
    reflects (P,): Fresnel's reflectance at it times its share of the projected area (the
    incidence cosine on the facet over that on the surface).

    Examples
    --------
    >>> import numpy as np
    >>> up = np.array([[0.0, 0.0, 1.0]])
    >>> normal, light = facet_light(up, np.zeros(1), np.zeros(1), None, 4.0 / 3.0)
    >>> normal.tolist(), round(float(light[0]), 4)  # ((n - 1) / (n + 1))^2 at normal incidence
    ([[-0.0, -0.0, 1.0]], 0.0204)
    """
    macro = np.column_stack([-gx, -gy, np.ones_like(gx)])
    facet = macro.copy()
    if slope_offset is not None:
        facet[:, :2] -= slope_offset
    macro /= np.linalg.norm(macro, axis=1, keepdims=True)
    facet /= np.linalg.norm(facet, axis=1, keepdims=True)
    cos_macro = np.abs(np.sum(dirs * macro, axis=1))
    cos_facet = np.abs(np.sum(dirs * facet, axis=1))
    return facet, fresnel_reflectance(cos_facet, n_water) * cos_facet / cos_macro


@dataclass(frozen=True)
class DotParticles:
    """The fixed particles that carry the dots' light (module notes).

    Attributes
    ----------
    origin_mm : (3,) or (P, 3) ndarray
        Where the particles' rays leave the projector (or its port), mm.
    dirs : (P, 3) ndarray
        Their unit directions in the water.
    dot : (P,) ndarray of int
        Each particle's dot (an index into the dots given).
    weight : (P,) ndarray
        Each particle's share of its dot's light (a dot's sum to 1).
    slope_offset : (P, 2) ndarray or None
        Each particle's microfacet slope (None: smooth water).
    n_dots : int
        The number of dots.
    """

    origin_mm: Array
    dirs: Array
    dot: NDArray[np.int64]
    weight: Array
    slope_offset: Array | None
    n_dots: int

    @classmethod
    def of(cls, rig: Any, panel_px: Array, order: int = 4, roughness: float = 0.0,
           facets: int = 8) -> DotParticles:
        """The particles of the dots at ``panel_px`` (K, 2), panel pixels: Gauss-Hermite
        points of each dot's Gaussian, ``order`` per axis (their centroid and spread exactly
        the dot's); with ``roughness`` (GGX alpha) > 0, each point with ``facets`` microfacet
        slopes (rings at GGX's radius quantiles, up to :data:`GGX_CAP`, and evenly spaced
        angles turned ring to ring: their mean is zero).

        Examples
        --------
        >>> from wai_core import load_system
        >>> rig = load_system("paper").rig
        >>> parts = DotParticles.of(rig, rig.dot_panel_px[:5], order=4)
        >>> parts.dirs.shape, round(float(parts.weight[parts.dot == 0].sum()), 12)
        ((80, 3), 1.0)
        """
        k = len(panel_px)
        offsets, weights = dot_quadrature(rig, order)
        slopes = None
        if roughness > 0:
            facet_slopes = ggx_facet_slopes(roughness, facets)
            m = len(offsets)
            offsets = np.repeat(offsets, facets, axis=0)
            weights = np.repeat(weights, facets) / facets
            slopes = np.tile(np.tile(facet_slopes, (m, 1)), (k, 1))
        per_dot = len(offsets)
        points = (np.asarray(panel_px, float)[:, None, :] + offsets[None]).reshape(-1, 2)
        origin, dirs = dot_rays(rig, points)
        dot = np.repeat(np.arange(k), per_dot)
        return cls(origin, dirs, dot, np.tile(weights, k), slopes, k)


@dataclass(frozen=True)
class Traced:
    """The particles traced through one surface (:meth:`PatternModel.trace`).

    Attributes
    ----------
    t : (P,) ndarray
        Ray parameters of the hits on the surface (the next trace's start).
    px : (P, 2) ndarray
        Camera s pixels ``(col, row)`` of the particles.
    index : (P, 16) ndarray of int
        The flat coefficients each particle depends on.
    jacobian : (P, 2, 16) ndarray
        ``d px / d coefficient``, px per mm.
    ok : (P,) ndarray of bool
        The particle meets the surface, the diffuser and camera s's image.
    """

    t: Array
    px: Array
    index: NDArray[np.int64]
    jacobian: Array
    ok: NDArray[np.bool_]


class PatternModel:
    """The dots' particles through a spline surface into camera s (module notes).

    Parameters
    ----------
    rig : wai_core.rig.Rig
        The rig (camera s, the diffuser plane, the water's level).
    particles : DotParticles
        The particles.
    shape : tuple of int
        Camera s's image size ``(H, W)``, px.
    """

    def __init__(self, rig: Any, particles: DotParticles, shape: tuple[int, int]) -> None:
        self.rig = rig
        self.particles = particles
        self.shape = (int(shape[0]), int(shape[1]))
        self.z_h_mm = float(rig.cfg.diffuser.z_mm)

    def reflectance(self, spline: BSplineSurface, traced: Traced, n_water: float) -> Array:
        """Each particle's share of its dot's light once reflected (P,): its weight times
        Fresnel's reflectance at its facet and the facet's share of the projected area,
        normalised so that a dot's shares sum to 1 (its brightness is fitted apart)."""
        p = self.particles
        hit = p.origin_mm + traced.t[:, None] * p.dirs
        _, gx, gy = spline.evaluate(hit[:, 0], hit[:, 1])[:3]
        light = p.weight * facet_light(p.dirs, gx, gy, p.slope_offset, n_water)[1]
        light = np.where(traced.ok & np.isfinite(light), light, 0.0)
        total = np.bincount(p.dot, light, minlength=p.n_dots)
        return light / np.where(total > 0, total, 1.0)[p.dot]

    def flat_t(self, level_mm: float) -> Array:
        """Ray parameters (P,) where the particles' rays reach the height ``level_mm``."""
        p = self.particles
        oz = p.origin_mm[..., 2]
        return (level_mm - oz) / p.dirs[:, 2]

    def _pixels(self, on_diffuser: Array) -> Array:
        """Camera s's real pixels (P, 2) of diffuser points (P, 3), mm."""
        cols, rows, front = self.rig.camera_s.project(on_diffuser)
        px = np.column_stack([cols, rows])
        px[~front] = np.nan
        return real_spot_px(self.rig, px)

    def trace(self, spline: BSplineSurface, t: Array) -> Traced:
        """Trace every particle through ``spline`` (Newton on its hit from ``t`` (P,)) into
        camera s, with the pixels' derivatives in the coefficients."""
        p = self.particles
        t = hits(spline, p.origin_mm, p.dirs, t, n_iter=3)
        lin = linearise(spline, p.origin_mm, p.dirs, t, self.z_h_mm, p.slope_offset)
        x = np.column_stack([lin.spots_mm, np.full(len(t), self.z_h_mm)])
        q = self._pixels(x)
        dq = np.empty((len(t), 2, 2))
        for axis in (0, 1):
            step = x.copy()
            step[:, axis] += _FD_MM
            dq[:, :, axis] = (self._pixels(step) - q) / _FD_MM
        jac = np.einsum("pab,pbk->pak", dq, lin.jacobian)
        h, w = self.shape
        ok = (lin.ok & np.isfinite(q).all(axis=1) & np.isfinite(jac).all(axis=(1, 2))
              & (q[:, 0] > -0.5) & (q[:, 0] < w - 0.5) & (q[:, 1] > -0.5) & (q[:, 1] < h - 0.5))
        return Traced(t, np.where(ok[:, None], q, 0.0), lin.index,
                      np.where(ok[:, None, None], jac, 0.0), ok)


class Raster:
    """Camera s's image blurred by ``sigma_px``: the splat of particles into it, and the
    adjoints the fit needs.

    Examples
    --------
    >>> import numpy as np
    >>> r = Raster((600, 800), sigma_px=1.0)
    >>> img = r.splat(np.array([[400.25, 300.0]]), np.array([1.0]), np.array([True]))
    >>> img.shape, round(float(img.sum()), 6), img[300, 400:402].tolist()
    ((600, 800), 1.0, [0.75, 0.25])
    """

    def __init__(self, shape: tuple[int, int], sigma_px: float) -> None:
        self.sigma_px = float(sigma_px)
        self.shape = (int(shape[0]), int(shape[1]))

    def blur(self, image: Array) -> Array:
        """``image`` blurred by the Gaussian of :attr:`sigma_px` (zero beyond the image)."""
        return gaussian_filter(image, self.sigma_px, mode="constant", truncate=BLUR_TRUNCATE)

    @property
    def kernel(self) -> Array:
        """The blur's one-dimensional kernel (2 r + 1,), weights summing to 1: :meth:`blur`
        applies it along each axis in turn (scipy's own, read off its response to an
        impulse)."""
        half = int(np.ceil(BLUR_TRUNCATE * self.sigma_px)) + 1
        impulse = np.zeros(2 * half + 1)
        impulse[half] = 1.0
        response = gaussian_filter1d(impulse, self.sigma_px, mode="constant",
                                     truncate=BLUR_TRUNCATE)
        return response[response > 0]

    def _cells(self, px: Array) -> tuple[NDArray, NDArray, Array, Array]:
        h, w = self.shape
        i0 = np.floor(px).astype(np.int64)
        # One pixel of border on every side: a particle's footprint never wraps.
        cx, cy = np.clip(i0[:, 0], -1, w - 1) + 1, np.clip(i0[:, 1], -1, h - 1) + 1
        return cx, cy, px[:, 0] - i0[:, 0], px[:, 1] - i0[:, 1]

    def splat(self, px: Array, weight: Array, ok: NDArray[np.bool_]) -> Array:
        """The particles at ``px`` (P, 2) pixels with ``weight`` (P,), bilinear, into the
        image (unblurred); particles not ``ok`` add nothing."""
        h, w = self.shape
        cx, cy, fx, fy = self._cells(px)
        wt = np.where(ok, weight, 0.0)
        stride, size = w + 2, (h + 2) * (w + 2)
        out = np.zeros(size)
        for dy, wy in ((0, 1 - fy), (1, fy)):
            for dx, wx in ((0, 1 - fx), (1, fx)):
                out += np.bincount((cy + dy) * stride + cx + dx, wt * wy * wx, minlength=size)
        return out.reshape(h + 2, w + 2)[1:-1, 1:-1]

    def sample(self, image: Array, px: Array) -> tuple[Array, Array]:
        """Bilinear values (P,) of ``image`` at ``px`` (P, 2) and their gradient in ``px``
        (P, 2), per pixel (zero beyond the image): the adjoint of :meth:`splat` and of its
        derivative in the particles' positions."""
        padded = np.pad(image, 1)
        cx, cy, fx, fy = self._cells(px)
        v00, v01 = padded[cy, cx], padded[cy, cx + 1]
        v10, v11 = padded[cy + 1, cx], padded[cy + 1, cx + 1]
        value = (1 - fy) * ((1 - fx) * v00 + fx * v01) + fy * ((1 - fx) * v10 + fx * v11)
        gx = (1 - fy) * (v01 - v00) + fy * (v11 - v10)
        gy = (1 - fx) * (v10 - v00) + fx * (v11 - v01)
        return value, np.column_stack([gx, gy])
