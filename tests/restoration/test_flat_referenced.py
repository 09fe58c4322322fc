"""Spots referred to the flat reference (the paper's dot shifts): an error that displaces the
flat-water and the wavy spots alike drops out, and the flat reference's level is the datum.

Exact spots of a swell are traced through the true rig; the restoration believes a rig whose
camera s is slightly wrong. Facts from outside the code: a differential measurement cancels a
common scale error of the camera to first order in the spots' displacement, and it measures
heights relative to the reference's level.
"""

from dataclasses import replace

import numpy as np
import pytest

from restoration import Calibration, StructuredLightOptions
from restoration.features import ReferenceGrid, flat_shifts, predict_flat_spots
from restoration.structured_light import estimate_surface
from tests.restoration.test_surface import CFG, H0, IJ, PANEL, features, height_errors, sine_surface
from wai_core.config import with_keys
from wai_core.light_paths import spots_through

SWELL = sine_surface(amp=2.0, wavelength=200.0, direction_deg=-20.0)


@pytest.fixture(scope="module")
def swell():
    return features(SWELL)


def believed(keys: dict) -> Calibration:
    """A calibration of the rig with ``keys`` changed, holding the true rig's flat spots."""
    cal = Calibration(with_keys(CFG, keys))
    true_flat = spots_through(CFG.rig, None, PANEL)
    ij, _, pred, _ = predict_flat_spots(cal.cfg)
    assert np.array_equal(ij, IJ)
    seen = np.isfinite(true_flat).all(axis=1) & np.isfinite(pred).all(axis=1)
    n = int(seen.sum())
    grid = ReferenceGrid(
        IJ[seen], true_flat[seen], np.ones(n, bool), np.ones(n, bool), np.full(n, 20.0),
        np.full((n, 2, 2), np.nan), np.zeros((0, 2), int), {}, 0.0, pred_px=pred[seen],
    )
    shape = (CFG.camera_s.height_px, CFG.camera_s.width_px)
    cal.reference = replace(grid, shift_px=flat_shifts(grid, shape))
    return cal


def rmse_mm(cal: Calibration, swell, referenced: bool) -> float:
    ij, _, spots, _, _, offset = swell
    est = estimate_surface(cal.observe(ij, spots, flat_referenced=referenced), cal,
                           StructuredLightOptions())
    return float(np.sqrt(np.mean(height_errors(est, SWELL, offset) ** 2)))


@pytest.mark.parametrize(("keys", "hurts_mm"), [
    ({"camera_s.focal_mm": CFG.camera_s.focal_mm * 1.0005}, 0.015),  # 0.05 % long
    ({"diffuser.z_mm": CFG.diffuser.z_mm + 0.3}, 0.1),  # the screen measured 0.3 mm high
])
def test_a_common_error_drops_out(swell, keys, hurts_mm):
    """Camera s's focal length 0.05 % long (what a checkerboard calibration may leave), or
    the diffuser's height 0.3 mm off: both move the flat and the wavy spots alike."""
    cal = believed(keys)
    as_detected = rmse_mm(cal, swell, referenced=False)
    referred = rmse_mm(cal, swell, referenced=True)
    assert as_detected > hurts_mm
    assert referred < as_detected / 5


def test_the_reference_level_is_the_datum(swell):
    """A believed level 0.3 mm high: as detected the data find the level; referred, the
    heights follow the datum and come out tenths of a millimetre off."""
    cal = believed({"water.h0_mm": H0 + 0.3})
    assert rmse_mm(cal, swell, referenced=False) < 0.02
    assert 0.1 < rmse_mm(cal, swell, referenced=True) < 0.45


def test_untrusted_flat_spots_take_their_neighbours_shift():
    """A flat spot 5 px from its prediction (cut by the image's edge, or a stray match) and
    one within four spot sigmas of the edge are replaced by their neighbours' mean."""
    ij = np.array([[i, 0] for i in range(5)])
    pred = np.array([[3.0 + 20.0 * i, 300.0] for i in range(5)])
    ref_px = pred + [0.2, -0.1]
    ref_px[2] += [5.0, 0.0]  # a stray match mid-row
    grid = ReferenceGrid(ij, ref_px, np.ones(5, bool), np.ones(5, bool), np.full(5, 20.0),
                         np.full((5, 2, 2), np.nan), np.zeros((0, 2), int), {}, 0.0,
                         pred_px=pred)
    shift = flat_shifts(grid, (600, 800))
    np.testing.assert_allclose(shift[1:], [[0.2, -0.1]] * 4)  # 2 from 1 and 3
    np.testing.assert_allclose(shift[0], [0.2, -0.1])  # x = 3 px: from its neighbour
    ref = replace(grid, shift_px=shift)
    np.testing.assert_allclose(ref.flat_shift_at(np.array([[9, 9], [1, 0]])),
                               [[0.0, 0.0], [0.2, -0.1]])


def test_referring_needs_the_reference():
    with pytest.raises(Exception, match="flat_referenced needs the flat-water reference"):
        Calibration(CFG).observe(IJ[:3], PANEL[:3], flat_referenced=True)
