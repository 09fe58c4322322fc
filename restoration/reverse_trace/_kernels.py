"""Compiled (numba) kernels of the inverse solve: the Newton iteration of
:mod:`restoration.reverse_trace.inverse`, one target at a time.

Every target's iteration is independent, so the solver is a loop over targets with the whole
Newton iteration inside (no per-iteration array passes: ~10x fewer memory sweeps than the
vectorised form), in chunks that the restoration's threads share
(:func:`wai_core.parallel.run_chunks`). The per-target helpers are inlined into the loop:
called as separate compiled functions, several times a target with many array arguments,
they cost more than their arithmetic. No fast-math and no fused multiply-adds, so results do
not depend on the compiler's choices; the refraction's Jacobian is carried along its residual
(forward mode). ``error_model="numpy"``: a singular Jacobian gives inf/NaN, as in NumPy, not
an exception.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from wai_core.optics import RayStatus
from wai_core.port import port_ray

_OK = int(RayStatus.OK)
_MISSED_SURFACE = int(RayStatus.MISSED_SURFACE)
_TIR = int(RayStatus.TIR)
_MISSED_OBJECT = int(RayStatus.MISSED_OBJECT)
_NOT_CONVERGED = int(RayStatus.NOT_CONVERGED)

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(inline="always", **_JIT)
def _along(c, p, u):
    """The cubic in x of power ``p`` of y of a cell's 16 coefficients ``c`` (index ``4 a +
    p`` for power ``a`` of x): value, first and second derivative at ``u`` mm from the cell's
    corner."""
    c0, c1, c2, c3 = c[p], c[4 + p], c[8 + p], c[12 + p]
    return (c0 + u * (c1 + u * (c2 + u * c3)), c1 + u * (2.0 * c2 + 3.0 * u * c3),
            2.0 * c2 + 6.0 * u * c3)


@njit(inline="always", **_JIT)
def _cell_of(g, x):
    """``searchsorted(g[1:-1], x)`` (side left) for ``g[0] <= x <= g[-1]``: the cell of the
    grid lines ``g`` (increasing) that holds ``x``. Guessed as if the lines were evenly
    spaced, then moved until it satisfies the definition (for any spacing): no
    unpredictable branches of a bisection on the near-uniform grids of a surface."""
    last = g.size - 2
    i = int((x - g[0]) * ((g.size - 1) / (g[-1] - g[0])))
    i = min(max(i, 0), last)
    while i > 0 and not g[i] < x:
        i -= 1
    while i < last and g[i + 1] < x:
        i += 1
    return i


@njit(inline="always", **_JIT)
def spline_jet(table, cell_ok, gx, gy, x, y):
    """Height and derivatives ``(h, h_x, h_y, h_xx, h_xy, h_yy)`` of a
    :class:`~restoration.reverse_trace._surface.SplinePatches` table at one point (x, y) mm;
    NaN off the known surface. ``table`` (ncx + 1, ncy, 16), ``cell_ok`` (ncx ncy,) bool,
    ``gx`` (ncx + 1,), ``gy`` (ncy + 1,) mm: as in that class."""
    nan = np.nan
    if not (x >= gx[0] and x <= gx[-1] and y >= gy[0] and y <= gy[-1]):
        return nan, nan, nan, nan, nan, nan
    ix = _cell_of(gx, x)
    iy = _cell_of(gy, y)
    ncy = gy.size - 1
    if not cell_ok[ix * ncy + iy]:
        return nan, nan, nan, nan, nan, nan
    c = table[ix, iy]  # the cell's 16 coefficients, contiguous: two cache lines
    u = x - gx[ix]
    v = y - gy[iy]
    # Along x for each power p of y: value a_p, first b_p and second derivative e_p (scalars:
    # a small array per call would cost more than the arithmetic).
    a0, b0, e0 = _along(c, 0, u)
    a1, b1, e1 = _along(c, 1, u)
    a2, b2, e2 = _along(c, 2, u)
    a3, b3, e3 = _along(c, 3, u)
    # Along y.
    h = a0 + v * (a1 + v * (a2 + v * a3))
    hy = a1 + v * (2.0 * a2 + 3.0 * v * a3)
    hyy = 2.0 * a2 + 6.0 * v * a3
    hx = b0 + v * (b1 + v * (b2 + v * b3))
    hxy = b1 + v * (2.0 * b2 + 3.0 * v * b3)
    hxx = e0 + v * (e1 + v * (e2 + v * e3))
    return h, hx, hy, hxx, hxy, hyy


@njit(**_JIT)
def _sign(a):
    """``np.sign`` of a scalar (NaN stays NaN)."""
    if a > 0.0:
        return 1.0
    if a < 0.0:
        return -1.0
    return a  # 0 or NaN


@njit(inline="always", **_JIT)
def _residual(optics, port, camera, x, y, h, hx, hy, hxx, hxy, hyy, tx, ty):
    """How far the air ray through surface point (x, y) misses its target ``(tx, ty)``, and
    the miss's derivatives in ``x`` and ``y``.

    The air direction seen through surface point ``(x, y, h)`` mm with slopes ``(hx, hy)`` is
    eq. 18-20: the ray from the camera centre refracted by vector Snell, with the normal turned
    against the ray whichever side it hits. The miss is measured between directions, not on
    the object plane: the air direction and the direction from the surface point to the
    target, both mapped by the stereographic chart ``(t_x, t_y) / (1 + t_z)`` of the upper
    hemisphere. Object-plane distances grow like ``tan`` towards the edge of Snell's window
    and make Newton crawl there; the chart stays smooth up to the horizon.

    The derivatives are carried along the same expressions (forward mode), the surface moving
    with the point: ``h`` by its slopes, the slopes by the second derivatives ``hxx, hxy,
    hyy`` (a forward difference took two more evaluations of the miss).

    Behind a port (``port`` (13,), :func:`wai_core.port.pack_port`, thickness > 0) the ray
    comes from the point of the axis where the port's water ray to ``(x, y, h)`` meets it
    (:func:`wai_core.port.port_ray`, with ``camera`` (15,) packed); the Jacobian takes that
    point as fixed (it moves ~1e-3 as fast as the surface point: Newton stays near-quadratic).

    ``optics`` (5,): camera centre (mm), refractive index, object-plane height (mm). Returns
    the residual ``(r_x, r_y)`` (dimensionless, zero at the solution), the air direction's
    vertical component ``t_z`` (the ray misses the object plane unless > 0), ``k = 1 - n^2
    sin^2`` of the incidence (negative under total internal reflection) and the Jacobian
    ``d r_x / dx, d r_x / dy, d r_y / dx, d r_y / dy`` (per mm).
    """
    cx, cy, cz, n, z_object = optics[0], optics[1], optics[2], optics[3], optics[4]
    if port[1] > 0.0:
        cx, cy, cz = port_ray(port, camera, x, y, h)[:3]
    wx, wy, wz = x - cx, y - cy, h - cz
    inv_w = 1.0 / math.sqrt(wx * wx + wy * wy + wz * wz)
    inv_m = 1.0 / math.sqrt(1.0 + hx * hx + hy * hy)
    p = wz - wx * hx - wy * hy
    cos = p * (inv_w * inv_m)
    k = (1.0 - n * n) + (n * n) * (cos * cos)
    kk = 0.0 if k < 0.0 else k  # np.maximum(k, 0): NaN stays NaN
    root = math.sqrt(kk)
    sign = _sign(cos)
    a_w = n * inv_w
    a_m = (n * cos - sign * root) * inv_m
    ax, ay, az = a_w * wx + a_m * hx, a_w * wy + a_m * hy, a_w * wz - a_m
    ex, ey, ez = tx - x, ty - y, z_object - h
    dist = math.sqrt(ex * ex + ey * ey + ez * ez)
    b = 1.0 / (dist + ez)
    a = 1.0 / (1.0 + az)
    # Along x, then along y: the point moves by (1, 0) or (0, 1), its height by the slope.
    v = (n, wx, wy, wz, hx, hy, inv_w, inv_m, p, cos, kk, root, sign, a_w, a_m, ax, ay, a,
         ex, ey, ez, dist, b)
    j00, j10 = _miss_derivative(v, 1.0, 0.0, hx, hxx, hxy)
    j01, j11 = _miss_derivative(v, 0.0, 1.0, hy, hxy, hyy)
    return ax * a - ex * b, ay * a - ey * b, az, k, j00, j01, j10, j11


@njit(inline="always", **_JIT)
def _miss_derivative(v, dx, dy, dh, dhx, dhy):
    """Derivative of :func:`_residual`'s miss ``(r_x, r_y)`` along a move ``(dx, dy)`` of the
    surface point, its height changing by ``dh`` and its slopes by ``(dhx, dhy)``; ``v``: the
    miss's intermediate values."""
    n, wx, wy, wz, hx, hy, inv_w, inv_m, p, cos, kk, root, sign, a_w, a_m, ax, ay, a = v[:18]
    ex, ey, ez, dist, b = v[18:]
    d_inv_w = -inv_w * inv_w * inv_w * (wx * dx + wy * dy + wz * dh)
    d_inv_m = -inv_m * inv_m * inv_m * (hx * dhx + hy * dhy)
    dp = dh - (dx * hx + wx * dhx) - (dy * hy + wy * dhy)
    dcos = dp * (inv_w * inv_m) + p * (d_inv_w * inv_m + inv_w * d_inv_m)
    droot = n * n * cos * dcos / root if kk > 0.0 else 0.0
    da_w = n * d_inv_w
    da_m = (n * dcos - sign * droot) * inv_m + (n * cos - sign * root) * d_inv_m
    dax = da_w * wx + a_w * dx + da_m * hx + a_m * dhx
    day = da_w * wy + a_w * dy + da_m * hy + a_m * dhy
    daz = da_w * wz + a_w * dh - da_m
    ddist = -(ex * dx + ey * dy + ez * dh) / dist
    db = -b * b * (ddist - dh)
    da = -a * a * daz
    return dax * a + ax * da + dx * b - ex * db, day * a + ay * da + dy * b - ey * db


