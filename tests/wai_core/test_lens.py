"""wai_core.lens: the real device model against OpenCV, Snell's law and the plate-shift formula."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from wai_core import load_system
from wai_core.geometry import pinhole_of
from wai_core.lens import DeviceOptics

N_WATER = 1.34
K = (-0.12, 0.03, 0.0012, -0.0008, -0.004)


def _device(name: str = "camera_v", **keys: object) -> object:
    return dataclasses.replace(getattr(load_system("paper"), name), **keys)


@pytest.mark.parametrize("name", ["camera_s", "camera_v", "projector"])
def test_defaults_are_the_pinhole_bit_for_bit(name: str) -> None:
    dev = _device(name)
    cam, optics = pinhole_of(dev), DeviceOptics.from_config(dev)
    assert optics.ideal
    cols, rows = cam.pixel_grid(9.7)
    o, d = optics.pixel_rays(cols, rows, N_WATER)
    o_ref, d_ref = cam.pixel_rays(cols, rows)
    assert np.array_equal(d, d_ref)
    assert np.array_equal(o, np.broadcast_to(o_ref, o.shape))
    points = o_ref + d_ref * np.linspace(10, 900, d_ref[..., 0].size).reshape(cols.shape)[..., None]
    for ours, ref in zip(optics.project(points, N_WATER), cam.project(points), strict=True):
        assert np.array_equal(ours, ref)


def test_projection_matches_opencv() -> None:
    dev = _device("camera_s", distortion=K, principal_offset_px=(6.5, -4.25))
    optics = DeviceOptics.from_config(dev)
    cam = pinhole_of(dev)
    rng = np.random.default_rng(3)
    # Points in front of the camera within its field (normalised |x|, |y| < 1.1).
    p_cam = np.column_stack([rng.uniform(-1.1, 1.1, 500), rng.uniform(-0.9, 0.9, 500),
                             np.ones(500)])
    p_cam *= rng.uniform(20, 800, 500)[:, None]
    p_lab = (p_cam - cam.pose.t_mm) @ cam.pose.R  # u_lab = R^T (u_cam - t)
    cols, rows, valid = optics.project(p_lab, N_WATER)
    f = cam.focal_px
    cx = (cam.width_px - 1) / 2 + 6.5
    cy = (cam.height_px - 1) / 2 - 4.25
    matrix = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    ref, _ = cv2.projectPoints(p_cam, np.zeros(3), np.zeros(3), matrix, np.array(K))
    assert valid.all()
    assert np.abs(cols - ref[:, 0, 0]).max() < 1e-6
    assert np.abs(rows - ref[:, 0, 1]).max() < 1e-6


@pytest.mark.parametrize("port_mm", [0.0, 6.0])
def test_pixel_rays_and_project_round_trip(port_mm: float) -> None:
    dev = _device("camera_v", distortion=K, principal_offset_px=(-3.0, 2.0),
                  port_thickness_mm=port_mm, port_gap_mm=4.0, port_n=1.52)
    optics = DeviceOptics.from_config(dev)
    cols, rows = pinhole_of(dev).pixel_grid(17.0)
    o, d = optics.pixel_rays(cols, rows, N_WATER)
    assert np.isfinite(d).all()
    points = o + d * np.random.default_rng(1).uniform(30, 700, cols.shape)[..., None]
    c2, r2, valid = optics.project(points, N_WATER)
    assert valid.all()
    assert np.abs(c2 - cols).max() < 1e-8 and np.abs(r2 - rows).max() < 1e-8


def test_port_obeys_snell_at_each_face_and_shifts_as_a_plate() -> None:
    t, gap, n_port = 7.0, 3.0, 1.52
    dev = _device("camera_s", port_thickness_mm=t, port_gap_mm=gap, port_n=n_port)
    optics = DeviceOptics.from_config(dev)
    cam = pinhole_of(dev)
    cols = np.linspace(0, cam.width_px - 1, 9)
    rows = np.full(9, 123.0)
    exit_cam, water_cam, air_cam = optics.rays_cam(cols, rows, N_WATER)
    # Camera s has R = I: cam axes are lab's; the port's faces are planes z_cam = const.
    sin_air = np.hypot(air_cam[:, 0], air_cam[:, 1])
    sin_water = np.hypot(water_cam[:, 0], water_cam[:, 1])
    # Snell: 1 * sin(theta_air) = n_water * sin(theta_water), in the plane of incidence.
    assert np.allclose(sin_air, N_WATER * sin_water, atol=1e-12)
    assert np.allclose(np.cross(air_cam, water_cam)[:, 2], 0.0, atol=1e-12)
    # The air ray meets the inner face at gap * tan(theta_air); inside the plate the ray runs
    # to the exit point. Its angle there obeys n_port sin(theta_port) = sin(theta_air).
    inner = air_cam * (gap / air_cam[:, 2:3])
    seg = exit_cam - inner
    sin_port = np.hypot(seg[:, 0], seg[:, 1]) / np.linalg.norm(seg, axis=1)
    assert np.allclose(n_port * sin_port, sin_air, atol=1e-12)
    assert np.allclose(exit_cam[:, 2], gap + t)
    # Lateral shift of the glass segment against the unrefracted air ray, measured
    # perpendicular to it: t sin(theta) (1 - cos(theta) / sqrt(n^2 - sin^2(theta))).
    straight = inner + air_cam * (t / air_cam[:, 2:3])
    shift = np.linalg.norm(np.cross(exit_cam - straight, air_cam), axis=1)
    theta = np.arcsin(sin_air)
    textbook = t * np.sin(theta) * (1 - np.cos(theta) / np.sqrt(n_port**2 - np.sin(theta) ** 2))
    assert np.allclose(shift, textbook, rtol=1e-9, atol=1e-12)
    assert textbook.max() > 1.0  # the shift is large enough to matter


def test_distortion_beyond_its_fold_is_invalid() -> None:
    # k1 = -0.3: r_d = r (1 - 0.3 r^2) folds at r^2 = 1 / 0.9; points beyond are not imaged.
    dev = _device("camera_s", distortion=(-0.3, 0.0, 0.0, 0.0, 0.0))
    optics = DeviceOptics.from_config(dev)
    cam = pinhole_of(dev)
    r = np.array([0.5, 1.2])
    p_cam = np.column_stack([r, np.zeros(2), np.ones(2)]) * 100.0
    _, _, valid = optics.project((p_cam - cam.pose.t_mm) @ cam.pose.R, N_WATER)
    assert valid.tolist() == [True, False]
