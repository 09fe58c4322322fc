"""Gradient integration (section 3.2.2, eq. 8-13) and gridding to a heightfield."""

import numpy as np
import pytest
from scipy.spatial import Delaunay

from restoration.integrate import (
    INTEGRATORS,
    MIN_SAMPLES,
    DifferenceGraph,
    integrate,
    to_heightfield,
)
from restoration.integrate.fourier import frankot_chellappa, poisson_dct
from restoration.integrate.gridding import gap_free_triangles
from restoration.integrate.lattice import solve_differences
from wai_core.errors import RestorationFailed, WaiInputError

D = 10.0  # grid spacing, mm
A, WAVELENGTH, DIRECTION = 3.0, 120.0, 0.5  # sinusoid: mm, mm (12 samples), radians
K = 2 * np.pi / WAVELENGTH
U = np.array([np.cos(DIRECTION), np.sin(DIRECTION)])


def grid(jitter_mm=0.0, seed=0):
    """A 29 x 25 sample grid, indices (i, j), positions i D, j D plus uniform jitter."""
    jj, ii = np.mgrid[-12:13, -14:15]
    ij = np.column_stack([ii.ravel(), jj.ravel()])
    xy = ij * D + np.random.default_rng(seed).uniform(-jitter_mm, jitter_mm, ij.shape)
    return ij, xy


def keystone(jitter_mm=1.0, seed=0):
    """The same 29 x 25 indices on a keystoned footprint: rows 7 mm apart in y, samples along a
    row 5 mm apart at the near edge (j = -12) to 15 mm at the far one (a trapezoid that fills
    2/3 of its bounding box), plus uniform jitter."""
    ij, _ = grid()
    xy = np.column_stack([ij[:, 0] * D * (1.0 + ij[:, 1] / 24.0), ij[:, 1] * 7.0])
    return ij, xy + np.random.default_rng(seed).uniform(-jitter_mm, jitter_mm, ij.shape)


def plane(xy):
    return 0.1 * xy[:, 0] - 0.2 * xy[:, 1], np.tile([0.1, -0.2], (len(xy), 1))


def paraboloid(xy):
    x, y = xy[:, 0], xy[:, 1]
    z = 1e-3 * (x**2 + 0.5 * y**2 + x * y) + 0.05 * x
    return z, np.column_stack([1e-3 * (2 * x + y) + 0.05, 1e-3 * (y + x)])


def sinusoid(xy):
    phase = K * xy @ U
    return A * np.sin(phase), (A * K * np.cos(phase))[:, None] * U


def errors(name, ij, xy, surface):
    z, g = surface(xy)
    h = INTEGRATORS[name](ij, xy, g)
    assert abs(np.nanmean(h)) < 1e-9  # heights come back zero-mean
    return h - (z - z.mean())


def test_registry_names():
    assert {"fourth_order", "paper", "trapezoid", "spline", "frankot_chellappa",
            "dct_poisson"} <= set(INTEGRATORS)


# Integrators exact for quadratic surfaces on irregular samples (the paper's central differences
# are not; Frankot-Chellappa comes close, see test_grid_integrators_on_plane_and_paraboloid).
EXACT_FOR_QUADRATICS = ("fourth_order", "trapezoid", "spline", "dct_poisson")
GRID_INTEGRATORS = ("frankot_chellappa", "dct_poisson")

# Frankot-Chellappa's error on the paraboloid, mm: the even mirror at the grid's borders makes
# kinks where the slopes (up to 0.4 here) are not zero, and their aliased spectrum errs there to
# first order in the node spacing (3.4-3.8 mm here). Measured 0.13 (jittered) and 0.16
# (keystone) max, 0.019 and 0.011 rms; swapped or sign-flipped slopes err by 16-130 mm max,
# 5.7-24 mm rms.
FC_PARABOLOID_MAX, FC_PARABOLOID_RMS = 0.3, 0.03


@pytest.mark.parametrize("name", sorted(INTEGRATORS))
def test_tilted_plane_is_exact(name):
    ij, xy = grid(jitter_mm=3.0)
    assert np.max(np.abs(errors(name, ij, xy, plane))) < 1e-9


@pytest.mark.parametrize("name", EXACT_FOR_QUADRATICS)
def test_paraboloid_on_irregular_grid_is_exact(name):
    # The trapezoid rule is exact for quadratics along any edge, and so is the fourth-order
    # rule (its neighbours' slopes are corrected for their offset across the edge by the
    # Hessian that the edge's own slopes give, constant here); the spline holds quadratics
    # and its third-difference penalty ignores them; dct_poisson interpolates the (linear)
    # slopes exactly, extends them with the exact curvature, solves the trapezoid rule on its
    # grid and reads back with trapezoid steps.
    ij, xy = grid(jitter_mm=3.0)
    assert np.max(np.abs(errors(name, ij, xy, paraboloid))) < 1e-9


