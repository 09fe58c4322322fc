"""Fit the surface to what camera s saw: Gauss-Newton on the spots through the exact model.

The reconstruction (:mod:`restoration.surface`) integrates slopes found at reflection points
that are themselves estimated (the paper's ``q_k`` on ``z = h0``, then a fixed-point
refinement along the rays), with the trapezoid rule between samples. This fit removes both
approximations instead of correcting them: the surface is a smooth cubic B-spline
``z(x, y) = sum_j c_j B_j(x, y)`` whose coefficients (absolute heights, so the level too) are
adjusted until every dot's projector ray, intersected with the spline and reflected about its
exact normal, lands on the diffuser where camera s saw the dot's spot:

    minimise  sum_k |X_k(c) - s_k|^2  +  lambda |L c|^2

``X_k`` is the reflected ray's hit on the diffuser plane (mm), ``s_k`` the detected spot
back-projected onto it, ``L`` second differences of the coefficients (a weak smoothness that
only matters where no dot constrains a coefficient). Each Gauss-Newton step linearises ``X_k``
in the height and slopes at the ray's hit point, including the hit's own move along the ray
(``dt = dz / (d_z - grad z . d_xy)``) and the slope change that move brings (the Hessian):
the Jacobian is sparse (16 coefficients per dot) and the normal equations are solved directly.
Levenberg-Marquardt damping keeps a step from growing where the fit is flat.

The level is the fit's nearly flat direction (the depth-normal ambiguity: raise the surface,
re-bend it, and every ray lands within microns of the same spot), so no damped step finds it;
:func:`fit_level` searches it explicitly, fitting the shape at fixed level offsets and taking
the minimum of the residual's profile.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import solveh_banded
from scipy.sparse.linalg import spsolve

from restoration.anchor import N_SETS, anchor_sigma_mm, parabola_vertex
from restoration.normals import projector_rays, spots_on_diffuser
from wai_core.geometry import PinholeCamera
from wai_core.heightfield import Heightfield

__all__ = ["BSplineSurface", "FitResult", "LevelFit", "fit_level", "fit_surface"]

Array = NDArray[np.float64]

DAMPING = 1e-5
"""Levenberg-Marquardt damping relative to the diagonal of J^T J: small, so that a step can
follow the compensating bend of a level change (larger damping leaves each probe of
:func:`fit_level` unconverged and biases its profile)."""
SMOOTHNESS = 1e-3
"""Weight of the second-difference penalty relative to the mean diagonal of J^T J."""
POLISH_MM = 0.01
"""A level search stops polishing once its minimum moves by less than this, mm."""
POLISH_STEPS = 2
"""Most polishing fits after the first fit at the profile's minimum."""
_FD_T_MM = 1e-3  # finite-difference steps of the per-dot forward model: along the ray, mm
_FD_SLOPE = 1e-6  # and in slope


def _basis(u: Array) -> tuple[Array, Array, Array]:
    """Uniform cubic B-spline weights (N, 4) at fractions ``u`` (N,), with first and second
    derivatives in ``u``."""
    u2, u3 = u * u, u * u * u
    b = np.stack([(1 - u) ** 3, 3 * u3 - 6 * u2 + 4, -3 * u3 + 3 * u2 + 3 * u + 1, u3], 1) / 6
    db = np.stack([-3 * (1 - u) ** 2, 9 * u2 - 12 * u, -9 * u2 + 6 * u + 3, 3 * u2], 1) / 6
    d2b = np.stack([6 * (1 - u), 18 * u - 12, -18 * u + 6, 6 * u], 1) / 6
    return b, db, d2b


