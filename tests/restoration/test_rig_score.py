"""The calibrated rig's corner score on a board drawn through flat water by Snell's law."""

import cv2
import numpy as np
import pytest

from restoration import rig_grid_score
from restoration.metrics import object_plane_center
from restoration.video import grid_score
from wai_core.optics import trace_to_object


@pytest.fixture(scope="module")
def flat_view(paper_cfg):
    """The paper's board as camera v sees it through still water (4 x 4 samples a pixel)."""
    cfg = paper_cfg
    cam = cfg.rig.camera_v
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    rows, cols = np.mgrid[0:cam.height_px, 0:cam.width_px].astype(float)
    img = np.zeros(rows.shape)
    c = object_plane_center(cfg)
    (sx, sy), (nx, ny) = cfg.object.size_mm, cfg.object.squares
    for dr in sub:
        for dc in sub:
            tr = trace_to_object(cam, None, cfg.water.h0_mm, cfg.water.n_water,
                                 cfg.object_z_mm, cols + dc, rows + dr)
            p = np.nan_to_num(tr.object_mm)
            i = np.floor((p[..., 0] - c[0] + sx / 2) / (sx / nx))
            j = np.floor((p[..., 1] - c[1] + sy / 2) / (sy / ny))
            on = tr.ok & (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
            img += np.where(on, 0.1 + 0.8 * ((i + j) % 2), 0.0)
    return cfg, (img / sub.size**2).astype(np.float32)


def _warp(img, matrix):
    h, w = img.shape
    return cv2.warpAffine(img, matrix, (w, h), flags=cv2.INTER_LINEAR)


def test_a_flat_water_view_lies_on_the_rig_corners(flat_view):
    cfg, img = flat_view
    s = rig_grid_score(img, cfg)
    assert s.fraction > 0.9 and s.n_found >= 40
    assert s.std_px < 0.1
    assert np.hypot(*s.shift_px) < 0.1


def test_a_common_shift_is_reported_not_scored(flat_view):
    cfg, img = flat_view
    s = rig_grid_score(_warp(img, np.float32([[1, 0, 2.0], [0, 1, -1.0]])), cfg)
    assert s.std_px < 0.1
    assert s.shift_px == pytest.approx([2.0, -1.0], abs=0.1)


def test_a_smooth_warp_the_free_grid_absorbs_is_seen(flat_view):
    """A 0.6 % zoom about the image centre: still a regular grid seen through flat water
    (the free model fits it) but up to ~3 px off the rig's corners."""
    cfg, img = flat_view
    h, w = img.shape
    zoom = cv2.getRotationMatrix2D((w / 2, h / 2), 0.0, 1.006)
    warped = _warp(img, zoom)
    rig = rig_grid_score(warped, cfg)
    nx, ny = cfg.object.squares
    free = grid_score(warped, (nx - 1, ny - 1), n_water=cfg.water.n_water)
    assert free.rms_px < 0.3
    assert rig.std_px > 4 * free.rms_px and rig.std_px > 0.8


def test_a_view_of_the_wrong_size_is_refused(flat_view):
    cfg, img = flat_view
    with pytest.raises(Exception, match="camera v"):
        rig_grid_score(img[:-1], cfg)
