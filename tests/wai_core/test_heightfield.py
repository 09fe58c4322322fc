"""Heightfields: bicubic interpolation, normals and ray hits against analytic surfaces."""

import numpy as np
import pytest

from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield, continue_surface, load_heightfield


def _plane(ax=0.1, ay=-0.05, c=150.0):
    x = np.linspace(0, 100, 21)
    y = np.linspace(-50, 50, 11)
    xx, yy = np.meshgrid(x, y)
    return Heightfield(x, y, c + ax * xx + ay * yy)


def test_plane_heights_normals_and_hits():
    hf = _plane()
    assert hf.height(33.3, 7.7) == pytest.approx(150 + 3.33 - 0.385)
    n = hf.normal(10.0, 0.0)
    assert np.allclose(n, np.array([-0.1, 0.05, 1]) / np.linalg.norm([-0.1, 0.05, 1]))
    d = np.array([[0.3, 0.1, 1.0]]) / np.linalg.norm([0.3, 0.1, 1.0])
    p, ok = hf.intersect(np.array([20.0, 0.0, 0.0]), d)
    assert ok[0] and p[0, 2] == pytest.approx(hf.height(p[0, 0], p[0, 1]), abs=1e-6)


def test_sinusoid_slopes_match_derivative():
    x = np.linspace(0, 200, 201)
    y = np.linspace(0, 10, 6)
    xx, _ = np.meshgrid(x, y)
    k = 2 * np.pi / 80
    hf = Heightfield(x, y, 2 * np.sin(k * xx))
    xs = np.linspace(20, 180, 17)
    gx, gy = hf.gradient(xs, np.full_like(xs, 5.0))
    assert np.allclose(gx, 2 * k * np.cos(k * xs), atol=1e-4)
    assert np.allclose(gy, 0, atol=1e-9)


def test_bad_heightfields(tmp_path):
    with pytest.raises(WaiInputError, match="shape"):
        Heightfield(np.arange(5.0), np.arange(4.0), np.zeros((5, 5)))
    with pytest.raises(WaiInputError, match="increasing"):
        Heightfield(np.array([0, 1, 1, 2.0, 3]), np.arange(4.0), np.zeros((4, 5)))
    path = tmp_path / "nan.npz"
    np.savez(path, x=np.arange(5.0), y=np.arange(5.0), z=np.full((5, 5), np.nan))
    with pytest.raises(WaiInputError, match="NaN"):
        load_heightfield(path)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(WaiInputError, match="not an .npz archive"):
        load_heightfield(junk)
    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"PK\x03\x04 and then nothing")
    with pytest.raises(WaiInputError, match="cannot be read"):
        load_heightfield(broken)
    words = tmp_path / "words.npz"
    np.savez(words, x=np.arange(5.0), y=np.arange(5.0), z=np.full((5, 5), "a"))
    with pytest.raises(WaiInputError, match="'z' is not numeric"):
        load_heightfield(words)
    short = tmp_path / "short.npz"
    np.savez(short, x=np.arange(5.0), y=np.arange(5.0), z=np.zeros((4, 5)))
    with pytest.raises(WaiInputError, match=r"short\.npz: z must have shape"):
        load_heightfield(short)


def test_holes_are_continued_by_the_nearest_known_tangent_plane():
    # A tilted plane z = 1 + 0.3 x - 0.2 y on an uneven grid, with a hole in the middle and a
    # missing border: next to the known nodes (within FILL_EXACT_NODES) the continuation is the
    # plane itself (central or one-sided differences are exact on a plane), and far out it
    # fades into the nearest known height, never running away.
    x = np.cumsum(np.linspace(0.8, 1.6, 30))
    y = np.cumsum(np.linspace(1.2, 0.7, 25))
    z = 1.0 + 0.3 * x[None, :] - 0.2 * y[:, None]
    valid = np.ones(z.shape, bool)
    valid[10:14, 12:17] = False
    valid[:, 20:] = False
    filled = continue_surface(x, y, np.where(valid, z, np.nan), valid)
    assert np.array_equal(filled[valid], z[valid])
    assert np.allclose(filled[10:14, 12:17], z[10:14, 12:17], atol=1e-12)
    assert np.allclose(filled[:, 20:22], z[:, 20:22], atol=1e-12)
    edge = z[:, 19]  # the nearest known heights of the far columns
    assert np.allclose(filled[:, 26:], edge[:, None], atol=1e-12)
    between = filled[:, 22:26]
    assert np.all((between >= np.minimum(edge, z[:, 22])[:, None] - 1e-12)
                  & (between <= np.maximum(edge[:, None], z[:, 22:26]) + 1e-12))


