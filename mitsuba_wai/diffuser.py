"""A real diffuser screen for system S: angular profile, back-reflection and thickness blur.

The paper's geometric model, and the default scene, assume an ideal one-way screen
(``oneway_diffuser`` in :mod:`mitsuba_wai.bsdfs`): light from above leaves below as a Lambertian
lobe, light from below passes straight through. A real screen differs in three ways, each a key
of ``[diffuser]`` and off by default:

``half_width_deg`` (``theta_h``)
    Transmitted radiance ``L(theta) ∝ exp(-ln 2 (theta / theta_h)^2)``, ``theta`` the angle from
    the screen's downward normal, so ``L`` falls to half at ``theta = theta_h`` (the half width
    at half maximum); 0 keeps Lambertian (constant radiance). The profile is cut at
    :data:`PROFILE_CUT_HWHM` ``theta_h`` (where it is below 3e-8 of its peak) or at 90 deg. The
    BSDF is ``f = tau g(theta_o) / (2 pi I)`` with ``g`` the profile,
    ``I = int_0^cut g cos sin dtheta`` and ``tau = (1 - reflectance) x albedo`` the transmitted
    share of the arriving flux: ``int f |cos theta_o| d omega = tau``, whatever the direction of
    arrival (a screen that forgets where the light came from).
``reflectance`` (``r``)
    That share of the light arriving from above goes back up as a Lambertian lobe,
    ``f = r / pi``. It meets the water from below, which reflects part of it (all of it beyond the
    critical angle, 1 - 1/n^2 = 44 % of a Lambertian source's flux at n = 4/3) back onto the
    screen: a glow about the spots. That path has two more vertices, so the particle tracer's
    depth grows from 4 to 6 (:func:`mitsuba_wai.scenes.pattern_depth`).
``blur_mm`` (``sigma_b``)
    Light spreads sideways inside the screen's thickness before it leaves: a Gaussian of
    standard deviation ``sigma_b`` on the screen plane, applied to camera s's image
    (:func:`screen_blur`).

Light from below still passes straight through (a delta transmission of weight 1): the screen
stays one-way for the projector's beam, as in the ideal one (see :mod:`mitsuba_wai.bsdfs`).

Sampling (``real_diffuser``): from above, the reflected lobe with probability
``r / (r + tau)`` (cosine-weighted hemisphere), else the transmitted lobe: ``phi`` uniform and
``theta`` by the inverse CDF of a piecewise-linear density tabulated at :data:`PROFILE_NODES`
nodes, ``p(theta) ∝ g(theta) cos(theta) sin(theta)`` on ``[0, cut]`` (Mitsuba's
``ContinuousDistribution``). ``pdf`` returns the density of exactly that warp,
``p_lin(theta) / (2 pi sin theta)`` per steradian; ``eval`` the exact profile; a sample's weight
is their ratio (within ~1e-5 of ``tau`` for the interpolant), so the estimate is unbiased.

The BSDF's arguments follow light transport (``TransportMode.Importance``, Mitsuba's
``ptracer`` and :mod:`mitsuba_wai.particles`): ``si.wi`` points to where the light came from.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.integrate import quad

from wai_core.config import SystemConfig

__all__ = [
    "PROFILE_CUT_HWHM",
    "PROFILE_NODES",
    "blur_sigma_px",
    "diffuser_bsdf",
    "profile",
    "profile_norm",
    "register",
    "screen_blur",
]

PROFILE_CUT_HWHM = 5.0
"""The profile is zero beyond this many half widths (``exp(-25 ln 2) = 3e-8`` of its peak)."""

PROFILE_NODES = 1024
"""Nodes of the tabulated density in ``theta`` that the transmitted lobe is sampled by."""

_REGISTERED = False
_LN2 = float(np.log(2.0))


def is_real(cfg: SystemConfig) -> bool:
    """True when any ``[diffuser]`` key of the real screen is on."""
    d = cfg.diffuser
    return d.half_width_deg > 0 or d.reflectance > 0 or d.blur_mm > 0


def profile(theta_rad: NDArray, half_width_rad: float) -> NDArray:
    """Transmitted radiance relative to the normal's, ``exp(-ln 2 (theta / theta_h)^2)``, zero
    past the cut (:data:`PROFILE_CUT_HWHM`) or 90 deg; 1 everywhere below for ``theta_h = 0``.

    Parameters
    ----------
    theta_rad : ndarray, any shape
        Angle from the screen's downward normal, radians.
    half_width_rad : float
        ``theta_h``, radians (0: Lambertian).

    Returns
    -------
    ndarray, same shape as ``theta_rad``
    """
    th = np.asarray(theta_rad, dtype=float)
    if half_width_rad <= 0:
        return np.where(th <= np.pi / 2, 1.0, 0.0)
    g = np.exp(-np.log(2.0) * (th / half_width_rad) ** 2)
    return np.where(th <= _cut_rad(half_width_rad), g, 0.0)


def profile_norm(half_width_rad: float) -> float:
    """``1 / (2 pi I)``, ``I = int g cos sin dtheta``: the BSDF per unit transmitted share
    at the profile's peak, 1/sr (``1 / pi`` for Lambertian)."""
    if half_width_rad <= 0:
        return 1.0 / np.pi
    cut = _cut_rad(half_width_rad)
    integral, _ = quad(
        lambda t: profile(t, half_width_rad) * np.cos(t) * np.sin(t), 0.0, cut,
        points=[half_width_rad], epsabs=0.0, epsrel=1e-12, limit=200,
    )
    return float(1.0 / (2.0 * np.pi * integral))


