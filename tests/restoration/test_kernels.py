"""The compiled (numba) kernels against NumPy oracles: the same numbers, to the last bit where
the kernel promises it."""

from __future__ import annotations

import contextlib

import numba
import numpy as np
import pytest
from scipy.interpolate import BSpline
from scipy.spatial import cKDTree

from restoration.features._kernels import nearest_two, spot_cells
from restoration.features._spot_kernels import segmented_pixels
from restoration.features.detect import _WINDOW_GAIN, _WINDOW_VAR, _refine_centres, detect_spots
from restoration.normals import (
    points_on_rays,
    reflection_normals,
    reflection_slopes,
    slopes_from_normals,
)
from restoration.reverse_trace import SplinePatches
from restoration.reverse_trace._kernels import (
    _residual,
    finish_rows,
    spline_jet,
    valid_box,
    warp_node_rows,
    warp_rows,
)
from restoration.reverse_trace._surface import _cell_polynomials
from restoration.reverse_trace.plan import _pixel_cells
from restoration.reverse_trace.warp import restore_view
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield
from wai_core.system import load_rig


@contextlib.contextmanager
def _threads(n):
    """The restoration's threads (numba's count) limited to ``n`` inside the block: the
    kernels it runs in chunks must not depend on how many there are."""
    before = numba.get_num_threads()
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    try:
        yield
    finally:
        numba.set_num_threads(before)


