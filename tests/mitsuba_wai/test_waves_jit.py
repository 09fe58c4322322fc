"""The wave sum on the renderer's device against the closed form and the host's sums."""

from __future__ import annotations

import numpy as np
import pytest

from mitsuba_wai import JitWaveGrid, sea_surface
from mitsuba_wai.waves import SeaSurface
from wai_core import load_system


def test_one_harmonic_is_its_travelling_cosine():
    # eta = a cos(omega t - k (x cos th + y sin th) + eps), written out by hand.
    a, omega, k, th, eps = 3.0, 2.5, 0.02, 0.4, 0.7
    sea = SeaSurface(np.array([[a]]), np.array([omega]), np.array([k]), np.array([th]),
                     np.array([[eps]]))
    x, y = np.linspace(-300.0, 500.0, 41), np.linspace(-200.0, 200.0, 23)
    grid = JitWaveGrid(x, y)
    t = 7.3
    eta, sx, sy = (np.asarray(v).reshape(y.size, x.size) for v in grid.eta(sea, t, slopes=True))
    xx, yy = np.meshgrid(x, y)
    phase = omega * t - k * (xx * np.cos(th) + yy * np.sin(th)) + eps
    np.testing.assert_allclose(eta, a * np.cos(phase), atol=1e-12)
    np.testing.assert_allclose(sx, a * k * np.cos(th) * np.sin(phase), atol=1e-14)
    np.testing.assert_allclose(sy, a * k * np.sin(th) * np.sin(phase), atol=1e-14)


@pytest.mark.parametrize("time_s", [0.0, 10.0, 123.4])
def test_the_papers_sea_matches_the_hosts_sums(time_s):
    cfg = load_system("paper")
    sea = sea_surface(cfg.waves)
    x, y = np.linspace(-250.0, 650.0, 61), np.linspace(-300.0, 300.0, 37)
    got = JitWaveGrid(x, y).heightfield(sea, time_s, mean_level_mm=cfg.water.h0_mm)
    # The host's matrix product and its cosine per point and harmonic.
    np.testing.assert_allclose(got.z, sea.grid(x, y, time_s, cfg.water.h0_mm).z, atol=1e-9)
    xx, yy = np.meshgrid(x, y)
    np.testing.assert_allclose(got.z - cfg.water.h0_mm, sea.height_mm(xx, yy, time_s),
                               atol=1e-9)
    assert np.ptp(got.z) > 1.0  # a sea, not flat water
    _, sx, sy = JitWaveGrid(x, y).eta(sea, time_s, slopes=True)
    gx, gy = sea.slopes(xx, yy, time_s)
    np.testing.assert_allclose(np.asarray(sx).reshape(xx.shape), gx, atol=1e-12)
    np.testing.assert_allclose(np.asarray(sy).reshape(xx.shape), gy, atol=1e-12)


def test_a_grid_serves_many_seas():
    cfg = load_system("paper")
    x, y = np.linspace(0.0, 400.0, 17), np.linspace(-100.0, 100.0, 9)
    grid = JitWaveGrid(x, y)
    for wind in (0.8, 1.5):
        sea = sea_surface(cfg.replace("waves", wind_speed_m_s=wind).waves)
        np.testing.assert_allclose(grid.heightfield(sea, 3.0).z, sea.grid(x, y, 3.0).z,
                                   atol=1e-9)
    calm = SeaSurface(np.zeros((2, 3)), np.ones(2), np.ones(2), np.zeros(3), np.zeros((2, 3)))
    assert np.all(grid.heightfield(calm, 1.0, mean_level_mm=5.0).z == 5.0)