def _cut_rad(half_width_rad: float) -> float:
    return float(min(np.pi / 2, PROFILE_CUT_HWHM * half_width_rad))


def diffuser_bsdf(cfg: SystemConfig) -> dict:
    """The diffuser's BSDF in system S: ``real_diffuser`` when any ``[diffuser]`` key of the
    real screen is on, else the ideal ``oneway_diffuser`` (the same dict as always)."""
    from mitsuba_wai.bsdfs import register as register_ideal

    register_ideal()
    if not is_real(cfg):
        return {"type": "oneway_diffuser"}
    register()
    d = cfg.diffuser
    return {
        "type": "real_diffuser",
        "half_width_deg": float(d.half_width_deg),
        "reflectance": float(d.reflectance),
    }


def blur_sigma_px(cfg: SystemConfig) -> float:
    """``blur_mm`` in camera-s pixels at the screen's centre: ``sigma_b f_px / z_cam``.

    The scale of a pinhole at depth ``z_cam`` (the screen centre's depth along camera s's axis).
    It holds across the image for a camera facing the screen squarely (the paper's camera s
    looks straight up); for a tilted one it is the scale at the centre, an approximation.
    """
    cam = cfg.rig.camera_s
    rect = cfg.rig.diffuser_rect
    centre = np.array([rect[0].mean(), rect[1].mean(), cfg.diffuser.z_mm])
    depth = float((centre - cam.pose.center_lab_mm) @ cam.pose.axis_lab)
    return float(cfg.diffuser.blur_mm) * cam.focal_px / depth


def screen_blur(image: NDArray[np.float32], cfg: SystemConfig) -> NDArray[np.float32]:
    """Camera s's image of the screen with the spread inside its thickness (``blur_mm``).

    A Gaussian of :func:`blur_sigma_px` over rows and columns of each channel; the image's
    border is continued by its mirror (``scipy.ndimage``'s ``reflect``), so a uniform glow stays
    uniform up to the edge. With ``blur_mm = 0`` the image itself is returned, untouched.

    Parameters
    ----------
    image : (H, W, 3) ndarray of float32
        Linear RGB seen by camera s.
    cfg : SystemConfig

    Returns
    -------
    (H, W, 3) ndarray of float32
    """
    if cfg.diffuser.blur_mm <= 0:
        return image
    from scipy.ndimage import gaussian_filter

    sigma = blur_sigma_px(cfg)
    return gaussian_filter(image, sigma=(sigma, sigma, 0.0), mode="reflect").astype(np.float32)


