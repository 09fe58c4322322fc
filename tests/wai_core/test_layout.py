"""Consistency of the paper's geometry (Table 1, section 5.1), worked out independently."""

import numpy as np
import pytest

from wai_core import layout
from wai_core.geometry import intersect_plane_z, reflect


def test_device_centres_from_table1(paper_cfg):
    assert np.allclose(paper_cfg.rig.projector.pose.center_lab_mm, 0, atol=1e-9)
    assert np.allclose(paper_cfg.rig.camera_s.pose.center_lab_mm, [286.4, 0, -190], atol=0.01)
    assert np.allclose(paper_cfg.rig.camera_v.pose.center_lab_mm, [107.0, 0, 0], atol=0.05)


def test_projector_axis_reflects_onto_the_diffuser_above_camera_s(paper_cfg):
    proj = paper_cfg.rig.projector
    # 40 deg elevation: flat water at x = 150 / tan 40 = 178.8 mm, diffuser at 240 / tan 40.
    q, _ = intersect_plane_z(np.zeros(3), proj.pose.axis_lab, 150.0)
    assert q[0] == pytest.approx(150 / np.tan(np.radians(40)), abs=0.2)
    s, _ = intersect_plane_z(q, reflect(proj.pose.axis_lab, np.array([0, 0, 1.0])), 60.0)
    assert s[0] == pytest.approx(286.1, abs=0.3)
    cam_s = paper_cfg.rig.camera_s
    cols, rows, front = cam_s.project(s)
    assert front and abs(cols - 399.5) < 2 and abs(rows - 299.5) < 2


def test_both_systems_look_at_the_same_patch(paper_cfg):
    cam_v = paper_cfg.rig.camera_v
    q, _ = intersect_plane_z(cam_v.pose.center_lab_mm, cam_v.pose.axis_lab, 150.0)
    assert q[0] == pytest.approx(180.2, abs=0.3)
    q_proj, _ = intersect_plane_z(np.zeros(3), paper_cfg.rig.projector.pose.axis_lab, 150.0)
    assert abs(q[0] - q_proj[0]) < 2.0


def test_diffuser_is_camera_s_view_of_its_plane(paper_cfg):
    rect = layout.diffuser_rect(paper_cfg)
    # Camera s looks straight up from 250 mm below: half-widths 250 * 2.5 / 2 and 250 * 1.875 / 2.
    assert rect[0] == pytest.approx([286.4 - 312.5, 286.4 + 312.5], abs=0.5)
    assert rect[1] == pytest.approx([-234.4, 234.4], abs=0.5)


def test_observed_patch_inside_the_modelled_surface(paper_cfg):
    patch, ext = layout.observed_patch(paper_cfg), layout.surface_extent(paper_cfg)
    assert (ext[:, 0] <= patch[:, 0]).all() and (ext[:, 1] >= patch[:, 1]).all()
    _, _, seen = layout.flat_pattern_hits(paper_cfg)
    assert seen.sum() > 300


def test_a_panel_wider_than_tall_lights_the_dots_camera_s_sees(paper_cfg):
    # The dot grid of a 1600 x 1200 panel has rows longer than its columns (once reshaped as
    # if it were square: a ValueError before any render).
    cfg = paper_cfg.replace("projector", width_px=1600, height_px=1200)
    _, _, seen = layout.flat_pattern_hits(cfg)
    lit = layout.lit_dots(cfg)
    assert seen.any() and lit[seen].all() and not lit.all()
