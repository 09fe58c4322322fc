"""The projector's dots drawn directly (:class:`mitsuba_wai.dots.DotEmitter`): particles where
the spots need them, and the thin-lens projector's defocus."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from wai_core.layout import dot_weights
from wai_core.pattern import dot_grid


def _emitter(cfg):
    from mitsuba_wai.dots import DotEmitter
    from mitsuba_wai.variant import select_variant

    select_variant()
    return DotEmitter(cfg)


def _draw(emitter, n, seed):
    """Origins (n, 3), unit directions (n, 3) and weights (n, 3) of ``n`` particles."""
    import drjit as dr

    ray, weight, travelled = emitter(0.0, n, seed)
    dr.eval(ray.o, ray.d, weight, travelled)
    return np.asarray(ray.o).T, np.asarray(ray.d).T, np.asarray(weight).T, np.asarray(travelled)


def _chief_rays(cfg):
    """Unit directions (K, 3) of the lit dots' chief rays, lab."""
    projector = cfg.rig.projector
    _, panel = dot_grid(cfg.pattern, projector)
    _, dirs = projector.pixel_rays(panel[:, 0], panel[:, 1])
    return dirs[dot_weights(cfg) > 0]


def _beyond_critical(dirs, n_water):
    """Chief rays (K,) that meet flat water beyond the critical angle (Snell: sin > 1 / n)."""
    return np.sqrt(1.0 - dirs[:, 2] ** 2) > 1.0 / n_water


def _on_diffuser(cfg, o, d):
    """Where the rays (lab) land on the diffuser after flat water's mirror reflection, (n, 2)."""
    q = o + d * ((cfg.water.h0_mm - o[:, 2]) / d[:, 2])[:, None]
    d = d * [1.0, 1.0, -1.0]
    return (q + d * ((cfg.diffuser.z_mm - q[:, 2]) / d[:, 2])[:, None])[:, :2]


def test_spots_beyond_the_critical_angle_are_as_steady_as_the_others(paper_cfg):
    # Beyond the critical angle water reflects all light (R = 1), elsewhere ~2 %: the adaptive
    # pattern makes those dots ~50x dimmer so all spots reach the diffuser about equally bright.
    # Particles must follow the delivered light, not the emitted: each spot's centroid on the
    # diffuser (mm) must scatter over seeds about equally beyond the critical angle and below
    # (``particle_shares = "delivered"``; the default shares by emitted power).
    emitter = _emitter(paper_cfg.replace("render", particle_shares="delivered"))
    dirs = _chief_rays(paper_cfg)
    far = _beyond_critical(dirs, paper_cfg.water.n_water)
    assert 0.2 < far.mean() < 0.8
    tree = cKDTree(dirs)
    centroids = []
    for seed in range(6):
        o, d, _, _ = _draw(emitter, 300_000, seed)
        dot = tree.query(d)[1]
        xy = _on_diffuser(paper_cfg, o.astype(float), d.astype(float))
        count = np.bincount(dot, minlength=len(dirs))
        centroids.append(np.stack([np.bincount(dot, xy[:, k], len(dirs)) / count
                                   for k in (0, 1)], 1))
    noise = np.linalg.norm(np.std(centroids, axis=0), axis=1)
    ratio = np.median(noise[far]) / np.median(noise[~far])
    assert ratio < 1.5


def test_each_dot_emits_its_brightness_whatever_its_particles(paper_cfg):
    # Unbiased: a dot's particles carry its emitted flux, which is its brightness in the panel's
    # bitmap times the Gaussian's integral (the same for every dot), however many it gets.
    emitter = _emitter(paper_cfg.replace("render", particle_shares="delivered"))
    dirs = _chief_rays(paper_cfg)
    w = dot_weights(paper_cfg)
    w = w[w > 0]
    n = 200_000
    _, d, weight, _ = _draw(emitter, n, 5)
    dot = cKDTree(dirs).query(d)[1]
    count = np.bincount(dot, minlength=len(w))
    flux = np.bincount(dot, weight.sum(1), len(w)) / n
    per_brightness = flux / w
    # Within the count's granularity (systematic sampling: one particle, two for a far tail).
    rel = np.abs(per_brightness / np.median(per_brightness) - 1.0)
    assert np.all(rel <= 2.5 / count)
    # And beyond the critical angle a dot gets about as many particles as the others, not ~2 %.
    far = _beyond_critical(dirs, paper_cfg.water.n_water)
    assert np.median(count[far]) > 0.5 * np.median(count[~far])


def _lens_cfg(cfg, aperture_mm, focus_mm):
    return cfg.replace("projector", aperture_mm=aperture_mm, focus_mm=focus_mm)


def _axial_spread(o, d, axis, centre, z):
    """RMS radius (mm) about their mean of the rays' hits on the plane at distance ``z`` (mm)
    along ``axis`` from ``centre``."""
    t = (z - (o - centre) @ axis) / (d @ axis)
    p = o + d * t[:, None]
    return np.sqrt(((p - p.mean(0)) ** 2).sum(1).mean())