def register() -> None:
    """Register ``real_diffuser`` with Mitsuba (once, after the variant is set)."""
    global _REGISTERED
    if _REGISTERED:
        return
    import drjit as dr
    import mitsuba as mi

    class RealDiffuser(mi.BSDF):
        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            albedo = float(props.get("albedo", 1.0))
            r = float(props.get("reflectance", 0.0))
            half_width = np.radians(float(props.get("half_width_deg", 0.0)))
            self.refl = r
            self.trans = (1.0 - r) * albedo
            self.p_refl = r / (r + self.trans) if r + self.trans > 0 else 0.0
            self.lambertian = half_width <= 0
            self.half_width = float(half_width)
            # BSDF at the profile's peak: tau / (2 pi I).
            self.peak = float(self.trans * profile_norm(half_width))
            if not self.lambertian:
                self.cut = float(_cut_rad(half_width))
                nodes = np.linspace(0.0, self.cut, PROFILE_NODES)
                density = profile(nodes, half_width) * np.cos(nodes) * np.sin(nodes)
                self.dist = mi.ContinuousDistribution(
                    mi.ScalarVector2f(0.0, self.cut), mi.Float(density)
                )
                # Slope of the interpolant at theta = 0 over (2 pi): the pdf's limit there.
                self.pdf_at_normal = float(
                    density[1] / nodes[1] / (2.0 * np.pi) / self.dist.integral()[0]
                )
            front = mi.BSDFFlags.FrontSide
            lobe = mi.BSDFFlags.DiffuseTransmission if self.lambertian else (
                mi.BSDFFlags.GlossyTransmission)
            self.trans_flag = lobe
            reflect = mi.BSDFFlags.DiffuseReflection | front
            through = mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.BackSide
            self.m_components = [lobe | front, reflect, through]
            self.m_flags = lobe | front | reflect | through

        def _theta(self, wo):
            """Angle of a local direction from the downward normal, and its sine."""
            sin_t = dr.sqrt(dr.square(wo.x) + dr.square(wo.y))
            return dr.atan2(sin_t, -wo.z), sin_t

        def _trans_eval(self, wo):
            """Transmitted BSDF times |cos theta_o| (the caller checks the side)."""
            cos_o = -mi.Frame3f.cos_theta(wo)
            if self.lambertian:
                return self.peak * cos_o
            theta, _ = self._theta(wo)
            g = dr.exp(-_LN2 * dr.square(theta / self.half_width))
            return dr.select(theta <= self.cut, self.peak * g * cos_o, 0.0)

        def _trans_pdf(self, wo):
            """Solid-angle density of the transmitted lobe's warp (the caller checks the side)."""
            if self.lambertian:
                return dr.inv_pi * -mi.Frame3f.cos_theta(wo)
            theta, sin_t = self._theta(wo)
            p_theta = self.dist.eval_pdf_normalized(theta)
            return dr.select(sin_t > 1e-6, p_theta / (2.0 * dr.pi * sin_t), self.pdf_at_normal)

        def sample(self, ctx, si, sample1, sample2, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            from_above = cos_i > 0
            reflect = from_above & (sample1 < self.p_refl)
            if self.lambertian:
                down = mi.warp.square_to_cosine_hemisphere(sample2)
                down = mi.Vector3f(down.x, down.y, -down.z)
            else:
                theta, _ = self.dist.sample_pdf(sample2.x)
                sin_t, cos_t = dr.sincos(theta)
                sin_p, cos_p = dr.sincos(2.0 * dr.pi * sample2.y)
                down = mi.Vector3f(sin_t * cos_p, sin_t * sin_p, -cos_t)
            up = mi.warp.square_to_cosine_hemisphere(sample2)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = dr.select(from_above, dr.select(reflect, up, down), -si.wi)
            pdf_t = (1.0 - self.p_refl) * self._trans_pdf(down)
            pdf_r = self.p_refl * mi.warp.square_to_cosine_hemisphere_pdf(up)
            bs.pdf = dr.select(from_above, dr.select(reflect, pdf_r, pdf_t), 1.0)
            bs.eta = 1.0
            bs.sampled_type = dr.select(
                from_above,
                dr.select(reflect, mi.UInt32(+mi.BSDFFlags.DiffuseReflection),
                          mi.UInt32(+self.trans_flag)),
                mi.UInt32(+mi.BSDFFlags.DeltaTransmission),
            )
            bs.sampled_component = dr.select(
                from_above, dr.select(reflect, mi.UInt32(1), mi.UInt32(0)), mi.UInt32(2)
            )
            value_t = self._trans_eval(down)
            value_r = self.refl * dr.inv_pi * mi.Frame3f.cos_theta(up)
            value = dr.select(reflect, value_r, value_t)
            weight = dr.select(from_above, value / dr.maximum(bs.pdf, 1e-30), 1.0)
            ok = active & (cos_i != 0) & (bs.pdf > 0)
            return bs, dr.select(ok, mi.Spectrum(weight), 0.0)

        def eval(self, ctx, si, wo, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            value = dr.select(cos_o < 0, self._trans_eval(wo), self.refl * dr.inv_pi * cos_o)
            ok = active & (cos_i > 0) & (cos_o != 0)
            return dr.select(ok, mi.Spectrum(value), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            value = dr.select(
                cos_o < 0,
                (1.0 - self.p_refl) * self._trans_pdf(wo),
                self.p_refl * dr.inv_pi * cos_o,
            )
            return dr.select(active & (cos_i > 0) & (cos_o != 0), value, 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def traverse(self, callback):
            pass

        def to_string(self):
            return (
                f"RealDiffuser[half_width={np.degrees(self.half_width):g} deg, "
                f"reflectance={self.refl}, transmitted={self.trans}]"
            )

    mi.register_bsdf("real_diffuser", lambda props: RealDiffuser(props))
    _REGISTERED = True
