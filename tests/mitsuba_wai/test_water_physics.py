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


def test_roughness_reflects_polarised_light_and_renders_dispersion_per_channel(paper_cfg):
    cfg = paper_cfg.replace("water", roughness=0.1).replace("pattern", polarisation="linear")
    polarised = water_bsdf(cfg, "S")
    assert polarised["type"] == "rough_water_reflection" and polarised["alpha"] == 0.1
    assert polarised["polarisation_axis"] == pytest.approx(list(projector_field_axis(cfg)))
    assert water_bsdf(cfg, "V")["type"] == "roughdielectric"
    with pytest.raises(WaiInputError, match="one colour channel at a time"):
        water_bsdf(paper_cfg.replace("water", roughness=0.1, index_model="quan_fry"), "V")
    rough = water_bsdf(paper_cfg.replace("water", roughness=0.1), "S")
    assert rough["type"] == "roughdielectric" and rough["alpha"] == 0.1


def test_a_nearly_smooth_rough_sea_disperses_the_view_as_the_smooth_one(paper_cfg):
    """Roughness and sea water's index compose: at a vanishing alpha the view's colour
    fringes (red minus blue, each channel refracted with its own index) are the smooth
    dispersive surface's; with one index there are none."""
    from scipy import ndimage

    from mitsuba_wai import FrameRenderer, wave_surface
    from tests.conftest import shrink

    base = shrink(paper_cfg, factor=2, spp=16)
    surface = wave_surface(base)
    sea = dict(index_model="quan_fry", salinity_psu=35.0, temperature_c=5.0)
    fringes = {}
    for name, keys in (("one index", dict(roughness=1e-4)), ("smooth", sea),
                       ("rough", dict(sea, roughness=1e-4))):
        cfg = base.replace("water", **keys)
        view = FrameRenderer(cfg, surface, systems=("view",)).render(
            surface, seed=2, which=("view",))["view"].astype(float)
        red, blue = view[..., 0], view[..., 2] * view[..., 0].mean() / view[..., 2].mean()
        fringes[name] = ndimage.gaussian_filter(red - blue, 1.0)
    assert np.abs(fringes["one index"]).max() < 1e-12
    smooth, rough = fringes["smooth"], fringes["rough"]
    assert np.abs(rough).mean() == pytest.approx(np.abs(smooth).mean(), rel=0.2)
    assert np.corrcoef(smooth.ravel(), rough.ravel())[0, 1] > 0.4


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
    R = paper_cfg.rig.projector.pose.R
    a0 = projector_field_axis(paper_cfg.replace("pattern", polarisation_deg=0.0))
    a90 = projector_field_axis(paper_cfg.replace("pattern", polarisation_deg=90.0))
    # The field lies in the panel, normal to the optical axis, and turns by psi.
    assert abs(a0 @ R[2]) < 1e-12 and abs(a90 @ R[2]) < 1e-12 and abs(a0 @ a90) < 1e-12
    cfg = paper_cfg.replace("pattern", polarisation="linear", polarisation_deg=90.0)
    assert water_bsdf(cfg, "S")["polarisation_axis"] == pytest.approx(list(a90))
    assert "polarisation_axis" not in water_bsdf(cfg, "V")


# --- Renders -------------------------------------------------------------------------------


def edge_scene(bsdf, tau_deg, fov_deg, x_edge_mm, uniform=False, size=(64, 8)):
    """Camera at the origin in water, looking up at ``tau_deg`` from the zenith towards +x,
    flat water at z = 100 mm, and an emitting plane at z = 1100 mm: dark for x < ``x_edge_mm``,
    radiance 1 beyond (or 1 everywhere, ``uniform``)."""
    from mitsuba_wai.scenes import rectangle_to_world

    mi = mitsuba()
    t = np.radians(tau_deg)
    tex = np.ones((1, 2, 3)) if uniform else np.array([[[0.0] * 3, [1.0] * 3]])
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 2, "hide_emitters": False},
        "sensor": {
            "type": "perspective", "fov": fov_deg, "fov_axis": "x", "near_clip": 1.0,
            "far_clip": 1e5, "sampler": {"type": "multijitter"},
            "to_world": mi.ScalarTransform4f().look_at(
                origin=[0, 0, 0], target=[np.sin(t), 0, np.cos(t)], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": size[0], "height": size[1],
                     "pixel_format": "rgb", "rfilter": {"type": "box"}},
        },
        "water": {"type": "rectangle", "bsdf": bsdf, "to_world": rectangle_to_world(
            np.array([0.0, 0.0, 100.0]), np.array([4000.0, 4000.0]), False)},
        "object": {
            "type": "rectangle",
            "to_world": rectangle_to_world(
                np.array([x_edge_mm, 0.0, 1100.0]), np.array([8000.0, 8000.0]), True),
            "emitter": {"type": "area", "radiance": {
                "type": "bitmap", "bitmap": mi.Bitmap(tex), "raw": True,
                "filter_type": "nearest"}},
        },
    })


