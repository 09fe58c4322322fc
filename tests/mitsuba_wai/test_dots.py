"""The projector's dots drawn directly (:class:`mitsuba_wai.dots.DotEmitter`): particles where
the spots need them, and the thin-lens projector's defocus."""

import numpy as np
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
    projector = cfg.projector.camera()
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
    # diffuser (mm) must scatter over seeds about equally beyond the critical angle and below.
    emitter = _emitter(paper_cfg)
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
    emitter = _emitter(paper_cfg)
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
