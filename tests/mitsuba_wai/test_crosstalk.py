"""Crosstalk: the projector's light on the object, against Snell's law and the Fresnel
transmittance written out here, the projector's emitted flux as Mitsuba's projector defines it
(irradiance x scale x pi x the panel's area at unit distance), and the view's own layout of
the object (a marker drawn in the texture where a dot lands shows where the dot shows)."""

import numpy as np
import pytest
from scipy import ndimage

from mitsuba_wai import FrameRenderer, wave_surface
from mitsuba_wai.crosstalk import camera_v_filter
from mitsuba_wai.mesh import flat_like
from mitsuba_wai.variant import select_variant
from wai_core import load_system
from wai_core.config import with_keys
from wai_core.errors import WaiInputError
from wai_core.forward import texture_coords


@pytest.fixture(scope="module")
def lit():
    select_variant()
    cfg = load_system("paper").replace("crosstalk", enabled=True)
    flat = flat_like(wave_surface(cfg), cfg.water.h0_mm)
    renderer = FrameRenderer(cfg, flat, systems=("view",))
    renderer._set_surface(flat)
    return cfg, flat, renderer


def _snell_hits(cfg):
    """Each dot's chief ray through flat water onto the object plane (K, 2) mm, its Fresnel
    transmittance (K,) and whether it leaves the water."""
    rig = cfg.rig
    n = cfg.water.n_water
    d = rig.flat_spots.dirs
    o = rig.projector.pose.center_lab_mm
    q = o + d * ((cfg.water.h0_mm - o[2]) / d[:, 2])[:, None]
    sin_w = np.hypot(d[:, 0], d[:, 1])
    out = n * sin_w < 1.0
    t_xy = d[:, :2] * n
    t_z = np.sqrt(np.clip(1.0 - (n * sin_w) ** 2, 0.0, None))
    z_obj = rig.object_center_mm[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        p = q[:, :2] + t_xy * ((z_obj - cfg.water.h0_mm) / t_z)[:, None]
        cw, ca = np.sqrt(1 - sin_w**2), t_z
        rs = (n * cw - ca) / (n * cw + ca)
        rp = (cw - n * ca) / (cw + n * ca)
    return p, np.where(out, 1.0 - (rs**2 + rp**2) / 2.0, 0.0), out & (d[:, 2] > 0)


def test_each_dot_lands_where_snell_says_with_its_transmitted_flux(lit):
    cfg, _, renderer = lit
    E = renderer._crosstalk.irradiance(seed=3)
    rows, cols = E.shape[:2]
    w, h = cfg.object.size_mm
    texel_mm = np.array([w / cols, h / rows])
    p, trans, out = _snell_hits(cfg)
    # Texel of each landing point, as the view shows the texture (the layout's own test below).
    uv = texture_coords(np.concatenate([p, np.zeros((len(p), 1))], axis=1), cfg, E.shape)
    col, row = uv[:, 0] + 0.5, uv[:, 1] + 0.5
    weights = cfg.rig.dot_weights
    inner = out & (weights > 0) & (col > 15) & (col < cols - 15) & (row > 15) & (row < rows - 15)
    assert inner.sum() > 50
    # The projector's flux per dot (Mitsuba's projector: irradiance x scale x pi x area).
    proj = cfg.rig.projector
    area = 4.0 * np.tan(np.radians(proj.fov_x_deg) / 2) ** 2 * proj.height_px / proj.width_px
    unit = 2 * np.pi * cfg.pattern.sigma_px**2 / (proj.width_px * proj.height_px)
    flux = weights * unit * cfg.pattern.power * np.pi * area * cfg.pattern.color[2]
    blue = E[..., 2] * np.prod(texel_mm)  # power per texel, the blue channel
    labels, n = ndimage.label(blue > 0.01 * blue.max())
    found = np.array(ndimage.center_of_mass(blue, labels, range(1, n + 1)))
    # Each predicted dot has a blob at its Snell point (texel centres at +0.5).
    dist = np.hypot(found[:, None, 0] - (row[inner] - 0.5)[None],
                    found[:, None, 1] - (col[inner] - 0.5)[None]).min(axis=0)
    assert np.median(dist) < 0.1 and np.percentile(dist, 95) < 0.5 and dist.max() < 3.0
    # Its power: the texels within 10 of its point (its Gaussian reaches ~4 sigma there).
    power = np.array([blue[int(r) - 10:int(r) + 11, int(k) - 10:int(k) + 11].sum()
                      for r, k in zip(row[inner], col[inner], strict=True)])
    ratio = power / (flux[inner] * trans[inner])
    assert np.median(ratio) == pytest.approx(1.0, abs=0.02)
    # (the dots leaving near the critical angle spread past the window: only the middle half)
    assert np.percentile(ratio, [25, 75]) == pytest.approx([1.0, 1.0], abs=0.08)


def test_the_view_lays_the_texture_out_as_the_light_is_binned(lit):
    """The layout the projector's light is binned in (wai_core.forward.texture_coords) is the
    one the view shows: a block in the texture's first rows, which no mirror symmetry of the
    rig can hide, lands in the render where the geometric model of camera v through flat
    water puts it (wai_core.forward.predict_view traces rays, not the scene)."""
    from wai_core.forward import predict_view

    cfg, flat, _ = lit
    tex = np.zeros((768, 1024, 3), np.float32)
    tex[100:250, 300:500] = 1.0
    plain = cfg.replace("crosstalk", enabled=False)
    shown = FrameRenderer(plain, flat, texture=tex, systems=("view",)).render(
        flat, 1, which=("view",), spp=4)["view"].sum(axis=2)
    predicted, _ = predict_view(plain, None, tex)
    predicted = predicted.sum(axis=2)

    def centre(img):
        rows, cols = np.nonzero(img > 0.5 * img.max())
        return np.array([rows.mean(), cols.mean()])

    np.testing.assert_allclose(centre(shown), centre(predicted), atol=0.5)
    mirrored = predict_view(plain, None, tex[::-1])[0].sum(axis=2)
    assert np.abs(centre(mirrored) - centre(shown)).max() > 20  # a flip would be seen


def test_the_dots_on_the_object_show_in_the_view(lit):
    cfg, flat, renderer = lit
    on = renderer.render(flat, 1, which=("view",), spp=8)["view"]
    off = renderer.render(flat, 1, which=("view",), spp=8, crosstalk=False)["view"]
    assert off.min() >= 0 and np.abs(on - off).max() > 0.01  # the dots are there, then not
    assert np.abs(on - off)[..., 0].max() == 0.0  # the pattern has no red


def test_a_red_filter_removes_the_blue_green_dots_and_off_is_free(lit):
    cfg, flat, _ = lit
    red = cfg.replace("crosstalk", camera_v_filter="red")
    r = FrameRenderer(red, flat, systems=("view",))
    on = r.render(flat, 2, which=("view",), spp=4)["view"]
    off = r.render(flat, 2, which=("view",), spp=4, crosstalk=False)["view"]
    assert np.abs(on - off).max() < 1e-6 and on[..., 1:].max() == 0.0
    plain = load_system("paper")
    assert FrameRenderer(plain, flat, systems=("view",))._crosstalk is None
    view = np.ones((2, 2, 3), np.float32)
    assert camera_v_filter(plain, view) is view
    with pytest.raises(WaiInputError, match="camera_v_filter"):
        with_keys(plain, {"crosstalk.camera_v_filter": "green"})
