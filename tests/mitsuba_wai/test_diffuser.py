"""The real diffuser screen: its BSDF against its defining profile, and what camera s sees."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from mitsuba_wai.variant import select_variant
from wai_core.geometry import pinhole_of

LN2 = np.log(2.0)
N_WATER = 4.0 / 3.0


def gaussian_profile(theta, half_width_deg):
    """The transmitted radiance's defining profile, exp(-ln 2 (theta / theta_h)^2)."""
    return np.exp(-LN2 * (theta / np.radians(half_width_deg)) ** 2)


def profile_integral(half_width_deg):
    """int_0^(pi/2) L(theta) cos sin dtheta: the transmitted flux per unit peak radiance / 2 pi."""
    return quad(lambda t: gaussian_profile(t, half_width_deg) * np.cos(t) * np.sin(t),
                0.0, np.pi / 2, epsrel=1e-12)[0]


def fresnel_unpolarised(cos_i, n_rel):
    """Reflectance of unpolarised light at a smooth interface (Fresnel), 1 beyond TIR."""
    sin_t2 = (1.0 - cos_i**2) / n_rel**2
    cos_t = np.sqrt(np.clip(1.0 - sin_t2, 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):  # grazing TIR: 0/0, replaced below
        rs = ((cos_i - n_rel * cos_t) / (cos_i + n_rel * cos_t)) ** 2
        rp = ((n_rel * cos_i - cos_t) / (n_rel * cos_i + cos_t)) ** 2
    return np.where(sin_t2 >= 1.0, 1.0, 0.5 * (rs + rp))


@pytest.fixture(scope="module")
def mi():
    select_variant()
    import mitsuba

    from mitsuba_wai.diffuser import register

    register()
    return mitsuba


def load(mi, half_width_deg, reflectance, albedo=1.0):
    return mi.load_dict({"type": "real_diffuser", "half_width_deg": half_width_deg,
                         "reflectance": reflectance, "albedo": albedo})


def incident(mi, n, from_above=True):
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    z = 0.8 if from_above else -0.8
    si.wi = mi.Vector3f(0.6, 0.0, z)  # light from 37 deg off the normal
    return si


def draws(mi, n, seed=1):
    rng = np.random.default_rng(seed)
    return mi.Float(rng.random(n)), mi.Point2f(rng.random(n), rng.random(n))


CASES = [(0.0, 0.3, 1.0), (20.0, 0.0, 1.0), (20.0, 0.3, 0.9), (5.0, 0.1, 1.0), (60.0, 0.2, 1.0)]


@pytest.mark.parametrize(("half_width", "r", "albedo"), CASES)
def test_transmitted_and_reflected_shares(mi, half_width, r, albedo):
    n = 200_000
    bsdf = load(mi, half_width, r, albedo)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    si = incident(mi, n)
    bs, weight = bsdf.sample(ctx, si, *draws(mi, n))
    down = np.asarray(bs.wo.z) < 0
    w = np.asarray(weight)[0]
    # Monte Carlo by the sampled weights.
    assert w[down].sum() / n == pytest.approx((1 - r) * albedo, rel=0.01)
    assert w[~down].sum() / n == pytest.approx(r, rel=0.01, abs=1e-12)
    # Independently of the sampler: eval integrated over uniformly drawn directions below.
    rng = np.random.default_rng(2)
    cos_o = rng.random(n)
    phi = 2 * np.pi * rng.random(n)
    sin_o = np.sqrt(1 - cos_o**2)
    wo = mi.Vector3f(sin_o * np.cos(phi), sin_o * np.sin(phi), -cos_o)
    value = np.asarray(bsdf.eval(ctx, si, wo))[0]
    assert value.mean() * 2 * np.pi == pytest.approx((1 - r) * albedo, rel=0.01)
    up = mi.Vector3f(sin_o * np.cos(phi), sin_o * np.sin(phi), cos_o)
    value = np.asarray(bsdf.eval(ctx, si, up))[0]
    assert value.mean() * 2 * np.pi == pytest.approx(r, rel=0.01, abs=1e-12)


@pytest.mark.parametrize("half_width", [5.0, 20.0, 45.0])
def test_radiance_falls_to_half_at_the_half_width(mi, half_width):
    bsdf = load(mi, half_width, 0.0)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    theta = np.radians(np.array([0.0, 0.5 * half_width, half_width, 2 * half_width]))
    si = incident(mi, theta.size)
    wo = mi.Vector3f(np.sin(theta), 0.0 * theta, -np.cos(theta))
    radiance = np.asarray(bsdf.eval(ctx, si, wo))[0] / np.cos(theta)
    np.testing.assert_allclose(radiance / radiance[0], [1.0, 2**-0.25, 0.5, 2**-4], rtol=1e-4)
    # The peak value: the transmitted share over 2 pi int L cos sin dtheta.
    assert radiance[0] == pytest.approx(1 / (2 * np.pi * profile_integral(half_width)), rel=1e-3)


def test_lambertian_when_half_width_is_zero(mi):
    bsdf = load(mi, 0.0, 0.2)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    theta = np.radians(np.array([0.0, 30.0, 60.0, 85.0]))
    wo = mi.Vector3f(np.sin(theta), 0.0 * theta, -np.cos(theta))
    radiance = np.asarray(bsdf.eval(ctx, incident(mi, 4), wo))[0] / np.cos(theta)
    np.testing.assert_allclose(radiance, 0.8 / np.pi, rtol=1e-5)


@pytest.mark.parametrize("half_width", [0.0, 10.0, 30.0])
def test_sampled_angles_follow_the_pdf(mi, half_width):
    n = 200_000
    bsdf = load(mi, half_width, 0.25)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    bs, _ = bsdf.sample(ctx, incident(mi, n), *draws(mi, n, seed=3))
    wo = np.asarray(bs.wo)
    down = wo[2] < 0
    assert down.mean() == pytest.approx(0.75, abs=0.005)
    theta = np.arctan2(np.hypot(wo[0], wo[1]), -wo[2])[down]
    # Expected share per bin of theta from the defining density L cos sin (independent of the
    # code), and from the BSDF's own pdf (its consistency with what it samples).
    top = np.pi / 2 if half_width == 0 else min(np.pi / 2, 3.5 * np.radians(half_width))
    edges = np.linspace(0.0, top, 31)
    counts, _ = np.histogram(theta, edges)
    fine = np.linspace(0.0, np.pi / 2, 20001)
    g = np.ones_like(fine) if half_width == 0 else gaussian_profile(fine, half_width)
    dens = g * np.cos(fine) * np.sin(fine)
    cdf = np.concatenate([[0], np.cumsum((dens[1:] + dens[:-1]) / 2 * np.diff(fine))])
    cdf /= cdf[-1]
    expected = np.diff(np.interp(edges, fine, cdf)) * down.sum()
    chi2 = np.sum((counts - expected) ** 2 / expected)
    assert chi2 < 30 + 5 * np.sqrt(60)  # 30 bins: mean 30, sd sqrt(60)
    # The pdf per steradian, times 2 pi sin theta, over the lower lobe (share 0.75).
    mid = 0.5 * (edges[1:] + edges[:-1])
    wo_mid = mi.Vector3f(np.sin(mid), 0.0 * mid, -np.cos(mid))
    pdf = np.asarray(bsdf.pdf(ctx, incident(mi, mid.size), wo_mid))
    share = pdf * 2 * np.pi * np.sin(mid) * np.diff(edges) / 0.75
    np.testing.assert_allclose(share, expected / down.sum(), rtol=0.01, atol=1e-4)


def test_light_from_below_passes_straight_through(mi):
    bsdf = load(mi, 20.0, 0.3)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    n = 1000
    si = incident(mi, n, from_above=False)
    bs, weight = bsdf.sample(ctx, si, *draws(mi, n))
    np.testing.assert_allclose(np.asarray(bs.wo), np.tile([[-0.6], [0.0], [0.8]], n), atol=1e-6)
    np.testing.assert_allclose(np.asarray(weight), 1.0)
    wo = mi.Vector3f(0.0, 0.0, 1.0)
    assert np.asarray(bsdf.eval(ctx, incident(mi, 1, from_above=False), wo)).max() == 0.0


def test_default_screen_is_the_ideal_one(small_cfg):
    from mitsuba_wai.diffuser import diffuser_bsdf, screen_blur
    from mitsuba_wai.scenes import pattern_depth

    assert diffuser_bsdf(small_cfg) == {"type": "oneway_diffuser"}
    assert pattern_depth(small_cfg) == 4
    assert pattern_depth(small_cfg.replace("diffuser", reflectance=0.1)) == 6
    assert pattern_depth(small_cfg.replace("diffuser", half_width_deg=10.0)) == 4
    image = np.ones((4, 4, 3), dtype=np.float32)
    assert screen_blur(image, small_cfg) is image


def test_blur_is_a_gaussian_of_blur_mm_on_the_screen(small_cfg):
    from mitsuba_wai.diffuser import blur_sigma_px, screen_blur

    cfg = small_cfg.replace("diffuser", blur_mm=3.0)
    dev = cfg.camera_s
    # Camera s looks straight up at the screen from z = -190 mm to 60 mm (Table 1): 250 mm.
    depth = cfg.diffuser.z_mm - pinhole_of(dev).pose.center_lab_mm[2]
    assert depth == pytest.approx(250.0)
    f_px = dev.focal_mm * dev.width_px / dev.sensor_width_mm
    assert blur_sigma_px(cfg) == pytest.approx(3.0 * f_px / depth, rel=1e-9)
    image = np.zeros((61, 81, 3), dtype=np.float32)
    image[30, 40] = 1.0
    out = screen_blur(image, cfg)[..., 0]
    rows, cols = np.mgrid[:61, :81]
    assert out.sum() == pytest.approx(1.0, rel=1e-5)
    var = (out * (cols - 40.0) ** 2).sum()
    assert np.sqrt(var) == pytest.approx(3.0 * f_px / depth, rel=0.02)


# --- what camera s sees through flat water ----------------------------------------------------


@pytest.fixture(scope="module")
def flat_patterns(small_cfg):
    from mitsuba_wai.mesh import flat_like
    from mitsuba_wai.render import FrameRenderer
    from mitsuba_wai.surface_sampling import wave_surface

    grid = wave_surface(small_cfg)
    flat = flat_like(grid, small_cfg.water.h0_mm)
    images = {}
    for name, keys in (("ideal", {}), ("reflect", {"reflectance": 0.3}),
                       ("profile", {"half_width_deg": 20.0})):
        cfg = small_cfg.replace("diffuser", **keys)
        renderer = FrameRenderer(cfg, grid, systems=("pattern",))
        images[name] = renderer.render(flat, seed=1, which=("pattern",))["pattern"].sum(axis=2)
    return images


def spot_windows(cfg, shape):
    """Camera-s pixels of the flat-water spots (5 x 5 windows inside the image) and their
    viewing angle from the screen's downward normal, radians."""
    from wai_core.layout import flat_pattern_hits

    _, s, seen = flat_pattern_hits(cfg)
    cam = cfg.rig.camera_s
    cols, rows, ok = cam.project(s[seen])
    r, c = np.round(rows).astype(int), np.round(cols).astype(int)
    keep = ok & (r >= 2) & (c >= 2) & (r < shape[0] - 2) & (c < shape[1] - 2)
    v = cam.pose.center_lab_mm - s[seen][keep]
    theta = np.arccos(-v[:, 2] / np.linalg.norm(v, axis=1))
    return r[keep], c[keep], theta


def window_sums(image, r, c):
    offsets = np.arange(-2, 3)
    rr = r[:, None, None] + offsets[None, :, None]
    cc = c[:, None, None] + offsets[None, None, :]
    return image[rr, cc].sum(axis=(1, 2))


def test_back_reflection_dims_the_spots_and_adds_a_glow(small_cfg, flat_patterns):
    ideal, refl = flat_patterns["ideal"], flat_patterns["reflect"]
    r, c, _ = spot_windows(small_cfg, ideal.shape)
    assert r.size > 200
    ratio = window_sums(refl, r, c) / window_sums(ideal, r, c)
    # The spots keep the transmitted 70 %, plus a little of the glow.
    assert 0.69 < np.percentile(ratio, 5) and np.median(ratio) < 0.75
    # Between the spots, where the ideal screen shows nothing at all, the glow lights up.
    dark = ideal == 0
    assert dark.mean() > 0.3
    assert refl[dark].sum() > 0.01 * refl.sum()
    # Energy: the glow is at most the reflected 30 % times the water's reflectance for a
    # Lambertian source below it (Fresnel, TIR beyond 48.6 deg) times the 70 % let through.
    mu = np.linspace(0.0, 1.0, 20001)
    r_hemi = np.trapezoid(fresnel_unpolarised(mu, 1.0 / N_WATER) * 2 * mu, mu)
    assert 1 - 1 / N_WATER**2 < r_hemi < 1 - 1 / N_WATER**2 + 0.1  # 44 % TIR + some Fresnel
    glow = refl.sum() - 0.7 * ideal.sum()
    assert 0.0 < glow < 0.3 * r_hemi * 0.7 * ideal.sum()


def test_profile_changes_the_spots_as_the_radiance_towards_camera_s(small_cfg, flat_patterns):
    ideal, prof = flat_patterns["ideal"], flat_patterns["profile"]
    r, c, theta = spot_windows(small_cfg, ideal.shape)
    assert np.degrees(theta).max() > 40  # the spots span a wide range of viewing angles
    # Lambertian radiance 1/pi against the profile's L(theta) / (2 pi int L cos sin).
    predicted = np.pi * gaussian_profile(theta, 20.0) / (2 * np.pi * profile_integral(20.0))
    ratio = window_sums(prof, r, c) / window_sums(ideal, r, c) / predicted
    assert np.median(ratio) == pytest.approx(1.0, abs=0.02)
    assert np.percentile(ratio, 5) > 0.93 and np.percentile(ratio, 95) < 1.07