def edge_profile(bsdf, tau_deg, fov_deg, x_edge_mm, spp=64):
    """Column profile (W, 3) of the edge image over the uniform one (same samples, so the
    Monte Carlo noise cancels) and the uniform image (H, W, 3)."""
    mi = mitsuba()
    edge = np.array(mi.render(edge_scene(bsdf, tau_deg, fov_deg, x_edge_mm), spp=spp, seed=1))
    flat = np.array(mi.render(edge_scene(bsdf, tau_deg, fov_deg, x_edge_mm, uniform=True),
                              spp=spp, seed=1))
    return edge.mean(0) / flat.mean(0), flat


def snell_edge_column(n, tau_deg, fov_deg, x_edge_mm, width=64):
    """Continuous column of the edge in the centre row by Snell's law: the water angle theta
    whose air ray (sin = n sin theta) meets the plane at the edge, on a pinhole image whose
    columns run against theta (Mitsuba's perspective: the first column is the camera's left)."""
    from scipy.optimize import brentq

    def miss(tw):
        return 100 * np.tan(tw) + 1000 * np.tan(np.arcsin(n * np.sin(tw))) - x_edge_mm

    tw = brentq(miss, 0.0, np.arcsin(1 / n) - 1e-9)
    half = np.tan(np.radians(fov_deg / 2))
    return width / 2 - width / 2 * np.tan(tw - np.radians(tau_deg)) / half


def test_flat_water_view_disperses_the_edge_per_channel(paper_cfg):
    """40 deg up through sea water, a 4 deg film: the edge lands in each channel where Snell's
    law with that channel's index puts it (red and blue 3.4 px apart)."""
    cfg = paper_cfg.replace("water", index_model="quan_fry")
    n_rgb = channel_indices(35.0, 20.0)
    tau, fov = 40.0, 4.0
    x_edge = 100 * np.tan(np.radians(tau)) + 1000 * np.tan(
        np.arcsin(n_rgb[1] * np.sin(np.radians(tau))))
    profile, _ = edge_profile(water_bsdf(cfg, "V"), tau, fov, x_edge)
    # The bright side is the first columns: the lit share of the row is the edge's column.
    got = profile.sum(0)
    want = [snell_edge_column(n, tau, fov, x_edge) for n in n_rgb]
    np.testing.assert_allclose(got, want, atol=0.15)
    assert want[2] - want[0] > 3.0


def test_rough_water_blurs_the_view_and_keeps_its_energy(paper_cfg):
    """GGX micro-roughness: the edge's spread grows with alpha, it stays where the smooth
    surface puts it, and a uniform sky seen through the interface keeps its radiance
    n^2 (1 - R) within a few per cent (a microfacet interface conserves energy)."""
    tau, fov = 20.0, 30.0
    x_edge = 100 * np.tan(np.radians(tau)) + 1000 * np.tan(
        np.arcsin(N43 * np.sin(np.radians(tau))))
    widths, energy = [], []
    for alpha in (0.0, 0.01, 0.03, 0.1):
        bsdf = water_bsdf(paper_cfg.replace("water", roughness=alpha), "V")
        profile, flat = edge_profile(bsdf, tau, fov, x_edge)
        g = -np.diff(profile[:, 1])
        x = np.arange(g.size)
        mean = (g * x).sum() / g.sum()
        widths.append(np.sqrt((g * (x - mean) ** 2).sum() / g.sum()))
        energy.append(flat.mean())
        assert profile[:, 1].sum() == pytest.approx(32.0, abs=0.3)
    assert widths[0] < 0.3 and np.all(np.diff(widths) > 0.4), widths
    np.testing.assert_allclose(energy[1:], energy[0], rtol=0.03)
    # The smooth surface's radiance: n^2 (1 - R) at the central ray's incidence, for scale.
    r_s, r_p = fresnel_sp(np.radians(tau), N43, 1.0)
    assert energy[0] == pytest.approx(N43**2 * (1 - (r_s + r_p) / 2), rel=0.02)


