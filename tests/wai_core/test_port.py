"""A camera behind a flat port: its rays against Snell's law worked by hand, the axial-camera
property (every water ray meets the optical axis), the exact diffuser-plane map, and how wrong
the pinhole shortcut is (the figure wai_core.port's docstring states)."""

from __future__ import annotations

import numpy as np
import pytest

from wai_core.config import with_keys
from wai_core.light_paths import pack_camera, real_spot_px
from wai_core.port import PortCamera, pack_port, port_ray

N_WATER = 4.0 / 3.0


def _port_cfg(paper_cfg, device, thickness_mm, gap_mm, n_port=1.49):
    return with_keys(paper_cfg, {f"{device}.port_thickness_mm": thickness_mm,
                                 f"{device}.port_gap_mm": gap_mm, f"{device}.port_n": n_port})


def _by_hand(cam, col, row, gap, thick, n_port):
    """A pixel's water ray, worked in the camera frame with scalar Snell's law at each face:
    (exit point, unit direction), camera frame, mm."""
    f = cam.focal_px
    x, y = col - (cam.width_px - 1) / 2.0, row - (cam.height_px - 1) / 2.0
    r = np.hypot(x, y)
    theta_air = np.arctan2(r, f)
    theta_port = np.arcsin(np.sin(theta_air) / n_port)
    theta_water = np.arcsin(np.sin(theta_air) / N_WATER)
    rho = gap * np.tan(theta_air) + thick * np.tan(theta_port)
    u = np.array([x, y]) / r if r > 0 else np.zeros(2)
    exit_point = np.array([*(rho * u), gap + thick])
    direction = np.array([*(np.sin(theta_water) * u), np.cos(theta_water)])
    return exit_point, direction


@pytest.mark.parametrize("thick, gap, n_port", [(2.0, 0.5, 1.49), (10.0, 10.0, 1.52)])
def test_rays_obey_snell_at_both_faces_and_meet_the_axis(paper_cfg, thick, gap, n_port):
    cfg = _port_cfg(paper_cfg, "camera_v", thick, gap, n_port)
    cam = PortCamera(cfg.rig.optics("camera_v"), N_WATER)
    pose = cam.pose
    packed, port = pack_camera(cam.camera), pack_port(cam)
    rng = np.random.default_rng(3)
    for col, row in rng.uniform([0, 0], [799, 599], (20, 2)):
        o, d = cam.pixel_rays(np.array([col]), np.array([row]))
        o_cam = pose.points_to_cam(o)[0]
        d_cam = pose.R @ d[0]
        exit_point, direction = _by_hand(cam, col, row, gap, thick, n_port)
        np.testing.assert_allclose(o_cam, exit_point, atol=1e-9)
        np.testing.assert_allclose(d_cam, direction, atol=1e-12)
        # Axial: the water ray, followed back, crosses the optical axis; port_ray finds where,
        # and the pixel, from a point 300 mm along it.
        p = o[0] + 300.0 * d[0]
        ax, ay, az, c, r = port_ray(port, packed, *p)
        a_cam = pose.points_to_cam(np.array([ax, ay, az]))
        assert np.hypot(a_cam[0], a_cam[1]) < 1e-9
        w = p - np.array([ax, ay, az])
        np.testing.assert_allclose(w / np.linalg.norm(w), d[0], atol=1e-12)
        np.testing.assert_allclose([c, r], [col, row], atol=1e-7)


def test_the_pinhole_shortcut_errs_as_documented(paper_cfg):
    """A pinhole at camera v's centre fitted to the port's rays at the mean water level: how far
    it misplaces points 10 mm above or below that level (wai_core.port's docstring)."""

    def worst_px(thick, gap):
        cam = PortCamera(_port_cfg(paper_cfg, "camera_v", thick, gap).rig.optics("camera_v"),
                         N_WATER)
        rows, cols = np.mgrid[0:600:20, 0:800:20].astype(float)
        o, d = cam.pixel_rays(cols, rows)
        at = {}
        for dz in (-10.0, 0.0, 10.0):
            t = (paper_cfg.water.h0_mm + dz - o[..., 2]) / d[..., 2]
            c, r, _ = cam.camera.project((o + t[..., None] * d).reshape(-1, 3))
            at[dz] = np.stack([c, r], axis=-1)
        return max(np.abs(at[10.0] - at[0.0]).max(), np.abs(at[-10.0] - at[0.0]).max())

    assert 0.5 < worst_px(10.0, 10.0) < 0.8
    assert worst_px(2.0, 0.5) < 0.01


def test_spot_centres_map_to_the_diffuser_exactly(paper_cfg):
    """A diffuser point's real pixel (through the port) maps back to the ideal pinhole's pixel
    of that very point: the map is exact on the plane whatever the port."""
    cfg = _port_cfg(paper_cfg, "camera_s", 6.0, 8.0)
    optics, cam = cfg.rig.optics("camera_s"), cfg.rig.camera_s
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(150, 420, 50), rng.uniform(-120, 120, 50),
                           np.full(50, cfg.diffuser.z_mm)])
    cols, rows, valid = optics.project(pts, cfg.water.n_water)
    assert valid.all()
    ideal = np.column_stack(cam.project(pts)[:2])
    back = optics.plane_pinhole_px(np.column_stack([cols, rows]), cfg.diffuser.z_mm,
                                   cfg.water.n_water)
    np.testing.assert_allclose(back, ideal, atol=1e-7)
    np.testing.assert_allclose(real_spot_px(cfg.rig, ideal), np.column_stack([cols, rows]),
                               atol=1e-7)


