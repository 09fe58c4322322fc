"""Normals from the law of reflection (section 3.2.1, eq. 3-7) and its sensitivity (section 4.1)."""

import numpy as np
import pytest

from restoration.normals import (
    normal_matrix,
    points_on_rays,
    projector_rays,
    reflected_dirs,
    reflection_normals,
    slopes_from_normals,
    spots_on_diffuser,
)
from wai_core.config import load_config
from wai_core.errors import RestorationFailed, WaiInputError
from wai_core.geometry import normalize, reflect


@pytest.fixture(scope="module")
def cfg():
    return load_config("scenes/paper.toml")


def random_case(n=200, seed=0):
    """Upward unit normals tilted up to ~25 deg and upward incident rays hitting at q."""
    rng = np.random.default_rng(seed)
    normals = normalize(np.column_stack([rng.normal(0, 0.2, (n, 2)), np.ones(n)]))
    v_p = normalize(np.column_stack([rng.normal(0.8, 0.4, n), rng.normal(0, 0.3, n), np.ones(n)]))
    q = np.column_stack([rng.uniform(50, 400, n), rng.uniform(-150, 150, n), np.full(n, 150.0)])
    # Keep the physical cases: the ray meets the underside and reflects down to the diffuser.
    ok = reflect(v_p, normals)[:, 2] < -0.05
    return normals[ok], v_p[ok], q[ok], rng


def test_reflection_normals_recover_the_normal():
    normals, v_p, q, rng = random_case()
    v = reflect(v_p, normals)
    s = q + rng.uniform(50, 300, (len(q), 1)) * v  # any point on the reflected ray
    assert len(q) > 150
    np.testing.assert_allclose(reflection_normals(v_p, q, s), normals, atol=1e-12)


def test_normal_matrix_null_space_is_the_normal():
    normals, v_p, q, _ = random_case(seed=1)
    v = reflect(v_p, normals)
    A = normal_matrix(v_p, v)
    assert A.shape == (len(q), 3, 3)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", A, normals), 0.0, atol=1e-12)
    np.testing.assert_allclose(A, -np.transpose(A, (0, 2, 1)))  # skew, as eq. 7 reads
    # Rank 2: the null space is one direction, so it fixes the normal up to sign.
    sv = np.linalg.svd(A, compute_uv=False)
    assert np.all(sv[:, 1] > 1e-3) and np.all(sv[:, 2] < 1e-12)
    # The closed form agrees with the SVD null vector of A (eq. 6).
    null = np.linalg.svd(A)[2][:, 2]
    null *= np.sign(null[:, 2:3])
    s = q + 100.0 * v
    np.testing.assert_allclose(reflection_normals(v_p, q, s), null, atol=1e-12)


@pytest.mark.parametrize("theta_pro_deg", [30.0, 45.0])
def test_sensitivity_meridional_is_two(theta_pro_deg):
    """Eq. 21-23: tilting N by theta in the plane of incidence turns the reflection by 2 theta."""
    a = np.radians(theta_pro_deg)
    v_p = np.array([np.cos(a), 0.0, np.sin(a)])
    v_flat = reflect(v_p, [0.0, 0.0, 1.0])
    theta = np.linspace(-0.3, 0.3, 61)
    tilted = np.column_stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)])
    v = reflect(np.broadcast_to(v_p, tilted.shape), tilted)
    psi = np.arccos(np.clip(v @ v_flat, -1.0, 1.0))
    np.testing.assert_allclose(psi, 2.0 * np.abs(theta), atol=1e-7)
    # And the inverse problem: the deflected ray gives back the tilted normal.
    q = np.zeros_like(tilted)
    np.testing.assert_allclose(
        reflection_normals(np.broadcast_to(v_p, tilted.shape), q, q + v), tilted, atol=1e-12
    )