def test_polarised_pattern_fades_near_brewster(paper_cfg):
    """Flat water, p-, s- and unpolarised projector light: each spot in the projector's plane
    of symmetry (its plane of incidence is the projector's xz plane, so the field at 0 deg is
    p, at 90 deg s) keeps R_p / R and R_s / R of its unpolarised energy (R = (R_s + R_p) / 2),
    the textbook Fresnel equations at its incidence; near Brewster's angle the p spots vanish."""
    from scipy.ndimage import uniform_filter

    from tests.conftest import shrink

    cfg = shrink(paper_cfg, factor=2, spp=4)
    images = _polarised_patterns(cfg)
    theta, rows, cols = _spots_in_projector_plane(cfg, margin_deg=1.0)
    # Each spot's energy: the sum over a 5 x 5 px window around its flat-water centre.
    energy = {k: 25.0 * uniform_filter(im, 5, mode="constant")[rows, cols]
              for k, im in images.items()}
    r_sp = np.array([fresnel_sp(t, N43, 1.0) for t in theta])
    r_mean = r_sp.mean(axis=1)
    np.testing.assert_allclose(energy["p"] / energy["none"], r_sp[:, 1] / r_mean, atol=0.01)
    np.testing.assert_allclose(energy["s"] / energy["none"], r_sp[:, 0] / r_mean, atol=0.01)
    near_brewster = np.abs(theta - np.arctan(1 / N43)) < np.radians(1.0)
    assert near_brewster.any() and np.all(energy["p"][near_brewster] < 0.01 * energy["none"][
        near_brewster])


def _polarised_patterns(cfg):
    """Camera s's grey pattern over flat water of ``cfg`` lit by unpolarised (``none``),
    p-polarised (``p``, the field at 0 deg) and s-polarised (``s``, 90 deg) projector light."""
    from mitsuba_wai.mesh import flat_like
    from mitsuba_wai.render import FrameRenderer
    from mitsuba_wai.surface_sampling import wave_surface

    flat = flat_like(wave_surface(cfg), cfg.water.h0_mm)
    images = {}
    for name, deg in (("none", None), ("p", 0.0), ("s", 90.0)):
        c = cfg if deg is None else cfg.replace(
            "pattern", polarisation="linear", polarisation_deg=deg)
        images[name] = FrameRenderer(c, flat, systems=("pattern",)).render(
            flat, 3, ("pattern",))["pattern"].sum(-1)
    return images


def _spots_in_projector_plane(cfg, margin_deg):
    """The flat-water spots of the dots in the projector's plane of symmetry (their plane of
    incidence is the projector's xz plane), more than ``margin_deg`` from the critical angle:
    each one's incidence (rad) and its centre's pixel row and column in camera s."""
    from wai_core.layout import flat_pattern_hits

    _, spot, seen = flat_pattern_hits(cfg)
    panel = cfg.rig.dot_panel_px
    _, d = cfg.rig.projector.pixel_rays(panel[:, 0], panel[:, 1])
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    theta = np.arccos(d[:, 2])
    sel = (seen & (np.abs(d[:, 1]) < 1e-9)
           & (np.abs(theta - np.arcsin(1 / N43)) > np.radians(margin_deg)))
    assert sel.sum() >= 20
    cols, rows, _ = cfg.rig.camera_s.project(spot[sel])
    return theta[sel], np.round(rows).astype(int), np.round(cols).astype(int)


def test_rough_water_pattern_matches_mitsubas_own_tracer(paper_cfg):
    """A rough surface is not a delta BSDF: its connections to camera s must be blocked by the
    diffuser (which diffuses that light instead). The stratified dot emitter's tracer then
    delivers what Mitsuba's projector and shadow-tested connections deliver."""
    from mitsuba_wai.mesh import flat_like
    from mitsuba_wai.render import FrameRenderer
    from mitsuba_wai.surface_sampling import wave_surface
    from tests.conftest import shrink

    cfg = shrink(paper_cfg, factor=4, spp=8).replace("water", roughness=0.05)
    flat = flat_like(wave_surface(cfg), cfg.water.h0_mm)
    total = {}
    for sampling in ("stratified", "independent"):
        c = cfg.replace("render", sampling=sampling)
        image = FrameRenderer(c, flat, systems=("pattern",)).render(flat, 3, ("pattern",))
        total[sampling] = float(image["pattern"].sum())
    assert total["stratified"] == pytest.approx(total["independent"], rel=0.03)