# Newton state of one target: surface point, height and slopes there, residual, Jacobian.
_QX, _QY, _H, _HX, _HY, _R0, _R1, _J00, _J01, _J10, _J11 = range(11)


@njit(inline="always", **_JIT)
def _evaluate(flat, h0, table, cell_ok, gx, gy, optics, port, camera, qx, qy, tx, ty, out):
    """Fill ``out`` (11,) for surface point (qx, qy) mm and target (tx, ty) mm; return its
    status."""
    if flat:
        h, hx, hy, hxx, hxy, hyy = h0, 0.0, 0.0, 0.0, 0.0, 0.0
    else:
        h, hx, hy, hxx, hxy, hyy = spline_jet(table, cell_ok, gx, gy, qx, qy)
    r0, r1, tz, k, j00, j01, j10, j11 = _residual(optics, port, camera, qx, qy, h, hx, hy,
                                                  hxx, hxy, hyy, tx, ty)
    out[_QX], out[_QY], out[_H], out[_HX], out[_HY] = qx, qy, h, hx, hy
    out[_R0], out[_R1] = r0, r1
    out[_J00], out[_J01], out[_J10], out[_J11] = j00, j01, j10, j11
    status = _MISSED_OBJECT
    if tz > 0.0:
        status = _OK
    if k < 0.0:
        status = _TIR
    if math.isnan(h):
        status = _MISSED_SURFACE
    return status


