"""BSDF plugins (written in Python) for what Mitsuba 3 has no material for.

``oneway_diffuser``: the diffuser screen of system S
----------------------------------------------------

The paper's layout (its Fig. 4 and 9, Table 1) puts the diffuser plane ``z = z_h`` between the
projector and the water, and the spots reflected from the steeper part of the pattern land where
the projector's own upward beam crosses that plane. A plain translucent screen there would shadow
the projector and add a direct image of the pattern. The paper's geometric model ignores both, so
the screen modelled here is *one-way*:

- light arriving from above (the side the normal points to) is transmitted diffusely
  (Lambertian, albedo ``reflectance``) to the side below, where camera s looks at it;
- light arriving from below passes straight through, unchanged (a delta transmission).

Mitsuba 3 has no such material (``twosided`` refuses transmissive BSDFs), hence this plugin. A
real rig would get the same effect with, e.g., a screen with a slot for the beam; the idealised
screen keeps the paper's geometry without modelling those details.

``water_interface``: a smooth water-air interface that follows one branch only
-------------------------------------------------------------------------------
Mitsuba's ``dielectric`` picks reflection or refraction at random (with probability F), which
is exact but noisy. Each of our scenes needs one branch only: in system V the reflected branch
sees the dark water below (it adds nothing), in system S the transmitted branch leaves into an
empty sky. ``water_interface`` follows the needed branch every time with the exact Fresnel weight
(``mode = "refract"``: ``1 - F``, zero under total internal reflection; ``mode = "reflect"``: F):
the same expected image, without the Fresnel noise and without wasting paths. Radiance crossing
the interface is scaled by ``eta^2`` as in Mitsuba's ``dielectric`` (radiance transport).
Normals point into the air (``ext_ior``); ``int_ior`` is the water.

Two optional properties add physics the restoration's model leaves out (absent: the above):

- ``int_ior_rgb`` (three floats, R G B): the water's index per colour channel (dispersion).
  Reflecting, each channel gets its own Fresnel weight along the one mirror direction.
  Refracting, one direction cannot follow three indices, so each sample picks one channel
  with ``sample1`` (probability 1/3), refracts with its index and carries ``3 (1 - F_c)`` in
  that channel only: unbiased, but each pixel's colour is noisier than with one index (a
  third of the samples per channel, each three times as heavy). A stratified sampler
  (``multijitter``) spreads ``sample1`` evenly over a pixel's samples, so a sample count
  that is a multiple of 3 gives every channel its third and most of that noise goes; other
  counts leave a channel one sample short or over in many pixels.
- ``polarisation_axis`` (a world vector; ``mode = "reflect"`` only): the incident light is
  linearly polarised, its field the axis made transverse to the ray (an LCD projector whose
  light reaches the water with nothing in between that changes it). The reflectance is
  ``R_s cos^2(phi) + R_p sin^2(phi)``, phi the field's angle from the s direction (normal to
  the plane of incidence), instead of ``(R_s + R_p) / 2``. What the diffuser then does to the
  polarisation does not matter: camera s records intensity.

``rough_water_reflection``: a rough water surface's reflection, with polarised light
-------------------------------------------------------------------------------------
Mitsuba's ``roughdielectric`` (GGX) has no polarisation. System S needs only the reflected
branch of a rough surface, so this plugin is that branch: a microfacet normal ``m`` drawn
from GGX's distribution of visible normals (``alpha``; seen from below, its mirror image, as
``roughdielectric`` does), the mirror direction about ``m``, and the weight ``F(m) G1(wo, m)``
with the Fresnel reflectance at the facet: the same expectation as ``roughdielectric``'s
reflections (which it keeps with probability F and weight ``G1``), every path reflected. With
``polarisation_axis`` (as ``water_interface``'s) the facet's reflectance is ``R_s cos^2(phi) +
R_p sin^2(phi)``, phi the field's angle from the facet's s direction (normal to the plane of
``m`` and the light's direction); without it ``(R_s + R_p) / 2``.
"""

from __future__ import annotations

_REGISTERED = False


