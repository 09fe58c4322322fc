"""The water's renderer-only physics: sea water's dispersion, polarised light, micro-roughness.

Facts from outside the code: Snell's law, the Fresnel equations and the n^2 law of radiance
(written here), and Brewster's angle.
"""

import numpy as np
import pytest

from mitsuba_wai.scenes import projector_field_axis, water_bsdf
from mitsuba_wai.variant import mitsuba
from wai_core.errors import WaiInputError
from wai_core.optics import channel_indices

N43 = 4.0 / 3.0


@pytest.fixture(autouse=True)
def _variant():
    mitsuba()


def fresnel_sp(theta_i: np.ndarray, n_i: float, n_t: float) -> tuple[np.ndarray, np.ndarray]:
    """Textbook Fresnel power reflectances (R_s, R_p) at incidence ``theta_i`` (radians)."""
    ci = np.cos(theta_i)
    st = n_i / n_t * np.sin(theta_i)
    if st >= 1.0:
        return 1.0, 1.0
    ct = np.sqrt(1.0 - st**2)
    rs = (n_i * ci - n_t * ct) / (n_i * ci + n_t * ct)
    rp = (n_i * ct - n_t * ci) / (n_i * ct + n_t * ci)
    return rs**2, rp**2


def surface_interaction(normal, wi_world, n: int = 1):
    """A SurfaceInteraction3f (``n`` lanes) on a surface of world ``normal`` seen from the
    world direction ``wi_world`` (pointing away from the surface)."""
    mi = mitsuba()
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    nrm = mi.Vector3f(*(float(v) for v in normal))
    si.n = nrm
    si.sh_frame = mi.Frame3f(nrm)
    si.wi = si.to_local(mi.Vector3f(*(float(v) for v in wi_world)))
    return si


def sample(bsdf_dict, si, sample1, importance: bool):
    mi = mitsuba()
    bsdf = mi.load_dict(bsdf_dict)
    mode = mi.TransportMode.Importance if importance else mi.TransportMode.Radiance
    ctx = mi.BSDFContext(mode)
    bs, w = bsdf.sample(ctx, si, sample1, mi.Point2f(0.5, 0.5))
    return bs, np.array(w).T.reshape(-1, 3), np.array(si.to_world(bs.wo)).T.reshape(-1, 3)


def test_effects_off_give_todays_dicts(paper_cfg):
    n = paper_cfg.water.n_water
    for system, mode in (("S", "reflect"), ("V", "refract"), ("A", "refract")):
        assert water_bsdf(paper_cfg, system) == {
            "type": "water_interface", "int_ior": n, "ext_ior": 1.0, "mode": mode
        }


def test_roughness_refuses_dispersion(paper_cfg):
    cfg = paper_cfg.replace("water", roughness=0.1, index_model="quan_fry")
    with pytest.raises(WaiInputError, match=r"\[water\]\.roughness"):
        water_bsdf(cfg, "V")
    rough = water_bsdf(paper_cfg.replace("water", roughness=0.1), "S")
    assert rough["type"] == "roughdielectric" and rough["alpha"] == 0.1


def test_dispersed_refraction_obeys_snell_per_channel():
    """Inside water, light leaving at 30 deg: each sample refracts with one channel's index
    (sin t = n_c sin i), each channel is chosen a third of the time, and its weight is
    3 (1 - F_c) n_c^2 (radiance gains n^2 into the denser medium, seen backwards)."""
    mi = mitsuba()
    n_rgb = channel_indices(35.0, 20.0)
    theta = np.radians(30.0)
    count = 30000
    # wi points back to the camera, below the surface: the camera ray goes up at 30 deg.
    si = surface_interaction((0, 0, 1), (-np.sin(theta), 0.0, -np.cos(theta)), count)
    u = mi.Float(np.random.default_rng(1).random(count))
    bsdf = {"type": "water_interface", "int_ior": N43, "ext_ior": 1.0, "mode": "refract",
            "int_ior_rgb": list(n_rgb)}
    _, w, wo = sample(bsdf, si, u, importance=False)
    channel = np.argmax(w, axis=1)
    assert np.all(np.count_nonzero(w, axis=1) == 1)
    share = np.bincount(channel, minlength=3) / count
    np.testing.assert_allclose(share, 1 / 3, atol=4 * np.sqrt(2 / 9 / count))
    for c, n in enumerate(n_rgb):
        sel = channel == c
        sin_t = np.hypot(wo[sel, 0], wo[sel, 1])
        np.testing.assert_allclose(sin_t, n * np.sin(theta), atol=1e-5)
        assert np.all(wo[sel, 2] > 0)
        r_s, r_p = fresnel_sp(theta, n, 1.0)
        np.testing.assert_allclose(w[sel, c], 3 * (1 - (r_s + r_p) / 2) * n**2, rtol=1e-4)
    # The indices differ enough to tell the channels apart.
    assert np.degrees(np.arcsin(n_rgb[2] * 0.5) - np.arcsin(n_rgb[0] * 0.5)) > 0.2


