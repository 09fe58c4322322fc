"""The Gauss-Newton fit to the spots, on spots the exact geometric model puts there."""

import numpy as np

from restoration import Calibration
from restoration.fit import BSplineSurface, fit_surface
from restoration.normals import projector_rays
from restoration.observations import Observations
from wai_core.heightfield import Heightfield
from wai_core.light_paths import spots_through


def _swell(h0, amplitude=1.5):
    x, y = np.linspace(-100.0, 700.0, 401), np.linspace(-350.0, 350.0, 351)
    xx, yy = np.meshgrid(x, y)
    return Heightfield(x, y, h0 + amplitude * np.sin(2 * np.pi * (xx + 0.5 * yy) / 200.0))


def test_a_bspline_reproduces_a_plane_and_its_slopes():
    spline = BSplineSurface(0.0, 0.0, 10.0, np.zeros((12, 12)))
    xx, yy = np.meshgrid(np.arange(12) * 10.0, np.arange(12) * 10.0)
    spline.coeffs = 5.0 + 0.1 * (xx - 10.0) - 0.2 * (yy - 10.0)  # knots offset by one step
    z, zx, zy, zxx, zxy, zyy = spline.evaluate(np.array([35.0, 52.0]), np.array([41.0, 47.0]))
    np.testing.assert_allclose(zx, 0.1, atol=1e-12)
    np.testing.assert_allclose(zy, -0.2, atol=1e-12)
    np.testing.assert_allclose([zxx, zxy, zyy], 0.0, atol=1e-12)


def test_the_fit_moves_a_wrong_start_towards_the_spots(paper_cfg):
    cfg = paper_cfg
    truth = _swell(cfg.water.h0_mm)
    ij = np.array([[i, j] for i in range(-10, 11) for j in range(-10, 11)])
    panel = Calibration(cfg).panel_px(ij)
    spots = spots_through(cfg.rig, truth, panel)
    keep = np.isfinite(spots).all(axis=1)
    ij, panel, spots = ij[keep], panel[keep], spots[keep]
    origin, dirs = projector_rays(panel, cfg.rig.projector)
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    hits, _ = truth.intersect(np.broadcast_to(origin, unit.shape), unit)
    gx, gy = truth.gradient(hits[:, 0], hits[:, 1])
    # A start 40 % too flat: heights and slopes both wrong, the level right.
    start = hits.copy()
    start[:, 2] = cfg.water.h0_mm + 0.6 * (hits[:, 2] - cfg.water.h0_mm)
    like = Heightfield(truth.x, truth.y, truth.z)
    obs = Observations.build(ij, panel, spots, cfg.rig.projector, cfg.rig.camera_s,
                             cfg.diffuser.z_mm)
    fit = fit_surface(start, 0.6 * np.column_stack([gx, gy]), obs, like)
    assert fit.rms_mm[-1] < 0.2 * fit.rms_mm[0]
    err_before = np.abs(start[:, 2] - hits[:, 2]).mean()
    err_after = np.abs(fit.points_mm[:, 2] - truth.height(fit.points_mm[:, 0],
                                                         fit.points_mm[:, 1])).mean()
    assert err_after < 0.5 * err_before


def _exact_samples(cfg, truth, n=10):
    ij = np.array([[i, j] for i in range(-n, n + 1) for j in range(-n, n + 1)])
    panel = Calibration(cfg).panel_px(ij)
    spots = spots_through(cfg.rig, truth, panel)
    keep = np.isfinite(spots).all(axis=1)
    panel, spots = panel[keep], spots[keep]
    origin, dirs = projector_rays(panel, cfg.rig.projector)
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    hits, _ = truth.intersect(np.broadcast_to(origin, unit.shape), unit)
    ok = np.isfinite(hits).all(axis=1)
    panel, spots, hits = panel[ok], spots[ok], hits[ok]
    return panel, spots, hits, np.column_stack(truth.gradient(hits[:, 0], hits[:, 1]))


def _exact_case(cfg, amplitude, start_mm):
    """A swell, its exact samples and spots, the samples started ``start_mm`` too high, and
    the rest of the fit's arguments: ``(truth, start, slopes, args)``."""
    truth = _swell(cfg.water.h0_mm, amplitude=amplitude)
    panel, spots, hits, slopes = _exact_samples(cfg, truth)
    start = hits.copy()
    start[:, 2] += start_mm
    like = Heightfield(truth.x, truth.y, truth.z)
    obs = Observations.build(np.zeros((len(panel), 2), np.int64), panel, spots,
                             cfg.rig.projector, cfg.rig.camera_s, cfg.diffuser.z_mm)
    return truth, start, slopes, (obs, like)


def test_the_level_search_finds_the_height_a_damped_fit_keeps(paper_cfg):
    # Exact spots of a swell, a start 0.3 mm too high with the right shape: the plain fit
    # keeps most of the offset (the depth-normal ambiguity), the level search removes it.
    from restoration.fit_level import fit_level

    truth, start, slopes, args = _exact_case(paper_cfg, amplitude=3.0, start_mm=0.3)

    def level_error(points):
        return float(np.nanmean(points[:, 2] - truth.height(points[:, 0], points[:, 1])))

    plain = fit_surface(start, slopes, *args, iterations=4)
    found = fit_level(start, slopes, *args)
    assert abs(level_error(found.fit.points_mm)) < 0.03
    assert abs(level_error(found.fit.points_mm)) < 0.3 * abs(level_error(plain.points_mm))
    # The search stopped at the lowest point of its profile, every probe within its steps.
    chosen = found.cost_mm2[found.offsets_mm == found.offset_mm]
    assert chosen.size == 1 and chosen[0] == found.cost_mm2.min()
    assert not found.kept_start and found.reason == ""
    assert found.iterations.max() <= 8


def test_the_level_profile_is_unimodal_for_exact_spots(paper_cfg):
    # Every probe fits from the same start with the level held, so the profile is a function
    # of the level alone: on exact spots it falls to one minimum, at the true level, and
    # rises after it (no probe's warm start makes a dip of its own).
    from restoration.fit_level import fit_level

    _, start, slopes, args = _exact_case(paper_cfg, amplitude=3.0, start_mm=0.2)
    found = fit_level(start, slopes, *args, probe_mm=0.1)
    x, y = found.offsets_mm, found.cost_mm2
    low = int(np.argmin(y))
    assert np.all(np.diff(y[:low + 1]) < 0) and np.all(np.diff(y[low:]) > 0)
    assert abs(x[low] + 0.2) < 0.03 and found.offset_mm == x[low]


def test_a_nearly_flat_surface_keeps_its_level(paper_cfg):
    # A swell of 0.1 mm (nearly flat: the level's profile is shallow) started at the right
    # level: the search must not walk away from it.
    from restoration.fit_level import fit_level

    truth, start, slopes, args = _exact_case(paper_cfg, amplitude=0.1, start_mm=0.0)
    found = fit_level(start, slopes, *args)
    err = found.fit.points_mm[:, 2] - truth.height(found.fit.points_mm[:, 0],
                                                   found.fit.points_mm[:, 1])
    assert abs(float(np.nanmean(err))) < 0.03