@dataclass
class BSplineSurface:
    """A uniform bicubic B-spline surface ``z(x, y)``, mm, over a rectangle.

    Attributes
    ----------
    x0_mm, y0_mm : float
        Position of coefficient (0, 0)'s knot cell corner, mm.
    step_mm : float
        Knot spacing, mm.
    coeffs : (ny, nx) ndarray
        Coefficients, mm (absolute heights).
    """

    x0_mm: float
    y0_mm: float
    step_mm: float
    coeffs: Array

    @classmethod
    def covering(cls, xy_mm: Array, step_mm: float, level_mm: float) -> BSplineSurface:
        """A flat spline at ``level_mm`` whose valid region covers the points ``xy_mm``."""
        lo = xy_mm.min(axis=0) - step_mm
        hi = xy_mm.max(axis=0) + step_mm
        n = np.ceil((hi - lo) / step_mm).astype(int) + 3
        return cls(float(lo[0] - step_mm), float(lo[1] - step_mm), float(step_mm),
                   np.full((n[1], n[0]), float(level_mm)))

    def _cells(self, x: Array, y: Array) -> tuple[NDArray, NDArray, Array, Array, NDArray]:
        gx = (np.asarray(x, float) - self.x0_mm) / self.step_mm
        gy = (np.asarray(y, float) - self.y0_mm) / self.step_mm
        ny, nx = self.coeffs.shape
        finite = np.isfinite(gx) & np.isfinite(gy)  # a ray that missed: outside, no warning
        gx, gy = np.where(finite, gx, -1.0), np.where(finite, gy, -1.0)
        ix, iy = np.floor(gx).astype(int), np.floor(gy).astype(int)
        inside = finite & (ix >= 0) & (iy >= 0) & (ix <= nx - 4) & (iy <= ny - 4)
        ix, iy = np.clip(ix, 0, nx - 4), np.clip(iy, 0, ny - 4)
        return ix, iy, gx - ix, gy - iy, inside

    def rows(self, x: Array, y: Array) -> tuple[NDArray, list[Array], NDArray]:
        """For points (N,): flat coefficient indices (N, 16) and basis weights (N, 16) of
        ``z``, ``z_x``, ``z_y``, ``z_xx``, ``z_xy``, ``z_yy`` (per mm), and which points lie
        where the spline is defined."""
        ix, iy, u, v, inside = self._cells(x, y)
        bu, dbu, d2bu = _basis(u)
        bv, dbv, d2bv = _basis(v)
        h = self.step_mm
        nx = self.coeffs.shape[1]
        k = np.arange(4)
        index = ((iy[:, None] + k)[:, :, None] * nx + (ix[:, None] + k)[:, None, :]).reshape(
            -1, 16
        )

        def outer(a: Array, b: Array) -> Array:  # rows (y) x columns (x)
            return (a[:, :, None] * b[:, None, :]).reshape(-1, 16)

        weights = [
            outer(bv, bu), outer(bv, dbu) / h, outer(dbv, bu) / h,
            outer(bv, d2bu) / h**2, outer(dbv, dbu) / h**2, outer(d2bv, bu) / h**2,
        ]
        return index, weights, inside

    def evaluate(self, x: Array, y: Array) -> tuple[Array, ...]:
        """``z, z_x, z_y, z_xx, z_xy, z_yy`` at points (N,); NaN outside."""
        index, weights, inside = self.rows(x, y)
        c = self.coeffs.ravel()[index]
        out = tuple(np.where(inside, np.sum(w * c, axis=1), np.nan) for w in weights)
        return out

    def to_heightfield(self, like: Heightfield) -> Heightfield:
        """The spline on the nodes of ``like`` where ``like`` is known (NaN elsewhere)."""
        xx, yy = np.meshgrid(like.x, like.y)
        z = self.evaluate(xx.ravel(), yy.ravel())[0].reshape(xx.shape)
        return Heightfield(like.x, like.y, np.where(np.isfinite(like.z), z, np.nan))


@dataclass
class FitResult:
    """The fitted surface and how the fit went.

    Attributes
    ----------
    spline : BSplineSurface
    heightfield : Heightfield
        The spline on the reconstruction's grid and support, mm.
    points_mm : (K, 3) ndarray
        Where each dot's ray meets the fitted surface, mm.
    slopes : (K, 2) ndarray
        The fitted surface's slopes there.
    residual_mm : (K,) ndarray
        Predicted minus detected spot on the diffuser, mm (NaN where a ray misses).
    rms_mm : list of float
        RMS residual before the fit and after each iteration, mm.
    iterations : int
    timings_ms : dict
    """

    spline: BSplineSurface
    heightfield: Heightfield
    points_mm: Array
    slopes: Array
    residual_mm: Array
    rms_mm: list[float]
    iterations: int
    timings_ms: dict[str, float]