def test_joint_height_and_slopes_are_exact_on_a_cubic_and_fitpacks_elsewhere():
    # A bicubic interpolating spline reproduces any cubic in x and y exactly (non-uniform
    # grid too): the one-pass evaluation must give the polynomial's height and slopes.
    x = np.r_[0.0, 2.0, 3.5, np.linspace(5.0, 40.0, 12)]
    y = np.linspace(-10.0, 20.0, 9)
    xx, yy = np.meshgrid(x, y)

    def cubic(x, y):
        return 0.002 * x**3 - 0.01 * x * y**2 + 0.3 * y - 0.05 * x * y + 1.0

    hf = Heightfield(x, y, cubic(xx, yy))
    rng = np.random.default_rng(4)
    px = np.r_[rng.uniform(x[0], x[-1], 2000), x[0], x[-1], 3.5]
    py = np.r_[rng.uniform(y[0], y[-1], 2000), y[0], y[-1], 20.0]
    h, gx, gy = hf.height_gradient(px, py)
    np.testing.assert_allclose(h, cubic(px, py), atol=1e-10)
    np.testing.assert_allclose(gx, 0.006 * px**2 - 0.01 * py**2 - 0.05 * py, atol=1e-10)
    np.testing.assert_allclose(gy, -0.02 * px * py + 0.3 - 0.05 * px, atol=1e-10)
    # On waves (no closed form) it is FITPACK's value; outside the grid NaN, as height().
    z = np.sin(0.3 * xx) * np.cos(0.2 * yy)
    waves = Heightfield(x, y, z)
    h, gx, gy = waves.height_gradient(np.r_[px, 50.0], np.r_[py, 0.0])
    np.testing.assert_allclose(h[:-1], waves.height(px, py), atol=1e-12)
    ref_gx, ref_gy = waves.gradient(px, py)
    np.testing.assert_allclose(gx[:-1], ref_gx, atol=1e-12)
    np.testing.assert_allclose(gy[:-1], ref_gy, atol=1e-12)
    assert np.isnan([h[-1], gx[-1], gy[-1]]).all()


@pytest.mark.parametrize("shape", [(4, 4), (9, 31), (118, 102)])
def test_even_grids_interpolate_like_fitpack(shape):
    """On evenly spaced axes the spline's coefficients are solved without FITPACK: the same
    knots and coefficients as scipy's interpolating RectBivariateSpline, to rounding, and
    exact on a bicubic."""
    from scipy.interpolate import RectBivariateSpline

    from wai_core.heightfield import interpolating_spline

    m, n = shape
    x, y = 12.5 + 0.8 * np.arange(n), -40.0 + 1.3 * np.arange(m)
    z = np.random.default_rng(m).standard_normal((m, n))
    fast, ref = interpolating_spline(x, y, z), RectBivariateSpline(y, x, z, kx=3, ky=3)
    for mine, theirs in zip(fast.get_knots(), ref.get_knots(), strict=True):
        np.testing.assert_array_equal(mine, theirs)
    np.testing.assert_allclose(fast.get_coeffs(), ref.get_coeffs(), rtol=0, atol=1e-11)
    xx, yy = np.meshgrid(x, y)
    cubic = 1e-3 * xx**3 - 2e-4 * xx * yy**2 + 0.1 * yy
    hf = Heightfield(x, y, cubic)
    px, py = x[0] + 0.37 * (x[-1] - x[0]), y[0] + 0.61 * (y[-1] - y[0])
    expected = 1e-3 * px**3 - 2e-4 * px * py**2 + 0.1 * py
    np.testing.assert_allclose(hf.height(px, py), expected, rtol=1e-12, atol=1e-9)


def test_even_grid_closed_form_is_exact_on_a_cubic():
    # On evenly spaced axes the basis takes the uniform B-spline's closed form everywhere
    # but the end spans: still exact on a bicubic, at knots, span edges and in between.
    x, y = np.linspace(-30.0, 50.0, 41), np.linspace(0.0, 24.0, 13)
    xx, yy = np.meshgrid(x, y)
    hf = Heightfield(x, y, 1e-3 * xx**3 - 2e-3 * xx * yy**2 + 0.2 * yy + 0.01 * xx * yy)
    px = np.r_[np.random.default_rng(1).uniform(x[0], x[-1], 3000), x, x[5] + 1e-12]
    py = np.r_[np.random.default_rng(2).uniform(y[0], y[-1], 3000), np.full(x.size + 1, 6.0)]
    h, gx, gy = hf.height_gradient(px, py)
    np.testing.assert_allclose(h, 1e-3 * px**3 - 2e-3 * px * py**2 + 0.2 * py + 0.01 * px * py,
                               atol=1e-9)
    np.testing.assert_allclose(gx, 3e-3 * px**2 - 2e-3 * py**2 + 0.01 * py, atol=1e-9)
    np.testing.assert_allclose(gy, -4e-3 * px * py + 0.2 + 0.01 * px, atol=1e-9)


def test_a_fan_of_rays_from_one_centre_hits_where_each_ray_alone_does():
    # A camera's pixels share an origin and start from their neighbour's hit: the hits must be
    # those of rays started one by one from the mean plane, on the surface and on the ray.
    x = y = np.linspace(-300.0, 300.0, 241)
    xx, yy = np.meshgrid(x, y)
    hf = Heightfield(x, y, 500.0 + 4.0 * np.sin(2 * np.pi * xx / 90.0) * np.cos(yy / 40.0))
    u, v = np.meshgrid(np.linspace(-0.4, 0.4, 60), np.linspace(-0.3, 0.3, 45))
    d = np.stack([u, v, np.ones_like(u)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    origin = np.array([5.0, -3.0, 0.0])
    p1, ok1, n1 = hf.intersect_normals(origin, d)
    p2, ok2, n2 = hf.intersect_normals(np.broadcast_to(origin, d.shape).copy(), d)
    assert ok1.all() and ok2.all()
    np.testing.assert_allclose(p1, p2, atol=1e-8)
    np.testing.assert_allclose(n1, n2, atol=1e-10)
    np.testing.assert_allclose(p1[..., 2], hf.height(p1[..., 0], p1[..., 1]), atol=1e-9)
    t = p1[..., 2] / d[..., 2]
    np.testing.assert_allclose(p1, origin + t[..., None] * d, atol=1e-9)
    np.testing.assert_allclose(n1, hf.normal(p1[..., 0], p1[..., 1]), atol=1e-12)
