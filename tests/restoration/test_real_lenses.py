"""Real lenses (distortion, a principal point off the centre) seen as their ideal pinholes.

Facts from outside the code: OpenCV's projection (cv2.projectPoints) of a lens's rays; a rig
restored with its lenses left out is wrong, and its flat-water reference says so; restored with
the lenses it was rendered with, the frame is as good as the ideal rig's.
"""

import cv2
import numpy as np
import pytest

from mitsuba_wai.render import render_folder
from restoration import Calibration, restore_folder
from restoration.undistort import PinholeRemap, diffuser_pinhole_px
from wai_core.config import with_keys

LENS = {"distortion": [-0.2, 0.05, 0.001, -0.0005, 0.0], "principal_offset_px": [15.0, -10.0]}


def _real(cfg, *devices):
    return with_keys(cfg, {f"{d}.{k}": v for d in devices for k, v in LENS.items()})


def _cv2_pixels(dev, rays_cam):
    """OpenCV's pixels of camera-frame rays through a lens with ``LENS``."""
    f = dev.focal_mm * dev.width_px / dev.sensor_width_mm
    c = np.array([(dev.width_px - 1) / 2, (dev.height_px - 1) / 2]) + LENS["principal_offset_px"]
    k = np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1]])
    px, _ = cv2.projectPoints(rays_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k,
                              np.array(LENS["distortion"]))
    return px[:, 0]


def test_spots_and_images_map_to_the_pinhole_opencv_projects_them_from(paper_cfg):
    real_cfg = _real(paper_cfg, "camera_s", "camera_v")
    dev, optics = real_cfg.camera_s, real_cfg.rig.optics("camera_s")
    rng = np.random.default_rng(1)
    ideal = rng.uniform([40, 40], [760, 560], (200, 2))  # ideal pinhole pixels
    f = dev.focal_mm * dev.width_px / dev.sensor_width_mm
    rays = np.column_stack([(ideal - [399.5, 299.5]) / f, np.ones(200)])
    real = _cv2_pixels(dev, rays)
    np.testing.assert_allclose(diffuser_pinhole_px(real_cfg, real), ideal, atol=1e-6)
    remap = PinholeRemap.of(optics, "camera_s")
    rows, cols = np.round(ideal[:, 1]).astype(int), np.round(ideal[:, 0]).astype(int)
    at = _cv2_pixels(dev, np.column_stack([(cols - 399.5) / f, (rows - 299.5) / f,
                                           np.ones(200)]))
    np.testing.assert_allclose(remap.map_cols[rows, cols], at[:, 0], atol=1e-3)
    np.testing.assert_allclose(remap.map_rows[rows, cols], at[:, 1], atol=1e-3)


def test_an_ideal_rig_costs_nothing(paper_cfg):
    cal = Calibration(paper_cfg)
    view = np.zeros((600, 800, 3), np.float32)
    assert cal.to_pinhole("view", view) is view and not cal.resamples("view")
    px = np.array([[1.5, 2.5]])
    assert diffuser_pinhole_px(paper_cfg, px) is px


@pytest.fixture(scope="module")
def lens_frame(paper_cfg, tmp_path_factory):
    out = tmp_path_factory.mktemp("lens") / "frame"
    cfg = paper_cfg.replace("render", spp_pattern=4, spp_view=4)
    render_folder(_real(cfg, "camera_s", "camera_v"), out, progress=False)
    return out


def test_restored_with_its_lenses_the_frame_is_ok_and_without_them_flagged(lens_frame):
    true_rig = restore_folder(lens_frame, write=False).metrics
    assert true_rig["status"] == "ok", true_rig["message"]
    assert true_rig["wai_rmse_mm"] < 0.15  # the ideal rig's frames: 0.02 mm on the mean
    assert true_rig["flat_reference"]["rms_of_spacing"] < 0.02
    ideal = {f"{d}.{k}": [0.0] * len(v) for d in ("camera_s", "camera_v")
             for k, v in LENS.items()}
    pinholes = restore_folder(lens_frame, write=False, rig=ideal).metrics
    assert pinholes["status"] == "bad_reference"


def test_the_flat_water_pattern_pins_camera_s_where_a_checkerboard_leaves_it(lens_frame):
    # Camera s 0.2 % off in focal length and 1 px off in principal point, as a checkerboard
    # calibration might leave it: the flat reference's spots bring it back.
    from restoration.rig_calibration import refine_on_flat_water
    from wai_core.images import find_image, read_image

    true = Calibration.from_folder(lens_frame).cfg
    off = with_keys(true, {"camera_s.focal_mm": true.camera_s.focal_mm * 1.002,
                           "camera_s.principal_offset_px": [16.0, -9.0]})
    fit = refine_on_flat_water(off, read_image(find_image(lens_frame, "pattern_flat")))
    keys = fit.config_keys
    assert keys["camera_s.focal_mm"] == pytest.approx(true.camera_s.focal_mm, rel=3e-4)
    np.testing.assert_allclose(keys["camera_s.principal_offset_px"], [15.0, -10.0], atol=0.2)
    assert fit.rms_after_px < 0.5 * fit.rms_before_px and fit.n_spots > 500


PINCUSHION = {"camera_v.distortion": [0.12, 0.0, 0.0, 0.0, 0.0],
              "camera_v.principal_offset_px": [-9.0, 0.0]}


@pytest.fixture(scope="module")
def view_lenses(paper_cfg, tmp_path_factory):
    """One sea through camera v's ideal lens and through a pincushion lens off centre, whose
    ideal pinhole sees past the real sensor's edge."""
    cfg = paper_cfg.replace("render", spp_pattern=4, spp_view=4)
    out = {}
    for name, lens in (("ideal", {}), ("pincushion", PINCUSHION)):
        out[name] = tmp_path_factory.mktemp(name) / "frame"
        render_folder(with_keys(cfg, lens), out[name], progress=False)
    return out


def test_a_real_lens_restores_no_pixel_its_sensor_did_not_record(view_lenses):
    """Every restored pixel's sample lies on the real sensor (OpenCV's projection of its ray
    through the lens), and the restored view scores as well as the ideal lens's."""
    ideal = restore_folder(view_lenses["ideal"], write=False)
    real = restore_folder(view_lenses["pincushion"], write=False)
    assert real.result.status == "ok", real.result.message
    view = real.result.view
    dev = real.cal.cfg.camera_v
    f = dev.focal_mm * dev.width_px / dev.sensor_width_mm
    centre = np.array([(dev.width_px - 1) / 2, (dev.height_px - 1) / 2])
    u = view.map_px[view.valid].astype(float)  # the pinhole pixels sampled
    rays = np.column_stack([(u - centre) / f, np.ones(len(u))])
    k = np.array([[f, 0, centre[0] + PINCUSHION["camera_v.principal_offset_px"][0]],
                  [0, f, centre[1] + PINCUSHION["camera_v.principal_offset_px"][1]], [0, 0, 1]])
    px, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k,
                              np.array(PINCUSHION["camera_v.distortion"]))
    px = px[:, 0]
    assert np.all((px >= -1e-3).all(axis=1) & (px[:, 0] <= dev.width_px - 1 + 1e-3)
                  & (px[:, 1] <= dev.height_px - 1 + 1e-3))
    assert (~view.valid).sum() > (~ideal.result.view.valid).sum()  # the band is left out
    psnr = {n: d.metrics["restored"]["psnr_db"] for n, d in (("ideal", ideal), ("real", real))}
    assert psnr["real"] > psnr["ideal"] - 1.0, psnr