def _forward(o: Array, d: Array, t: Array, gx: Array, gy: Array, z_h: float) -> Array:
    """Hit on the diffuser (K, 2), mm, of rays ``o + t d`` reflected about slopes ``gx, gy``."""
    p = o + t[:, None] * d
    n = np.stack([-gx, -gy, np.ones_like(gx)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    r = d - 2.0 * np.sum(d * n, axis=1, keepdims=True) * n
    s = (z_h - p[:, 2]) / r[:, 2]
    return p[:, :2] + s[:, None] * r[:, :2]


def _hits(spline: BSplineSurface, o: Array, d: Array, t: Array, n_iter: int = 6) -> Array:
    """Ray parameters ``t`` (K,) where rays ``o + t d`` meet the spline (Newton from ``t``)."""
    for _ in range(n_iter):
        p = o + t[:, None] * d
        z, zx, zy = spline.evaluate(p[:, 0], p[:, 1])[:3]
        t = t - (p[:, 2] - z) / (d[:, 2] - zx * d[:, 0] - zy * d[:, 1])
    return t


def _solve_spd(lhs: sp.spmatrix, rhs: Array) -> Array:
    """Solve a symmetric positive definite banded system: the coefficients couple only within
    a 4 x 4 support, so in grid order the matrix is a band of ~3 rows of the grid, and a banded
    Cholesky is several times faster than a general sparse LU."""
    coo = lhs.tocoo()
    upper = coo.col >= coo.row
    rows, cols, vals = coo.row[upper], coo.col[upper], coo.data[upper]
    width = int((cols - rows).max()) if rows.size else 0
    band = np.zeros((width + 1, lhs.shape[0]))
    np.add.at(band, (width + rows - cols, cols), vals)
    try:
        return solveh_banded(band, rhs, check_finite=False)
    except np.linalg.LinAlgError:  # not positive definite (a degenerate fit): general solver
        return spsolve(lhs.tocsc(), rhs)


def _second_differences(ny: int, nx: int) -> sp.csr_matrix:
    """Rows of second differences of a (ny, nx) coefficient grid along x and along y."""
    def along(n: int) -> sp.csr_matrix:
        return sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n))

    return sp.vstack([
        sp.kron(sp.eye(ny), along(nx)), sp.kron(along(ny), sp.eye(nx)),
    ]).tocsr()


def _initial_spline(
    xy: Array, z: Array, slopes: Array, step_mm: float, lam: float
) -> BSplineSurface:
    """Least-squares spline through heights and slopes at the samples (the warm start)."""
    spline = BSplineSurface.covering(xy, step_mm, float(np.mean(z)))
    ny, nx = spline.coeffs.shape
    index, w, _ = spline.rows(xy[:, 0], xy[:, 1])
    k = len(xy)
    rows = np.repeat(np.arange(k), 16)
    scale = step_mm  # slopes in mm per step, so all rows weigh alike
    blocks = [
        sp.csr_matrix((w[i].ravel() * (scale if i else 1.0), (rows, index.ravel())),
                      shape=(k, ny * nx))
        for i in range(3)
    ]
    a = sp.vstack(blocks).tocsr()
    b = np.concatenate([z, slopes[:, 0] * scale, slopes[:, 1] * scale])
    reg = _second_differences(ny, nx)
    ata = (a.T @ a).tocsc()
    mu = lam * float(ata.diagonal().mean())
    lhs = ata + mu * (reg.T @ reg) + 1e-9 * mu * sp.eye(ny * nx)
    spline.coeffs = _solve_spd(lhs, a.T @ b).reshape(ny, nx)
    return spline


