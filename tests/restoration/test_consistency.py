"""The forward-consistency check against spots the exact geometric model puts there.

Spots come from :func:`wai_core.forward.spots_through` on a known analytic surface (no renderer,
no detector): the true surface must reproduce them to rounding, a wrong one must not.
"""

import numpy as np
import pytest

from restoration.consistency import INCONSISTENT_FRACTION, spot_consistency
from restoration.normals import projector_rays
from restoration.structured_light import panel_positions
from wai_core.forward import spots_through
from wai_core.heightfield import Heightfield

SPACING_PX = 13.0  # the paper rig's median dot spacing in camera s


def _swell(cfg, amplitude_mm=2.0, offset_mm=0.0, wavelength_mm=160.0):
    x = np.linspace(-100.0, 700.0, 401)
    y = np.linspace(-350.0, 350.0, 351)
    xx, yy = np.meshgrid(x, y)
    phase = 2 * np.pi * (xx + 0.5 * yy) / wavelength_mm
    z = cfg.water.h0_mm + offset_mm + amplitude_mm * np.sin(phase)
    return Heightfield(x, y, z)


def _check(cfg, truth, surface):
    ij = np.array([[i, j] for i in range(-12, 13) for j in range(-12, 13)])
    panel = panel_positions(cfg, ij)
    spots = spots_through(cfg, truth, panel)
    keep = np.isfinite(spots).all(axis=1)
    origin, dirs = projector_rays(panel[keep], cfg.projector.camera())
    # The samples: where each ray meets the true surface (what a good reconstruction gives).
    hits, _ = truth.intersect(np.broadcast_to(origin, dirs.shape),
                              dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    return spot_consistency(surface, hits, origin, dirs, spots[keep], cfg.camera_s.camera(),
                            cfg.diffuser.z_mm, SPACING_PX)


def test_the_true_surface_reproduces_its_spots(paper_cfg):
    truth = _swell(paper_cfg)
    check = _check(paper_cfg, truth, truth)
    assert check.n_predicted > 400
    assert check.median_px < 1e-3 and check.p95_px < 1e-2
    assert check.consistent
    assert check.threshold_px == pytest.approx(INCONSISTENT_FRACTION * SPACING_PX)


@pytest.mark.parametrize("wrong", ["level", "shape"])
def test_a_wrong_surface_is_inconsistent(paper_cfg, wrong):
    truth = _swell(paper_cfg)
    # 1 mm too high everywhere, or the right level with a 30 % weaker swell.
    surface = _swell(paper_cfg, offset_mm=1.0) if wrong == "level" else _swell(paper_cfg, 1.4)
    check = _check(paper_cfg, truth, surface)
    assert not check.consistent
    assert check.median_px > 3 * check.threshold_px


def test_the_confidence_map_follows_the_residuals(paper_cfg):
    truth = _swell(paper_cfg)
    good, bad = _check(paper_cfg, truth, truth), _check(paper_cfg, truth, _swell(paper_cfg, 1.4))
    known = np.isfinite(good.confidence)
    assert known.any() and np.nanmin(good.confidence) > 0.99
    assert np.nanmedian(bad.confidence) < 0.5