def test_paper_scheme_is_not_exact_for_paraboloid_on_irregular_grid():
    # Central differences hold the slope at the centre node, not at the chord's midpoint.
    ij, xy = grid(jitter_mm=3.0)
    assert np.max(np.abs(errors("paper", ij, xy, paraboloid))) > 1e-3


def test_sinusoid_error_bounds():
    """12 samples per wavelength of a 3 mm sinusoid, oblique to the grid.

    A difference over one step d errs by the truncation error of its rule, a smooth slope error
    that integrates to a height error of at most (slope error) / k for a sinusoid:
    trapezoid: f''' d^3 / 12 -> A (k d)^2 / 12; the paper's central differences
    f''' d^3 / 6 inside, but forward/backward differences at the border err by f'' d^2 / 2
    -> A (k d)^2 / 2 (first order, which dominates); the cubic spline (control step h = 1.5 d)
    approximates to the classic (5 / 384) h^4 f'''' -> (5 / 384) A (k h)^4.
    """
    ij, xy = grid()
    kd = K * D
    assert np.max(np.abs(errors("trapezoid", ij, xy, sinusoid))) < A * kd**2 / 12
    assert np.max(np.abs(errors("paper", ij, xy, sinusoid))) < A * kd**2 / 2
    assert np.max(np.abs(errors("spline", ij, xy, sinusoid))) < 5 / 384 * A * (1.5 * kd) ** 4
    # Irregular grid: the trapezoid bound with the longest edge still holds.
    ij, xy = grid(jitter_mm=3.0, seed=1)
    d_max = np.hypot(D + 6.0, 6.0)
    assert np.max(np.abs(errors("trapezoid", ij, xy, sinusoid))) < A * (K * d_max) ** 2 / 12


def test_fourth_order_sinusoid_error_bound():
    """The same sinusoid with the fourth-order rule: inside the grid its steps err by
    O(d^5); an edge at the border has one neighbour, a quadratic interpolant of the slope,
    whose step errs by d^4 h_4 / 24 (h_4 the fourth derivative) -> a height error of at most
    A (k d)^3 / 24. Measured 0.0032 mm against the trapezoid's 0.050 on the regular grid,
    0.019 against 0.11 on the keystone."""
    kd = K * D
    ij, xy = grid()
    fourth = np.max(np.abs(errors("fourth_order", ij, xy, sinusoid)))
    assert fourth < A * kd**3 / 24
    assert fourth < 0.1 * np.max(np.abs(errors("trapezoid", ij, xy, sinusoid)))
    ij, xy = keystone()
    assert np.max(np.abs(errors("fourth_order", ij, xy, sinusoid))) < 0.3 * np.max(
        np.abs(errors("trapezoid", ij, xy, sinusoid))
    )


def test_fourth_order_steps_are_exact_for_quartics_along_a_line():
    """Unevenly spaced samples on a line: with both neighbours the step of h = s^4 is exact,
    with one that of h = s^3, with none the trapezoid rule's (exact for s^2 only)."""
    from restoration.integrate.rules import edge_steps

    x = np.array([-1.3, 0.0, 0.8, 2.1])
    xy = np.column_stack([x, 0.5 * x])  # along a slanted line: steps are along it
    s = x * np.hypot(1.0, 0.5)  # arc length from sample 1

    def slopes(power):  # h = s^power: (dh/dx, dh/dy)
        g = power * s ** (power - 1) / np.hypot(1.0, 0.5)
        return np.column_stack([g, 0.5 * g])

    a, b, none = np.array([1]), np.array([2]), np.array([-1])
    exact = {p: s[2] ** p - s[1] ** p for p in (2, 3, 4)}
    both = edge_steps(xy, slopes(4), a, b, np.array([0]), np.array([3]))
    assert both[0] == pytest.approx(exact[4], abs=1e-12)
    for before, after in ((np.array([0]), none), (none, np.array([3]))):
        assert edge_steps(xy, slopes(3), a, b, before, after)[0] == pytest.approx(
            exact[3], abs=1e-12
        )
    assert edge_steps(xy, slopes(2), a, b, none, none)[0] == pytest.approx(exact[2], abs=1e-12)
    assert abs(edge_steps(xy, slopes(3), a, b, none, none)[0] - exact[3]) > 1e-3