def test_reflection_slopes_are_the_numpy_steps_exactly():
    rng = np.random.default_rng(1)
    origin = np.array([1.0, -2.0, 3.0])
    dirs = rng.normal(size=(500, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 0.5
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    spots = np.c_[rng.uniform(-50, 50, (500, 2)), np.full(500, 60.0)]
    heights = rng.uniform(140, 160, 500)
    q = points_on_rays(origin, dirs, heights)
    normals = reflection_normals(dirs, q, spots)
    got = reflection_slopes(origin, dirs, spots, heights)
    for a, b in zip(got, (q, normals, slopes_from_normals(normals)), strict=True):
        np.testing.assert_array_equal(a, b)
    dirs[3, 2] = -0.1
    with pytest.raises(WaiInputError, match="upwards"):
        reflection_slopes(origin, dirs, spots, heights)


def test_spline_jet_matches_the_spline_patches_exactly():
    x = np.r_[0.0, 7.0, np.linspace(15.0, 300.0, 40)]
    y = np.linspace(-100.0, 120.0, 31)
    xx, yy = np.meshgrid(x, y)
    z = 150.0 + 2.0 * np.sin(xx / 23.0) * np.cos(yy / 17.0)
    z[5:9, 10:13] = np.nan
    model = SplinePatches(Heightfield(x, y, z))
    rng = np.random.default_rng(4)
    px = np.r_[rng.uniform(-5.0, 305.0, 2000), x[[0, -1, 5]]]
    py = np.r_[rng.uniform(-105.0, 125.0, 2000), y[[0, -1, 3]]]
    want = np.stack(model.jet(px, py), axis=1)
    got = np.array([spline_jet(model.table, model.cell_ok, model.x, model.y, a, b)
                    for a, b in zip(px, py, strict=True)])
    np.testing.assert_array_equal(got, want)


def test_nearest_two_is_the_kd_tree_answer():
    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 400, (800, 2))
    queries = rng.uniform(-20, 420, (3000, 2))
    bound = 30.0
    cells = spot_cells(pts, 13.0)
    d, i = cKDTree(pts).query(queries, k=2, distance_upper_bound=bound)
    for q, dq, iq in zip(queries, d, i, strict=True):
        d1, d2, best = nearest_two(pts, *cells, 13.0, bound, q[0], q[1])
        assert (d1, d2) == (dq[0], dq[1])
        assert best == (iq[0] if np.isfinite(dq[0]) else len(pts) - 1)


def test_segmented_pixels_are_the_labelled_pixels_and_their_bincounts():
    rng = np.random.default_rng(6)
    h, w, pad = 40, 50, 3
    labels = rng.integers(0, 7, (h, w)).astype(np.int32)
    smooth = rng.normal(size=(h, w)).astype(np.float32)
    padded = np.zeros((h + 2 * pad, w + 2 * pad), np.float32)
    padded[pad:-pad, pad:-pad] = rng.random((h, w))
    count = int(np.count_nonzero(labels))
    rows, cols, lab, val, raw, first, second, peak, flux, area = segmented_pixels(
        labels, smooth, padded, pad, 7, count, 24.5, 19.5
    )
    want_rows, want_cols = np.nonzero(labels)  # raster order
    np.testing.assert_array_equal(rows, want_rows)
    np.testing.assert_array_equal(cols, want_cols)
    np.testing.assert_array_equal(lab, labels[want_rows, want_cols])
    np.testing.assert_array_equal(val, smooth[want_rows, want_cols].astype(float))
    np.testing.assert_array_equal(raw, padded[pad:-pad, pad:-pad][want_rows, want_cols])
    w_, x, y = np.clip(val, 0.0, None), cols - 24.5, rows - 19.5
    for col, v in enumerate((np.ones(count), x, y)):
        np.testing.assert_allclose(first[:, col], np.bincount(lab, w_ * v, 7), rtol=1e-12)
    for col, v in enumerate((x * x, x * y, y * y)):
        np.testing.assert_allclose(second[:, col], np.bincount(lab, w_ * v, 7), rtol=1e-12)
    np.testing.assert_allclose(flux, np.bincount(lab, raw.astype(float), 7), rtol=1e-12)
    np.testing.assert_array_equal(area, np.bincount(lab, minlength=7))
    np.testing.assert_array_equal(peak[1:], [val[lab == i].max() for i in range(1, 7)])
    assert peak[0] == -np.inf  # no pixel of the background is listed
    # A count short of the labelled pixels is never written past.
    short = segmented_pixels(labels, smooth, padded, pad, 7, count - 5, 24.5, 19.5)
    np.testing.assert_array_equal(short[0], want_rows[: count - 5])


@pytest.mark.parametrize("n_iter", [2, 4])
@pytest.mark.parametrize("cov", [[[4.0, 1.5], [1.5, 2.0]], [[30.0, 29.95], [29.95, 30.0]]],
                         ids=["elongated", "thin-streak"])
def test_windowed_centroid_matches_a_direct_evaluation(n_iter, cov):
    """One spot, away from others, from a start 2 px off (so the window moves by a whole
    pixel, past what a moved window may reuse): the compiled window (exponentials by
    recurrence, later steps by a separable factor) against the window evaluated pixel by
    pixel at every step. The thin diagonal streak's window is so narrow across its rows that
    a recurrence down the box's centre column would leave float64's range: the kernel then
    starts each row at its own maximum."""
    pad, h, w = 48, 64, 64
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    cov = np.array(cov)
    centre = np.array([30.3, 31.6])
    d = np.stack([xx - centre[0], yy - centre[1]], axis=-1)
    spot = np.exp(-0.5 * np.einsum("...i,ij,...j", d, np.linalg.inv(cov), d))
    padded = np.zeros((h + 2 * pad, w + 2 * pad), np.float32)
    padded[pad:-pad, pad:-pad] = spot
    labels = np.zeros(padded.shape, np.int32)
    labels[pad:-pad, pad:-pad] = spot > 0.25
    start = np.array([[28.4, 33.2]])
    got = _refine_centres(padded, labels, 2, np.array([1]), start, cov[None], n_iter=n_iter)
    # Direct: the same box (3.5 sd + 1, rounded up to 3 px) and steps.
    half = 3 * ((np.ceil(3.5 * np.sqrt(np.diag(cov)) + 1.0).astype(int) + 2) // 3)
    base = np.rint(start[0]).astype(int)
    box = spot[base[1] - half[1] : base[1] + half[1] + 1, base[0] - half[0] : base[0] + half[0] + 1]
    fy, fx = np.mgrid[-half[1] : half[1] + 1, -half[0] : half[0] + 1]
    inv = np.linalg.inv(_WINDOW_VAR * cov)
    if cov[0, 1] > 20:  # the streak: the window's exponent down the centre column passes 1200
        assert inv[1, 1] * half[1] ** 2 > 1200
    s = start[0] - base
    for _ in range(n_iter):
        r = np.stack([fx - s[0], fy - s[1]], axis=-1)
        wgt = np.exp(-0.5 * np.einsum("...i,ij,...j", r, inv, r)) * box
        m = np.array([np.sum(wgt * fx), np.sum(wgt * fy)]) / wgt.sum()
        s = s + np.clip(_WINDOW_GAIN * (m - s), -1.0, 1.0)
    np.testing.assert_allclose(got[0], s + base, atol=1e-10)
    if cov[0, 1] < 20:
        assert np.abs(got[0] - centre).max() < (0.01 if n_iter > 2 else 0.5)


def _numpy_cell_polynomials(grid, knots):
    """The former NumPy construction: interval polynomials from scipy's design matrix, shifted
    to each cell's start."""
    breaks = knots[3:-3]
    starts, widths = breaks[:-1], np.diff(breaks)
    frac = np.array([0.125, 0.375, 0.625, 0.875])
    pts = (starts[:, None] + frac[None, :] * widths[:, None]).ravel()
    basis = BSpline.design_matrix(pts, knots, 3).toarray().reshape(starts.size, 4, -1)
    k = np.arange(starts.size)[:, None, None]
    vals = basis[k, np.arange(4)[None, :, None], k + np.arange(4)]
    poly = np.linalg.inv(np.vander(frac, 4, increasing=True))[None] @ vals
    k = np.clip(np.searchsorted(starts, grid[:-1], side="right") - 1, 0, starts.size - 1)
    s0 = ((grid[:-1] - starts[k]) / widths[k])[:, None, None]
    s1 = (1.0 / widths[k])[:, None, None]
    a = np.arange(4)
    binom = np.array([[1, 0, 0, 0], [1, 1, 0, 0], [1, 2, 1, 0], [1, 3, 3, 1]], dtype=float)
    shift = binom * s0 ** np.maximum(a[:, None] - a, 0) * s1**a
    return k, np.einsum("cab,caj->cbj", shift, poly[k])


def test_refraction_miss_carries_its_jacobian():
    """The Newton solve's Jacobian, carried along the refraction (forward mode), is the
    derivative of the miss: central differences on a tilted quadric surface (its height and
    slopes moving with the point), across Snell's window, to 1e-6 of the largest entry."""

    def surface(x, y):  # height mm, slopes and second derivatives
        return (150.0 + 0.002 * x * x + 0.001 * x * y - 0.0015 * y * y + 0.05 * x,
                0.004 * x + 0.001 * y + 0.05, 0.001 * x - 0.003 * y, 0.004, 0.001, -0.003)

    optics = np.array([3.0, -2.0, -300.0, 1.333, 400.0])  # camera centre, n, object plane
    no_port, camera = np.array([0.0, 0.0, 1.0, 1.0]), np.zeros(15)  # a pinhole: unused
    rng = np.random.default_rng(1)
    checked, eps = 0, 1e-5
    for x, y, tx, ty in rng.uniform([-60, -60, -300, -300], [60, 60, 300, 300], (100, 4)):
        r = _residual(optics, no_port, camera, x, y, *surface(x, y), tx, ty)
        if r[3] < 0.1:  # near or past total internal reflection the miss is not smooth
            continue

        def miss(u, v, tx=tx, ty=ty):
            return np.array(_residual(optics, no_port, camera, u, v, *surface(u, v), tx, ty)[:2])

        along_x = (miss(x + eps, y) - miss(x - eps, y)) / (2 * eps)
        along_y = (miss(x, y + eps) - miss(x, y - eps)) / (2 * eps)
        want = np.array([along_x[0], along_y[0], along_x[1], along_y[1]])
        np.testing.assert_allclose(r[4:], want, rtol=0, atol=1e-6 * np.abs(want).max())
        checked += 1
    assert checked > 50


def test_cell_polynomials_match_scipy_b_splines():
    x = np.r_[0.0, 7.0, np.linspace(15.0, 300.0, 40)]
    y = np.linspace(-100.0, 120.0, 31)
    z = 150.0 + np.sin(x[None, :] / 23.0) * np.cos(y[:, None] / 17.0)
    ty, tx = Heightfield(x, y, z)._spline.get_knots()
    for grid, knots in ((x, tx), (y, ty)):
        first, poly = _cell_polynomials(grid, knots)
        want_first, want = _numpy_cell_polynomials(grid, knots)
        np.testing.assert_array_equal(first, want_first)
        np.testing.assert_allclose(poly, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
        # And the cubics are the B-splines themselves, at points inside each cell.
        t = 0.3 * np.diff(grid)
        basis = BSpline.design_matrix(grid[:-1] + t, knots, 3).toarray()
        got = np.einsum("cbj,cb->cj", poly, t[:, None] ** np.arange(4))
        want_b = basis[np.arange(t.size)[:, None], first[:, None] + np.arange(4)]
        np.testing.assert_allclose(got, want_b, atol=1e-12)


def test_warp_rows_are_the_bilinear_upsampling():
    rng = np.random.default_rng(6)
    h, w, step = 37, 53, 8
    n_rows, n_cols = -(-(h - 1) // step) + 1, -(-(w - 1) // step) + 1
    dx = rng.normal(0, 3, (n_rows, n_cols)).astype(np.float32)
    dy = rng.normal(0, 3, (n_rows, n_cols)).astype(np.float32)
    dx[0, :] -= 5.0  # some pixels sample outside the image
    cell_ok = rng.random((n_rows - 1, n_cols - 1)) > 0.2
    map_x, map_y = np.empty((h, w), np.float32), np.empty((h, w), np.float32)
    valid = np.empty((h, w), bool)
    per_row, first, last = np.empty(h, np.int64), np.empty(h, np.int64), np.empty(h, np.int64)
    col_i, col_t = _pixel_cells(w, n_cols, step)
    along = warp_node_rows(dx, dy, cell_ok, col_i, col_t)
    for r0, r1 in ((0, 10), (10, 11), (11, h)):  # in 3 bands of rows
        warp_rows(r0, r1, *along, *_pixel_cells(h, n_rows, step), map_x, map_y, valid,
                  per_row, first, last)
    n_valid, box = valid_box(per_row, first, last, w)
    # Oracle: bilinear interpolation of the node grid, pixel by pixel.
    rows, cols = np.mgrid[0:h, 0:w]
    iy, ix = np.minimum(rows // step, n_rows - 2), np.minimum(cols // step, n_cols - 2)
    ty, tx = (rows - iy * step) / step, (cols - ix * step) / step

    def bilinear(d):
        return ((1 - ty) * ((1 - tx) * d[iy, ix] + tx * d[iy, ix + 1])
                + ty * ((1 - tx) * d[iy + 1, ix] + tx * d[iy + 1, ix + 1]))

    want_x, want_y = cols + bilinear(dx), rows + bilinear(dy)
    np.testing.assert_allclose(map_x, want_x, atol=1e-4)
    np.testing.assert_allclose(map_y, want_y, atol=1e-4)
    inside = (map_x >= -0.5) & (map_x <= w - 0.5) & (map_y >= -0.5) & (map_y <= h - 0.5)
    want_valid = cell_ok[iy, ix] & inside
    np.testing.assert_array_equal(valid, want_valid)
    assert n_valid == want_valid.sum()
    r, c = np.flatnonzero(want_valid.any(axis=1)), np.flatnonzero(want_valid.any(axis=0))
    np.testing.assert_array_equal(box, [r[0], r[-1] + 1, c[0], c[-1] + 1])


def test_finish_rows_divides_the_box_and_zeroes_the_rest():
    """Inside the box: divided by the gain, 0 where not valid; outside it: 0 (the image comes
    uninitialised)."""
    rng = np.random.default_rng(9)
    h, w, box = 11, 17, np.array([2, 9, 3, 14])
    for n_ch, gain in ((1, 1.7), (3, 1.7), (3, 1.0)):
        out = rng.random((h, w, n_ch)).astype(np.float32) + 1.0
        valid = rng.random((h, w)) <= 0.7
        gain = np.float32(gain)
        want = np.zeros_like(out)
        inner = (slice(box[0], box[1]), slice(box[2], box[3]))
        want[inner] = np.where(valid[inner][..., None], out[inner] / gain, 0.0)
        for r0, r1 in ((0, 4), (4, 5), (5, h)):  # in 3 bands of rows
            finish_rows(r0, r1, out, valid, box, gain)
        np.testing.assert_array_equal(out, want)


def test_restore_view_does_not_depend_on_the_thread_count():
    """The Newton chunks and the warp's rows, whichever thread runs them."""
    cfg = load_rig("paper")
    cam = cfg.rig.camera_v
    x = y = np.linspace(-1500.0, 1500.0, 151)
    z = cfg.water.h0_mm + 3.0 * np.sin(x[None, :] / 41.0) * np.cos(y[:, None] / 29.0)
    surface = Heightfield(x, y, z)
    img = np.random.default_rng(8).random((cam.height_px, cam.width_px, 3)).astype(np.float32)
    args = (img, cam, surface, cfg.water.h0_mm, cfg.water.n_water, cfg.object_z_mm)
    with _threads(1):
        want = restore_view(*args, warp_step_px=16, gain=1.5)
    got = restore_view(*args, warp_step_px=16, gain=1.5)
    assert want.counts["ok"] > 0 and got.counts == want.counts
    for name in ("image", "valid", "map_cols", "map_rows"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_detect_spots_does_not_depend_on_the_thread_count():
    """The segmented pixels' rows and the centroid chunks, whichever thread runs them."""
    rng = np.random.default_rng(9)
    yy, xx = np.mgrid[0:240, 0:320].astype(float)
    img = np.zeros(yy.shape)
    for cx, cy in rng.uniform(10, [310, 230], (150, 2)):
        img += rng.uniform(0.2, 1.0) * np.exp(-0.5 * ((xx - cx) ** 2 + (yy - cy) ** 2) / 2.3)
    img += rng.normal(0, 0.002, img.shape)
    with _threads(1):
        want = detect_spots(img)
    got = detect_spots(img)
    assert len(want) > 50
    for name in ("centres_px", "flux", "peak", "area_px", "cov_px2", "merged", "border"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
