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

    class WaterInterface(mi.BSDF):
        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            self.eta = props.get("int_ior", 1.333) / props.get("ext_ior", 1.0)
            self.refract_mode = props.get("mode", "refract") == "refract"
            lobe = (
                mi.BSDFFlags.DeltaTransmission
                if self.refract_mode
                else mi.BSDFFlags.DeltaReflection
            )
            self.m_components = [lobe | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide]
            self.m_flags = self.m_components[0]

        def sample(self, ctx, si, sample1, sample2, active=True):
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
            return f"WaterInterface[eta={self.eta}, mode={mode}]"

    mi.register_bsdf("oneway_diffuser", lambda props: OneWayDiffuser(props))
    mi.register_bsdf("water_interface", lambda props: WaterInterface(props))
    _REGISTERED = True