def holes(ij):
    """Drop scattered single nodes and a 3 x 4 block inside the grid."""
    rng = np.random.default_rng(5)
    drop = rng.random(len(ij)) < 0.08
    drop |= (np.abs(ij[:, 0] - 4) <= 1) & (np.abs(ij[:, 1] + 3) <= 1.5)
    return ~drop


@pytest.mark.parametrize(
    ("name", "surface"),
    [
        ("paper", plane),
        ("trapezoid", paraboloid),
        ("fourth_order", paraboloid),
        ("spline", paraboloid),
        ("frankot_chellappa", plane),
        ("dct_poisson", paraboloid),
    ],
)
def test_holes_keep_exactness(name, surface):
    ij, xy = grid(jitter_mm=2.0)
    keep = holes(ij)
    e = errors(name, ij[keep], xy[keep], surface)
    assert np.all(np.isfinite(e))
    assert np.max(np.abs(e)) < 1e-9


@pytest.mark.parametrize("name", sorted(INTEGRATORS))
def test_island_is_left_unknown(name):
    """Samples that share no grid edge with the main piece get NaN, not a guessed offset."""
    ij, xy = grid(jitter_mm=2.0)
    cut = ij[:, 0] == 10  # a full column removed isolates the columns i = 11..14
    ij, xy = ij[~cut], xy[~cut]
    z, g = paraboloid(xy)
    h = INTEGRATORS[name](ij, xy, g)
    island = ij[:, 0] > 10
    assert np.all(np.isnan(h[island])) and np.all(np.isfinite(h[~island]))
    if name in EXACT_FOR_QUADRATICS:
        np.testing.assert_allclose(h[~island], z[~island] - z[~island].mean(), atol=1e-9)
    elif name == "frankot_chellappa":  # measured 0.15
        np.testing.assert_allclose(
            h[~island], z[~island] - z[~island].mean(), atol=FC_PARABOLOID_MAX
        )


