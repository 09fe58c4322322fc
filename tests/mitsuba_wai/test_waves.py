"""Tests of the Longuet-Higgins sea surface against facts of ocean-wave theory, not the code."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import quad

import mitsuba_wai.waves as waves_mod
from mitsuba_wai.waves import (
    G_M_S2,
    PM_PEAK_FACTOR,
    SeaSurface,
    ittc_spreading,
    mesh_spacing_mm,
    peak_frequency_rad_s,
    pm_spectrum,
    sea_surface,
    wavenumber_rad_m,
)
from wai_core.config import WavesConfig
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield

G = 9.81  # m/s^2, stated independently of the module

# The sea state the tests assume, pinned here so that changes to the config defaults or to
# scenes/paper.toml do not move the expected numbers.
SEA = WavesConfig(
    wind_speed_m_s=1.0,
    seed=0,
    wind_direction_deg=0.0,
    n_frequencies=64,
    n_directions=24,
    omega_min_rel=0.5,
    omega_max_rel=5.0,
)


def make_sea(**changes) -> SeaSurface:
    """The pinned sea with some config keys changed."""
    return sea_surface(replace(SEA, **changes))


def pm_hs_m(wind_speed_m_s: float) -> float:
    """Textbook P-M significant wave height, Hs = 0.21 U^2 / g, m."""
    return 0.21 * wind_speed_m_s**2 / G


def one_harmonic(a_mm=3.0, omega=6.0, theta=0.4, eps=1.1) -> SeaSurface:
    """A sea of a single deep-water harmonic."""
    k_rad_per_mm = omega**2 / G / 1000.0
    return SeaSurface([[a_mm]], [omega], [k_rad_per_mm], [theta], [[eps]])


@pytest.fixture(scope="module")
def paper_sea() -> SeaSurface:
    return make_sea()


# --- spectrum and spreading -------------------------------------------------------------------


def test_gravity_constant():
    assert G_M_S2 == pytest.approx(G)


def test_peak_factor_is_where_the_derivative_vanishes():
    # dS/dw = 0 for S ~ w^-5 exp(-0.74 (g/(U w))^4) gives (U w_p / g)^4 = 4 * 0.74 / 5.
    assert PM_PEAK_FACTOR == pytest.approx((4 * 0.74 / 5) ** 0.25, rel=1e-12)
    assert PM_PEAK_FACTOR == pytest.approx(0.877, abs=5e-4)


@pytest.mark.parametrize("wind", [1.0, 5.0, 10.0])
def test_pm_peak_found_numerically(wind):
    omega = np.linspace(0.2, 3.0, 200_001) * G / wind
    peak = omega[np.argmax(pm_spectrum(omega, wind))]
    assert peak == pytest.approx(0.877 * G / wind, rel=1e-3)
    assert peak_frequency_rad_s(wind) == pytest.approx(peak, rel=1e-4)


@pytest.mark.parametrize("wind", [1.0, 5.0, 10.0])
def test_pm_continuous_hs(wind):
    m0, _ = quad(pm_spectrum, 0.0, np.inf, args=(wind,), limit=200)
    assert 4 * np.sqrt(m0) == pytest.approx(pm_hs_m(wind), rel=0.01)


def test_pm_spectrum_edges():
    assert np.all(pm_spectrum([0.0, -1.0, 1e-300, 1.0], 0.0) == 0.0)
    s = pm_spectrum(np.array([0.0, -2.0, 1e-300, 1e300]), 1.0)
    assert np.all(np.isfinite(s)) and np.all(s == 0.0)


def test_ittc_integrates_to_one():
    total, _ = quad(ittc_spreading, -np.pi / 2, np.pi / 2)
    assert total == pytest.approx(1.0, rel=1e-10)
    # No energy against the wind, and angles wrap.
    assert np.all(ittc_spreading([np.pi / 2 + 0.1, np.pi, -2.0]) == 0.0)
    assert ittc_spreading(2 * np.pi + 0.3) == pytest.approx(ittc_spreading(0.3))
    assert ittc_spreading(0.0) == pytest.approx(2 / np.pi)


@pytest.mark.parametrize("wind", [1.0, 5.0, 10.0])
def test_discrete_hs_matches_pierson_moskowitz(wind):
    sea = make_sea(wind_speed_m_s=wind)
    assert sea.significant_wave_height_mm == pytest.approx(pm_hs_m(wind) * 1000.0, rel=0.05)


@pytest.mark.parametrize("n_directions", [1, 2, 7, 24])
def test_direction_count_keeps_energy(n_directions):
    sea = make_sea(n_directions=n_directions)
    assert sea.significant_wave_height_mm == pytest.approx(pm_hs_m(1.0) * 1000.0, rel=0.05)


def test_height_scale_makes_the_same_sea_steeper(paper_sea):
    # Twice the height scale: Hs twice Pierson-Moskowitz's at the same U, the same wavelengths
    # and phases (so the same shape: heights and slopes doubled everywhere).
    steep = make_sea(height_scale=2.0)
    assert steep.significant_wave_height_mm == pytest.approx(2 * pm_hs_m(1.0) * 1000.0,
                                                             rel=0.05)
    assert steep.shortest_wavelength_mm == paper_sea.shortest_wavelength_mm
    x, y = np.meshgrid(np.linspace(-300.0, 300.0, 13), np.linspace(-200.0, 200.0, 9))
    np.testing.assert_allclose(steep.height_mm(x, y, 3.0), 2 * paper_sea.height_mm(x, y, 3.0),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(steep.slopes(x, y, 3.0), 2 * np.asarray(paper_sea.slopes(x, y, 3.0)),
                               rtol=1e-12, atol=1e-15)


def test_a_negative_height_scale_is_refused():
    from wai_core import load_system
    from wai_core.config import validate

    with pytest.raises(WaiInputError, match=r"\[waves\]\.height_scale"):
        validate(load_system("paper").replace("waves", height_scale=-1.0))


# --- sampling and dispersion ------------------------------------------------------------------


def test_dispersion_and_sampling(paper_sea):
    sea = paper_sea
    omega = sea.omega_rad_s
    k_per_m = sea.k_rad_per_mm * 1000.0
    # Deep water: phase speed omega/k = g/omega, wavelength 2 pi g / omega^2.
    np.testing.assert_allclose(omega / k_per_m, G / omega, rtol=1e-12)
    np.testing.assert_allclose(2 * np.pi / sea.k_rad_per_mm, 2 * np.pi * G / omega**2 * 1e3)
    # One frequency in each of 64 equal bins of [0.5, 5] omega_p.
    omega_p = 0.877 * G / 1.0
    edges = np.linspace(0.5, 5.0, 65) * omega_p
    assert np.all((omega > edges[:-1] * 0.999) & (omega < edges[1:] * 1.001))
    assert np.all(np.diff(omega) > 0)
    assert np.ptp(np.diff(omega)) > 1e-3 * omega_p  # jittered, not evenly spaced
    # Directions: 24 bin midpoints over +-90 deg about the wind (0 deg).
    np.testing.assert_allclose(np.diff(sea.directions_rad), np.pi / 24)
    assert sea.directions_rad.mean() == pytest.approx(0.0, abs=1e-12)
    assert np.all((sea.phases >= 0) & (sea.phases < 2 * np.pi))
    assert sea.amplitudes_mm.shape == (64, 24) and sea.n_components == 1536


def test_shortest_wavelength_and_mesh_spacing(paper_sea):
    omega_max = 5.0 * PM_PEAK_FACTOR * G / 1.0
    expected = 2 * np.pi * G / omega_max**2 * 1000.0
    assert paper_sea.shortest_wavelength_mm == pytest.approx(expected, rel=1e-12)
    assert paper_sea.shortest_wavelength_mm == pytest.approx(33.3, abs=0.1)
    assert mesh_spacing_mm(paper_sea, 12.0) == pytest.approx(expected / 12.0)
    # Without a recorded band, the fastest component sets it.
    single = one_harmonic(omega=6.0)
    assert single.shortest_wavelength_mm == pytest.approx(2 * np.pi * G / 36.0 * 1000.0)


def test_wind_direction_rotates_the_sea():
    sea = make_sea(wind_direction_deg=90.0)
    assert sea.directions_rad.mean() == pytest.approx(np.pi / 2)
    base = make_sea()
    np.testing.assert_allclose(sea.amplitudes_mm, base.amplitudes_mm)


# --- evaluation ---------------------------------------------------------------------------------


def test_single_harmonic_height_and_slopes():
    a, omega, theta, eps = 3.0, 6.0, 0.4, 1.1
    sea = one_harmonic(a, omega, theta, eps)
    k = omega**2 / G / 1000.0
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-500, 500, (2, 200))
    t = rng.uniform(0, 20, 200)
    phase = omega * t - k * (x * np.cos(theta) + y * np.sin(theta)) + eps
    np.testing.assert_allclose(sea.height_mm(x, y, t), a * np.cos(phase), atol=1e-12)
    gx, gy = sea.slopes(x, y, t)
    np.testing.assert_allclose(gx, a * k * np.cos(theta) * np.sin(phase), atol=1e-14)
    np.testing.assert_allclose(gy, a * k * np.sin(theta) * np.sin(phase), atol=1e-14)
    h = 1e-3  # mm; central-difference error ~ a k^3 h^2 / 6, far below the tolerance
    fd_x = (sea.height_mm(x + h, y, t) - sea.height_mm(x - h, y, t)) / (2 * h)
    fd_y = (sea.height_mm(x, y + h, t) - sea.height_mm(x, y - h, t)) / (2 * h)
    np.testing.assert_allclose(gx, fd_x, atol=1e-9)
    np.testing.assert_allclose(gy, fd_y, atol=1e-9)


def test_slopes_match_finite_differences_of_full_sea(paper_sea):
    rng = np.random.default_rng(2)
    x, y = rng.uniform(0, 660, (2, 50))
    h = 1e-3
    gx, gy = paper_sea.slopes(x, y, 10.0)
    fd_x = (paper_sea.height_mm(x + h, y, 10.0) - paper_sea.height_mm(x - h, y, 10.0)) / (2 * h)
    fd_y = (paper_sea.height_mm(x, y + h, 10.0) - paper_sea.height_mm(x, y - h, 10.0)) / (2 * h)
    np.testing.assert_allclose(gx, fd_x, atol=1e-7)
    np.testing.assert_allclose(gy, fd_y, atol=1e-7)


def test_temporal_period():
    omega = 6.0
    sea = one_harmonic(omega=omega)
    period = 2 * np.pi / omega
    t = np.linspace(0.0, 3.0, 31)
    h = sea.height_mm(0.0, 0.0, t)
    np.testing.assert_allclose(sea.height_mm(0.0, 0.0, t + period), h, atol=1e-12)
    np.testing.assert_allclose(sea.height_mm(0.0, 0.0, t + period / 2), -h, atol=1e-12)
    # The shortest period: half a cycle reverses the sign, a quarter is not a repeat either.
    assert np.max(np.abs(sea.height_mm(0.0, 0.0, t + period / 4) - h)) > 1.0


def test_broadcasting_shapes(paper_sea):
    x = np.linspace(0, 660, 5)[:, None]
    y = np.linspace(-330, 330, 4)[None, :]
    assert paper_sea.height_mm(x, y, 10.0).shape == (5, 4)
    assert paper_sea.height_mm(1.0, 2.0, np.arange(3.0)).shape == (3,)
    assert paper_sea.height_mm(1.0, 2.0, 0.0).shape == ()
    gx, gy = paper_sea.slopes(x, y, np.zeros((5, 4)))
    assert gx.shape == gy.shape == (5, 4)


def test_grid_equals_pointwise(paper_sea):
    x = np.linspace(0.0, 660.0, 37)
    y = np.linspace(-330.0, 330.0, 23)
    hf = paper_sea.grid(x, y, 10.0, mean_level_mm=150.0)
    assert isinstance(hf, Heightfield) and hf.z.shape == (23, 37)
    xx, yy = np.meshgrid(x, y)
    expected = 150.0 + paper_sea.height_mm(xx, yy, 10.0)
    np.testing.assert_allclose(hf.z, expected, rtol=0, atol=1e-9)
    # An uneven axis takes the plain path.
    x_uneven = np.sort(np.random.default_rng(3).uniform(0.0, 660.0, 29))
    hf2 = paper_sea.grid(x_uneven, y, 7.5, mean_level_mm=150.0)
    xx, yy = np.meshgrid(x_uneven, y)
    np.testing.assert_allclose(hf2.z, 150.0 + paper_sea.height_mm(xx, yy, 7.5), atol=1e-9)


def test_blocked_evaluation_is_unchanged(paper_sea, monkeypatch):
    x = np.linspace(0.0, 660.0, 40)
    y = np.linspace(-330.0, 330.0, 30)
    pts = np.random.default_rng(4).uniform(0, 660, (2, 100))
    z = paper_sea.grid(x, y, 3.0).z
    h = paper_sea.height_mm(*pts, 3.0)
    g = paper_sea.slopes(*pts, 3.0)
    # Blocks of 7 points (pointwise) and 3 rows/columns (grid).
    monkeypatch.setattr(waves_mod, "_BLOCK_BYTES", 16 * paper_sea.n_components * 7 // 2)
    np.testing.assert_allclose(paper_sea.height_mm(*pts, 3.0), h, atol=1e-12)
    np.testing.assert_allclose(paper_sea.slopes(*pts, 3.0), g, atol=1e-14)
    monkeypatch.setattr(waves_mod, "_BLOCK_BYTES", 16 * paper_sea.n_components * 3)
    np.testing.assert_allclose(paper_sea.grid(x, y, 3.0).z, z, atol=1e-12)


# --- determinism and calm water -------------------------------------------------------------


def test_seed_determinism():
    x = np.linspace(0, 660, 11)
    a = make_sea(seed=7)
    b = make_sea(seed=7)
    c = make_sea(seed=8)
    for name in ("amplitudes_mm", "omega_rad_s", "k_rad_per_mm", "directions_rad", "phases"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(a.height_mm(x, 0.0, 10.0), b.height_mm(x, 0.0, 10.0))
    assert np.max(np.abs(a.height_mm(x, 0.0, 10.0) - c.height_mm(x, 0.0, 10.0))) > 0.1


def test_config_time_is_not_used():
    a = make_sea(time_s=0.0)
    b = make_sea(time_s=99.0)
    np.testing.assert_array_equal(a.phases, b.phases)


def test_calm_water_is_flat():
    sea = make_sea(wind_speed_m_s=0.0)
    assert sea.significant_wave_height_mm == 0.0
    assert np.all(sea.amplitudes_mm == 0.0)
    x = np.linspace(0, 660, 9)
    y = np.linspace(-330, 330, 5)
    np.testing.assert_array_equal(sea.grid(x, y, 10.0, mean_level_mm=150.0).z, 150.0)
    np.testing.assert_array_equal(sea.height_mm(x, 0.0, 10.0), 0.0)
    gx, gy = sea.slopes(x, 1.0, 10.0)
    assert np.all(gx == 0.0) and np.all(gy == 0.0)
    assert sea.shortest_wavelength_mm == np.inf
    assert mesh_spacing_mm(sea, 12.0) == pytest.approx(660.0 / 4)
    assert mesh_spacing_mm(sea, 12.0, extent_mm=400.0) == pytest.approx(100.0)
    assert peak_frequency_rad_s(0.0) == np.inf


def test_surface_arrays_are_read_only(paper_sea):
    with pytest.raises(ValueError):
        paper_sea.amplitudes_mm[0, 0] = 1.0


# --- statistics -------------------------------------------------------------------------------


def test_height_std_is_a_quarter_of_hs():
    # For a random-phase sum the ensemble mean of eta^2 is m0 = (Hs/4)^2 exactly. A 20 m square
    # holds ~24 peak wavelengths (0.83 m at U = 1 m/s), so each seed's sample std lies within
    # ~3 % of sqrt(m0); pooling 4 seeds gives ~1 %. The bound against the textbook Hs also carries
    # the 5 % discretisation allowance. The coarse 156 mm sampling aliases the short waves, which
    # leaves the variance unchanged.
    x = np.linspace(0.0, 20_000.0, 128)
    var = []
    own = []
    for seed in range(4):
        sea = make_sea(wind_speed_m_s=1.0, seed=seed)
        z = sea.grid(x, x, 10.0).z
        var.append(z.var())
        own.append((sea.significant_wave_height_mm / 4) ** 2)
    std = np.sqrt(np.mean(var))
    assert std == pytest.approx(np.sqrt(np.mean(own)), rel=0.03)
    assert std == pytest.approx(pm_hs_m(1.0) * 1000.0 / 4, rel=0.07)


def test_cos2_spreading_gives_3_to_1_slope_variance():
    # Mean-square slope along the wind over across it is
    # int cos^2 cos^2 / int cos^2 sin^2 = (3 pi/8) / (pi/8) = 3 for cos^2 spreading.
    # Pooled over 4 seeds x 1500 random points the ratio scatters by ~4 %.
    rng = np.random.default_rng(1)
    sx = sy = 0.0
    for seed in range(4):
        sea = make_sea(seed=seed)
        x, y = rng.uniform(0, 20_000, (2, 1500))
        gx, gy = sea.slopes(x, y, 3.0)
        sx += np.sum(gx**2)
        sy += np.sum(gy**2)
    assert sx / sy == pytest.approx(3.0, rel=0.12)


# --- gravity-capillary dispersion -----------------------------------------------------------

SIGMA = 0.074  # N/m, surface tension of sea water (textbook value)
RHO = 1025.0  # kg/m^3, sea water


def test_capillary_wavenumber_solves_the_dispersion_relation():
    omega = np.geomspace(0.1, 300.0, 400)
    k = wavenumber_rad_m(omega, "capillary")
    # omega^2 = g k + (sigma / rho) k^3 (Lamb, Hydrodynamics, art. 267), deep water.
    np.testing.assert_allclose(G * k + SIGMA / RHO * k**3, omega**2, rtol=1e-10)
    assert np.all(np.diff(k) > 0)


def test_capillary_phase_speed_minimum():
    # c = sqrt(g / k + sigma k / rho) is least at k_m = sqrt(rho g / sigma), where
    # c_min = (4 g sigma / rho)^(1/4): 0.231 m/s at 1.70 cm for sea water.
    c_min = (4.0 * G * SIGMA / RHO) ** 0.25
    lambda_min_m = 2.0 * np.pi * np.sqrt(SIGMA / (RHO * G))
    assert c_min == pytest.approx(0.231, abs=5e-4)
    assert lambda_min_m == pytest.approx(0.0170, abs=1e-4)
    omega = np.linspace(5.0, 200.0, 200_001)
    k = wavenumber_rad_m(omega, "capillary")
    c = omega / k
    i = int(np.argmin(c))
    assert c[i] == pytest.approx(c_min, rel=1e-6)
    assert 2.0 * np.pi / k[i] == pytest.approx(lambda_min_m, rel=2e-3)
    # Gravity waves have no minimum: c = g / omega falls for ever.
    assert np.all(np.diff(omega / wavenumber_rad_m(omega, "gravity")) < 0)


def test_dispersions_agree_for_long_waves():
    omega = np.array([0.5, 1.0, 3.0])  # wavelengths 250 m .. 7 m
    deep = omega**2 / G
    np.testing.assert_allclose(wavenumber_rad_m(omega, "capillary"), deep, rtol=1e-4)
    # Short waves: surface tension stiffens the surface, so a frequency has a longer wave.
    assert wavenumber_rad_m(80.0, "capillary") < 0.6 * 80.0**2 / G


def test_gravity_dispersion_is_the_deep_water_default(paper_sea):
    assert SEA.dispersion == "gravity"
    assert np.array_equal(paper_sea.k_rad_per_mm, paper_sea.omega_rad_s**2 / G / 1000.0)
    same = make_sea(dispersion="gravity")
    assert np.array_equal(same.k_rad_per_mm, paper_sea.k_rad_per_mm)
    assert same.shortest_wavelength_mm == paper_sea.shortest_wavelength_mm


def test_capillary_sea_wavelengths_and_mesh_follow_the_dispersion(paper_sea):
    from scipy.optimize import brentq

    sea = make_sea(dispersion="capillary")
    # Same frequencies and amplitudes (a frequency spectrum), other wave numbers.
    assert np.array_equal(sea.omega_rad_s, paper_sea.omega_rad_s)
    assert np.array_equal(sea.amplitudes_mm, paper_sea.amplitudes_mm)
    omega_max = 5.0 * PM_PEAK_FACTOR * G / 1.0
    k_max = brentq(lambda k: G * k + SIGMA / RHO * k**3 - omega_max**2, 1.0, 1e4, xtol=1e-12)
    expected_mm = 2.0 * np.pi / k_max * 1000.0
    assert sea.shortest_wavelength_mm == pytest.approx(expected_mm, rel=1e-9)
    assert sea.shortest_wavelength_mm > 1.15 * paper_sea.shortest_wavelength_mm
    assert mesh_spacing_mm(sea, 48.0) == pytest.approx(expected_mm / 48.0, rel=1e-9)


def test_a_cutoff_too_far_is_refused_naming_omega_max_rel():
    from mitsuba_wai.surface_sampling import wave_surface
    from wai_core import load_system

    cfg = load_system("paper").replace(
        "waves", wind_speed_m_s=1.0, omega_max_rel=10.0, dispersion="capillary"
    )
    with pytest.raises(WaiInputError, match=r"\[waves\]\.omega_max_rel"):
        wave_surface(cfg)


def test_rejects_unknown_dispersion():
    with pytest.raises(WaiInputError, match="dispersion"):
        wavenumber_rad_m(1.0, "shallow")
    with pytest.raises(WaiInputError, match="dispersion"):
        SeaSurface([[1.0]], [1.0], [1.0], [0.0], [[0.0]], dispersion="shallow")


# --- input checks -------------------------------------------------------------------------------


def test_rejects_bad_input():
    with pytest.raises(WaiInputError, match="amplitudes_mm"):
        SeaSurface([[1.0, 2.0]], [1.0], [1.0], [0.0], [[0.0]])
    with pytest.raises(WaiInputError, match="non-negative"):
        SeaSurface([[-1.0]], [1.0], [1.0], [0.0], [[0.0]])
    with pytest.raises(WaiInputError, match="NaN"):
        SeaSurface([[1.0]], [np.nan], [1.0], [0.0], [[0.0]])
    with pytest.raises(WaiInputError):
        make_sea(wind_speed_m_s=-1.0)
    with pytest.raises(WaiInputError):
        make_sea(n_frequencies=0)
    with pytest.raises(WaiInputError):
        make_sea(omega_min_rel=2.0, omega_max_rel=1.0)
    with pytest.raises(WaiInputError):
        mesh_spacing_mm(one_harmonic(), 0.0)
