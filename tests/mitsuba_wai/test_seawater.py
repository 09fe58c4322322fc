"""Sea water ([water_optics]) and daylight ([ambient]): off costs nothing, on is checked."""

import numpy as np
import pytest

from mitsuba_wai.ambient import hemispherical_reflectance, sky_image
from mitsuba_wai.mesh import flat_like
from mitsuba_wai.render import FrameRenderer, render_image
from mitsuba_wai.seawater import coefficients_per_mm, medium_view_scene, pattern_path_lengths_mm
from mitsuba_wai.surface_sampling import wave_surface
from mitsuba_wai.textures import object_texture
from mitsuba_wai.variant import mitsuba
from tests.conftest import shrink
from wai_core.config import config_from_dict
from wai_core.errors import WaiInputError


@pytest.fixture(scope="module")
def surface(small_cfg):
    return wave_surface(small_cfg)


@pytest.fixture(scope="module")
def clear(small_cfg, surface):
    return FrameRenderer(small_cfg, surface).render(surface, 7)


def test_sections_default_off_and_name_their_keys(paper_cfg):
    assert not paper_cfg.water_optics.enabled and not paper_cfg.ambient.enabled
    data = paper_cfg.to_dict()
    data["water_optics"] = {"turbidity": -1.0}
    with pytest.raises(WaiInputError, match=r"\[water_optics\]\.turbidity"):
        config_from_dict(data)
    data = paper_cfg.to_dict()
    data["ambient"] = {"sun_zenith_deg": 95.0}
    with pytest.raises(WaiInputError, match=r"\[ambient\]\.sun_zenith_deg"):
        config_from_dict(data)
    data = paper_cfg.to_dict()
    del data["water_optics"], data["ambient"]  # an older scene.json
    assert config_from_dict(data) == paper_cfg


def test_disabled_sections_leave_the_renders_unchanged(small_cfg, surface, clear):
    cfg = small_cfg.replace("water_optics", turbidity=500.0, forward_fraction=0.5)
    cfg = cfg.replace("ambient", sky_radiance=3.0)
    out = FrameRenderer(cfg, surface).render(surface, 7)
    # zero coefficients: the weighted code path, every weight exactly 1
    zero = small_cfg.replace("water_optics", enabled=True, absorption_per_m=(0.0, 0.0, 0.0),
                             scattering_per_m=(0.0, 0.0, 0.0))
    weighted = FrameRenderer(zero, surface).render(surface, 7)
    for key in ("pattern", "view"):
        assert np.array_equal(out[key], clear[key])
        assert np.array_equal(weighted[key], clear[key])


def test_pattern_attenuation_follows_beer_lambert_on_each_path(small_cfg, surface):
    """Same seed, same particles: on / off per pixel is exp(-c L) of that pixel's paths, L
    within the flat geometry's range of dot paths (projector -> water -> diffuser -> camera)."""
    flat = flat_like(surface, small_cfg.water.h0_mm)
    cfg = small_cfg.replace("water_optics", enabled=True, turbidity=100.0)
    off = FrameRenderer(small_cfg, flat, systems=("pattern",)).render(flat, 3, ("pattern",))
    on = FrameRenderer(cfg, flat, systems=("pattern",)).render(flat, 3, ("pattern",))
    a, b = coefficients_per_mm(cfg.water_optics)
    lengths = pattern_path_lengths_mm(cfg)
    for c in range(1, 3):  # the pattern's green and blue
        lit = off["pattern"][..., c] > 0.2 * off["pattern"][..., c].max()
        ratio = on["pattern"][lit, c] / off["pattern"][lit, c]
        lo, hi = np.exp(-(a[c] + b[c]) * lengths.max()), np.exp(-(a[c] + b[c]) * lengths.min())
        assert lo * 0.999 <= ratio.min() and ratio.max() <= hi * 1.001
        assert np.median(ratio) == pytest.approx(
            np.exp(-(a[c] + b[c]) * np.median(lengths)), rel=0.01)


