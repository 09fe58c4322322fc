"""A one-way diffuser screen for system S (a Mitsuba BSDF plugin written in Python).

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
"""

from __future__ import annotations

_REGISTERED = False


def register() -> None:
    """Register the ``oneway_diffuser`` BSDF with Mitsuba (once, after the variant is set)."""
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

    mi.register_bsdf("oneway_diffuser", lambda props: OneWayDiffuser(props))
    _REGISTERED = True