@pytest.mark.parametrize("theta_deg", [30.0, float(np.degrees(np.arctan(1 / N43))), 45.0, 60.0])
def test_rough_polarised_reflection_tends_to_fresnel_and_its_fields_add_up(theta_deg):
    """The rough surface's reflection with polarised light: nearly smooth (alpha 1e-4), the
    mirror direction and the textbook R_s, R_p, (R_s + R_p) / 2; rough (alpha 0.3), any two
    orthogonal fields across the ray share each facet's reflectance between them, so their
    weights add up to twice the unpolarised one, sample by sample."""
    import drjit as dr

    from mitsuba_wai.bsdfs import register

    mi = mitsuba()
    register()
    theta = np.radians(theta_deg)
    n, t1, t2 = _tilted_frame()
    d = np.sin(theta) * t1 + np.cos(theta) * n
    p_axis, s_axis = np.cos(theta) * t1 - np.sin(theta) * n, t2
    r_s, r_p = fresnel_sp(theta, N43, 1.0)
    smooth = {"type": "rough_water_reflection", "alpha": 1e-4, "int_ior": N43, "ext_ior": 1.0}
    si = surface_interaction(n, -d)
    got = {}
    for name, axis in (("s", s_axis), ("p", p_axis), ("none", None)):
        bsdf = dict(smooth) if axis is None else {**smooth, "polarisation_axis": list(axis)}
        _, w, wo = sample(bsdf, si, mi.Float(0.5), importance=True)
        np.testing.assert_allclose(wo[0], d - 2 * np.dot(d, n) * n, atol=1e-3)
        got[name] = w[0, 0]
    np.testing.assert_allclose([got["s"], got["p"], got["none"]], [r_s, r_p, (r_s + r_p) / 2],
                               atol=5e-4)
    k = 256
    rng = np.random.default_rng(int(theta_deg))
    si = surface_interaction(n, -d, k)
    u = mi.Point2f(*(mi.Float(rng.random(k)) for _ in range(2)))
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    w = {}
    for name, axis in (("s", s_axis), ("p", p_axis), ("none", None)):
        rough = {**smooth, "alpha": 0.3}
        if axis is not None:
            rough["polarisation_axis"] = list(axis)
        bsdf = mi.load_dict(rough)
        bs, weight = bsdf.sample(ctx, si, mi.Float(0.5), u)
        w[name] = np.array(dr.ravel(weight)).reshape(-1, 3)[:, 0]
        # The connections' eval and pdf are the sampling's: eval / pdf is its weight.
        value, pdf = bsdf.eval_pdf(ctx, si, bs.wo)
        ratio = np.array(dr.ravel(value)).reshape(-1, 3)[:, 0] / np.maximum(np.array(pdf), 1e-30)
        lit = w[name] > 0
        np.testing.assert_allclose(ratio[lit], w[name][lit], rtol=1e-4)
    assert np.count_nonzero(w["none"]) > k // 2
    np.testing.assert_allclose(w["s"] + w["p"], 2 * w["none"], rtol=1e-5, atol=1e-7)
    assert np.all((w["s"] >= 0) & (w["s"] <= 1) & (w["p"] >= 0) & (w["p"] <= 1))


def test_rough_water_reflects_polarised_light_as_fresnel_says(paper_cfg):
    """Roughness and polarisation compose: flat water of GGX alpha 0.01 lit by p- and by
    s-polarised projector light; each spot in the projector's plane of symmetry keeps the ratio
    R_p / R_s of the textbook Fresnel equations at its incidence (the facets tilt it by tenths
    of a degree), near Brewster's angle the p spots vanish, and the two polarisations' mean
    against the unpolarised rough surface (Mitsuba's roughdielectric) is what it is on smooth
    water (not 1: off the projector's plane the panel's two axes, made transverse to a ray,
    are not orthogonal)."""
    from scipy.ndimage import uniform_filter

    from tests.conftest import shrink

    cfg = shrink(paper_cfg, factor=2, spp=4).replace("water", roughness=0.01)
    images = _polarised_patterns(cfg)
    theta, rows, cols = _spots_in_projector_plane(cfg, margin_deg=2.0)
    energy = {k: uniform_filter(im, 9, mode="constant")[rows, cols] for k, im in images.items()}
    r_sp = np.array([fresnel_sp(t, N43, 1.0) for t in theta])
    ratio = energy["p"] / energy["s"]
    np.testing.assert_allclose(ratio, r_sp[:, 1] / r_sp[:, 0], atol=0.02)
    near_brewster = np.abs(theta - np.arctan(1 / N43)) < np.radians(1.0)
    assert near_brewster.any() and np.all(ratio[near_brewster] < 0.02)
    shares = []
    for patterns in (images, _polarised_patterns(cfg.replace("water", roughness=0.0))):
        total = {k: float(im.sum()) for k, im in patterns.items()}
        shares.append((total["p"] + total["s"]) / 2 / total["none"])
    assert shares[0] == pytest.approx(shares[1], abs=0.01)
