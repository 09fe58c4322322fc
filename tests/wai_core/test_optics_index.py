"""Sea water's refractive index (Quan & Fry 1995) against published measurements."""

import numpy as np
import pytest

from wai_core.optics import CHANNEL_WAVELENGTHS_NM, channel_indices, quan_fry_index

# Pure water at 20 deg C, relative to air (Tilton & Taylor 1938, as tabulated in the CRC
# Handbook): the hydrogen F line, the sodium D line, the hydrogen C line.
PURE_WATER_20C = {486.13: 1.33712, 589.26: 1.33299, 656.28: 1.33115}


@pytest.mark.parametrize("wavelength_nm", sorted(PURE_WATER_20C))
def test_pure_water_matches_tilton_taylor(wavelength_nm: float) -> None:
    n = float(quan_fry_index(0.0, 20.0, wavelength_nm))
    assert n == pytest.approx(PURE_WATER_20C[wavelength_nm], abs=1e-4)


def test_sea_water_sodium_line_matches_tables() -> None:
    # S = 35 PSU, 20 deg C, 589.3 nm: 1.3394 in Austin & Halikas's (1976) and Millard &
    # Seaver's (1990) tables.
    assert float(quan_fry_index(35.0, 20.0, 589.3)) == pytest.approx(1.3394, abs=3e-4)


def test_dispersion_of_sea_water() -> None:
    # Salt raises the index by about 1.8e-4 per PSU at every visible wavelength and leaves the
    # dispersion nearly as it is: the F - C difference of pure water is 0.00597 (table above).
    lam = np.array([486.13, 656.28])
    fc_sea = np.diff(quan_fry_index(35.0, 20.0, lam))[0]
    assert -fc_sea == pytest.approx(0.00597, abs=3e-4)
    rise = quan_fry_index(35.0, 20.0, 589.3) - quan_fry_index(0.0, 20.0, 589.3)
    assert rise / 35.0 == pytest.approx(1.8e-4, rel=0.1)


def test_channel_indices_are_the_fit_at_the_channel_wavelengths() -> None:
    n = np.array(channel_indices(35.0, 20.0))
    assert CHANNEL_WAVELENGTHS_NM == (600.0, 530.0, 460.0)
    np.testing.assert_allclose(n, quan_fry_index(35.0, 20.0, np.array([600.0, 530.0, 460.0])))
    # Normal dispersion: the shortest wavelength (blue) bends most.
    assert n[0] < n[1] < n[2]
