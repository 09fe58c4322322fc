"""Fit the surface to what camera s saw: Gauss-Newton on the spots through the exact model.

The reconstruction (:mod:`restoration.surface`) integrates slopes found at reflection points
that are themselves estimated (the paper's ``q_k`` on ``z = h0``, then a fixed-point
refinement along the rays), with a quadrature rule between samples. This fit removes both
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
:func:`~restoration.fit_level.fit_level` searches it explicitly, fitting the shape with the
level held at fixed offsets (a linear constraint on the coefficients) and taking the minimum
of the residual's profile.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import solveh_banded
from scipy.sparse.linalg import spsolve
from threadpoolctl import threadpool_limits

from restoration.observations import Observations
from wai_core.heightfield import Heightfield
from wai_core.light_paths import reflect_to_diffuser
from wai_core.timings import Timings

__all__ = ["BSplineSurface", "FitResult", "Linearised", "basis_terms", "fit_surface", "hits",
           "knot_step", "linearise", "spline_through"]

Array = NDArray[np.float64]

DAMPING = 1e-5
"""Levenberg-Marquardt damping relative to the diagonal of J^T J: small, so that a step can
follow the compensating bend of a level change (larger damping leaves each probe of
:func:`~restoration.fit_level.fit_level` unconverged and biases its profile)."""
SMOOTHNESS = 1e-4
"""Weight of the second-difference penalty relative to the mean diagonal of J^T J (1e-3 kept
the fit from following sharp crests, and the rays there then pulled the level 0.15 mm off on
a nearly flat trochoid)."""
CAUCHY_SCALE = 2.385
"""Scale of :func:`~restoration.fit_level.fit_level`'s Cauchy loss in standard deviations of
the spot residual (the loss's 95 % efficiency constant for Gaussian noise)."""
_MEDIAN_NORM = 1.1774  # median norm of a 2-D Gaussian of unit variance per axis: sqrt(2 ln 2)
POLISH_MM = 0.01
"""A level search stops once its parabola's vertex lies this close to a probe, mm."""
PROBE_STEPS = 8
"""Most Gauss-Newton steps per probe of :func:`~restoration.fit_level.fit_level`."""
PROBE_TOL_MM = 1e-4
"""A probe has converged once a step changes no coefficient by more than this, mm."""
PROBE_COST_TOL = 1e-4
"""... or once a step lowers its cost by less than this fraction of it."""
MAX_PROBES = 9
"""Most probes of :func:`~restoration.fit_level.fit_level`, its start included."""
_FD_T_MM = 1e-3  # finite-difference steps of the per-dot forward model: along the ray, mm
_FD_SLOPE = 1e-6  # and in slope


def basis_terms(u: Any) -> tuple[list[Any], list[Any], list[Any]]:
    """Uniform cubic B-spline weights at fractions ``u``, with first and second derivatives in
    ``u``: three lists of four terms, each like ``u`` (any array type with arithmetic: NumPy's
    or Dr.Jit's)."""
    u2, u3 = u * u, u * u * u
    b = [(1 - u) ** 3 / 6, (3 * u3 - 6 * u2 + 4) / 6, (-3 * u3 + 3 * u2 + 3 * u + 1) / 6, u3 / 6]
    db = [-3 * (1 - u) ** 2 / 6, (9 * u2 - 12 * u) / 6, (-9 * u2 + 6 * u + 3) / 6, 3 * u2 / 6]
    d2b = [6 * (1 - u) / 6, (18 * u - 12) / 6, (-18 * u + 6) / 6, 6 * u / 6]
    return b, db, d2b


def _basis(u: Array) -> tuple[Array, Array, Array]:
    """Uniform cubic B-spline weights (N, 4) at fractions ``u`` (N,), with first and second
    derivatives in ``u``."""
    return tuple(np.stack(terms, 1) for terms in basis_terms(u))


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
    converged : bool
        Whether the last step changed no coefficient by more than the tolerance.
    timings_ms : dict
    """

    spline: BSplineSurface
    heightfield: Heightfield
    points_mm: Array
    slopes: Array
    residual_mm: Array
    rms_mm: list[float]
    iterations: int
    converged: bool
    timings_ms: dict[str, float]


def _forward(o: Array, d: Array, t: Array, gx: Array, gy: Array, z_h: float) -> Array:
    """Hit on the diffuser (K, 2), mm, of rays ``o + t d`` reflected about slopes ``gx, gy``
    (system S's path: :func:`wai_core.light_paths.reflect_to_diffuser`)."""
    n = np.stack([-gx, -gy, np.ones_like(gx)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return reflect_to_diffuser(o + t[:, None] * d, d, n, z_h)[:, :2]


def hits(spline: BSplineSurface, o: Array, d: Array, t: Array, n_iter: int = 6) -> Array:
    """Ray parameters ``t`` (K,) where rays ``o + t d`` meet the spline (Newton from ``t``)."""
    for _ in range(n_iter):
        p = o + t[:, None] * d
        z, zx, zy = spline.evaluate(p[:, 0], p[:, 1])[:3]
        t = t - (p[:, 2] - z) / (d[:, 2] - zx * d[:, 0] - zy * d[:, 1])
    return t


@dataclass(frozen=True)
class Linearised:
    """Rays reflected off a spline onto the diffuser, and how their hits move with the
    spline's coefficients (:func:`linearise`).

    Attributes
    ----------
    index : (K, 16) ndarray of int
        The flat coefficient indices each ray's hit depends on.
    spots_mm : (K, 2) ndarray
        The reflected rays' hits on the diffuser plane, mm.
    jacobian : (K, 2, 16) ndarray
        Their derivatives in those coefficients, mm per mm.
    ok : (K,) ndarray of bool
        The ray meets the spline where it is defined and reaches the diffuser.
    """

    index: NDArray[np.int64]
    spots_mm: Array
    jacobian: Array
    ok: NDArray[np.bool_]


def linearise(spline: BSplineSurface, o: Array, d: Array, t: Array, z_h: float,
              slope_offset: Array | None = None) -> Linearised:
    """System S's path through ``spline`` at the hits ``o + t d`` of rays ``o`` (K, 3) or
    (3,), ``d`` (K, 3) unit (``t`` (K,) from :func:`hits`), and its derivatives in the
    coefficients: a coefficient change ``dz, dz_x, dz_y`` at a hit moves the hit by
    ``dt = dz / (d_z - grad z . d_xy)`` along its ray, and the slopes there follow the move
    (the Hessian). ``slope_offset`` (K, 2): a microfacet's slope added to the spline's at each
    hit (a rough surface's facet), which the coefficients do not move.

    Examples
    --------
    >>> import numpy as np
    >>> flat = BSplineSurface(-50.0, -50.0, 10.0, np.full((14, 14), 100.0))
    >>> o, d = np.zeros(3), np.array([[0.1, 0.0, 1.0]]) / np.hypot(0.1, 1.0)
    >>> lin = linearise(flat, o, d, hits(flat, o, d, np.array([90.0])), 60.0)
    >>> lin.spots_mm.round(3).tolist()  # up 100 mm, 10 mm along x, down 40 mm: 4 mm more
    [[14.0, 0.0]]
    >>> float(lin.jacobian[0, 0].sum().round(6))  # the water 1 mm higher: the spot 0.2 mm on
    0.2
    """
    p = o + t[:, None] * d
    index, w, inside = spline.rows(p[:, 0], p[:, 1])
    c = spline.coeffs.ravel()[index]
    _, gx, gy, gxx, gxy, gyy = (np.sum(wi * c, axis=1) for wi in w)
    if slope_offset is not None:
        gx, gy = gx + slope_offset[:, 0], gy + slope_offset[:, 1]
    x_pred = _forward(o, d, t, gx, gy, z_h)
    ok = inside & np.isfinite(x_pred).all(axis=1)
    # The forward model's partials in (t, g_x, g_y), by finite differences per ray.
    f_t = (_forward(o, d, t + _FD_T_MM, gx, gy, z_h) - x_pred) / _FD_T_MM
    f_x = (_forward(o, d, t, gx + _FD_SLOPE, gy, z_h) - x_pred) / _FD_SLOPE
    f_y = (_forward(o, d, t, gx, gy + _FD_SLOPE, z_h) - x_pred) / _FD_SLOPE
    denom = d[:, 2] - gx * d[:, 0] - gy * d[:, 1]
    w_t = w[0] / denom[:, None]
    w_gx = w[1] + (gxx * d[:, 0] + gxy * d[:, 1])[:, None] * w_t
    w_gy = w[2] + (gxy * d[:, 0] + gyy * d[:, 1])[:, None] * w_t
    jac = (f_t[:, :, None] * w_t[:, None, :] + f_x[:, :, None] * w_gx[:, None, :]
           + f_y[:, :, None] * w_gy[:, None, :])
    return Linearised(index, x_pred, jac, ok)


# The fit's banded solves are small (~1e4 unknowns, bandwidth ~100): OpenBLAS's threads gain
# nothing there and, on a busy 2-core machine, made each solve 50x slower (10 ms -> 500 ms).
_ONE_BLAS_THREAD = threadpool_limits.wrap(limits=1, user_api="blas")


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


def spline_through(
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


@dataclass
class _Rays:
    """The dots' projector rays and their detected spots, as the fit uses them."""

    o: Array  # (K, 3) origins, mm
    d: Array  # (K, 3) unit directions
    target: Array  # (K, 2) detected spots on the diffuser plane, mm
    z_h: float  # the diffuser plane's height, mm

    @classmethod
    def of(cls, obs: Observations) -> _Rays:
        """The rays and diffuser spots the observations hold already."""
        d = obs.dirs / np.linalg.norm(obs.dirs, axis=1, keepdims=True)
        return cls(np.broadcast_to(obs.origin_mm, d.shape), d, obs.spots_mm[:, :2],
                   float(obs.z_h_mm))

    def t_at(self, z_mm: Array) -> Array:
        """Ray parameters where the rays reach heights ``z_mm`` (K,)."""
        return (z_mm - self.o[:, 2]) / self.d[:, 2]


@dataclass
class _Prediction:
    """Where the rays meet a spline and where their reflections land."""

    t: Array  # (K,) ray parameters of the hits
    points_mm: Array  # (K, 3) hits on the spline
    gx: Array  # (K,) slopes there
    gy: Array
    residual_mm: Array  # (K, 2) predicted minus detected spot on the diffuser
    rms_mm: float  # over the rays that meet the spline


def _predict(spline: BSplineSurface, rays: _Rays, t: Array) -> _Prediction:
    """The rays (Newton from ``t``) against ``spline``: hits, slopes, spot residuals."""
    t = hits(spline, rays.o, rays.d, t)
    p = rays.o + t[:, None] * rays.d
    z, gx, gy = spline.evaluate(p[:, 0], p[:, 1])[:3]
    res = _forward(rays.o, rays.d, t, gx, gy, rays.z_h) - rays.target
    ok = np.isfinite(res).all(axis=1)
    rms = float(np.sqrt(np.mean(np.sum(res[ok] ** 2, axis=1))))
    return _Prediction(t, np.column_stack([p[:, :2], z]), gx, gy, res, rms)


@dataclass
class _Fit:
    """One Gauss-Newton fit: the spline, its prediction, and how it converged."""

    spline: BSplineSurface
    prediction: _Prediction
    rms_mm: list[float]  # before the first step and after each
    iterations: int
    converged: bool  # the last step changed no coefficient by more than the tolerance


def _gauss_newton(
    spline: BSplineSurface,
    rays: _Rays,
    t: Array,
    *,
    iterations: int,
    tol_mm: float,
    smoothness: float,
    level: tuple[Array, float] | None = None,
    scale_mm: float | None = None,
) -> _Fit:
    """Damped Gauss-Newton on the spot residuals from ``spline`` (left unchanged).

    ``level = (a, value)`` holds ``a . c = value`` (``c`` the flattened coefficients) at every
    step: each step is the damped step projected onto the constraint (one more solve with the
    same factorisation, a Lagrange multiplier). ``scale_mm`` weighs each ray by the Cauchy
    loss of that scale (iteratively reweighted least squares). Stops after ``iterations``
    steps, or once a step moves no coefficient by more than ``tol_mm`` or lowers the cost by
    less than :data:`PROBE_COST_TOL` of it (converged).
    """
    spline = BSplineSurface(spline.x0_mm, spline.y0_mm, spline.step_mm, spline.coeffs.copy())
    o, d = rays.o, rays.d
    ny, nx = spline.coeffs.shape
    rtr = (_second_differences(ny, nx).T @ _second_differences(ny, nx)).tocsc()
    k = len(d)
    rows = np.repeat(np.arange(k), 16)
    pred = _predict(spline, rays, t)
    cost = _total_cost(pred, scale_mm)
    rms, done, converged = [pred.rms_mm], 0, False
    while done < int(iterations) and not converged:
        done += 1
        lin = linearise(spline, o, d, pred.t, rays.z_h)
        index, ok = lin.index, lin.ok
        res = lin.spots_mm - rays.target
        blocks = []
        for comp in (0, 1):
            vals = np.where(ok[:, None], lin.jacobian[:, comp], 0.0)
            blocks.append(sp.csr_matrix((vals.ravel(), (rows, index.ravel())),
                                        shape=(k, ny * nx)))
        jac = sp.vstack(blocks).tocsr()
        if scale_mm is not None:
            root = np.sqrt(_cauchy_weights(np.linalg.norm(np.where(ok[:, None], res, 0.0),
                                                           axis=1), scale_mm))
            res = res * root[:, None]
            jac = sp.diags(np.concatenate([root, root])) @ jac
        r = np.where(ok[:, None], res, 0.0).T.ravel()
        jtj = (jac.T @ jac).tocsc()
        scale = float(jtj.diagonal().mean())
        lhs = jtj + smoothness * scale * rtr + DAMPING * sp.diags(jtj.diagonal() + 1e-9 * scale)
        cvec = spline.coeffs.ravel()
        rhs = -(jac.T @ r) - smoothness * scale * (rtr @ cvec)
        if level is None:
            step = _solve_spd(lhs, rhs)
        else:
            a, value = level
            free, along = _solve_spd(lhs, np.column_stack([rhs, a])).T
            step = free - along * ((a @ (cvec + free) - value) / (a @ along))
        spline.coeffs = (cvec + step).reshape(ny, nx)
        pred = _predict(spline, rays, t)
        rms.append(pred.rms_mm)
        before, cost = cost, _total_cost(pred, scale_mm)
        converged = bool(np.max(np.abs(step)) < tol_mm or before - cost < PROBE_COST_TOL * cost)
    return _Fit(spline, pred, rms, done, converged)


def _cauchy_weights(r: Array, scale: float) -> Array:
    """IRLS weights of the Cauchy loss at residual norms ``r``."""
    return 1.0 / (1.0 + (r / scale) ** 2)


def _cost(r2: Array, scale: float | None) -> Array:
    """Each ray's cost from its squared residual norm ``r2``: the square itself, or the Cauchy
    loss ``s^2 log(1 + r2 / s^2)`` for a scale ``s``, mm."""
    return r2 if scale is None else scale**2 * np.log1p(r2 / scale**2)


def _total_cost(pred: _Prediction, scale: float | None) -> float:
    """The summed :func:`_cost` of the rays that meet the spline."""
    r2 = np.sum(pred.residual_mm ** 2, axis=1)
    return float(np.sum(_cost(r2[np.isfinite(r2)], scale)))


def _result(fit: _Fit, like: Heightfield, timings: Timings) -> FitResult:
    """The public result of a fit, gridded on ``like``; ``timings`` (the fit's steps) gains
    ``grid`` and ``total``, the sum of all steps."""
    with timings("grid"):
        heightfield = fit.spline.to_heightfield(like)
        pred = fit.prediction
    timings.add("total", timings.total())
    return FitResult(
        spline=fit.spline,
        heightfield=heightfield,
        points_mm=pred.points_mm,
        slopes=np.column_stack([pred.gx, pred.gy]),
        residual_mm=np.linalg.norm(pred.residual_mm, axis=1),
        rms_mm=fit.rms_mm,
        iterations=fit.iterations,
        converged=fit.converged,
        timings_ms=timings.to_dict(),
    )


def knot_step(xy: Array) -> float:
    """The samples' median nearest-neighbour spacing, mm: the default knot spacing."""
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1]))


@_ONE_BLAS_THREAD
def fit_surface(
    points_mm: Array,
    slopes: Array,
    obs: Observations,
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
    obs : Observations
        The samples' dots: their projector rays and their spots on the diffuser plane, one per
        sample (:meth:`~restoration.observations.Observations.take`).
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
    timings = Timings()
    with timings("warm_start"):
        xy = points_mm[:, :2]
        step_mm = knot_step(xy) if step_mm is None else float(step_mm)
        start = spline_through(xy, points_mm[:, 2], slopes, step_mm, smoothness)
        rays = _Rays.of(obs)
    with timings("gauss_newton"):
        fit = _gauss_newton(start, rays, rays.t_at(points_mm[:, 2]), iterations=iterations,
                            tol_mm=tol_mm, smoothness=smoothness)
    return _result(fit, like, timings)
