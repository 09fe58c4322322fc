"""The Longuet-Higgins sum (eq. 38) on the renderer's device, one Dr.Jit lane per grid point.

:meth:`mitsuba_wai.waves.SeaSurface.grid` sums the harmonics on the host as one matrix
product (BLAS, float64), which on a CPU is the fastest way there is. On a GPU the host's
product is the slow part of a frame: :class:`JitWaveGrid` evaluates the same sum on the
backend of the active Mitsuba variant (``drjit.cuda`` on ``cuda_ad_rgb``, ``drjit.llvm`` on
``llvm_ad_rgb``), in float64, each lane a grid point looping over the harmonics:

    eta = sum_c Re(A_c exp(-i (kx_c x + ky_c y))),   A_c = a_c exp(i (omega_c t + eps_c))

and, when asked, the exact slopes ``d eta/dx = sum_c kx_c Im(A_c exp(-i (kx_c x + ky_c y)))``
(likewise in y). The complex amplitudes ``A_c`` are formed on the host per time (C numbers);
the grid's points stay on the device for the grid's life, so a dataset's worker keeps one grid per
mesh level and hands it each frame's sea. The heights agree with the host's product to float64
rounding of the sum (under 1e-12 mm on the paper's sea, ``tests/mitsuba_wai/test_waves_jit.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mitsuba_wai.variant import jit_arrays
from mitsuba_wai.waves import SeaSurface
from wai_core.heightfield import Heightfield

__all__ = ["JitWaveGrid"]


class JitWaveGrid:
    """One rectilinear grid's points on the renderer's device, where seas are summed.

    Parameters
    ----------
    x_mm : (n,) array_like
        Strictly increasing x samples, mm.
    y_mm : (m,) array_like
        Strictly increasing y samples, mm.

    Examples
    --------
    >>> import numpy as np
    >>> from mitsuba_wai import sea_surface
    >>> from wai_core import load_system
    >>> sea = sea_surface(load_system("paper").waves)
    >>> x, y = np.linspace(0.0, 200.0, 21), np.linspace(-50.0, 50.0, 11)
    >>> grid = JitWaveGrid(x, y)
    >>> z = grid.heightfield(sea, 10.0, mean_level_mm=150.0).z
    >>> bool(np.allclose(z, sea.grid(x, y, 10.0, mean_level_mm=150.0).z, atol=1e-9))
    True
    """

    def __init__(self, x_mm: ArrayLike, y_mm: ArrayLike) -> None:
        import drjit as dr

        jit = jit_arrays()
        self.x_mm = np.asarray(x_mm, dtype=float).ravel()
        self.y_mm = np.asarray(y_mm, dtype=float).ravel()
        self._jit = jit
        n, m = self.x_mm.size, self.y_mm.size
        lane = dr.arange(jit.UInt32, n * m)
        self._x = dr.gather(jit.Float64, jit.Float64(self.x_mm), lane % n)
        self._y = dr.gather(jit.Float64, jit.Float64(self.y_mm), lane // n)
        dr.eval(self._x, self._y)

    @property
    def shape(self) -> tuple[int, int]:
        """``(m, n)``: rows (y) by columns (x)."""
        return self.y_mm.size, self.x_mm.size

    def eta(self, sea: SeaSurface, time_s: float, slopes: bool = False) -> tuple[Any, ...]:
        """The elevation of ``sea`` about its mean level (mm) at every grid point, row-major,
        as a Dr.Jit Float64 array on the device (and ``d eta/dx``, ``d eta/dy`` when
        ``slopes``).

        Parameters
        ----------
        sea : SeaSurface
            The harmonics (:func:`mitsuba_wai.sea_surface`).
        time_s : float
            Time, s.
        slopes : bool
            Also the exact slopes (dimensionless).

        Returns
        -------
        tuple of Dr.Jit Float64 arrays, each (m n,)
            ``(eta,)`` or ``(eta, d eta/dx, d eta/dy)``.
        """
        import drjit as dr

        jit = self._jit
        a, kx_host, ky_host, omega, eps = sea.harmonics()
        x, y = self._x, self._y
        width = dr.width(x)
        if not a.size:  # calm: nothing to sum
            return tuple(dr.zeros(jit.Float64, width) for _ in range(3 if slopes else 1))
        amp = a * np.exp(1j * (omega * float(time_s) + eps))
        re, im = jit.Float64(amp.real), jit.Float64(amp.imag)
        kx_all, ky_all = jit.Float64(kx_host), jit.Float64(ky_host)

        def body(c: Any, z: Any, sx: Any, sy: Any) -> tuple[Any, ...]:
            kx = dr.gather(jit.Float64, kx_all, c)
            ky = dr.gather(jit.Float64, ky_all, c)
            s, co = dr.sincos(kx * x + ky * y)
            # A exp(-i p) = (re co + im s) + i (im co - re s)
            a_re = dr.gather(jit.Float64, re, c)
            a_im = dr.gather(jit.Float64, im, c)
            z = dr.fma(a_re, co, dr.fma(a_im, s, z))
            if slopes:
                part = dr.fma(a_im, co, -a_re * s)
                sx = dr.fma(kx, part, sx)
                sy = dr.fma(ky, part, sy)
            return c + 1, z, sx, sy

        state = (dr.zeros(jit.UInt32, width), *(dr.zeros(jit.Float64, width) for _ in range(3)))
        count = dr.opaque(jit.UInt32, int(a.size))
        _, z, sx, sy = dr.while_loop(state, lambda c, *_: c < count, body)
        return (z, sx, sy) if slopes else (z,)

    def heightfield(self, sea: SeaSurface, time_s: float, mean_level_mm: float = 0.0
                    ) -> Heightfield:
        """The surface ``z = mean_level_mm + eta`` of ``sea`` at ``time_s`` as a host
        :class:`~wai_core.heightfield.Heightfield` (m, n), mm: what
        :meth:`SeaSurface.grid <mitsuba_wai.waves.SeaSurface.grid>` returns, summed on the
        device."""
        (z,) = self.eta(sea, time_s)
        heights: NDArray[np.float64] = np.asarray(z, dtype=float).reshape(self.shape)
        return Heightfield(self.x_mm, self.y_mm, heights + float(mean_level_mm))