def test_dispersed_reflection_weights_each_channel():
    theta = np.radians(40.0)
    n_rgb = channel_indices(35.0, 20.0)
    si = surface_interaction((0, 0, 1), (np.sin(theta), 0.0, -np.cos(theta)))
    bsdf = {"type": "water_interface", "int_ior": N43, "ext_ior": 1.0, "mode": "reflect",
            "int_ior_rgb": list(n_rgb)}
    _, w, _ = sample(bsdf, si, mitsuba().Float(0.5), importance=True)
    want = [sum(fresnel_sp(theta, n, 1.0)) / 2 for n in n_rgb]
    np.testing.assert_allclose(w[0], want, rtol=1e-4)
    assert w[0, 2] > w[0, 0]  # closer to the critical angle in blue


def _tilted_frame():
    """A water normal tilted by 20 deg about an oblique axis, with two unit vectors spanning
    its tangent plane: tests the BSDF's use of the local frame."""
    a = np.radians(20.0)
    k = np.array([1.0, 2.0, 0.0]) / np.sqrt(5.0)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rot = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
    return rot @ np.array([0.0, 0.0, 1.0]), rot @ np.array([1.0, 0.0, 0.0]), rot @ [0.0, 1, 0]


@pytest.mark.parametrize("theta_deg", [30.0, float(np.degrees(np.arctan(1 / N43))), 45.0, 60.0])
def test_polarised_reflection_follows_fresnel_s_and_p(theta_deg):
    """Light in the water going up at theta: field in the plane of incidence (p), normal to
    it (s), at 45 deg (the mean), and with a component along the ray that a field cannot have
    (ignored). At Brewster's angle (tan = 1/n) R_p = 0; beyond the critical angle R = 1."""
    mi = mitsuba()
    theta = np.radians(theta_deg)
    n, t1, t2 = _tilted_frame()
    d = np.sin(theta) * t1 + np.cos(theta) * n  # the light's direction of travel
    p_axis = np.cos(theta) * t1 - np.sin(theta) * n
    s_axis = t2
    r_s, r_p = fresnel_sp(theta, N43, 1.0)
    base = {"type": "water_interface", "int_ior": N43, "ext_ior": 1.0, "mode": "reflect"}
    si = surface_interaction(n, -d)
    got = {}
    for name, axis in (("s", s_axis), ("p", p_axis), ("mix", s_axis + p_axis),
                       ("p_along", p_axis + 0.7 * d), ("none", None)):
        bsdf = dict(base) if axis is None else {**base, "polarisation_axis": list(axis)}
        _, w, wo = sample(bsdf, si, mi.Float(0.5), importance=True)
        np.testing.assert_allclose(wo[0], d - 2 * np.dot(d, n) * n, atol=1e-6)
        got[name] = w[0, 0]
    np.testing.assert_allclose(got["s"], r_s, atol=1e-6)
    np.testing.assert_allclose(got["p"], r_p, atol=1e-6)
    np.testing.assert_allclose(got["p_along"], r_p, atol=1e-6)
    np.testing.assert_allclose(got["mix"], (r_s + r_p) / 2, atol=1e-6)
    np.testing.assert_allclose(got["none"], (r_s + r_p) / 2, atol=1e-6)
    if abs(theta_deg - 36.87) < 0.01:
        assert got["p"] < 1e-8 and got["s"] > 0.02


def test_projector_field_axis_is_transverse(paper_cfg):
    R = paper_cfg.projector.camera().pose.R
    a0 = projector_field_axis(paper_cfg.replace("pattern", polarisation_deg=0.0))
    a90 = projector_field_axis(paper_cfg.replace("pattern", polarisation_deg=90.0))
    # The field lies in the panel, normal to the optical axis, and turns by psi.
    assert abs(a0 @ R[2]) < 1e-12 and abs(a90 @ R[2]) < 1e-12 and abs(a0 @ a90) < 1e-12
    cfg = paper_cfg.replace("pattern", polarisation="linear", polarisation_deg=90.0)
    assert water_bsdf(cfg, "S")["polarisation_axis"] == pytest.approx(list(a90))
    assert "polarisation_axis" not in water_bsdf(cfg, "V")
