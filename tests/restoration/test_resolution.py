"""A finer camera must not make the restoration worse: the pixel-scale constants of detection,
matching and corner scoring follow from the calibration, not from one resolution.

The paper's rig is rendered with both cameras at 800 x 600 and at 1600 x 1200 (same sensors,
so the same fields of view) under the same light: samples per pixel are per pixel, so the finer
render gets a quarter of them (2 against 8) and both carry the same number of light paths. At
equal spp the finer image would hold four times the light, and its result would differ through
the noise rather than the pixels. Corner offsets are compared in pixels of the 800 x 600
camera v (the same angle).

Tolerances: surface RMSE within 25 % + 0.01 mm of the coarse camera's, because the least-squares
surface turns centroid noise of a few hundredths of a pixel into RMSE changes of a few hundredths
of a millimetre (its level and tilt are weakly constrained); corner STD within 10 %; matched and
order-rejected dots within 2 % of the reference dots; centroid error (against the exact spot of
each dot's central ray through the true surface) within 10 %.
"""

import numpy as np
import pytest

import mitsuba_wai as mw
from restoration import Calibration, StructuredLight, Truth, score
from restoration.consistency import predict_spots_px
from restoration.features import spot_sigma_px
from restoration.normals import projector_rays

COARSE, FINE = (800, 600, 8), (1600, 1200, 2)  # width, height, spp: equal light paths


def _sized(cfg, width, height):
    cfg = cfg.replace("camera_s", width_px=width, height_px=height)
    return cfg.replace("camera_v", width_px=width, height_px=height)


def _centroid_error_px800(cfg, frame, features):
    """Median distance of the matched spots from the exact spots of their dots' central rays
    through the true surface, in pixels of the 800-px-wide camera s."""
    origin, dirs = projector_rays(Calibration(cfg).panel_px(features.ij), cfg.rig.projector)
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    start = origin + ((cfg.water.h0_mm - origin[2]) / d[:, 2])[:, None] * d
    exact = predict_spots_px(
        frame.surface, origin, dirs, start, cfg.rig.camera_s, cfg.diffuser.z_mm
    )
    err = np.linalg.norm(features.spot_px - exact, axis=1)
    return float(np.nanmedian(err)) * 800.0 / cfg.camera_s.width_px


@pytest.fixture(scope="module")
def runs(paper_cfg):
    out = {}
    for width, height, spp in (COARSE, FINE):
        cfg = _sized(paper_cfg.replace("waves", seed=0), width, height)
        cfg = cfg.replace("render", spp_pattern=spp, spp_view=spp)
        frame = mw.render_frame(cfg, spp=spp)
        cal = Calibration(cfg, frame.view_gain)
        result = StructuredLight()(frame.images, cal)
        assert result.restored, result.message
        truth = Truth(frame.surface, cal.radiance(frame.images["view_truth"]))
        scores = score(result, cal.radiance(frame.images["view"]), cal, truth)
        out[width] = (cfg, frame, cal, result, scores)
    return out


def test_spot_scale_follows_the_camera(paper_cfg):
    """The calibrated spot size doubles with the pixel count per axis (same sensor)."""
    coarse = spot_sigma_px(_sized(paper_cfg, 800, 600))
    fine = spot_sigma_px(_sized(paper_cfg, 1600, 1200))
    assert coarse == pytest.approx(1.518, abs=0.01)  # the tuned spot size
    assert fine / coarse == pytest.approx(2.0, rel=1e-6)


def test_finer_camera_matches_as_many_dots(runs):
    # Order rejections of one frame scatter with the render's noise (25-68 at either
    # resolution over four sampler seeds), so they are summed over two renders of each camera.
    counts = {}
    for width, (cfg, frame, cal, result, _) in runs.items():
        again = mw.render_frame(cfg, frame.surface, spp=cfg.render.spp_pattern, seed=99)
        second = StructuredLight()(again.images, cal)
        counts[width] = {k: result.counts[k] + second.counts[k]
                         for k in ("matched", "rejected_order")}
    coarse, fine = counts[COARSE[0]], counts[FINE[0]]
    n_ref = 2 * runs[COARSE[0]][2].reference.counts["observed"]
    assert fine["matched"] >= coarse["matched"] - 0.02 * n_ref
    assert fine["rejected_order"] <= coarse["rejected_order"] + 0.02 * n_ref


def test_finer_camera_centroids_no_worse(runs):
    errs = [_centroid_error_px800(cfg, frame, res.features) for cfg, frame, _, res, _ in
            (runs[COARSE[0]], runs[FINE[0]])]
    assert errs[1] <= 1.1 * errs[0], errs


def test_finer_camera_surface_and_corners_no_worse(runs):
    coarse, fine = runs[COARSE[0]][4], runs[FINE[0]][4]
    assert fine.rmse_mm <= 1.25 * coarse.rmse_mm + 0.01, (fine.rmse_mm, coarse.rmse_mm)
    # Same angle: the fine camera's native pixels are half the coarse camera's.
    assert coarse.corner_std_restored_px800 == pytest.approx(coarse.corner_std_restored_px)
    assert fine.corner_std_restored_px800 == pytest.approx(0.5 * fine.corner_std_restored_px)
    assert fine.corner_std_restored_px800 <= 1.1 * coarse.corner_std_restored_px800
