"""Camera v's exact warp through a surface, traced by Dr.Jit on the renderer's device.

The dataset's truth (:func:`wai.dataset.true_view_warp`) takes each pixel of camera v through
the true surface to the object plane and back through flat water to the pixel that sees the
same object point. :class:`ViewWarpTracer` does the same arithmetic as the compiled CPU kernels
(:func:`wai_core._bispline.intersect_rays`, :func:`wai_core.light_paths.view_warp_px`), one
Dr.Jit lane per pixel, in float64, on the backend of the active Mitsuba variant: on
``cuda_ad_rgb`` the GPU, on ``llvm_ad_rgb`` every core. Per pixel:

1. Newton's steps on ``f(t) = o_z + t d_z - z(o + t d)`` from the plane at the surface's mean
   height, the bicubic spline's height and slopes evaluated in place (its knot span from the
   same lookup table, Cox-de Boor's recursion written out for degree 3, the 16 coefficients
   gathered); a ray that leaves the knots' rectangle or does not settle is invalid.
2. Snell's law into the air (eq. 20) and the object plane.
3. The flat-water inverse, Newton's method in the air-side tangent (five steps), and the pinhole
   projection of the refraction point.

The CPU kernel starts each ray from its neighbour's hit where that converged; here every ray
starts from the plane (the kernel's fallback), so a ray that crosses the surface more than once
may settle on another crossing than the CPU's: the warps agree to within 1e-3 px but on such
rays (``tests/wai/test_dataset.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from mitsuba_wai.variant import jit_arrays
from wai_core.heightfield import Heightfield
from wai_core.light_paths import pack_camera

__all__ = ["ViewWarpTracer"]

_CONVERGED_MM = 1e-9  # as wai_core._bispline: a residual below which a step changes nothing
_DEGREE = 3


class _Axis:
    """One axis of the spline on the device: knots, span lookup table, their constants."""

    def __init__(self, jit: Any, knots: NDArray, table: NDArray) -> None:
        import drjit as dr

        n_coef = knots.size - _DEGREE - 1
        self.jit = jit
        self.knots = jit.Float64(knots)
        self.table = jit.Int32(table.astype(np.int32))
        self.n_coef = n_coef
        self.lo = dr.opaque(jit.Float64, float(knots[_DEGREE]))
        self.hi = dr.opaque(jit.Float64, float(knots[n_coef]))
        self.cells = dr.opaque(jit.Float64, float(table.size - 1) / float(knots[n_coef]
                                                                          - knots[_DEGREE]))
        self.last_cell = dr.opaque(jit.Int32, table.size - 1)
        self.first_span = dr.opaque(jit.Int32, _DEGREE)
        self.last_span = dr.opaque(jit.Int32, n_coef - 1)

    def basis(self, u: Any) -> tuple[Any, list[Any], list[Any]]:
        """The span ``s`` holding ``u`` (clamped to the knots), the four cubic basis functions
        and their derivatives (1/mm), each an array of the lanes."""
        import drjit as dr

        jit = self.jit
        j = jit.Int32(dr.floor((u - self.lo) * self.cells))
        s = dr.gather(jit.Int32, self.table, dr.clip(j, 0, self.last_cell))
        t = self.knots
        # The table's cells are no wider than a span: at most one step either way.
        s = dr.select((s < self.last_span) & (u >= dr.gather(jit.Float64, t, s + 1)), s + 1, s)
        s = dr.select((s > self.first_span) & (u < dr.gather(jit.Float64, t, s)), s - 1, s)
        k = [dr.gather(jit.Float64, t, s + o) for o in range(-2, 4)]  # t[s-2] .. t[s+3]
        left = [None, u - k[2], u - k[1], u - k[0]]   # u - t[s+1-j]
        right = [None, k[3] - u, k[4] - u, k[5] - u]  # t[s+j] - u
        # Cox-de Boor's triangle for degree 3 (The NURBS Book, A2.2), written out.
        temp = 1.0 / (right[1] + left[1])
        q0, q1 = right[1] * temp, left[1] * temp
        temp = q0 / (right[1] + left[2])
        l0, saved = right[1] * temp, left[2] * temp
        temp = q1 / (right[2] + left[1])
        l1, l2 = saved + right[2] * temp, left[1] * temp  # the quadratic basis
        temp = l0 / (right[1] + left[3])
        b0, saved = right[1] * temp, left[3] * temp
        temp = l1 / (right[2] + left[2])
        b1, saved = saved + right[2] * temp, left[2] * temp
        temp = l2 / (right[3] + left[1])
        b2, b3 = saved + right[3] * temp, left[1] * temp
        # Derivatives from the quadratic basis (A2.3): 3 (N_{i,2} / (t_{i+3} - t_i) - ...).
        e0 = l0 / (k[3] - k[0])
        e1 = l1 / (k[4] - k[1])
        e2 = l2 / (k[5] - k[2])
        d = [-3.0 * e0, 3.0 * (e0 - e1), 3.0 * (e1 - e2), 3.0 * e2]
        return s, [b0, b1, b2, b3], d


class ViewWarpTracer:
    """Camera v's exact warp through surfaces (module notes), its pixel rays kept on the device.

    Parameters
    ----------
    rig : wai_core.rig.Rig
        The rig (``cfg.rig``): camera v, the water's index and level, the object plane.
    rays : (origin (3,), directions (H, W, 3)), optional
        Camera v's pixel rays (``camera_v.pixel_rays(*camera_v.pixel_grid())``).

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core import load_system
    >>> cfg = load_system("paper").replace("camera_v", width_px=40, height_px=30)
    >>> x = y = np.linspace(-600.0, 600.0, 9)
    >>> flat = Heightfield(x, y, np.full((9, 9), cfg.water.h0_mm))
    >>> warp = ViewWarpTracer(cfg.rig)(cfg.rig, flat)
    >>> cols, rows = np.meshgrid(np.arange(40.0), np.arange(30.0))
    >>> ok = np.isfinite(warp[..., 0])
    >>> bool(np.allclose(warp[ok], np.stack([cols, rows], axis=-1)[ok], atol=1e-3))
    True
    """

    def __init__(self, rig: Any, rays: tuple[NDArray, NDArray] | None = None) -> None:
        cam = rig.camera_v
        origin, dirs = cam.pixel_rays(*cam.pixel_grid()) if rays is None else rays
        self._jit = jit = jit_arrays()
        self.shape = np.shape(dirs)[:-1]
        flat = np.asarray(dirs, dtype=float).reshape(-1, 3)
        self._dirs = [jit.Float64(np.ascontiguousarray(flat[:, c])) for c in range(3)]
        self._origin = np.asarray(origin, dtype=float).reshape(3)

    def __call__(self, rig: Any, surface: Heightfield, n_iter: int = 4, tol_mm: float = 1e-6,
                 iterations: int = 5) -> NDArray[np.float32]:
        """The flat-water view's (col, row) of each pixel through ``surface``, (H, W, 2)
        float32, NaN where the ray misses the surface (or does not settle on it), is totally
        reflected or misses the object plane.

        Parameters
        ----------
        rig : wai_core.rig.Rig
            The rig whose camera v gave the rays.
        surface : Heightfield
            The true surface, absolute heights, mm, without holes.
        n_iter : int
            Newton steps to the surface (four reach float64 rounding on sea waves).
        tol_mm : float
            Largest height residual of a hit, mm.
        iterations : int
            Newton steps of the flat-water inverse.
        """
        import drjit as dr

        if surface.has_holes:
            raise ValueError("ViewWarpTracer: the surface has holes (unknown heights)")
        jit = self._jit
        ty, tx, _, _, ly, lx, coef = surface.compiled_spline()
        ay, ax = _Axis(jit, ty, ly), _Axis(jit, tx, lx)
        coef_d = jit.Float64(np.ascontiguousarray(coef).ravel())
        ncx = dr.opaque(jit.Int32, coef.shape[1])

        f64 = self._scalar
        ox, oy, oz = (f64(v) for v in self._origin)
        dx, dy, dz = self._dirs
        x_lo, x_hi, y_lo, y_hi = f64(tx[0]), f64(tx[-1]), f64(ty[0]), f64(ty[-1])
        t = (f64(np.nanmean(surface.z)) - oz) / dz
        live = jit.Bool(dr.isfinite(t))
        settled = jit.Bool(False)
        h = gx = gy = jit.Float64(0.0)
        for step in range(n_iter + 1):
            px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
            live &= (px >= x_lo) & (px <= x_hi) & (py >= y_lo) & (py <= y_hi)
            sy, by, dby = ay.basis(py)
            sx, bx, dbx = ax.basis(px)
            base = (sy - _DEGREE) * ncx + (sx - _DEGREE)
            h_new, gx_new, gy_new = jit.Float64(0.0), jit.Float64(0.0), jit.Float64(0.0)
            for r in range(4):
                row = [dr.gather(jit.Float64, coef_d, base + r * ncx + c, live)
                       for c in range(4)]
                along = row[0] * bx[0] + row[1] * bx[1] + row[2] * bx[2] + row[3] * bx[3]
                slope = row[0] * dbx[0] + row[1] * dbx[1] + row[2] * dbx[2] + row[3] * dbx[3]
                h_new += by[r] * along
                gx_new += by[r] * slope
                gy_new += dby[r] * along
            moving = live & ~settled
            h = dr.select(moving, h_new, h)
            gx = dr.select(moving, gx_new, gx)
            gy = dr.select(moving, gy_new, gy)
            f = pz - h
            settled |= moving & (dr.abs(f) < _CONVERGED_MM)
            if step < n_iter:
                t = dr.select(live & ~settled, t - f / (dz - gx * dx - gy * dy), t)
        px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
        valid = live & (dr.abs(pz - h) < f64(max(tol_mm, 1e-9) * 1e3)) & (t > 0.0)
        col, row = self._refract_and_return(rig, (px, py, pz), (gx, gy), valid, iterations)
        dr.eval(col, row)
        out = np.empty((int(np.prod(self.shape, dtype=np.int64)), 2), dtype=np.float32)
        out[:, 0] = col.numpy()
        out[:, 1] = row.numpy()
        return out.reshape(*self.shape, 2)

    def _scalar(self, value: float) -> Any:
        """``value`` as an opaque float64 of the backend: a frame's constants change without
        a new kernel."""
        import drjit as dr

        return dr.opaque(self._jit.Float64, float(value))

    def _refract_and_return(self, rig: Any, hit: tuple, slopes: tuple, valid: Any,
                            iterations: int) -> tuple[Any, Any]:
        """Each ray refracted at its hit into the air, carried to the object plane and taken
        back through flat water to camera v's pixel (:func:`~wai_core.light_paths.
        view_warp_px`'s arithmetic): (col, row), NaN where invalid."""
        import drjit as dr

        jit = self._jit
        cfg = rig.cfg

        f64 = self._scalar
        n = f64(cfg.water.n_water)
        dx, dy, dz = self._dirs
        gx, gy = slopes
        inv = 1.0 / dr.sqrt(gx * gx + gy * gy + 1.0)
        nx, ny, nz = -gx * inv, -gy * inv, inv
        cos_i = dx * nx + dy * ny + dz * nz
        flip = cos_i > 0.0  # the normal against the ray
        nx, ny, nz = (dr.select(flip, -v, v) for v in (nx, ny, nz))
        cos_i = dr.abs(cos_i)
        k = 1.0 - n * n * (1.0 - cos_i * cos_i)
        valid &= k >= 0.0  # else totally reflected
        m = n * cos_i - dr.sqrt(dr.maximum(k, 0.0))
        tx, ty, tz = n * dx + m * nx, n * dy + m * ny, n * dz + m * nz
        t = (f64(cfg.object_z_mm) - hit[2]) / tz
        valid &= dr.isfinite(t) & (t > 0.0)
        px, py, pz = hit[0] + t * tx, hit[1] + t * ty, hit[2] + t * tz
        valid &= dr.isfinite(px) & dr.isfinite(py) & dr.isfinite(pz)
        # Back through flat water (light_paths.flat_pixel_of): the air-side tangent v.
        c = rig.camera_v.pose.center_lab_mm
        cx, cy, cz = f64(c[0]), f64(c[1]), f64(c[2])
        h0 = f64(cfg.water.h0_mm)
        ddx, ddy = px - cx, py - cy
        d = dr.sqrt(ddx * ddx + ddy * ddy)
        a = h0 - cz
        b = pz - h0
        kk = n * n - 1.0
        v = dr.maximum(d / (a / n + b), (d - a / dr.sqrt(kk)) / b)
        for _ in range(iterations):
            q = dr.sqrt(n * n + kk * v * v)
            g = a * v / q + b * v - d
            v = v - g / (a * n * n / (q * q * q) + b)
        r = d - b * v
        scale = dr.select(d > 0.0, r / d, r)
        qx, qy = cx + scale * ddx, cy + scale * ddy
        cam = [f64(v) for v in pack_camera(rig.camera_v)]
        ex = qx * cam[0] + qy * cam[1] + h0 * cam[2] + cam[9]
        ey = qx * cam[3] + qy * cam[4] + h0 * cam[5] + cam[10]
        ez = qx * cam[6] + qy * cam[7] + h0 * cam[8] + cam[11]
        ez = dr.select(dr.abs(ez) > 1e-12, ez, 1e-12)
        nan = jit.Float64(np.nan)
        col = dr.select(valid, cam[12] * ex / ez + cam[13], nan)
        row = dr.select(valid, cam[12] * ey / ez + cam[14], nan)
        return col, row
