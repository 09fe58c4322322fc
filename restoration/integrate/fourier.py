"""Grid integrators (``"frankot_chellappa"`` and ``"dct_poisson"``): the slopes are resampled
onto a regular grid (:class:`SlopeGrid`, :func:`resample_slopes`), integrated there in the
Fourier domain (:func:`frankot_chellappa`, :func:`poisson_dct`) and the heights read back at the
samples (:func:`sample_heights`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.fft import dctn, idctn, irfft2, rfft2
from scipy.ndimage import distance_transform_edt
from scipy.spatial import Delaunay, QhullError

from restoration.integrate._common import _MAX_GRID_NODES, Array
from restoration.integrate.gridding import _scan_triangles
from restoration.integrate.lattice import check_samples, largest_grid_piece
from wai_core.errors import RestorationFailed

# Slope-grid node spacing in units of the median nearest-neighbour distance of the samples (about
# the smallest lattice spacing, across the keystone): at least two nodes per sample spacing, so
# the grid resolves the piecewise-linear slopes between samples. Measured on the tests' surfaces:
# 1.0 doubles FC's border error (0.30 vs 0.13 mm on the jittered paraboloid) and the DCT's error
# on the jittered sinusoid (0.31 vs 0.17 mm); 1/3 and 1/4 do not help consistently (better on
# one footprint, worse on another) while the cost grows as 1 / step^2.
_FOURIER_STEP = 0.5


@dataclass(frozen=True)
class SlopeGrid:
    """Slopes resampled onto a regular grid; node ``(r, c)`` sits at ``(x0 + c h, y0 + r h)``.

    Attributes
    ----------
    x0, y0 : float
        Position of node ``(0, 0)``, mm.
    step_mm : float
        Node spacing ``h``, mm.
    p, q : (ny, nx) ndarray
        ``dz/dx`` and ``dz/dy`` at the nodes, dimensionless.
    inside : (ny, nx) ndarray of bool
        Nodes inside the samples' convex hull (the others hold extrapolated slopes, see
        :func:`_extrapolate_slopes`).
    """

    x0: float
    y0: float
    step_mm: float
    p: Array
    q: Array
    inside: NDArray[np.bool_]


def _regular_axes(xy: Array, step_mm: float) -> tuple[Array, Array]:
    """Node coordinates (nx,), (ny,) in mm from the samples' minimum x and y past their maximum.

    Raises
    ------
    RestorationFailed
        When the grid would exceed :data:`_MAX_GRID_NODES` (samples spread far beyond their
        spacing).
    """
    lo = xy.min(axis=0)
    n = np.maximum(np.ceil((xy.max(axis=0) - lo) / step_mm).astype(np.int64) + 1, 2)
    if n[0] * n[1] > _MAX_GRID_NODES:
        raise RestorationFailed(
            f"integrate: samples {step_mm:.3g} mm apart span a {n[0]} x {n[1]} grid, too large"
        )
    # (Rounding the node counts up to FFT-friendly sizes would save ~1 ms but add nodes outside
    # the hull, whose extrapolated slopes cost accuracy: 0.07 -> 0.39 mm on the unjittered test
    # sinusoid; see _extrapolate_slopes.)
    return lo[0] + step_mm * np.arange(n[0]), lo[1] + step_mm * np.arange(n[1])


def _triangulate(xy: Array) -> Delaunay:
    """Delaunay triangulation of sample positions (K, 2), mm.

    Raises
    ------
    RestorationFailed
        When the samples are collinear.
    """
    try:
        return Delaunay(xy)
    except QhullError:
        raise RestorationFailed("integrate: samples are collinear (no area to grid)") from None


def _median_neighbour_distance(tri: Delaunay) -> float:
    """Median distance from each sample to its nearest other sample, mm.

    Every nearest neighbour is a Delaunay neighbour, so the triangles' edges suffice (no search
    tree); samples left out of the triangulation (repeated positions) are skipped.
    """
    s, pts = tri.simplices, tri.points
    edge = pts[s] - pts[np.roll(s, -1, axis=1)]
    length = np.hypot(edge[..., 0], edge[..., 1])  # (T, 3): corner v to corner v + 1
    nearest = np.full(pts.shape[0], np.inf)
    np.minimum.at(nearest, s.ravel(), np.minimum(length, np.roll(length, 1, axis=1)).ravel())
    return float(np.median(nearest[np.isfinite(nearest)]))


def _linear_on_grid(tri: Delaunay, values: Array, gx: Array, gy: Array) -> Array:
    """Piecewise-linear interpolation on a Delaunay triangulation of scattered samples.

    Parameters
    ----------
    tri : Delaunay
        Triangulation of the sample positions, mm.
    values : (K, C) ndarray
        Values at the samples.
    gx, gy : (nx,), (ny,) ndarray
        Regular node coordinates, mm, equally spaced along both axes.

    Returns
    -------
    (C, ny, nx) ndarray
        Interpolated values; NaN at nodes outside the convex hull.
    """
    xy = tri.points
    verts = tri.simplices
    spans = _scan_triangles(xy[verts], gx, gy)
    corner_values = values[verts].transpose(2, 1, 0)  # (C, 3, T)
    # On each triangle the interpolant is v_0 + dv/dx (x - x_0) + dv/dy (y - y_0), with the
    # derivatives from the barycentric weights' gradients (see _Spans); it is evaluated at the
    # first node of each run and stepped along the run, so each node costs one multiply-add.
    dv_dx = np.sum(spans.bx * corner_values, axis=1)  # (C, T)
    dv_dy = np.sum(spans.by * corner_values, axis=1)
    t = spans.tri
    first = verts[t, 0]
    rx = gx[spans.col] - xy[first, 0]
    ry = gy[spans.row] - xy[first, 1]
    start = corner_values[:, 0, t] + dv_dx[:, t] * rx + dv_dy[:, t] * ry  # (C, runs)
    along = dv_dx[:, t] * (gx[1] - gx[0])
    node, _, k = spans.nodes(gx.size)
    out = np.full((values.shape[1], gy.size * gx.size), np.nan)
    for c in range(values.shape[1]):  # per channel: 1-D gathers are several times faster
        out[c, node] = np.repeat(start[c], spans.count) + k * np.repeat(along[c], spans.count)
    return out.reshape(values.shape[1], gy.size, gx.size)


def _mean_hessian(xy: Array, slopes: Array) -> Array:
    """Symmetric 2 x 2 Hessian (1/mm) of the quadratic surface whose slopes fit ``slopes`` best.

    Least squares of ``slopes ~ a + H (xy - mean)``: with centred positions the constant ``a``
    is the mean slope, and ``(H_xx, H_xy, H_yy)`` solve 3 x 3 normal equations built from the
    second moments.
    """
    x, y = (xy - xy.mean(axis=0)).T
    p, q = (slopes - slopes.mean(axis=0)).T
    sxx, sxy, syy = x @ x, x @ y, y @ y
    normal = np.array([[sxx, sxy, 0.0], [sxy, sxx + syy, sxy], [0.0, sxy, syy]])
    hxx, hxy, hyy = np.linalg.lstsq(normal, [x @ p, y @ p + x @ q, y @ q], rcond=None)[0]
    return np.array([[hxx, hxy], [hxy, hyy]])


def _extrapolate_slopes(
    field: Array, inside: NDArray[np.bool_], hessian: Array, step_mm: float
) -> Array:
    """Fill the nodes outside ``inside`` (ny, nx) of a slope grid ``field`` (2, ny, nx).

    Each outside node ``x`` takes the slopes of its nearest inside node ``n`` plus
    ``hessian (x - n)``. Nearest values alone are not a gradient field (they are constant along
    lines that fan out from the hull), and their curl leaks into the solution inside the hull
    (0.8 mm on a paraboloid over a keystoned footprint); with the mean curvature added, the
    extension of a quadratic surface's slopes is that surface's exact gradient, and where the
    curvature averages out (waves) it is the plain nearest value.
    """
    _, (rows, cols) = distance_transform_edt(~inside, return_indices=True)
    r, c = np.nonzero(~inside)
    near_r, near_c = rows[r, c], cols[r, c]
    dx, dy = (c - near_c) * step_mm, (r - near_r) * step_mm  # x - n, mm
    out = field.copy()
    for k in range(2):  # the Hessian is symmetric: row k is the gradient of slope k
        out[k, r, c] = field[k, near_r, near_c] + hessian[k, 0] * dx + hessian[k, 1] * dy
    return out


def resample_slopes(xy_mm: Array, slopes: Array, step_mm: float | None = None) -> SlopeGrid:
    """Slopes at scattered samples resampled onto a regular grid covering their bounding box.

    Inside the convex hull the slopes are interpolated linearly on the Delaunay triangles of
    the samples (holes are bridged). Outside, each node takes the slopes of the nearest inside
    node, extrapolated with the mean curvature of the samples (see
    :func:`_extrapolate_slopes`): unlike zeros this adds no jump in slope along the hull, and
    planes and quadratic surfaces remain exact gradient fields over the whole grid.

    Parameters
    ----------
    xy_mm : (K, 2) ndarray
        Sample positions, mm.
    slopes : (K, 2) ndarray
        ``(dz/dx, dz/dy)`` at the samples.
    step_mm : float, optional
        Node spacing, mm; default half the median nearest-neighbour distance of the samples
        (see :data:`_FOURIER_STEP`).

    Returns
    -------
    SlopeGrid

    Raises
    ------
    RestorationFailed
        When the samples are collinear, leave no node inside their hull, or need too large a
        grid.
    """
    tri = _triangulate(xy_mm)
    if step_mm is None:
        step_mm = _FOURIER_STEP * _median_neighbour_distance(tri)
    gx, gy = _regular_axes(xy_mm, step_mm)
    field = _linear_on_grid(tri, slopes, gx, gy)
    inside = np.isfinite(field[0])
    if not inside.any():
        raise RestorationFailed("integrate: no grid node falls inside the samples' hull")
    p, q = _extrapolate_slopes(field, inside, _mean_hessian(xy_mm, slopes), step_mm)
    return SlopeGrid(float(gx[0]), float(gy[0]), float(step_mm), p, q, inside)


def sample_heights(grid: SlopeGrid, z_mm: Array, xy_mm: Array) -> Array:
    """Heights on the grid read back at scattered positions inside it.

    Each corner ``c`` of the cell holding a point ``x`` predicts ``z_c + g_c . (x - c) / 2``
    (its half-step tangent plane), blended with bilinear weights. Since the bilinear weights
    reproduce ``x`` from the corners, this equals the blend of trapezoid-rule steps
    ``z_c + (g_c + g(x)) . (x - c) / 2``, exact for quadratic surfaces. Plain bilinear reading
    errs by up to ``h^2 |z''| / 8`` (a few µm on the tests' paraboloid): small next to the
    resampling's errors, but the blend keeps quadratics exact end to end.

    Parameters
    ----------
    grid : SlopeGrid
        The grid and its slopes.
    z_mm : (ny, nx) ndarray
        Heights at the nodes, mm.
    xy_mm : (K, 2) ndarray
        Positions, mm, within the grid's extent.

    Returns
    -------
    (K,) ndarray
        Heights, mm.
    """
    ny, nx = z_mm.shape
    u = (xy_mm - [grid.x0, grid.y0]) / grid.step_mm  # grid units
    cell = np.clip(np.floor(u).astype(np.int64), 0, [nx - 2, ny - 2])
    out = np.zeros(xy_mm.shape[0])
    for corner in ((0, 0), (1, 0), (0, 1), (1, 1)):  # vectorised over the points
        c, r = (cell + corner).T
        du, dv = (u - cell - corner).T  # x - corner, grid units
        weight = (1.0 - np.abs(du)) * (1.0 - np.abs(dv))
        tangent = 0.5 * grid.step_mm * (grid.p[r, c] * du + grid.q[r, c] * dv)
        out += weight * (z_mm[r, c] + tangent)
    return out


def poisson_dct(p: Array, q: Array, step_mm: float) -> Array:
    """Least-squares heights of a gridded slope field: Neumann Poisson equation solved by DCT.

    Minimises the squared misfit of every grid edge to its trapezoid-rule rise,
    ``z[r, c+1] - z[r, c] = h (p[r, c] + p[r, c+1]) / 2`` and likewise along y. The normal
    equations are ``L z = b``: ``L`` is the grid's 5-point graph Laplacian with free (Neumann)
    borders and ``b`` minus the divergence of the rises. The DCT-II diagonalises ``L`` exactly,
    with eigenvalues ``(2 - 2 cos(pi k / nx)) + (2 - 2 cos(pi l / ny))``, so the solve is two
    transforms and a division (Simchony, Chellappa & Shao 1990). Exact for quadratic surfaces
    sampled without error.

    Parameters
    ----------
    p, q : (ny, nx) ndarray
        ``dz/dx`` and ``dz/dy`` at the nodes, dimensionless.
    step_mm : float
        Node spacing, mm.

    Returns
    -------
    (ny, nx) ndarray
        Heights, mm, zero mean.
    """
    ny, nx = p.shape
    rise_x = 0.5 * step_mm * (p[:, 1:] + p[:, :-1])
    rise_y = 0.5 * step_mm * (q[1:] + q[:-1])
    b = np.zeros_like(p)
    b[:, 1:] += rise_x
    b[:, :-1] -= rise_x
    b[1:] += rise_y
    b[:-1] -= rise_y
    eig = (2.0 - 2.0 * np.cos(np.pi * np.arange(ny) / ny))[:, None] + (
        2.0 - 2.0 * np.cos(np.pi * np.arange(nx) / nx)
    )
    eig[0, 0] = 1.0  # the constant mode: its coefficient (the mean) is set to zero below
    coef = dctn(b, type=2, norm="ortho") / eig
    coef[0, 0] = 0.0
    return idctn(coef, type=2, norm="ortho")


def _mirrored(a: Array, sign_x: float, sign_y: float) -> Array:
    """``a`` (ny, nx) extended to (2 ny, 2 nx) by half-sample mirrors about its right and top
    borders, the copies mirrored across x times ``sign_x`` and those across y times ``sign_y``."""
    ny, nx = a.shape
    out = np.empty((2 * ny, 2 * nx))
    out[:ny, :nx] = a
    out[:ny, nx:] = sign_x * a[:, ::-1]
    out[ny:] = sign_y * out[ny - 1 :: -1]
    return out


def frankot_chellappa(p: Array, q: Array, step_mm: float) -> Array:
    """Heights of a gridded slope field by projection onto integrable Fourier modes.

    Frankot & Chellappa (1988): each Fourier mode of the height, ``Z exp(i (u x + v y))``, has
    slopes ``(i u Z, i v Z)``; the ``Z`` nearest in least squares to the slopes' transforms
    ``P, Q`` is ``Z = -i (u P + v Q) / (u^2 + v^2)``.

    The Fourier series is periodic, and the field is not. Its mean slope (a tilt) is removed
    first and added back as a plane, so planes are exact. The rest is extended to twice the
    size by mirroring the heights evenly about each border (half-sample mirrors, the DCT-II's
    symmetry), which makes ``p`` odd in x and even in y (``q`` the other way round): the
    extended surface is periodic and continuous, so the wrap adds no height step (plain
    periodic FC would spread one over the whole grid). What remains is a kink in the extended
    surface wherever ``p`` (or ``q``) is not zero at the left and right (bottom and top)
    borders; its sampled spectrum aliases, which costs an error near the borders of first
    order in the node spacing (0.1-0.35 mm on the tests' paraboloid, whose border slopes reach
    0.4). Modes whose even extension is smooth (DCT-II modes) are recovered exactly.

    Parameters
    ----------
    p, q : (ny, nx) ndarray
        ``dz/dx`` and ``dz/dy`` at the nodes, dimensionless.
    step_mm : float
        Node spacing, mm.

    Returns
    -------
    (ny, nx) ndarray
        Heights, mm, zero mean.
    """
    ny, nx = p.shape
    tilt_x, tilt_y = float(p.mean()), float(q.mean())
    p0, q0 = p - tilt_x, q - tilt_y
    u = 2.0 * np.pi * np.fft.rfftfreq(2 * nx, d=step_mm)  # rad/mm, along x (last axis)
    v = 2.0 * np.pi * np.fft.fftfreq(2 * ny, d=step_mm)[:, None]
    norm = u**2 + v**2
    norm[0, 0] = 1.0  # the mean height, unknown from slopes: set to zero below
    spectrum = rfft2(_mirrored(p0, -1.0, 1.0))
    spectrum *= u
    spectrum += v * rfft2(_mirrored(q0, 1.0, -1.0))
    spectrum *= -1j / norm
    spectrum[0, 0] = 0.0
    z = irfft2(spectrum, s=(2 * ny, 2 * nx))[:ny, :nx]
    plane = tilt_x * step_mm * np.arange(nx) + tilt_y * step_mm * np.arange(ny)[:, None]
    return z + plane - plane.mean()


def _integrate_on_grid(
    ij: ArrayLike,
    xy_mm: ArrayLike,
    slopes: ArrayLike,
    solve: Callable[[Array, Array, float], Array],
) -> Array:
    """Heights (K,) mm: the largest connected piece's slopes resampled onto a grid (see
    :func:`resample_slopes`), integrated there by ``solve(p, q, step_mm) -> z``, read back at
    the samples (see :func:`sample_heights`); zero mean, NaN off the piece."""
    ij_a, xy_all, g_all = check_samples(ij, xy_mm, slopes)
    keep = largest_grid_piece(ij_a)
    xy, g = xy_all[keep], g_all[keep]
    grid = resample_slopes(xy, g)
    h = sample_heights(grid, solve(grid.p, grid.q, grid.step_mm), xy)
    heights = np.full(ij_a.shape[0], np.nan)
    heights[keep] = h - h.mean()
    return heights


def integrate_frankot_chellappa(
    ij: ArrayLike, xy_mm: ArrayLike, slopes: ArrayLike, weight_xy_mm: ArrayLike | None = None
) -> Array:
    """Frankot-Chellappa on slopes resampled to a regular grid (see :func:`frankot_chellappa`).

    Parameters and return as :func:`integrate_paper`; ``weight_xy_mm`` is unused (every grid
    node weighs the same). Samples outside the largest 4-connected piece of the ``(i, j)`` grid
    are NaN, as for the other integrators, although the grid could bridge the gap.

    Raises
    ------
    WaiInputError, RestorationFailed
        As :func:`check_samples` and :func:`largest_grid_piece`; RestorationFailed when the
        samples are collinear (see :func:`resample_slopes`).
    """
    return _integrate_on_grid(ij, xy_mm, slopes, frankot_chellappa)


def integrate_dct_poisson(
    ij: ArrayLike, xy_mm: ArrayLike, slopes: ArrayLike, weight_xy_mm: ArrayLike | None = None
) -> Array:
    """Least squares on slopes resampled to a regular grid, by DCT (see :func:`poisson_dct`).

    Parameters, return and errors as :func:`integrate_frankot_chellappa`.
    """
    return _integrate_on_grid(ij, xy_mm, slopes, poisson_dct)