def fit_surface(
    points_mm: Array,
    slopes: Array,
    panel_px: Array,
    spot_px: Array,
    projector: PinholeCamera,
    camera_s: PinholeCamera,
    z_h_mm: float,
    like: Heightfield,
    *,
    step_mm: float | None = None,
    iterations: int = 4,
    tol_mm: float = 1e-4,
    smoothness: float = SMOOTHNESS,
) -> FitResult:
    """Fit a B-spline surface to the detected spots through the exact reflection model.

    Parameters
    ----------
    points_mm : (K, 3) ndarray
        The reconstruction's samples (reflection points and heights, mm): the warm start.
    slopes : (K, 2) ndarray
        Their slopes.
    panel_px, spot_px : (K, 2) ndarray
        Each dot's projector panel position and detected spot in camera s, px.
    projector, camera_s : PinholeCamera
    z_h_mm : float
        Height of the diffuser plane, mm.
    like : Heightfield
        The reconstruction's grid: the fitted surface is returned on its nodes and support.
    step_mm : float, optional
        Knot spacing (default: the samples' median neighbour spacing).
    iterations : int
        Most Gauss-Newton steps.
    tol_mm : float
        Stop once a step changes no coefficient by more than this, mm.
    smoothness : float
        Weight of the second-difference penalty (see the module notes).

    Returns
    -------
    FitResult
    """
    from scipy.spatial import cKDTree

    t_start = time.perf_counter()
    xy = points_mm[:, :2]
    if step_mm is None:
        dist = cKDTree(xy).query(xy, k=2)[0][:, 1]
        step_mm = float(np.median(dist))
    spline = _initial_spline(xy, points_mm[:, 2], slopes, step_mm, smoothness)
    o, d = projector_rays(panel_px, projector)
    o = np.broadcast_to(o, d.shape)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    target = spots_on_diffuser(spot_px, camera_s, z_h_mm)[:, :2]
    t = (points_mm[:, 2] - o[:, 2]) / d[:, 2]
    ny, nx = spline.coeffs.shape
    reg = _second_differences(ny, nx)
    rtr = (reg.T @ reg).tocsc()
    k = len(xy)
    rows = np.repeat(np.arange(k), 16)
    rms, done, damping = [], 0, DAMPING
    t0 = time.perf_counter()
    while done < int(iterations):
        done += 1
        t = _hits(spline, o, d, t)
        p = o + t[:, None] * d
        index, w, inside = spline.rows(p[:, 0], p[:, 1])
        c = spline.coeffs.ravel()[index]
        z, gx, gy, gxx, gxy, gyy = (np.sum(wi * c, axis=1) for wi in w)
        x_pred = _forward(o, d, t, gx, gy, z_h_mm)
        res = x_pred - target
        ok = inside & np.isfinite(res).all(axis=1)
        if not rms:
            rms.append(float(np.sqrt(np.mean(np.sum(res[ok] ** 2, axis=1)))))
        # The forward model's partials in (t, g_x, g_y), by finite differences per dot.
        f_t = (_forward(o, d, t + _FD_T_MM, gx, gy, z_h_mm) - x_pred) / _FD_T_MM
        f_x = (_forward(o, d, t, gx + _FD_SLOPE, gy, z_h_mm) - x_pred) / _FD_SLOPE
        f_y = (_forward(o, d, t, gx, gy + _FD_SLOPE, z_h_mm) - x_pred) / _FD_SLOPE
        # A coefficient change dz, dz_x, dz_y at the hit moves the hit by dt along the ray,
        # and the slopes there follow the move (Hessian).
        denom = d[:, 2] - gx * d[:, 0] - gy * d[:, 1]
        w_t = w[0] / denom[:, None]
        w_gx = w[1] + (gxx * d[:, 0] + gxy * d[:, 1])[:, None] * w_t
        w_gy = w[2] + (gxy * d[:, 0] + gyy * d[:, 1])[:, None] * w_t
        blocks = []
        for comp in (0, 1):
            vals = (f_t[:, comp, None] * w_t + f_x[:, comp, None] * w_gx
                    + f_y[:, comp, None] * w_gy)
            vals[~ok] = 0.0
            blocks.append(sp.csr_matrix((vals.ravel(), (rows, index.ravel())),
                                        shape=(k, ny * nx)))
        jac = sp.vstack(blocks).tocsr()
        r = np.where(ok[:, None], res, 0.0).T.ravel()
        jtj = (jac.T @ jac).tocsc()
        scale = float(jtj.diagonal().mean())
        lhs = jtj + smoothness * scale * rtr + damping * sp.diags(jtj.diagonal() + 1e-9 * scale)
        cvec = spline.coeffs.ravel()
        step = _solve_spd(lhs, -(jac.T @ r) - smoothness * scale * (rtr @ cvec))
        spline.coeffs = (cvec + step).reshape(ny, nx)
        last = _predict(spline, o, d, t, target, z_h_mm)
        rms.append(last.rms_mm)
        if np.max(np.abs(step)) < tol_mm:
            break
    if done == 0:  # no iteration asked: the warm start as it is
        last = _predict(spline, o, d, t, target, z_h_mm)
    p, gx, gy = last.points_mm, last.gx, last.gy
    residual = np.linalg.norm(last.residual_mm, axis=1)
    t1 = time.perf_counter()
    heightfield = spline.to_heightfield(like)
    t2 = time.perf_counter()
    return FitResult(
        spline=spline,
        heightfield=heightfield,
        points_mm=p,
        slopes=np.column_stack([gx, gy]),
        residual_mm=residual,
        rms_mm=rms,
        iterations=done,
        timings_ms={"warm_start": 1e3 * (t0 - t_start), "gauss_newton": 1e3 * (t1 - t0),
                    "grid": 1e3 * (t2 - t1), "total": 1e3 * (t2 - t_start)},
    )