def register() -> None:
    """Register the plugins with Mitsuba (once, after the variant is set)."""
    global _REGISTERED
    if _REGISTERED:
        return
    import drjit as dr
    import mitsuba as mi

    class OneWayDiffuser(mi.BSDF):
        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            self.albedo = props.get("reflectance", 1.0)
            diffuse = mi.BSDFFlags.DiffuseTransmission | mi.BSDFFlags.FrontSide
            through = mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.BackSide
            self.m_components = [diffuse, through]
            self.m_flags = diffuse | through

        def sample(self, ctx, si, sample1, sample2, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            from_above = cos_i > 0
            wo_diffuse = mi.warp.square_to_cosine_hemisphere(sample2)
            wo_diffuse = mi.Vector3f(wo_diffuse.x, wo_diffuse.y, -wo_diffuse.z)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = dr.select(from_above, wo_diffuse, -si.wi)
            bs.pdf = dr.select(
                from_above, mi.warp.square_to_cosine_hemisphere_pdf(-wo_diffuse), 1.0
            )
            bs.eta = 1.0
            bs.sampled_type = dr.select(
                from_above,
                mi.UInt32(+mi.BSDFFlags.DiffuseTransmission),
                mi.UInt32(+mi.BSDFFlags.DeltaTransmission),
            )
            bs.sampled_component = dr.select(from_above, mi.UInt32(0), mi.UInt32(1))
            weight = dr.select(from_above, self.albedo, 1.0)
            ok = active & (cos_i != 0) & (bs.pdf > 0)
            return bs, dr.select(ok, mi.Spectrum(weight), 0.0)

        def eval(self, ctx, si, wo, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            ok = active & (cos_i > 0) & (cos_o < 0)
            return dr.select(ok, mi.Spectrum(self.albedo * dr.inv_pi * -cos_o), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            ok = active & (cos_i > 0) & (cos_o < 0)
            return dr.select(ok, dr.inv_pi * -cos_o, 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"OneWayDiffuser[albedo={self.albedo}]"

    def fresnel_sp(cos_i, eta):
        """Fresnel power reflectances ``(R_s, R_p)`` for the local ``cos_i`` of ``wi`` (> 0:
        arriving from the exterior, index 1; < 0: from the interior, index ``eta``); 1 under
        total internal reflection."""
        outside = cos_i > 0
        n_i = dr.select(outside, 1.0, eta)
        n_t = dr.select(outside, eta, 1.0)
        ci = dr.abs(cos_i)
        sin_t2 = dr.square(n_i / n_t) * (1.0 - dr.square(ci))
        tir = sin_t2 >= 1.0
        ct = dr.safe_sqrt(1.0 - sin_t2)
        r_s = (n_i * ci - n_t * ct) / (n_i * ci + n_t * ct)
        r_p = (n_t * ci - n_i * ct) / (n_t * ci + n_i * ct)
        return dr.select(tir, 1.0, dr.square(r_s)), dr.select(tir, 1.0, dr.square(r_p))

    def one_channel(index, value):
        """An RGB spectrum with ``value`` in channel ``index`` (0, 1, 2) and 0 in the others."""
        return mi.Color3f(*(dr.select(index == c, value, 0.0) for c in range(3)))

    class WaterInterface(mi.BSDF):
        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            ext = props.get("ext_ior", 1.0)
            self.eta = props.get("int_ior", 1.333) / ext
            self.refract_mode = props.get("mode", "refract") == "refract"
            # Optional physics (absent: the plain interface above): a per-channel index
            # (int_ior_rgb, R G B) and, when reflecting, linearly polarised incident light
            # (polarisation_axis: its field's direction at the source, world frame).
            self.eta_rgb = (
                tuple(float(v) / ext for v in props.get("int_ior_rgb"))
                if "int_ior_rgb" in props else None
            )
            self.axis = None
            if "polarisation_axis" in props:
                if self.refract_mode:
                    raise ValueError("water_interface: polarisation_axis needs mode 'reflect'")
                a = [float(v) for v in props.get("polarisation_axis")]
                norm = sum(v * v for v in a) ** 0.5
                self.axis = mi.Vector3f(*(v / norm for v in a))
            lobe = (
                mi.BSDFFlags.DeltaTransmission
                if self.refract_mode
                else mi.BSDFFlags.DeltaReflection
            )
            self.m_components = [lobe | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide]
            self.m_flags = self.m_components[0]

        def sample(self, ctx, si, sample1, sample2, active=True):
            if self.eta_rgb is not None and self.refract_mode:
                return self._sample_dispersed_refraction(ctx, si, sample1, active)
            if self.eta_rgb is not None or self.axis is not None:
                return self._sample_reflection(ctx, si, active)
            cos_i = mi.Frame3f.cos_theta(si.wi)
            f, cos_t, eta_it, eta_ti = mi.fresnel(cos_i, self.eta)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.pdf = 1.0
            bs.sampled_component = mi.UInt32(0)
            if self.refract_mode:
                bs.wo = mi.refract(si.wi, cos_t, eta_ti)
                bs.eta = eta_it
                bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DeltaTransmission)
                weight = 1.0 - f
                if ctx.mode == mi.TransportMode.Radiance:
                    weight = weight * dr.square(eta_ti)
                ok = active & (f < 1.0)
            else:
                bs.wo = mi.reflect(si.wi)
                bs.eta = 1.0
                bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DeltaReflection)
                weight = f
                ok = active
            return bs, dr.select(ok, mi.Spectrum(weight), 0.0)

        def _sample_dispersed_refraction(self, ctx, si, sample1, active):
            # One direction per sample cannot follow three indices: choose the channel with
            # sample1 (probability 1/3 each), refract with its index and weight that channel
            # by 3 (1 - F_c) (x eta^2 for radiance), the others by 0. Unbiased per channel.
            channel = dr.minimum(mi.UInt32(sample1 * 3.0), 2)
            eta = dr.select(
                channel == 0, self.eta_rgb[0], dr.select(channel == 1, self.eta_rgb[1],
                                                         self.eta_rgb[2])
            )
            cos_i = mi.Frame3f.cos_theta(si.wi)
            f, cos_t, eta_it, eta_ti = mi.fresnel(cos_i, eta)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.pdf = 1.0
            bs.sampled_component = mi.UInt32(0)
            bs.wo = mi.refract(si.wi, cos_t, eta_ti)
            bs.eta = eta_it
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DeltaTransmission)
            weight = 3.0 * (1.0 - f)
            if ctx.mode == mi.TransportMode.Radiance:
                weight = weight * dr.square(eta_ti)
            ok = active & (f < 1.0)
            return bs, dr.select(ok, one_channel(channel, weight), 0.0)

        def _sample_reflection(self, ctx, si, active):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.pdf = 1.0
            bs.sampled_component = mi.UInt32(0)
            bs.wo = mi.reflect(si.wi)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DeltaReflection)
            etas = self.eta_rgb if self.eta_rgb is not None else (self.eta,)
            if self.axis is None:
                r = [mi.fresnel(cos_i, e)[0] for e in etas]
            else:
                # Share of the incident field along s (normal to the plane of incidence):
                # with d the light's direction of travel and E its field (the source's axis
                # made transverse to d), |E.s|^2 / |E|^2; s is normal to d, so E.s = axis.s.
                d = -si.wi if ctx.mode == mi.TransportMode.Importance else -bs.wo
                axis = si.to_local(self.axis)
                s_dir = mi.Vector3f(-d.y, d.x, 0.0)
                e_dot_d = dr.dot(axis, d)
                e_sq = dr.maximum(dr.squared_norm(axis) - dr.square(e_dot_d), 1e-12)
                s_share = dr.square(dr.dot(axis, s_dir)) / (
                    dr.maximum(dr.squared_norm(s_dir), 1e-12) * e_sq
                )
                s_share = dr.clip(s_share, 0.0, 1.0)
                r = []
                for e in etas:
                    r_s, r_p = fresnel_sp(cos_i, e)
                    r.append(r_s * s_share + r_p * (1.0 - s_share))
            return bs, dr.select(active, mi.Color3f(*(r * (3 // len(r)))), 0.0)

        def eval(self, ctx, si, wo, active=True):
            return mi.Spectrum(0.0)

        def pdf(self, ctx, si, wo, active=True):
            return mi.Float(0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return mi.Spectrum(0.0), mi.Float(0.0)

        def traverse(self, callback):
            pass

        def to_string(self):
            mode = "refract" if self.refract_mode else "reflect"
            extra = "" if self.eta_rgb is None else f", eta_rgb={self.eta_rgb}"
            extra += "" if self.axis is None else ", polarised"
            return f"WaterInterface[eta={self.eta}, mode={mode}{extra}]"

    def s_share_of(axis, d, m):
        """Share of a field along ``axis`` (made transverse to the light's direction of travel
        ``d``) that lies along s, the normal of the plane of ``d`` and the facet normal ``m``
        (local vectors); 1/2 where that plane is undefined."""
        s_dir = dr.cross(m, d)
        e_dot_d = dr.dot(axis, d)
        e_sq = dr.maximum(dr.squared_norm(axis) - dr.square(e_dot_d), 1e-12)
        s_sq = dr.squared_norm(s_dir)
        share = dr.square(dr.dot(axis, s_dir)) / (dr.maximum(s_sq, 1e-24) * e_sq)
        return dr.select(s_sq > 1e-20, dr.clip(share, 0.0, 1.0), 0.5)

    class RoughWaterReflection(mi.BSDF):
        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            self.eta = props.get("int_ior", 1.333) / props.get("ext_ior", 1.0)
            self.alpha = float(props.get("alpha", 0.01))
            self.distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, self.alpha, True)
            self.axis = None
            if "polarisation_axis" in props:
                a = [float(v) for v in props.get("polarisation_axis")]
                norm = sum(v * v for v in a) ** 0.5
                self.axis = mi.Vector3f(*(v / norm for v in a))
            lobe = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_components = [lobe]
            self.m_flags = lobe

        def _reflectance(self, ctx, si, wi, wo, m_up, side):
            """F at the facet ``m_up`` (upper hemisphere, the frame mirrored to the side
            ``side`` of ``wi``: +1 air, -1 water), for the light between ``wi`` and ``wo``."""
            cos_im = dr.dot(mi.Vector3f(wi.x, wi.y, dr.abs(wi.z)), m_up)
            r_s, r_p = fresnel_sp(side * cos_im, self.eta)
            if self.axis is None:
                return 0.5 * (r_s + r_p)
            m = mi.Vector3f(m_up.x, m_up.y, side * m_up.z)
            d = -wi if ctx.mode == mi.TransportMode.Importance else -wo
            share = s_share_of(si.to_local(self.axis), d, m)
            return r_s * share + r_p * (1.0 - share)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wi = si.wi
            side = dr.select(wi.z < 0, -1.0, 1.0)
            wi_up = mi.Vector3f(wi.x, wi.y, dr.abs(wi.z))
            m_up, pdf_m = self.distr.sample(wi_up, sample2)
            cos_im = dr.dot(wi_up, m_up)
            wo_up = 2.0 * cos_im * m_up - wi_up
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = mi.Vector3f(wo_up.x, wo_up.y, side * wo_up.z)
            bs.pdf = pdf_m / dr.maximum(4.0 * dr.abs(dr.dot(wo_up, m_up)), 1e-12)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            weight = (self._reflectance(ctx, si, wi, bs.wo, m_up, side)
                      * self.distr.smith_g1(wo_up, m_up))
            ok = active & (wi.z != 0) & (wo_up.z > 0) & (cos_im > 0) & (pdf_m > 0)
            return bs, dr.select(ok, mi.Spectrum(weight), 0.0)

        def _half(self, si, wo):
            wi = si.wi
            side = dr.select(wi.z < 0, -1.0, 1.0)
            wi_up = mi.Vector3f(wi.x, wi.y, dr.abs(wi.z))
            wo_up = mi.Vector3f(wo.x, wo.y, side * wo.z)
            m_up = dr.normalize(wi_up + wo_up)
            ok = (wi.z != 0) & (wo_up.z > 0)
            return wi, wi_up, wo_up, m_up, side, ok

        def eval(self, ctx, si, wo, active=True):
            wi, wi_up, wo_up, m_up, side, ok = self._half(si, wo)
            value = (self._reflectance(ctx, si, wi, wo, m_up, side) * self.distr.eval(m_up)
                     * self.distr.G(wi_up, wo_up, m_up) / (4.0 * dr.abs(wi.z)))
            return dr.select(active & ok, mi.Spectrum(value), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            _, wi_up, wo_up, m_up, _, ok = self._half(si, wo)
            pdf = self.distr.pdf(wi_up, m_up) / (4.0 * dr.abs(dr.dot(wo_up, m_up)))
            return dr.select(active & ok, pdf, 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def traverse(self, callback):
            pass

        def to_string(self):
            extra = "" if self.axis is None else ", polarised"
            return f"RoughWaterReflection[eta={self.eta}, alpha={self.alpha}{extra}]"

    mi.register_bsdf("oneway_diffuser", lambda props: OneWayDiffuser(props))
    mi.register_bsdf("rough_water_reflection", lambda props: RoughWaterReflection(props))
    mi.register_bsdf("water_interface", lambda props: WaterInterface(props))
    _REGISTERED = True