@pytest.mark.parametrize("theta_pro_deg", [30.0, 45.0])
def test_sensitivity_sagittal_is_two_cos_incidence(theta_pro_deg):
    """Eq. 24: tilting N about an axis in the plane of incidence.

    The paper states d psi / d theta = 2 for both planes; that holds only in the meridional
    plane. For a sagittal tilt, psi = arccos(cos^2 a + sin^2 a cos 2 theta) (a = theta_pro),
    so d psi / d theta = 2 sin a = 2 cos(incidence) at theta -> 0 (1 at 30 deg, sqrt 2 at 45).
    """
    a = np.radians(theta_pro_deg)
    v_p = np.array([np.cos(a), 0.0, np.sin(a)])
    v_flat = reflect(v_p, [0.0, 0.0, 1.0])
    theta = np.linspace(1e-3, 0.3, 30)
    tilted = np.column_stack([np.zeros_like(theta), np.sin(theta), np.cos(theta)])
    psi = np.arccos(np.clip(reflect(np.broadcast_to(v_p, tilted.shape), tilted) @ v_flat, -1, 1))
    expected = np.arccos(np.cos(a) ** 2 + np.sin(a) ** 2 * np.cos(2 * theta))
    np.testing.assert_allclose(psi, expected, atol=1e-7)
    np.testing.assert_allclose(psi[0] / theta[0], 2.0 * np.sin(a), rtol=1e-5)


def test_slopes_from_normals():
    gx, gy = np.array([0.1, -0.3, 0.0]), np.array([0.05, 0.2, 0.0])
    n = normalize(np.column_stack([-gx, -gy, np.ones(3)]))
    np.testing.assert_allclose(slopes_from_normals(n), np.column_stack([gx, gy]), atol=1e-15)
    with pytest.raises(RestorationFailed, match="horizontal"):
        slopes_from_normals([[1.0, 0.0, 0.0]])


def test_points_on_rays_is_eq3():
    o = np.array([1.0, 2.0, -5.0])
    d = normalize([[0.5, 0.1, 1.0], [-0.2, 0.3, 0.8]])
    q = points_on_rays(o, d, [150.0, 140.0])
    np.testing.assert_allclose(q[:, 2], [150.0, 140.0])
    np.testing.assert_allclose(np.cross(q - o, d), 0.0, atol=1e-12)  # still on the rays
    with pytest.raises(WaiInputError, match="upwards"):
        points_on_rays(o, [[0.0, 0.0, -1.0]], 150.0)


def test_spots_and_projector_rays_on_the_paper_rig(cfg):
    cam = cfg.rig.camera_s
    proj = cfg.rig.projector
    # Diffuser points project to pixels, which back-project to the same diffuser points.
    pts = np.column_stack([np.linspace(100, 450, 5), np.linspace(-150, 150, 5), np.full(5, 60.0)])
    cols, rows, _ = cam.project(pts)
    np.testing.assert_allclose(
        spots_on_diffuser(np.column_stack([cols, rows]), cam, 60.0), pts, atol=1e-9
    )
    origin, dirs = projector_rays([[499.5, 499.5], [0.0, 0.0]], proj)
    np.testing.assert_allclose(origin, 0.0, atol=1e-12)  # projector at the lab origin
    np.testing.assert_allclose(dirs[0], proj.pose.axis_lab, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)


def test_bad_input_raises():
    with pytest.raises(WaiInputError, match="spot_px"):
        spots_on_diffuser(np.zeros((3, 3)), None, 60.0)
    with pytest.raises(WaiInputError, match="NaN"):
        reflection_normals([[0, 0, 1.0]], [[0, 0, 150.0]], [[np.nan, 0, 60.0]])
    with pytest.raises(RestorationFailed, match="coincides"):
        reflected_dirs([[0, 0, 1.0]], [[0, 0, 1.0]])
    with pytest.raises(RestorationFailed, match="parallel"):
        # A reflected "ray" along the incident one: no normal reflects it.
        reflection_normals([[0, 0, 1.0]], [[0, 0, 0.0]], [[0, 0, 5.0]])
