"""The pattern fit's image loss and its gradient on Dr.Jit: LLVM on the CPU, CUDA on a GPU.

The same loss as :class:`restoration.inverse_rendering` evaluates in NumPy (the particles
through the B-spline surface into camera s, bilinear splats, the Gaussian blur, the masked
squared residual), written once as Dr.Jit array code and differentiated by its automatic
adjoint (``drjit.backward``) instead of the hand-written one: the particles' hits by Newton's
method (detached; the hit's derivative is the implicit one, ``dz / (d_z - grad z . d_xy)``,
as in :func:`restoration.fit.linearise`), the reflection about the facet's normal, the
diffuser plane, camera s's pinhole, the splats (scatter-adds into the image), the blur (a
sum of shifted gathers with the NumPy model's kernel,
:attr:`~restoration.pattern_model.Raster.kernel`) and the loss. One evaluation is one kernel
launch for the forward pass and one for the adjoint, on whichever device Dr.Jit has; the
spline's coefficients come in and their gradient goes out (a few hundred numbers a call), the
images and the particles stay on the device for the pass.

Camera s must be the ideal pinhole (no lens distortion, principal offset or port): the
lens models live in NumPy; :func:`usable` says whether a rig qualifies.
``tests/restoration/test_pattern_jit.py`` checks the loss and its gradient against the NumPy
model's.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from restoration.fit import BSplineSurface, basis_terms
from restoration.pattern_model import PatternModel, Raster

__all__ = ["JitImageLoss", "jit_module", "usable"]

Array = NDArray[np.float64]

NEWTON_STEPS = 3
"""Newton steps on each particle's hit per evaluation, from the last evaluation's (as the
NumPy model's trace)."""


def jit_module(backend: str = "auto") -> ModuleType:
    """Dr.Jit's differentiable array module: ``drjit.cuda.ad`` for ``"cuda"`` (and for
    ``"auto"`` where a CUDA device is present), else ``drjit.llvm.ad``."""
    import drjit as dr

    if backend == "cuda" or (backend == "auto" and dr.has_backend(dr.JitBackend.CUDA)):
        import drjit.cuda.ad as jit
    else:
        import drjit.llvm.ad as jit
    return jit


def usable(rig: Any) -> bool:
    """Whether the Dr.Jit loss models ``rig``'s camera s (its ideal pinhole only)."""
    return bool(rig.optics("camera_s").ideal)


class JitImageLoss:
    """One pass's image loss ``1/2 |W (M(c) - I)|^2 / norm`` as a function of the spline's
    coefficients ``c``, on Dr.Jit (module notes).

    Parameters
    ----------
    model : PatternModel
        The dots' particles and the rig (camera s an ideal pinhole: :func:`usable`).
    raster : Raster
        The image size and the blur.
    like : BSplineSurface
        The spline whose knots the coefficients belong to.
    observed, mask : (H, W) ndarray
        The pattern image and the pixels scored (0 or 1).
    norm : float
        The loss's normaliser (the image's contrast energy under the mask).
    weights : (P,) ndarray
        Each particle's light (its dot's brightness times its share), held for the pass.
    background : float
        The model image's constant.
    t : (P,) ndarray
        The particles' ray parameters to start Newton's method from.
    backend : str
        ``"auto"``, ``"llvm"`` or ``"cuda"`` (:func:`jit_module`).

    Examples
    --------
    >>> from restoration.pattern_jit import jit_module
    >>> jit_module("llvm").__name__
    'drjit.llvm.ad'
    """

    def __init__(self, model: PatternModel, raster: Raster, like: BSplineSurface,
                 observed: Array, mask: Array, norm: float, weights: Array, background: float,
                 t: Array, backend: str = "auto") -> None:
        import drjit as dr

        jit = jit_module(backend)
        self._dr, self._jit = dr, jit
        F = jit.Float64
        p = model.particles
        n = len(p.dirs)
        origin = np.broadcast_to(np.asarray(p.origin_mm, float), (n, 3))
        self._o = [F(np.ascontiguousarray(origin[:, k])) for k in range(3)]
        self._d = [F(np.ascontiguousarray(p.dirs[:, k])) for k in range(3)]
        slopes = np.zeros((n, 2)) if p.slope_offset is None else p.slope_offset
        self._s = [F(np.ascontiguousarray(slopes[:, k])) for k in range(2)]
        self._w = F(np.asarray(weights, float))
        self._t = F(np.asarray(t, float))
        self._x0, self._y0, self._step = float(like.x0_mm), float(like.y0_mm), float(like.step_mm)
        self._ny, self._nx = like.coeffs.shape
        h, w = raster.shape
        self._h, self._w_px = h, w
        self._kernel = raster.kernel
        self._observed = F(np.asarray(observed, float).ravel())
        self._mask = F(np.asarray(mask, float).ravel())
        self._norm = float(norm)
        self._background = float(background)
        cam = model.rig.camera_s
        # Python floats: a NumPy scalar times a Dr.Jit array would become a NumPy array.
        self._R = [[float(v) for v in r] for r in np.asarray(cam.pose.R, float)]
        self._tc = [float(v) for v in np.asarray(cam.pose.t_mm, float)]
        self._f = float(cam.focal_px)
        self._z_h = float(model.z_h_mm)

    @contextmanager
    def in_order(self) -> Iterator[None]:
        """Evaluations within are reproducible bit for bit: on LLVM, Dr.Jit runs on one
        thread (its parallel scatter-adds would sum in any order; one thread is still 4x
        the NumPy model's speed on rough water); on CUDA nothing changes (the GPU's atomic
        sums are unordered: a rerun agrees to rounding, not bit for bit)."""
        dr = self._dr
        llvm = self._jit.__name__.startswith("drjit.llvm")
        before = dr.thread_count()
        if llvm:
            dr.set_thread_count(1)
        try:
            yield
        finally:
            if llvm:
                dr.set_thread_count(before)

    @property
    def t(self) -> Array:
        """The particles' ray parameters after the last evaluation (P,)."""
        return np.asarray(self._t.numpy(), float)

    def _spline(self, c: Any, x: Any, y: Any) -> tuple[Any, Any, Any, Any]:
        """``z, z_x, z_y`` of the spline of coefficients ``c`` at ``x, y``, and where it is
        defined (:meth:`~restoration.fit.BSplineSurface.rows`)."""
        dr, jit = self._dr, self._jit
        h = self._step
        gx, gy = (x - self._x0) / h, (y - self._y0) / h
        fx, fy = dr.floor(dr.detach(gx)), dr.floor(dr.detach(gy))
        finite = dr.isfinite(fx) & dr.isfinite(fy)
        fx, fy = dr.select(finite, fx, -1.0), dr.select(finite, fy, -1.0)
        ix, iy = jit.Int32(fx), jit.Int32(fy)
        inside = (finite & (ix >= 0) & (iy >= 0) & (ix <= self._nx - 4)
                  & (iy <= self._ny - 4))
        ix = dr.clip(ix, 0, self._nx - 4)
        iy = dr.clip(iy, 0, self._ny - 4)
        u, v = gx - jit.Float64(ix), gy - jit.Float64(iy)
        bu, dbu, _ = basis_terms(u)
        bv, dbv, _ = basis_terms(v)
        z = zx = zy = 0.0
        for a in range(4):
            row = (iy + a) * self._nx + ix
            for b in range(4):
                coeff = dr.gather(jit.Float64, c, jit.UInt32(row + b))
                z = z + bv[a] * bu[b] * coeff
                zx = zx + bv[a] * dbu[b] * coeff
                zy = zy + dbv[a] * bu[b] * coeff
        return z, zx / h, zy / h, inside

    def _blur_axis(self, image: Any, along_x: bool) -> Any:
        """``image`` (flat, H x W) convolved with the kernel along one axis, zero beyond it."""
        dr, jit = self._dr, self._jit
        h, w = self._h, self._w_px
        index = dr.arange(jit.Int32, h * w)
        col, row = index % w, index // w
        radius = len(self._kernel) // 2
        out = jit.Float64(0.0)
        for k, weight in enumerate(self._kernel):
            shift = k - radius
            if along_x:
                src, ok = index + shift, (col + shift >= 0) & (col + shift < w)
            else:
                src, ok = index + shift * w, (row + shift >= 0) & (row + shift < h)
            out = out + float(weight) * dr.gather(jit.Float64, image, jit.UInt32(src), ok)
        return out

    def __call__(self, c: Array) -> tuple[float, Array]:
        """The loss at coefficients ``c`` (flat) and its gradient in them."""
        dr, jit = self._dr, self._jit
        F = jit.Float64
        coeffs = F(np.asarray(c, float).ravel())
        dr.enable_grad(coeffs)
        (ox, oy, oz), (dx, dy, dz) = self._o, self._d
        fixed = dr.detach(coeffs)
        t = self._t
        for _ in range(NEWTON_STEPS):  # NaN once a ray leaves the spline, as in NumPy
            z, zx, zy, defined = self._spline(fixed, ox + t * dx, oy + t * dy)
            z = dr.select(defined, z, np.nan)
            t = t - (oz + t * dz - z) / (dz - zx * dx - zy * dy)
        hit = dr.isfinite(t)
        t = dr.select(hit, t, self._t)
        self._t = dr.detach(t)
        dr.eval(self._t)
        # The hit's implicit derivative: its value t, its gradient dz/dc over the denominator.
        z, zx, zy, inside = self._spline(coeffs, ox + t * dx, oy + t * dy)
        denom = dr.detach(dz - zx * dx - zy * dy)
        ta = t + (z - dr.detach(z)) / denom
        px, py, pz = ox + ta * dx, oy + ta * dy, oz + ta * dz
        _, gx, gy, _ = self._spline(coeffs, px, py)
        gx, gy = gx + self._s[0], gy + self._s[1]
        inv = dr.rsqrt(gx * gx + gy * gy + 1.0)
        nx, ny, nz = -gx * inv, -gy * inv, inv
        dn = dx * nx + dy * ny + dz * nz
        rx, ry, rz = dx - 2.0 * dn * nx, dy - 2.0 * dn * ny, dz - 2.0 * dn * nz
        s = (self._z_h - pz) / rz
        X, Y, Z = px + s * rx, py + s * ry, pz + s * rz
        R, tc = self._R, self._tc
        qx = R[0][0] * X + R[0][1] * Y + R[0][2] * Z + tc[0]
        qy = R[1][0] * X + R[1][1] * Y + R[1][2] * Z + tc[1]
        qz = R[2][0] * X + R[2][1] * Y + R[2][2] * Z + tc[2]
        col = self._f * qx / qz + (self._w_px - 1) / 2.0
        row = self._f * qy / qz + (self._h - 1) / 2.0
        ok = (hit & inside & dr.isfinite(col) & dr.isfinite(row) & (s > 0) & (qz > 0)
              & (col > -0.5) & (col < self._w_px - 0.5) & (row > -0.5) & (row < self._h - 0.5))
        col, row = dr.select(ok, col, 0.0), dr.select(ok, row, 0.0)
        weight = dr.select(ok, self._w, 0.0)
        image = self._splat(col, row, weight)
        image = self._blur_axis(self._blur_axis(image, along_x=False), along_x=True)
        res = (image + self._background - self._observed) * self._mask
        loss = 0.5 * dr.sum(res * res) / self._norm
        dr.backward(loss)
        grad = np.asarray(dr.grad(coeffs).numpy(), float)
        return float(np.asarray(loss.numpy()).ravel()[0]), grad

    def _splat(self, col: Any, row: Any, weight: Any) -> Any:
        """Bilinear splats of the particles into the (H, W) image, flat (as
        :meth:`restoration.pattern_model.Raster.splat`: one pixel of border, cells clipped)."""
        dr, jit = self._dr, self._jit
        h, w = self._h, self._w_px
        i0x, i0y = dr.floor(dr.detach(col)), dr.floor(dr.detach(row))
        fx, fy = col - i0x, row - i0y
        cx = dr.clip(jit.Int32(i0x), -1, w - 1) + 1
        cy = dr.clip(jit.Int32(i0y), -1, h - 1) + 1
        stride = w + 2
        padded = dr.zeros(jit.Float64, (h + 2) * stride)
        for ddy, wy in ((0, 1.0 - fy), (1, fy)):
            for ddx, wx in ((0, 1.0 - fx), (1, fx)):
                dr.scatter_reduce(dr.ReduceOp.Add, padded, weight * wy * wx,
                                  jit.UInt32((cy + ddy) * stride + cx + ddx))
        index = dr.arange(jit.Int32, h * w)
        inner = (index // w + 1) * stride + index % w + 1
        return dr.gather(jit.Float64, padded, jit.UInt32(inner))