@pytest.mark.parametrize("seed", range(4))
def test_largest_piece_matches_a_graph_library(seed):
    """The largest connected piece of random sparse graphs (many pieces, ties included) is
    scipy's largest connected component, the lowest-numbered of equal ones."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    from restoration.integrate.lattice import largest_piece

    rng = np.random.default_rng(seed)
    n = 400
    a, b = rng.integers(0, n, (2, 260 + 40 * seed))
    _, labels = connected_components(sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)))
    expected = labels == np.bincount(labels).argmax()
    np.testing.assert_array_equal(largest_piece(n, a, b), expected)
    # Two disjoint paths of equal length: the one holding node 0 wins.
    two = largest_piece(8, np.array([5, 6, 7, 0, 1, 2]), np.array([6, 7, 4, 1, 2, 3]))
    np.testing.assert_array_equal(two, np.arange(8) < 4)


def test_bad_input():
    ij, xy = grid()
    _, g = plane(xy)
    with pytest.raises(RestorationFailed, match="too few features"):
        integrate(ij[: MIN_SAMPLES - 1], xy[:3], g[:3])
    with pytest.raises(RestorationFailed, match="too few connected"):
        # Five samples, none a grid neighbour of another.
        integrate(ij[::7][:5] * 3, xy[::7][:5], g[:5])
    with pytest.raises(WaiInputError, match="share one grid index"):
        integrate(np.r_[ij, ij[:1]], np.r_[xy, xy[:1] + 1], np.r_[g, g[:1]])
    with pytest.raises(WaiInputError, match="NaN"):
        integrate(ij, xy, np.where(np.arange(len(g))[:, None] == 3, np.nan, g))
    with pytest.raises(WaiInputError, match="shape"):
        integrate(ij, xy[:, :1], g)
    with pytest.raises(WaiInputError, match="unknown integrator"):
        integrate(ij, xy, g, method="magic")
    with pytest.raises(RestorationFailed, match="too wide"):
        integrate(np.r_[ij[:-1], [[10**5, 10**5]]], xy, g)


# ---------------------------------------------------------------------------------------------
# Grid integrators: slopes resampled onto a regular grid, integrated by FFT or DCT
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", GRID_INTEGRATORS)
@pytest.mark.parametrize("footprint", [grid, keystone])
def test_grid_integrators_on_plane_and_paraboloid(name, footprint):
    ij, xy = footprint(jitter_mm=3.0) if footprint is grid else footprint()
    assert np.max(np.abs(errors(name, ij, xy, plane))) < 1e-9
    e = errors(name, ij, xy, paraboloid)
    if name == "dct_poisson":
        assert np.max(np.abs(e)) < 1e-9
    else:
        assert np.max(np.abs(e)) < FC_PARABOLOID_MAX
        assert np.sqrt(np.mean(e**2)) < FC_PARABOLOID_RMS


@pytest.mark.parametrize("name", GRID_INTEGRATORS)
def test_grid_integrators_on_sinusoid(name):
    """Slopes interpolated linearly along an edge of length d err by up to d^2 |g''| / 8, which
    integrates over the wave to a height error up to A (k d)^2 / 8 (measured 0.17-0.18 mm on the
    jittered grid, 0.30 allowed; the trapezoid integrator errs by 0.06). On the keystone, a
    third of the bounding box lies outside the samples' hull: the extrapolated slopes there are
    not a gradient field and leak inwards (measured 0.86 max, 0.17 rms; trapezoid 0.11, 0.04).
    Swapped or sign-flipped slopes err by 5.5-13 mm max, 1.0-4.2 rms."""
    ij, xy = grid(jitter_mm=3.0)
    d_max = np.hypot(D + 6.0, 6.0)
    assert np.max(np.abs(errors(name, ij, xy, sinusoid))) < A * (K * d_max) ** 2 / 8
    e = errors(name, *keystone(), sinusoid)
    assert np.max(np.abs(e)) < 1.5
    assert np.sqrt(np.mean(e**2)) < 0.3


@pytest.mark.parametrize("name", GRID_INTEGRATORS)
def test_grid_integrators_reject_swapped_or_flipped_slopes(name):
    """The tolerances above are far below what an x/y swap or a sign error costs."""
    ij, xy = keystone()
    tolerances = ((paraboloid, FC_PARABOLOID_MAX, FC_PARABOLOID_RMS), (sinusoid, 1.5, 0.3))
    for surface, max_tol, rms_tol in tolerances:
        z, g = surface(xy)
        for bad in (g[:, ::-1], -g, g * [1.0, -1.0], g * [-1.0, 1.0]):
            e = INTEGRATORS[name](ij, xy, bad) - (z - z.mean())
            assert np.max(np.abs(e)) > 3 * max_tol and np.sqrt(np.mean(e**2)) > 3 * rms_tol


def test_frankot_chellappa_recovers_smooth_even_modes():
    """Modes cos(pi a (c + 1/2) / nx) cos(pi b (r + 1/2) / ny) stay smooth under the even
    mirror, so the spectral projection is exact (checks the frequencies' axes and signs)."""
    ny, nx, h = 24, 40, 2.5
    c = (np.arange(nx) + 0.5) * np.pi / nx
    r = (np.arange(ny) + 0.5)[:, None] * np.pi / ny
    for a, b in ((2, 0), (0, 4), (4, 2), (6, 10)):
        z = np.cos(a * c) * np.cos(b * r)
        p = -a * np.pi / (nx * h) * np.sin(a * c) * np.cos(b * r)
        q = -b * np.pi / (ny * h) * np.cos(a * c) * np.sin(b * r)
        np.testing.assert_allclose(frankot_chellappa(p, q, h), z - z.mean(), atol=1e-12)


def test_poisson_dct_is_least_squares_over_grid_edges():
    """On a random (non-integrable) field the DCT solution is the sparse least-squares solution
    of the trapezoid rises along every grid edge, zero mean."""
    rng = np.random.default_rng(4)
    ny, nx, h = 6, 9, 3.0
    p, q = rng.normal(size=(2, ny, nx))
    node = np.arange(ny * nx).reshape(ny, nx)
    a = np.r_[node[:, :-1].ravel(), node[:-1].ravel()]
    b = np.r_[node[:, 1:].ravel(), node[1:].ravel()]
    rise = np.r_[(0.5 * h * (p[:, :-1] + p[:, 1:])).ravel(), (0.5 * h * (q[:-1] + q[1:])).ravel()]
    ref = solve_differences(ny * nx, a, b, rise, np.ones(a.size)).reshape(ny, nx)
    np.testing.assert_allclose(poisson_dct(p, q, h), ref, atol=1e-12)


@pytest.mark.parametrize("name", GRID_INTEGRATORS)
def test_grid_integrators_bad_input_and_unused_weights(name):
    ij, xy = grid()
    z, g = paraboloid(xy)
    with pytest.raises(RestorationFailed, match="too few features"):
        integrate(ij[: MIN_SAMPLES - 1], xy[:3], g[:3], name)
    with pytest.raises(WaiInputError, match="NaN"):
        integrate(ij, xy, np.where(np.arange(len(g))[:, None] == 3, np.nan, g), name)
    with pytest.raises(RestorationFailed, match="too few connected"):
        integrate(ij[::7][:5] * 3, xy[::7][:5], g[:5], name)
    row = ij[:, 1] == 0  # one row of samples: connected, but no area to grid
    # Samples whose every triangle bridges dots missing between them: no node to grid (a
    # status of the frame, not an error of the input).
    with pytest.raises(RestorationFailed, match="spans a gap"):
        to_heightfield(xy, z, g, 5.0, lattice_ij=ij * 8)
    with pytest.raises(RestorationFailed, match="collinear"):
        integrate(ij[row], xy[row], g[row], name)
    other = xy + np.random.default_rng(2).uniform(-2.0, 2.0, xy.shape)
    np.testing.assert_array_equal(
        integrate(ij, xy, g, name, weight_xy_mm=other), integrate(ij, xy, g, name)
    )


def test_difference_solve_matches_dense_least_squares():
    """Random graph with repeated edges and an island: the sparse solve is the least-squares
    solution (zero mean) on the largest piece and NaN on the island."""
    rng = np.random.default_rng(3)
    n = 60
    a = rng.integers(0, 50, 400)
    b = rng.integers(0, 50, 400)
    a, b = np.r_[a[a != b], 50, 51, 52], np.r_[b[a != b], 51, 52, 50]  # island 50..52
    a, b = np.r_[a, a[:20]], np.r_[b, b[:20]]  # repeated pairs add up
    diff, w = rng.normal(size=a.size), rng.uniform(0.5, 2.0, a.size)
    h = solve_differences(n, a, b, diff, w)
    main = np.zeros(n, dtype=bool)
    main[:50] = True
    main[np.setdiff1d(np.arange(50), np.r_[a, b])] = False  # nodes without edges
    assert np.all(np.isnan(h[~main])) and np.all(np.isfinite(h[main]))
    keep = np.flatnonzero(main)
    on = main[a] & main[b]
    pos = np.full(n, -1)
    pos[keep] = np.arange(keep.size)
    design = np.zeros((on.sum(), keep.size))
    design[np.arange(on.sum()), pos[b[on]]] += 1.0
    design[np.arange(on.sum()), pos[a[on]]] -= 1.0
    sw = np.sqrt(w[on])
    ref = np.linalg.lstsq(design * sw[:, None], diff[on] * sw, rcond=None)[0]
    np.testing.assert_allclose(h[keep], ref - ref.mean(), atol=1e-10)


def test_difference_graph_reuses_its_factorisation():
    ij, xy = grid(jitter_mm=2.0)
    _, g = paraboloid(xy)
    first = integrate(ij, xy, g, weight_xy_mm=xy)
    np.testing.assert_array_equal(first, integrate(ij, xy, g))  # default weights: xy's own
    graph = DifferenceGraph.build(4, np.array([0, 1, 2]), np.array([1, 2, 3]))
    w = np.array([1.0, 2.0, 3.0])
    h1 = graph.solve(np.array([1.0, 1.0, 1.0]), w)
    h2 = graph.solve(np.array([2.0, 0.0, 1.0]), w)  # same weights: the cached factorisation
    assert len(graph._factors) == 1
    np.testing.assert_allclose(np.diff(h1), [1.0, 1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(np.diff(h2), [2.0, 0.0, 1.0], atol=1e-12)


@pytest.mark.parametrize("name", ["trapezoid", "paper"])
def test_weights_from_other_positions_keep_exactness(name):
    """Weights only distribute inconsistency: consistent differences stay exact whatever the
    positions that set them (refinement passes weigh by the first pass's geometry)."""
    ij, xy = grid(jitter_mm=3.0)
    surface = paraboloid if name == "trapezoid" else plane
    z, g = surface(xy)
    other = xy + np.random.default_rng(2).uniform(-2.0, 2.0, xy.shape)
    h = integrate(ij, xy, g, name, weight_xy_mm=other)
    np.testing.assert_allclose(h, z - z.mean(), atol=1e-9)
    with pytest.raises(WaiInputError, match="weight_xy_mm"):
        integrate(ij, xy, g, name, weight_xy_mm=other[:-1])


# ---------------------------------------------------------------------------------------------
# Gridding
# ---------------------------------------------------------------------------------------------


def truth_on_nodes(hf, surface):
    x, y = np.meshgrid(hf.x, hf.y)
    return surface(np.column_stack([x.ravel(), y.ravel()]))[0].reshape(x.shape)


@pytest.mark.parametrize("method", ["tangent_blend", "hermite_spline"])
def test_gridding_with_slopes_is_exact_for_paraboloid(method):
    ij, xy = grid(jitter_mm=3.0)
    z, g = paraboloid(xy)
    hf = to_heightfield(xy, z + 150.0, g, 4.0, method=method)
    err = hf.z - 150.0 - truth_on_nodes(hf, paraboloid)
    assert np.isfinite(err).mean() > 0.8
    assert np.nanmax(np.abs(err)) < 1e-8


def test_gridding_accuracy_on_sinusoid():
    ij, xy = grid(jitter_mm=3.0)
    z, g = sinusoid(xy)
    rms = {}
    for method in ("tangent_blend", "hermite_spline", "clough_tocher"):
        hf = to_heightfield(xy, z, g, 4.0, method=method)
        rms[method] = np.sqrt(np.nanmean((hf.z - truth_on_nodes(hf, sinusoid)) ** 2))
    # The blend's error is the trapezoid rule's, A (k d)^2 / 12 at most; the spline's is O(h^4).
    assert rms["tangent_blend"] < A * (K * D) ** 2 / 12
    assert rms["hermite_spline"] < 0.3 * rms["tangent_blend"]
    assert rms["clough_tocher"] < A * (K * D) ** 2 / 12


def test_gridding_is_nan_outside_convex_hull():
    # Samples filling a triangle: nodes beyond its hypotenuse lie outside the hull.
    ij, xy = grid()
    tri = xy[:, 0] + xy[:, 1] <= 0
    z, g = plane(xy[tri])
    hf = to_heightfield(xy[tri], z, g, 5.0)
    x, y = np.meshgrid(hf.x, hf.y)
    assert np.all(np.isnan(hf.z[x + y > 1e-6]))
    inside = x + y < -1e-6
    np.testing.assert_allclose(hf.z[inside], (0.1 * x - 0.2 * y)[inside], atol=1e-9)
    # clough_tocher (heights only) is exact for planes too, up to its iterative gradient fit.
    hf_ct = to_heightfield(xy[tri], z, None, 5.0, method="clough_tocher")
    np.testing.assert_allclose(hf_ct.z, hf.z, atol=1e-5)


def test_gridding_drops_triangles_that_bridge_missing_dots_on_the_lattice():
    # Rows 2x farther apart than the dots along a row (a keystone's far field): with two dots
    # missing along some rows, the triangles across the slit are only ~3.6x the dots' spacing,
    # which the edge ratio (4) keeps; their corners are 3 dots apart on the lattice.
    jj, ii = np.mgrid[-6:7, -12:13]
    ij = np.column_stack([ii.ravel(), jj.ravel()])
    xy = ij * [4.0, 8.0]
    slit = (np.abs(ij[:, 1]) <= 3) & np.isin(ij[:, 0], [0, 1])
    ij, xy = ij[~slit], xy[~slit]
    z, g = plane(xy)
    by_distance = to_heightfield(xy, z, g, 1.0)
    on_lattice = to_heightfield(xy, z, g, 1.0, lattice_ij=ij)
    x, y = np.meshgrid(on_lattice.x, on_lattice.y)
    middle = (np.abs(x - 2.0) < 1.5) & (np.abs(y) < 20.0)
    assert np.isfinite(by_distance.z[middle]).all()  # bridged by the edge ratio alone
    assert np.isnan(on_lattice.z[middle]).all()
    # Everywhere else the two agree (to rounding on shared edges), and the plane is exact.
    known = np.isfinite(on_lattice.z)
    assert known.mean() > 0.8
    np.testing.assert_allclose(on_lattice.z[known], by_distance.z[known], atol=1e-9)
    np.testing.assert_allclose(on_lattice.z[known], (0.1 * x - 0.2 * y)[known], atol=1e-9)
    # A single missing dot is still bridged (its neighbours are 2 dots apart).
    hole = np.flatnonzero((ij == [5, 0]).all(axis=1))
    keep = np.ones(len(ij), bool)
    keep[hole] = False
    one = to_heightfield(xy[keep], z[keep], g[keep], 1.0, lattice_ij=ij[keep])
    assert np.isfinite(one.z[np.argmin(np.abs(one.y)), np.argmin(np.abs(one.x - 20.0))])


def test_gridding_bad_input():
    ij, xy = grid()
    z, g = plane(xy)
    with pytest.raises(RestorationFailed, match="too few samples"):
        to_heightfield(xy[:3], z[:3], g[:3], 5.0)
    with pytest.raises(WaiInputError, match="needs finite slopes"):
        to_heightfield(xy, z, None, 5.0)
    with pytest.raises(RestorationFailed, match="too many nodes"):
        to_heightfield(xy, z, g, 1e-3)
    with pytest.raises(RestorationFailed, match="span too little"):
        to_heightfield(xy, z, g, 1000.0)
    # Samples whose every triangle bridges dots missing between them: no node to grid (a
    # status of the frame, not an error of the input).
    with pytest.raises(RestorationFailed, match="spans a gap"):
        to_heightfield(xy, z, g, 5.0, lattice_ij=ij * 8)
    with pytest.raises(RestorationFailed, match="collinear"):
        to_heightfield(np.column_stack([np.arange(9.0) * 10, np.arange(9.0) * 10]), z[:9],
                       g[:9], 5.0)
    with pytest.raises(WaiInputError, match="unknown method"):
        to_heightfield(xy, z, g, 5.0, method="nearest")


def _blend_reference(xy, z, g, spacing, max_edge_ratio=4.0):
    """The tangent blend node by node: qhull's point location and barycentric weights."""
    tri = Delaunay(xy)

    def key(t):
        return np.sort(t, axis=1) @ [len(xy) ** 2, len(xy), 1]

    keep = np.isin(key(tri.simplices), key(gap_free_triangles(tri, max_edge_ratio)))
    lo = xy.min(axis=0)
    n = np.ceil((xy.max(axis=0) - lo) / spacing).astype(int) + 1
    gx, gy = lo[0] + spacing * np.arange(n[0]), lo[1] + spacing * np.arange(n[1])
    p = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    s = tri.find_simplex(p, tol=1e-12)
    out = np.full(len(p), np.nan)
    inside = (s >= 0) & keep[np.maximum(s, 0)]
    t = tri.transform[s[inside]]
    lam2 = np.einsum("nij,nj->ni", t[:, :2], p[inside] - t[:, 2])
    lam = np.column_stack([lam2, 1 - lam2.sum(axis=1)])
    v = tri.simplices[s[inside]]
    pred = z[v] + 0.5 * np.sum(g[v] * (p[inside][:, None] - xy[v]), axis=2)
    out[inside] = np.sum(lam * pred, axis=1)
    return out.reshape(gy.size, gx.size)


def test_tangent_blend_matches_node_by_node_reference():
    """The scan conversion finds the same nodes as qhull's point location and the per-run
    quadratics give the same blend, on jittered samples whose hull has gaps and slivers."""
    ij, xy = grid(jitter_mm=4.0, seed=7)
    keep = holes(ij) & (xy[:, 0] + 0.5 * xy[:, 1] < 90)
    z, g = sinusoid(xy[keep])
    for spacing in (1.3, 2.0, 5.0):
        hf = to_heightfield(xy[keep], z, g, spacing)
        ref = _blend_reference(xy[keep], z, g, spacing)
        both = np.isfinite(hf.z) & np.isfinite(ref)
        # Nodes on a triangle edge may be located in either neighbour: a handful differ only
        # at the hull, where the gap filter dropped one of them.
        assert (np.isfinite(hf.z) != np.isfinite(ref)).sum() <= 0.002 * hf.z.size
        np.testing.assert_allclose(hf.z[both], ref[both], atol=1e-10)


def _numpy_blend(xy, z, g, spacing, max_edge_ratio):
    """The tangent blend by the NumPy steps (gap filter, scan conversion, per-run quadratics)
    that the compiled pass of :func:`to_heightfield` replaces."""
    from restoration.integrate.gridding import _grid_axes, _scan_triangles, _tangent_blend

    gx, gy = _grid_axes(xy, spacing)
    simplices = gap_free_triangles(Delaunay(xy), max_edge_ratio)
    spans = _scan_triangles(xy[simplices], gx, gy)
    node, values = _tangent_blend(xy, z, g, simplices, spans, gx, gy)
    out = np.full(gy.size * gx.size, np.nan)
    out[node] = values
    return out.reshape(gy.size, gx.size)


@pytest.mark.parametrize("max_edge_ratio", [4.0, 1.5, None])
def test_compiled_blend_is_the_numpy_steps_exactly(max_edge_ratio):
    ij, xy = grid(jitter_mm=4.0, seed=7)
    keep = holes(ij) & (xy[:, 0] + 0.5 * xy[:, 1] < 90)
    z, g = sinusoid(xy[keep])
    # Samples on whole grid lines too: nodes on triangle edges and corners, rows through
    # vertices (the scan's tie-breaks).
    for points in (xy[keep], np.round(xy[keep] / 2.0) * 2.0 + 0.1 * (ij[keep] % 2)):
        for spacing in (1.3, 2.0, 5.0):
            got = to_heightfield(points, z, g, spacing, max_edge_ratio=max_edge_ratio).z
            np.testing.assert_array_equal(
                got, _numpy_blend(points, z, g, spacing, max_edge_ratio)
            )


def test_ldl_solve_is_superlu_to_rounding():
    from restoration.integrate.ldl import pinned_laplacian_ldl

    ij, xy = grid(jitter_mm=2.0, seed=3)
    keep = holes(ij)
    nb = {tuple(p): k for k, p in enumerate(ij[keep])}
    a, b = zip(*[(k, nb[(i + di, j + dj)]) for k, (i, j) in enumerate(ij[keep])
                 for di, dj in ((1, 0), (0, 1)) if (i + di, j + dj) in nb], strict=True)
    graph = DifferenceGraph.build(int(keep.sum()), np.array(a), np.array(b))
    w = np.random.default_rng(4).uniform(0.5, 2.0, graph.edges.size)
    factors = pinned_laplacian_ldl(ij[keep][graph.node], graph.ea, graph.eb, w)
    rhs = np.random.default_rng(5).normal(size=graph.node.size - 1)
    want = graph._factor(w).solve(rhs)
    np.testing.assert_allclose(factors.solve(rhs), want, rtol=0, atol=1e-12 * np.abs(want).max())
    # A fill-reducing order: L holds a fraction of the dense lower triangle.
    m = graph.node.size - 1
    assert factors.l_val.size < 0.1 * m * (m - 1) / 2


def test_ldl_refuses_a_node_not_tied_to_the_pinned_one():
    from restoration.integrate.ldl import pinned_laplacian_ldl

    ij = np.array([[0, 0], [1, 0], [2, 0], [5, 0]])
    with pytest.raises(RestorationFailed, match="singular"):
        pinned_laplacian_ldl(ij, np.array([0, 1]), np.array([1, 2]), np.ones(2))


def _small_span_delaunay(xy, ij, max_step):
    """qhull's triangles whose corners lie at most ``max_step`` dots apart, as sorted triples."""
    simplices = Delaunay(xy).simplices
    corners = ij[simplices]
    span = (corners.max(axis=1) - corners.min(axis=1)).max(axis=1)
    return {tuple(sorted(t)) for t in simplices[span <= max_step].tolist()}


@pytest.mark.parametrize(("jitter_mm", "keystoned"), [(2.0, False), (6.0, False), (1.0, True)])
def test_lattice_delaunay_is_qhulls_small_span_triangles(jitter_mm, keystoned):
    """Holes, a keystoned footprint, and a jitter of 0.6 spacings that folds the lattice's map
    to the plane in places: the same triangles as qhull's, and the nearest-neighbour distances
    of a k-d tree."""
    from scipy.spatial import cKDTree

    from restoration.integrate.triangulate import lattice_delaunay

    ij, xy = keystone(jitter_mm) if keystoned else grid(jitter_mm=jitter_mm, seed=8)
    keep = holes(ij)
    ij, xy = ij[keep], xy[keep]
    for max_step in (1, 2, 3):
        simplices, nearest = lattice_delaunay(xy, ij, max_step)
        got = {tuple(sorted(t)) for t in simplices.tolist()}
        assert len(got) == len(simplices)
        assert got == _small_span_delaunay(xy, ij, max_step)
    np.testing.assert_array_equal(nearest, cKDTree(xy).query(xy, k=2)[0][:, 1])


def test_gridding_on_the_lattice_is_the_qhull_gridding(monkeypatch):
    import restoration.integrate.gridding as gridding

    ij, xy = grid(jitter_mm=3.0, seed=9)
    keep = holes(ij)
    ij, xy = ij[keep], xy[keep]
    z, g = sinusoid(xy)
    fast = to_heightfield(xy, z, g, 2.0, lattice_ij=ij).z
    monkeypatch.setattr(gridding, "lattice_delaunay", lambda *args: None)
    slow = to_heightfield(xy, z, g, 2.0, lattice_ij=ij).z
    np.testing.assert_array_equal(np.isnan(fast), np.isnan(slow))
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12)


def test_lattice_delaunay_leaves_cocircular_samples_to_qhull():
    """A regular lattice: every cell's four corners on one circle, two Delaunay choices."""
    from restoration.integrate.triangulate import lattice_delaunay

    ij, xy = grid()
    assert lattice_delaunay(xy, ij, 2) is None
    z, g = paraboloid(xy)
    hf = to_heightfield(xy, z, g, 5.0, lattice_ij=ij)
    assert np.isfinite(hf.z).mean() > 0.9