@dataclass
class _Prediction:
    """Where the rays meet a spline and where their reflections land."""

    points_mm: Array  # (K, 3) hits on the spline
    gx: Array  # (K,) slopes there
    gy: Array
    residual_mm: Array  # (K, 2) predicted minus detected spot on the diffuser
    rms_mm: float  # over the rays that meet the spline


def _predict(
    spline: BSplineSurface, o: Array, d: Array, t: Array, target: Array, z_h: float
) -> _Prediction:
    """Rays ``o + t d`` (Newton from ``t``) against ``spline``: hits, slopes, spot residuals."""
    t = _hits(spline, o, d, t)
    p = o + t[:, None] * d
    z, gx, gy = spline.evaluate(p[:, 0], p[:, 1])[:3]
    res = _forward(o, d, t, gx, gy, z_h) - target
    ok = np.isfinite(res).all(axis=1)
    rms = float(np.sqrt(np.mean(np.sum(res[ok] ** 2, axis=1))))
    return _Prediction(np.column_stack([p[:, :2], z]), gx, gy, res, rms)


@dataclass
class LevelFit:
    """:func:`fit_level`'s result: the fit at the chosen level and the level's profile.

    Attributes
    ----------
    fit : FitResult
        The fit at the chosen level.
    offsets_mm : (P,) ndarray
        The probes' levels against the first fit's (per ray), mm.
    sum_squares_mm2 : (P,) ndarray
        Each probe's sum of squared spot residuals over the rays every probe keeps, mm^2.
    offset_mm : float
        The chosen level (the profile's minimum) against the first fit's, mm.
    sigma_mm : float
        The minimum's standard error, mm, from the spread of interleaved subsets' own minima
        (noise only: the remaining error can be several times larger, and a nearly flat
        surface's profile can mislead it; docs/results.md).
    """

    fit: FitResult
    offsets_mm: Array
    sum_squares_mm2: Array
    offset_mm: float
    sigma_mm: float


def _shifted(fit: FitResult, dz_mm: float, fallback: tuple[Array, Array]) -> tuple[Array, Array]:
    """A fit's samples raised by ``dz_mm``: the warm start of the next probe (a ray that
    missed the fitted spline keeps the ``fallback`` sample and slopes)."""
    hit = np.isfinite(fit.points_mm).all(axis=1) & np.isfinite(fit.slopes).all(axis=1)
    p = np.where(hit[:, None], fit.points_mm, fallback[0])
    p[:, 2] += np.where(hit, dz_mm, 0.0)
    return p, np.where(hit[:, None], fit.slopes, fallback[1])