@njit(inline="always", **_JIT)
def _project(camera, port, x, y, z):
    """Pixel ``(col, row)`` of a lab point mm; ``camera`` (15,): R (row-major), t (mm), focal
    (px), principal point (px) (:meth:`PinholeCamera.project`); behind a port (``port``
    thickness > 0), :func:`wai_core.port.port_ray`'s."""
    if port[1] > 0.0:
        return port_ray(port, camera, x, y, z)[3:]
    zc = camera[6] * x + camera[7] * y + camera[8] * z + camera[11]
    scale = camera[12] / (zc if abs(zc) > 1e-12 else 1e-12)
    cols = (camera[0] * x + camera[1] * y + camera[2] * z + camera[9]) * scale + camera[13]
    rows = (camera[3] * x + camera[4] * y + camera[5] * z + camera[10]) * scale + camera[14]
    return cols, rows


@njit(inline="always", **_JIT)
def _solve_one(flat, h0, table, cell_ok, gx, gy, optics, port, camera, pulls, fracs, tol,
               max_iter, tx, ty, q0x, q0y, px_out, q_out, t, state, trial):
    """Newton for target ``t``; writes ``px_out[t]`` and ``q_out[t]`` when it converges and
    returns ``(status, iterations run)``. ``state``, ``trial`` (11,): scratch (the caller's,
    reused across targets: two allocations per target cost as much as a Newton step)."""
    status = _evaluate(flat, h0, table, cell_ok, gx, gy, optics, port, camera, q0x, q0y, tx,
                       ty, state)
    if status == _TIR or status == _MISSED_OBJECT:
        # Beyond the edge of Snell's window: pull towards the nadir, the mildest pull first.
        nx, ny = optics[0], optics[1]
        for p in range(pulls.size):
            s = _evaluate(flat, h0, table, cell_ok, gx, gy, optics, port, camera,
                          nx + pulls[p] * (state[_QX] - nx), ny + pulls[p] * (state[_QY] - ny),
                          tx, ty, trial)
            if s == _OK:
                state[:] = trial
                status = _OK
                break
    if status != _OK:
        return status, 0
    for it in range(1, max_iter + 1):
        a, b, c, d = state[_J00], state[_J01], state[_J10], state[_J11]
        r0, r1 = state[_R0], state[_R1]
        inv = 1.0 / (a * d - b * c)
        if not math.isfinite(inv):
            inv = np.nan
        sx, sy = (b * r1 - d * r0) * inv, (c * r0 - a * r1) * inv
        # A step below tolerance is taken on the tangent plane, without a new evaluation.
        x, y = state[_QX] + sx, state[_QY] + sy
        h = state[_H] + state[_HX] * sx + state[_HY] * sy
        u1, v1 = _project(camera, port, x, y, h)
        u0, v0 = _project(camera, port, state[_QX], state[_QY], state[_H])
        if math.hypot(u1 - u0, v1 - v0) < tol:
            px_out[t, 0], px_out[t, 1] = u1, v1
            q_out[t, 0], q_out[t, 1], q_out[t, 2] = x, y, h
            return _OK, it
        if not (math.isfinite(sx) and math.isfinite(sy)):
            return _NOT_CONVERGED, it
        # Damped move: the longest of the step and its halvings that stays on the surface,
        # without TIR, and shrinks |r|; none: stop with the failure of the shortest try.
        r2 = r0 * r0 + r1 * r1
        s = _OK
        moved = False
        for f in range(fracs.size):
            s = _evaluate(flat, h0, table, cell_ok, gx, gy, optics, port, camera,
                          state[_QX] + fracs[f] * sx, state[_QY] + fracs[f] * sy, tx, ty, trial)
            if s == _OK and trial[_R0] ** 2 + trial[_R1] ** 2 < r2:
                state[:] = trial
                moved = True
                break
        if not moved:
            return (_NOT_CONVERGED if s == _OK else s), it
    return _NOT_CONVERGED, max_iter


