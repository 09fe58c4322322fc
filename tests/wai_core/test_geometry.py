"""Ray geometry against textbook optics and the paper's Table 1."""

import numpy as np
import pytest

from wai_core.geometry import (
    PinholeCamera,
    Pose,
    critical_angle_rad,
    fresnel_reflectance,
    intersect_plane_z,
    reflect,
    refract,
    rotation_y,
)

UP = np.array([0.0, 0.0, 1.0])


def test_snells_window_is_97_2_degrees():
    # Half-angle of the cone of rays that leave the water: arcsin(1/n) with n = 4/3.
    assert np.degrees(2 * critical_angle_rad(4 / 3)) == pytest.approx(97.2, abs=0.05)
    angles = np.radians(np.linspace(0, 89, 891))
    d = np.stack([np.sin(angles), 0 * angles, np.cos(angles)], 1)
    _, tir = refract(d, np.broadcast_to(UP, d.shape), 4 / 3)
    edge = np.degrees(angles[np.argmax(tir)])
    assert edge == pytest.approx(48.6, abs=0.15)


def test_refraction_obeys_snell_law():
    theta_w = np.radians(30.0)
    d = np.array([[np.sin(theta_w), 0.0, np.cos(theta_w)]])
    t, tir = refract(d, UP[None], 4 / 3)
    assert not tir[0]
    assert np.sin(np.arccos(t[0, 2])) == pytest.approx(4 / 3 * np.sin(theta_w), rel=1e-12)


def test_reflection_doubles_the_normal_tilt():
    # dpsi/dtheta = 2: tilting the mirror by theta turns the reflected ray by 2 theta.
    d = np.array([np.cos(np.radians(40)), 0, np.sin(np.radians(40))])
    flat = reflect(d, UP)
    for theta in np.radians([0.5, 2.0, 5.0]):
        n = np.array([np.sin(theta), 0, np.cos(theta)])
        psi = np.arccos(np.clip(reflect(d, n) @ flat, -1, 1))
        assert psi == pytest.approx(2 * theta, rel=1e-9)


def test_table1_rotation_matches_elevation_angles():
    table_projector = np.array([[0.6428, 0, -0.7660], [0, 1, 0], [0.7660, 0, 0.6428]])
    table_camera_v = np.array([[0.8988, 0, -0.4384], [0, 1, 0], [0.4384, 0, 0.8988]])
    assert np.allclose(rotation_y(np.radians(50)), table_projector, atol=1e-4)
    assert np.allclose(rotation_y(np.radians(26)), table_camera_v, atol=1e-4)


def test_projection_inverts_pixel_rays():
    cam = PinholeCamera(80, 60, 3.0, 0.0625, Pose.from_center(rotation_y(0.3), [10, -5, 2]))
    cols, rows = np.meshgrid(np.linspace(-0.5, 79.5, 7), np.linspace(-0.5, 59.5, 5))
    o, d = cam.pixel_rays(cols, rows)
    p = o + 123.0 * d
    c2, r2, front = cam.project(p)
    assert front.all()
    assert np.allclose(c2, cols) and np.allclose(r2, rows)


def test_centre_pixel_looks_along_the_axis():
    cam = PinholeCamera(81, 61, 3.0, 0.01, Pose(rotation_y(np.radians(26)), np.zeros(3)))
    _, d = cam.pixel_rays(40.0, 30.0)
    assert np.allclose(d, cam.pose.axis_lab)


def test_plane_intersection_behind_origin_is_nan():
    p, t = intersect_plane_z(np.zeros(3), np.array([[0, 0, 1.0], [0, 0, -1.0]]), 5.0)
    assert np.allclose(p[0], [0, 0, 5]) and np.isnan(t[1])


def test_fresnel_reflectance_textbook_values():
    # Normal incidence: ((n1 - n2) / (n1 + n2))^2 = (1/7)^2 for water/air; 1 beyond 48.6 deg.
    assert fresnel_reflectance(1.0, 4 / 3) == pytest.approx((1 / 7) ** 2, rel=1e-9)
    assert fresnel_reflectance(np.cos(np.radians(50)), 4 / 3) == 1.0
    assert fresnel_reflectance(np.cos(np.radians(45)), 4 / 3) < 0.2