def fit_level(
    points_mm: Array,
    slopes: Array,
    panel_px: Array,
    spot_px: Array,
    projector: PinholeCamera,
    camera_s: PinholeCamera,
    z_h_mm: float,
    like: Heightfield,
    *,
    probe_mm: float = 0.15,
    iterations: int = 3,
    max_probes: int = 7,
) -> LevelFit:
    """:func:`fit_surface` with the level found by a search along the fit's flat direction.

    Raising the surface and re-bending it sends every ray to nearly the same spot (the
    depth-normal ambiguity): the spot residual changes by microns per 0.1 mm of level, far
    less than Gauss-Newton's damping lets one step move along it, so the fit keeps the level
    it starts from. This search fits the shape at fixed level offsets (the probes, each warm
    started from the last), takes the minimum of the parabola through their sums of squared
    residuals (the profile), and fits there. With the renders' exact spots the profile's
    minimum is the true level within 0.01 mm where the integrability level is off by 0.1-0.3
    mm (docs/results.md).

    Parameters
    ----------
    points_mm, slopes, panel_px, spot_px, projector, camera_s, z_h_mm, like
        As :func:`fit_surface`.
    probe_mm : float
        Spacing of the first three probes around the warm start's level, mm.
    iterations : int
        Gauss-Newton steps per probe and for the final fit.
    max_probes : int
        Most probes; the search walks on while the minimum lies outside the probed range.

    Returns
    -------
    LevelFit
    """
    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    args = (panel_px, spot_px, projector, camera_s, z_h_mm, like)
    # One knot layout for every probe, or their residuals would not compare.
    step_mm = float(np.median(cKDTree(points_mm[:, :2]).query(points_mm[:, :2], k=2)[0][:, 1]))

    def probe(start: FitResult | None, dz_mm: float) -> FitResult:
        p, g = (points_mm, slopes) if start is None else _shifted(start, dz_mm,
                                                                  (points_mm, slopes))
        return fit_surface(p, g, *args, step_mm=step_mm, iterations=iterations)

    base = probe(None, 0.0)

    def level(fit: FitResult) -> float:
        # A probe's actual level against the base's, per ray: Gauss-Newton moves it a little
        # from the offset it started at, and the profile must be read at the actual one.
        return float(np.nanmean(fit.points_mm[:, 2] - base.points_mm[:, 2]))

    fits = {0.0: base}
    for off in (-probe_mm, probe_mm):
        fit = probe(base, off)
        fits[level(fit)] = fit
    while True:
        offsets, ss, _ = _profile(fits)
        vertex = parabola_vertex(offsets, ss)
        if offsets[0] <= vertex <= offsets[-1] or len(fits) >= max_probes:
            break
        # Walk downhill: one probe a step beyond the lowest end.
        end = offsets[int(np.argmin(ss))]
        step = probe_mm if end == offsets[-1] else -probe_mm
        fit = probe(fits[end], step)
        fits[level(fit)] = fit
    if not np.isfinite(vertex):
        vertex = float(offsets[int(np.argmin(ss))])
    vertex = float(np.clip(vertex, offsets[0], offsets[-1]))
    # Polish: fit at the minimum, then take the minimum of the three probes nearest to it;
    # fit again where it moved.
    for polish in range(POLISH_STEPS + 1):
        nearest = min(fits, key=lambda o: abs(o - vertex))
        final = probe(fits[nearest], vertex - nearest)
        vertex = level(final)
        fits[vertex] = final
        near = dict(sorted(fits.items(), key=lambda kv: abs(kv[0] - vertex))[:3])
        x_near, ss_near, _ = _profile(near)
        moved = parabola_vertex(x_near, ss_near)
        if polish == POLISH_STEPS or not abs(moved - vertex) >= POLISH_MM:
            break
        vertex = float(np.clip(moved, offsets[0], offsets[-1]))
    sigma = _profile_sigma(fits)
    final.timings_ms["total"] = 1e3 * (time.perf_counter() - t0)
    offsets, ss, _ = _profile(fits)
    return LevelFit(final, offsets, ss, vertex, sigma)


def _profile(fits: dict[float, FitResult]) -> tuple[Array, Array, int]:
    """Probe levels (sorted, mm), their sums of squared spot residuals over the rays all of
    them keep (mm^2), and how many rays that is."""
    offsets = np.array(sorted(fits))
    residuals = np.stack([fits[o].residual_mm for o in offsets])
    common = np.isfinite(residuals).all(axis=0)
    return offsets, np.sum(residuals[:, common] ** 2, axis=1), int(common.sum())


def _profile_sigma(fits: dict[float, FitResult]) -> float:
    """Standard error of the profile's minimum, mm: :func:`restoration.anchor.anchor_sigma_mm`
    on the sums of squared residuals of interleaved subsets of the rays (inf when a subset
    finds no minimum within the probed span of the probes)."""
    offsets, _, _ = _profile(fits)
    residuals = np.stack([fits[o].residual_mm for o in offsets])
    common = np.isfinite(residuals).all(axis=0)
    sets = np.arange(residuals.shape[1]) % N_SETS
    set_ss = np.stack([np.sum(residuals[:, common & (sets == k)] ** 2, axis=1)
                       for k in range(N_SETS)], axis=1)
    return anchor_sigma_mm(offsets, set_ss, float(np.ptp(offsets)))