def test_a_rig_without_ports_keeps_its_pinholes(paper_cfg):
    rig = paper_cfg.rig
    assert rig.camera_model("camera_v") is rig.camera_v
    o, _ = rig.dot_rays
    assert o.shape == (3,)
    assert pack_port(rig.camera_v)[1] == 0.0


def _vector_snell(d, normal, n1, n2):
    """Refract unit rays ``d`` (K, 3) at a plane of unit ``normal`` (facing along them) from
    index ``n1`` into ``n2``: the vector form of Snell's law (tangential part scaled by
    n1 / n2, the normal part what keeps the ray unit)."""
    cos_i = d @ normal
    tangential = d - cos_i[:, None] * normal
    t = tangential * (n1 / n2)
    cos_t = np.sqrt(1.0 - np.sum(t * t, axis=1))
    return t + cos_t[:, None] * normal


@pytest.mark.parametrize("tilt", [(6.0, 0.0), (-4.0, 9.0)])
def test_a_tilted_port_refracts_at_its_own_faces(paper_cfg, tilt):
    # The port's faces are the planes n . x = gap and gap + t, n = (tan a_x, tan a_y, 1)
    # normalised (the docs' definition), refracting by Snell's law in vector form: written
    # here from the pixel's air ray, not from the port's frame the code works in.
    thick, gap, n_port = 6.0, 3.0, 1.52
    cfg = with_keys(_port_cfg(paper_cfg, "camera_v", thick, gap, n_port),
                    {"camera_v.port_tilt_deg": list(tilt)})
    cam = PortCamera(cfg.rig.optics("camera_v"), N_WATER)
    pose, f = cam.pose, cam.focal_px
    n = np.array([np.tan(np.radians(tilt[0])), np.tan(np.radians(tilt[1])), 1.0])
    n /= np.linalg.norm(n)
    rng = np.random.default_rng(5)
    pix = rng.uniform([0, 0], [799, 599], (30, 2))
    air = np.column_stack([pix[:, 0] - 399.5, pix[:, 1] - 299.5, np.full(30, f)])
    air /= np.linalg.norm(air, axis=1, keepdims=True)
    inner = air * (gap / (air @ n))[:, None]
    glass = _vector_snell(air, n, 1.0, n_port)
    outer = inner + glass * (thick / (glass @ n))[:, None]
    water = _vector_snell(glass, n, n_port, N_WATER)
    o, d = cam.pixel_rays(pix[:, 0], pix[:, 1])
    np.testing.assert_allclose(pose.points_to_cam(o), outer, atol=1e-9)
    np.testing.assert_allclose(d @ pose.R.T, water, atol=1e-12)
    # The tilt matters: the untilted port's rays leave several pixels' worth elsewhere.
    square = PortCamera(_port_cfg(paper_cfg, "camera_v", thick, gap, n_port)
                        .rig.optics("camera_v"), N_WATER)
    assert np.degrees(np.arccos(np.clip(np.sum(square.pixel_rays(*pix.T)[1] * d, axis=1),
                                        -1, 1))).max() > 1.0
    # Projection inverts it, and port_ray's axis point lies on each water ray (the port's
    # normal through the pinhole: the camera stays axial about it).
    p = o + 250.0 * d
    cols, rows, ok = cam.project(p)
    assert ok.all()
    np.testing.assert_allclose(np.column_stack([cols, rows]), pix, atol=1e-7)
    packed, port = pack_camera(cam.camera), pack_port(cam)
    axis_lab = pose.R.T @ n
    for k in range(len(p)):
        ax, ay, az, c, r = port_ray(port, packed, *p[k])
        a = np.array([ax, ay, az]) - pose.center_lab_mm
        assert np.linalg.norm(np.cross(a, axis_lab)) < 1e-9  # on the port's axis
        w = p[k] - np.array([ax, ay, az])
        np.testing.assert_allclose(w / np.linalg.norm(w), d[k], atol=1e-10)
        np.testing.assert_allclose([c, r], pix[k], atol=1e-7)


def test_a_tilt_needs_a_port_and_a_plausible_angle(paper_cfg):
    from wai_core.errors import WaiInputError

    with pytest.raises(WaiInputError, match=r"\[camera_s\].port_tilt_deg tilts a port"):
        with_keys(paper_cfg, {"camera_s.port_tilt_deg": [2.0, 0.0]})
    with pytest.raises(WaiInputError, match=r"\[projector\].port_tilt_deg must be two angles"):
        with_keys(_port_cfg(paper_cfg, "projector", 5.0, 5.0),
                  {"projector.port_tilt_deg": [45.0, 0.0]})