def test_view_beer_lambert_agrees_with_mitsubas_homogeneous_medium(paper_cfg):
    """volpath + homogeneous medium (max_depth 2: direct light) against path x exp(-c L)."""
    cfg = shrink(paper_cfg, factor=8, spp=16).replace(
        "water_optics", enabled=True, absorption_per_m=(3.0, 1.0, 0.3),
        scattering_per_m=(0.5, 0.5, 0.5))
    surface = wave_surface(cfg)
    model = FrameRenderer(cfg, surface, systems=("view",)).render(surface, 1, ("view",))["view"]
    scene = mitsuba().load_dict(medium_view_scene(cfg, surface, object_texture(cfg.object)))
    reference, _ = render_image(scene, 512, 3)
    lit = model.sum(-1) > 0.05
    ratio = reference[lit].sum(0) / model[lit].sum(0)
    assert np.allclose(ratio, 1.0, atol=0.01), ratio
    # and the water really attenuates, red most
    clear = FrameRenderer(cfg.replace("water_optics", enabled=False), surface,
                          systems=("view",)).render(surface, 1, ("view",))["view"]
    t = model[lit].sum(0) / clear[lit].sum(0)
    assert t[0] < t[1] < t[2] < 1


def test_daylight_on_the_diffuser_matches_its_irradiance(small_cfg, surface):
    """Flat water: the sun's particles give E cos(th) (1 - F) / pi on the diffuser (under the
    wave mesh); the sky is L (1 - F_h) everywhere."""
    cfg = small_cfg.replace("ambient", enabled=True, sky_radiance=0.0, sun_zenith_deg=30.0,
                            sun_irradiance=10.0, sun_spp=64)
    flat = flat_like(surface, cfg.water.h0_mm)
    img = FrameRenderer(cfg, flat, systems=("pattern",)).render(flat, 5, ("pattern",))["pattern"]
    h, w = img.shape[:2]
    centre = img[h // 3 : 2 * h // 3, w // 4 : w // 2]  # inside the wave mesh's pre-image
    th = np.radians(30.0)
    n = cfg.water.n_water
    ct = np.sqrt(1 - (np.sin(th) / n) ** 2)
    rs = ((np.cos(th) - n * ct) / (np.cos(th) + n * ct)) ** 2
    rp = ((ct - n * np.cos(th)) / (ct + n * np.cos(th))) ** 2
    expected = 10.0 * np.cos(th) * (1 - (rs + rp) / 2) / np.pi
    assert centre.mean(axis=(0, 1)) == pytest.approx([expected] * 3, rel=0.02)
    assert hemispherical_reflectance(4.0 / 3.0) == pytest.approx(0.066, abs=0.002)
    sky = sky_image(cfg.replace("ambient", sky_radiance=2.0))
    assert np.allclose(sky, 2.0 * np.array(cfg.ambient.sky_color) * (1 - 0.0661), rtol=0.01)


def test_the_sky_lights_the_view_beyond_the_object(small_cfg, surface, clear):
    cfg = small_cfg.replace("ambient", enabled=True, sun_irradiance=0.0)
    view = FrameRenderer(cfg, surface, systems=("view",)).render(surface, 7, ("view",))["view"]
    # Two tracers (Mitsuba's path integrator with the sky, the direct one without): equal
    # where the sky adds nothing, up to the object plane's float32 intersection point, which
    # moves a texture edge by a fraction of a pixel (a few 1e-4 of its value on LLVM; on
    # CUDA, whose rounding differs, across a pixel's edge): the sky's view is at least the
    # clear view's darkest neighbour.
    from scipy.ndimage import minimum_filter

    darkest = minimum_filter(clear["view"], size=(3, 3, 1))
    assert (view >= darkest * (1.0 - 1e-3) - 1e-6).all()
    assert view.sum() > clear["view"].sum()