@njit(**_JIT)
def newton_chunk(chunk, n_chunks, flat, h0, table, cell_ok, gx, gy, optics, port, camera,
                 pulls, fracs, tol, max_iter, targets, q0, px, status, q, iters
                 ):  # pragma: no cover
    """Solve the ``chunk``-th of ``n_chunks`` equal runs of consecutive targets of the N
    targets (N, 2) mm from surface points ``q0`` (N, 2) mm. The targets are independent: any
    thread may run any chunk. Consecutive targets are neighbouring nodes, which read
    neighbouring cells of the spline table: a run keeps them in cache.

    Parameters
    ----------
    chunk, n_chunks : int
        This chunk, and how many there are.
    flat : bool
        Flat water at ``h0`` mm (the table arguments are then ignored).
    table, cell_ok, gx, gy : ndarray
        The spline surface (:func:`spline_jet`).
    optics : (5,) ndarray
        Camera centre (mm), refractive index, object-plane height (mm).
    port : (13,) ndarray
        The camera's port (:func:`wai_core.port.pack_port`; thickness 0: a pinhole).
    camera : (15,) ndarray
        Projection constants (:func:`_project`).
    pulls, fracs : ndarray
        Factors of the pulls towards the nadir, and of the damped steps (full step first).
    tol : float
        Convergence threshold on the pixel step, px.
    max_iter : int
        Newton iterations at most.
    px : (N, 2) ndarray
        Out: pixels ``(col, row)``; left as they are (NaN) unless converged.
    status : (N,) ndarray of int8
        Out: :class:`RayStatus` codes.
    q : (N, 3) ndarray
        Out: surface points, mm; left as they are (NaN) unless converged.
    iters : (N,) ndarray of int
        Out: iterations run.
    """
    state, trial = np.empty(11), np.empty(11)
    n = targets.shape[0]
    for t in range(chunk * n // n_chunks, (chunk + 1) * n // n_chunks):
        s, it = _solve_one(flat, h0, table, cell_ok, gx, gy, optics, port, camera, pulls, fracs,
                           tol, max_iter, targets[t, 0], targets[t, 1], q0[t, 0], q0[t, 1],
                           px, q, t, state, trial)
        status[t] = s
        iters[t] = it


# --- spline tables ----------------------------------------------------------------------------


@njit(**_JIT)
def cell_polynomials(grid, knots, vinv):  # pragma: no cover
    """The four cubic B-splines of ``knots`` active on each cell of ``grid`` (n,) mm, as cubics
    in mm from the cell's start; see :func:`restoration.reverse_trace._surface._cell_polynomials`.

    Each cell lies in one knot interval: the B-splines are evaluated (Cox-de Boor) at four
    points of the cell, at fractions ``frac`` of its width, and ``vinv`` (4, 4), the inverse
    of ``frac``'s Vandermonde matrix, turns the values into power-basis coefficients.

    Returns ``first`` (n - 1,) int64, the first active B-spline of each cell, and ``poly``
    (n - 1, 4, 4): ``B_{first[c] + j}(grid[c] + t) = sum_b poly[c, b, j] t^b``.
    """
    frac = np.array([0.125, 0.375, 0.625, 0.875])
    n_int = knots.size - 7  # intervals between the breaks knots[3:-3]
    n_cell = grid.size - 1
    first = np.empty(n_cell, np.int64)
    poly = np.empty((n_cell, 4, 4))
    vals = np.empty((4, 4))  # [point, B-spline]
    left = np.empty(4)
    right = np.empty(4)
    for c in range(n_cell):
        g0, width = grid[c], grid[c + 1] - grid[c]
        # searchsorted(breaks[:-1], g0, side="right") - 1, clipped to the intervals.
        k = 0
        while k + 1 < n_int and knots[3 + k + 1] <= g0:
            k += 1
        first[c] = k
        span = 3 + k
        for a in range(4):
            x = g0 + frac[a] * width
            nb = vals[a]
            nb[0] = 1.0
            for j in range(1, 4):
                left[j] = x - knots[span + 1 - j]
                right[j] = knots[span + j] - x
                saved = 0.0
                for r in range(j):
                    temp = nb[r] / (right[r + 1] + left[j - r])
                    nb[r] = saved + right[r + 1] * temp
                    saved = left[j - r] * temp
                nb[j] = saved
        scale = 1.0
        for b in range(4):
            for j in range(4):
                acc = 0.0
                for a in range(4):
                    acc += vinv[b, a] * vals[a, j]
                poly[c, b, j] = acc * scale
            scale /= width
    return first, poly


@njit(**_JIT)
def spline_table(first_x, poly_x, first_y, poly_y, coeffs):  # pragma: no cover
    """Power-basis coefficients of a bicubic spline on every grid cell, (ncx + 1, ncy, 16).

    ``coeffs`` (ny, nx) are the spline's B-spline coefficients ``c[j, l]`` (y, x);
    ``first_*``, ``poly_*`` come from :func:`cell_polynomials` for each axis. Entry
    ``[ix, iy, 4 a + b]`` multiplies ``u^a v^b`` (``u, v`` mm from the cell's corner); slab
    ``ncx`` is NaN (the entry of points off the known surface). Two separable passes: first
    along y for every x coefficient, then along x.
    """
    ncx, ncy, nx = first_x.size, first_y.size, coeffs.shape[1]
    rows = np.empty((4, nx, ncy))  # [power of y, x coefficient, y cell]
    for iy in range(ncy):
        ky = first_y[iy]
        for b in range(4):
            p0, p1, p2, p3 = poly_y[iy, b, 0], poly_y[iy, b, 1], poly_y[iy, b, 2], poly_y[iy, b, 3]
            for m in range(nx):
                rows[b, m, iy] = (p0 * coeffs[ky, m] + p1 * coeffs[ky + 1, m]
                                  + p2 * coeffs[ky + 2, m] + p3 * coeffs[ky + 3, m])
    table = np.empty((ncx + 1, ncy, 16))
    for ix in range(ncx):
        kx = first_x[ix]
        out = table[ix]
        for a in range(4):
            q0, q1, q2, q3 = poly_x[ix, a, 0], poly_x[ix, a, 1], poly_x[ix, a, 2], poly_x[ix, a, 3]
            for b in range(4):
                r0, r1, r2, r3 = rows[b, kx], rows[b, kx + 1], rows[b, kx + 2], rows[b, kx + 3]
                for iy in range(ncy):
                    out[iy, 4 * a + b] = q0 * r0[iy] + q1 * r1[iy] + q2 * r2[iy] + q3 * r3[iy]
    table[ncx] = np.nan
    return table


# --- the restored image -----------------------------------------------------------------------


@njit(**_JIT)
def node_warp(truth_status, node_index, node_px, px, status, disp_x, disp_y,
              node_status):  # pragma: no cover
    """Scatter the solved nodes into the coarse grid (flat, rows cols): ``node_status`` the
    truth view's ``truth_status`` with the solve's ``status`` (K,) at ``node_index`` (K,);
    ``disp_x``, ``disp_y`` (float32) the displacement ``px - node_px`` (K, 2) px of the OK
    nodes, 0 elsewhere."""
    for i in range(truth_status.size):
        node_status[i] = truth_status[i]
        disp_x[i] = 0.0
        disp_y[i] = 0.0
    for k in range(node_index.size):
        i = node_index[k]
        node_status[i] = status[k]
        if status[k] == _OK:
            disp_x[i] = np.float32(px[k, 0] - node_px[k, 0])
            disp_y[i] = np.float32(px[k, 1] - node_px[k, 1])


@njit(**_JIT)
def warp_node_rows(disp_x, disp_y, cell_ok, col_i, col_t):  # pragma: no cover
    """The coarse warp interpolated along x at every pixel column of each node row: the
    displacements (rows, W) float32 and whether each column's cell is solved (rows - 1, W).
    :func:`warp_rows` then interpolates between two of these rows: both steps are plain
    passes over contiguous columns, which vectorise (a per-pixel lookup of the cell's nodes
    does not).

    Parameters
    ----------
    disp_x, disp_y : (rows, cols) ndarray of float32
        Warp displacement ``u - p`` at the coarse nodes, px.
    cell_ok : (rows - 1, cols - 1) ndarray of bool
        Cells whose four nodes were solved.
    col_i : (W,) ndarray of int
        Cell of each pixel column, non-decreasing; a last pixel lying exactly on the last node
        belongs to the cell before it.
    col_t : (W,) ndarray of float32
        Its fraction of the way across that cell.
    """
    n_rows = disp_x.shape[0]
    w = col_i.size
    along_x = np.empty((n_rows, w), np.float32)
    along_y = np.empty((n_rows, w), np.float32)
    ok = np.empty((n_rows - 1, w), np.bool_)
    for i in range(n_rows):
        x, y = disp_x[i], disp_y[i]
        for j in range(w):
            c, t = col_i[j], col_t[j]
            along_x[i, j] = x[c] + t * (x[c + 1] - x[c])
            along_y[i, j] = y[c] + t * (y[c + 1] - y[c])
    for i in range(n_rows - 1):
        for j in range(w):
            ok[i, j] = cell_ok[i, col_i[j]]
    return along_x, along_y, ok


@njit(**_JIT)
def warp_rows(r0, r1, along_x, along_y, ok_x, row_i, row_t, map_x, map_y, valid, per_row,
              first, last):  # pragma: no cover
    """Upsample a coarse warp to the pixels of rows ``r0`` to ``r1 - 1``, with its validity.
    The rows are independent: any thread may run any range.

    Parameters
    ----------
    r0, r1 : int
        The rows, from ``r0`` to one before ``r1``.
    along_x, along_y, ok_x
        The warp at the node rows and the cells' validity, per pixel column
        (:func:`warp_node_rows`).
    row_i : (H,) ndarray of int
        Cell of each pixel row, non-decreasing (as ``col_i`` of :func:`warp_node_rows`).
    row_t : (H,) ndarray of float32
        Its fraction of the way across that cell.
    map_x, map_y : (H, W) ndarray of float32
        Out: the sampling column and row ``u`` of every pixel.
    valid : (H, W) ndarray of bool
        Out: in a solved cell and ``-0.5 <= u <= size - 0.5`` (as :meth:`PinholeCamera.in_image`).
    per_row, first, last : (H,) ndarray of int
        Out: each row's valid pixels, and the first and one past the last valid column (``W``
        and 0 where none): :func:`valid_box` reduces them.
    """
    h, w = map_x.shape
    lo = np.float32(-0.5)
    wx, hy = np.float32(w - 0.5), np.float32(h - 0.5)
    col_f = np.arange(w).astype(np.float32)
    for r in range(r0, r1):
        iy, ty = row_i[r], row_t[r]
        x0, x1, y0, y1 = along_x[iy], along_x[iy + 1], along_y[iy], along_y[iy + 1]
        ok_row = ok_x[iy]
        mx_row, my_row, valid_row = map_x[r], map_y[r], valid[r]
        fr = np.float32(r)
        n_ok = 0
        for j in range(w):
            mx = col_f[j] + (x0[j] + ty * (x1[j] - x0[j]))
            my = fr + (y0[j] + ty * (y1[j] - y0[j]))
            ok = ok_row[j] & (mx >= lo) & (mx <= wx) & (my >= lo) & (my <= hy)
            mx_row[j], my_row[j], valid_row[j] = mx, my, ok
            n_ok += ok
        lo_c, hi_c = w, 0
        if n_ok:
            lo_c, hi_c = 0, w
            while not valid_row[lo_c]:
                lo_c += 1
            while not valid_row[hi_c - 1]:
                hi_c -= 1
        per_row[r], first[r], last[r] = n_ok, lo_c, hi_c


@njit(**_JIT)
def valid_box(per_row, first, last, w):  # pragma: no cover
    """Valid pixels in all and their bounding box (4,): first and one past the last row, then
    column (empty: all 0), from :func:`warp_rows`' per-row figures of an image ``w`` wide."""
    box = np.zeros(4, np.int64)
    n_valid = 0
    for r in range(per_row.size):
        if per_row[r]:
            if n_valid == 0:
                box[0], box[2] = r, w
            n_valid += per_row[r]
            box[1] = r + 1
            box[2] = min(box[2], first[r])
            box[3] = max(box[3], last[r])
    return n_valid, box


@njit(**_JIT)
def finish_rows(rows0, rows1, out, valid, box, gain):  # pragma: no cover
    """Rows ``rows0`` to ``rows1 - 1`` of the resampled image ``out`` (H, W, C): inside ``box``
    (4,) (first and one past the last row, then column, where ``cv2.remap`` wrote) divided by
    ``gain`` (of its type; 1 leaves them as they are), and 0 where ``valid`` (H, W) is not
    set; 0 outside it (``out`` comes uninitialised, which spares a pass zeroing the whole
    image)."""
    h, w, n_ch = out.shape
    r0, r1, c0, c1 = box[0], box[1], box[2], box[3]
    for r in range(rows0, rows1):
        row = out[r].reshape(-1)  # contiguous: the division vectorises
        if r < r0 or r >= r1:
            row[:] = 0.0
            continue
        row[: c0 * n_ch] = 0.0
        row[c1 * n_ch :] = 0.0
        if gain != 1.0:
            part = row[c0 * n_ch : c1 * n_ch]
            for j in range(part.size):  # from 0: no negative-index check, so it vectorises
                part[j] = part[j] / gain
        valid_row = valid[r]
        for c in range(c0, c1):
            if not valid_row[c]:
                for k in range(n_ch):
                    row[c * n_ch + k] = 0.0