def test_thin_lens_blur_disk_grows_as_aperture_times_defocus(paper_cfg):
    # Thin-lens optics: a point in focus at distance f, seen through a lens of diameter A, blurs
    # on the plane at distance z into a uniform disk of diameter A |z - f| / f, whose RMS radius
    # is that diameter / (2 sqrt 2). The panel's Gaussian adds its own spread in quadrature
    # (independent), which the pinhole's rays measure; at z = f the lens adds nothing.
    aperture, focus = 6.0, 400.0
    # Shares by delivered power: enough particles in every dot, whatever its brightness.
    paper_cfg = paper_cfg.replace("render", particle_shares="delivered")
    pin = _emitter(paper_cfg)
    lens = _emitter(_lens_cfg(paper_cfg, aperture, focus))
    dirs = _chief_rays(paper_cfg)
    projector = paper_cfg.rig.projector
    axis, centre = projector.pose.axis_lab, projector.pose.center_lab_mm
    dot = int(np.argmax(dirs @ axis))  # the dot nearest the axis
    # The same seed gives the same panel points: particle i of both is the same dot's.
    draws = {name: _draw(e, 400_000, 2) for name, e in (("pin", pin), ("lens", lens))}
    mine = cKDTree(dirs).query(draws["pin"][1])[1] == dot
    assert mine.sum() > 200
    rays = {k: (v[0][mine].astype(float), v[1][mine].astype(float), v[3][mine])
            for k, v in draws.items()}
    # The lens' rays start past the diffuser too, their distance from their lens point.
    o, d, travelled = rays["lens"]
    assert np.allclose(o[:, 2], paper_cfg.diffuser.z_mm, atol=2e-3)
    start = o - d * travelled[:, None]
    assert np.allclose((start - centre) @ axis, 0.0, atol=1e-3)
    radius = np.linalg.norm(start - centre, axis=1)
    assert radius.max() <= aperture / 2 + 1e-3 and radius.max() > 0.45 * aperture
    # Uniform on the disk: the mean squared radius of a uniform disk is (A / 2)^2 / 2.
    assert np.mean(radius**2) == pytest.approx((aperture / 2) ** 2 / 2, rel=0.05)
    for z in (200.0, 300.0, focus, 600.0, 900.0):
        hit = {}
        for k, (o, d, _, _) in draws.items():
            o, d = o.astype(float), d.astype(float)
            hit[k] = o + d * ((z - (o - centre) @ axis) / (d @ axis))[:, None]
        # Less the pinhole ray's hit (the same panel point), the blur disk alone.
        blur = np.linalg.norm(hit["lens"] - hit["pin"], axis=1)
        diameter = aperture * abs(z - focus) / focus
        assert 2.0 * blur.max() == pytest.approx(diameter, rel=0.02, abs=2e-3)
        assert np.sqrt(np.mean(blur**2)) == pytest.approx(diameter / (2 * np.sqrt(2)), rel=0.02,
                                                          abs=1e-3)
        # And the spot: the dot's own spread and the blur add in quadrature.
        lens_rms = _axial_spread(*rays["lens"][:2], axis, centre, z)
        pin_rms = _axial_spread(*rays["pin"][:2], axis, centre, z)
        assert lens_rms == pytest.approx(np.hypot(pin_rms, diameter / (2 * np.sqrt(2))),
                                         rel=0.05, abs=1e-3)

def test_aperture_keeps_the_flux_and_widens_the_spots(paper_cfg):
    # A lens that blurs the pattern moves light, it does not make or lose any: the emitted flux
    # per channel is the projector's whatever the aperture; and out of focus (the water lies
    # nearer than the plane in focus) the spots in camera s get wider.
    from mitsuba_wai.mesh import flat_like
    from mitsuba_wai.render import FrameRenderer
    from mitsuba_wai.surface_sampling import wave_surface
    from tests.conftest import shrink

    cfg = shrink(paper_cfg, factor=2, spp=1)
    _, _, w_pin, _ = _draw(_emitter(cfg), 100_000, 1)
    blurred = _lens_cfg(cfg, 8.0, 2000.0)  # water ~370 mm away (unfolded): a 6.5 mm blur
    _, _, w_lens, _ = _draw(_emitter(blurred), 100_000, 1)
    assert np.allclose(w_lens.sum(0), w_pin.sum(0), rtol=1e-6)
    widths = []
    for c in (cfg, blurred):
        surface = flat_like(wave_surface(c), c.water.h0_mm)
        image = FrameRenderer(c, surface, systems=("pattern",)).render(
            surface, 3, which=("pattern",), spp=1)["pattern"].sum(2)
        assert image.sum() > 0
        widths.append(_mean_spot_width(image))
    assert widths[1] > 1.3 * widths[0]


def _mean_spot_width(image):
    """A width (px) of the spots of an image: the square root of its participation ratio
    ``(sum I)^2 / sum I^2``, the pixels it effectively covers (per spot ``4 pi sigma^2``)."""
    return np.sqrt(image.sum() ** 2 / (image**2).sum())
