"""A water surface as heights on a rectilinear grid, with smooth interpolation and ray hits.

The file format (``heightfield.npz``, ``--heightfield``) holds arrays ``x`` (n,), ``y`` (m,), both
strictly increasing, mm, ``lab`` frame, and ``z`` (m, n): absolute heights in mm, ``z[j, i]`` at
``(x[i], y[j])``. Between samples the surface is the bicubic interpolating spline (scipy's
``RectBivariateSpline``, k = 3), so slopes are continuous and exact for cubics.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import BSpline, RectBivariateSpline

from wai_core.errors import WaiInputError

if TYPE_CHECKING:  # imported where used: trimesh is slow to import and swallows Ctrl-C then
    import trimesh

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Heightfield:
    """Heights ``z`` (m, n) in mm over ``x`` (n,) and ``y`` (m,) in mm, ``lab`` frame.

    ``z`` may hold NaN where the surface is unknown (a reconstruction's uncovered border);
    :meth:`height` then returns NaN near those samples.
    """

    x: Array
    y: Array
    z: Array

    def __post_init__(self) -> None:
        x = np.asarray(self.x, dtype=float)
        y = np.asarray(self.y, dtype=float)
        z = np.asarray(self.z, dtype=float)
        if x.ndim != 1 or y.ndim != 1 or z.shape != (y.size, x.size):
            raise WaiInputError(
                f"heightfield: z must have shape (len(y), len(x)) = ({y.size}, {x.size}), "
                f"got {z.shape}"
            )
        if x.size < 4 or y.size < 4:
            raise WaiInputError("heightfield: needs at least 4 samples along x and along y")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise WaiInputError("heightfield: x or y holds NaN or inf")
        if np.any(np.diff(x) <= 0) or np.any(np.diff(y) <= 0):
            raise WaiInputError("heightfield: x and y must be strictly increasing")
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", y)
        object.__setattr__(self, "z", z)
        valid = np.isfinite(z)
        if not valid.any():
            raise WaiInputError("heightfield: z holds no finite height")
        # The spline needs finite values: fill unknown samples, then mask them on evaluation.
        filled = z if valid.all() else continue_surface(x, y, z, valid)
        object.__setattr__(self, "_spline", interpolating_spline(x, y, filled))
        object.__setattr__(self, "_valid", valid)

    @property
    def has_holes(self) -> bool:
        """True when some samples are NaN."""
        return not bool(self._valid.all())

    def contains(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.bool_]:
        """True where ``(x, y)`` lies inside the grid and away from unknown samples."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        inside = (x >= self.x[0]) & (x <= self.x[-1]) & (y >= self.y[0]) & (y <= self.y[-1])
        if not self.has_holes:
            return inside
        ix = np.clip(np.searchsorted(self.x, np.where(inside, x, self.x[0])), 1, self.x.size - 1)
        iy = np.clip(np.searchsorted(self.y, np.where(inside, y, self.y[0])), 1, self.y.size - 1)
        v = self._valid
        cell_ok = v[iy, ix] & v[iy - 1, ix] & v[iy, ix - 1] & v[iy - 1, ix - 1]
        return inside & cell_ok

    def height(self, x: ArrayLike, y: ArrayLike) -> Array:
        """Surface height at points, mm; NaN outside the known surface."""
        return self._eval(x, y, 0, 0)

    def gradient(self, x: ArrayLike, y: ArrayLike) -> tuple[Array, Array]:
        """Slopes ``(dz/dx, dz/dy)`` at points (dimensionless); NaN outside."""
        return self._eval(x, y, 1, 0), self._eval(x, y, 0, 1)

    def height_gradient(self, x: ArrayLike, y: ArrayLike) -> tuple[Array, Array, Array]:
        """Height (mm) and slopes ``(dz/dx, dz/dy)`` at points in one compiled pass (the
        values of :meth:`height` and :meth:`gradient` to rounding); NaN outside.

        Examples
        --------
        >>> import numpy as np
        >>> x = y = np.linspace(0.0, 30.0, 7)
        >>> hf = Heightfield(x, y, 0.1 * x[None, :] + 0.2 * y[:, None])
        >>> h, gx, gy = hf.height_gradient(np.array([12.5]), np.array([3.0]))
        >>> [round(float(v), 9) for v in (h[0], gx[0], gy[0])]
        [1.85, 0.1, 0.2]
        """
        from wai_core._bispline import height_gradient

        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        ok = self.contains(x, y)
        out = [np.full(x.shape, np.nan) for _ in range(3)]
        if ok.any():
            n = int(ok.sum())
            h, gx, gy = np.empty(n), np.empty(n), np.empty(n)
            height_gradient(*self.compiled_spline(), np.ascontiguousarray(y[ok]),
                            np.ascontiguousarray(x[ok]), h, gx, gy)
            for o, v in zip(out, (h, gx, gy), strict=True):
                o[ok] = v
        return out[0], out[1], out[2]

    def normal(self, x: ArrayLike, y: ArrayLike) -> Array:
        """Unit normals pointing up (into the air), shape (..., 3)."""
        _, gx, gy = self.height_gradient(x, y)
        return _unit_normals(gx, gy)

    def grid_normals(self) -> Array:
        """:meth:`normal` at every grid sample, shape (len(y), len(x), 3): the spline
        evaluated on its own grid at once, the same values as pointwise.

        Examples
        --------
        >>> import numpy as np
        >>> x = y = np.linspace(0.0, 30.0, 7)
        >>> hf = Heightfield(x, y, 0.1 * x[None, :] + 0.0 * y[:, None])
        >>> xx, yy = np.meshgrid(x, y)
        >>> bool(np.allclose(hf.grid_normals(), hf.normal(xx, yy)))
        True
        """
        gx = self._spline(self.y, self.x, dx=0, dy=1)
        gy = self._spline(self.y, self.x, dx=1, dy=0)
        xx, yy = np.meshgrid(self.x, self.y)
        off = ~self.contains(xx, yy)
        gx[off] = np.nan
        gy[off] = np.nan
        return _unit_normals(gx, gy)

    def _eval(self, x: ArrayLike, y: ArrayLike, dx: int, dy: int) -> Array:
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        ok = self.contains(x, y)
        out = np.full(x.shape, np.nan)
        if ok.any():
            # RectBivariateSpline's first axis is y (rows of z).
            out[ok] = self._spline.ev(y[ok], x[ok], dx=dy, dy=dx)
        return out

    def intersect(
        self, origins: ArrayLike, dirs: ArrayLike, n_iter: int = 8, tol_mm: float = 1e-6
    ) -> tuple[Array, NDArray[np.bool_]]:
        """First hit of rays with the surface: Newton steps on ``f(t) = o_z + t d_z - z(o + t d)``.

        Starts from the hit with the horizontal plane at the mean height (rays from one origin,
        a camera's pixels in order, from the previous ray's hit, and from the plane again if
        that fails) and stops once the height residual is below 1e-9 mm. Converges in a few
        steps for the gentle slopes of sea waves; rays that do not converge, leave the grid or
        run along the surface are flagged invalid. On a surface with holes every ray starts
        from the plane and takes ``n_iter`` steps.

        Parameters
        ----------
        origins : (..., 3) or (3,) array_like
            Ray origins, mm, below the surface.
        dirs : (..., 3) array_like
            Unit directions.
        n_iter : int
            Newton steps at most.
        tol_mm : float
            The hit's largest height residual is ``1000 tol_mm`` (``1e-9`` mm at least).

        Returns
        -------
        points_mm : (..., 3) ndarray
            Hit points; NaN where invalid.
        valid : (...,) ndarray of bool
        """
        points, valid, _ = self.intersect_normals(origins, dirs, n_iter, tol_mm)
        return points, valid

    def intersect_normals(
        self, origins: ArrayLike, dirs: ArrayLike, n_iter: int = 8, tol_mm: float = 1e-6
    ) -> tuple[Array, NDArray[np.bool_], Array]:
        """:meth:`intersect`, and the unit normals (..., 3) at the hits (:meth:`normal`'s, NaN
        where invalid) from the spline evaluation that checks them: a ray's refraction or
        reflection needs both.

        Examples
        --------
        >>> import numpy as np
        >>> x = y = np.linspace(-50.0, 50.0, 11)
        >>> hf = Heightfield(x, y, 10.0 + 0.1 * x[None, :] + 0.0 * y[:, None])
        >>> p, ok, n = hf.intersect_normals(np.zeros(3), np.array([[0.0, 0.0, 1.0]]))
        >>> np.round(p[0], 9).tolist(), bool(np.allclose(n[0] * np.sqrt(1.01), [-0.1, 0, 1]))
        ([0.0, 0.0, 10.0], True)
        """
        d = np.asarray(dirs, dtype=float)
        o = np.broadcast_to(np.asarray(origins, dtype=float), d.shape)
        z_ref = float(np.nanmean(self.z))
        tol = max(tol_mm, 1e-9) * 1e3
        if not self.has_holes:
            from wai_core._bispline import intersect_rays

            flat_d = np.ascontiguousarray(d.reshape(-1, 3))
            o_in = np.asarray(origins, dtype=float)
            flat_o = (o_in.reshape(1, 3) if o_in.size == 3
                      else np.ascontiguousarray(o.reshape(-1, 3)))
            p = np.empty_like(flat_d)
            n = np.empty_like(flat_d)
            valid = np.empty(flat_d.shape[0], dtype=bool)
            intersect_rays(*self.compiled_spline(), flat_o, flat_d, z_ref, int(n_iter), tol,
                           p, n, valid)
            return p.reshape(d.shape), valid.reshape(d.shape[:-1]), n.reshape(d.shape)
        # With holes, each step's points are checked against them (:meth:`contains`).
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (z_ref - o[..., 2]) / d[..., 2]
        for _ in range(n_iter):
            p = o + t[..., None] * d
            h, gx, gy = self.height_gradient(p[..., 0], p[..., 1])
            f = p[..., 2] - h
            df = d[..., 2] - gx * d[..., 0] - gy * d[..., 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                step = f / df
            t = t - step
        p = o + t[..., None] * d
        h, gx, gy = self.height_gradient(p[..., 0], p[..., 1])
        residual = np.abs(p[..., 2] - h)
        valid = np.isfinite(residual) & (residual < tol) & (t > 0)
        p[~valid] = np.nan
        n = _unit_normals(gx, gy)
        n[~valid] = np.nan
        return p, valid, n

    def compiled_spline(self) -> tuple[NDArray, ...]:
        """The spline's knots along y and x, their :func:`~wai_core._bispline.uniform_spans`
        and :func:`~wai_core._bispline.span_table`, and its coefficients (len(ty) - 4,
        len(tx) - 4), as the compiled kernels take them; worked out once per surface."""
        cached = self.__dict__.get("_compiled")
        if cached is None:
            from wai_core._bispline import span_table, uniform_spans

            ty, tx, c = self._spline.tck  # first axis y (rows of z)
            coef = np.ascontiguousarray(c).reshape(ty.size - 4, tx.size - 4)
            cached = (ty, tx, uniform_spans(ty), uniform_spans(tx), span_table(ty),
                      span_table(tx), coef)
            object.__setattr__(self, "_compiled", cached)
        return cached

    def to_trimesh(self) -> trimesh.Trimesh:
        """Triangle mesh through the samples, normals up (counter-clockwise seen from above),
        with the spline's exact vertex normals; cells touching an unknown sample are left out."""
        import trimesh

        xx, yy = np.meshgrid(self.x, self.y)
        vertices = np.stack([xx.ravel(), yy.ravel(), self.z.ravel()], axis=1)
        faces = grid_faces(self.y.size, self.x.size)
        faces = faces[self._valid.ravel()[faces].all(axis=1)]
        normals = np.nan_to_num(self.grid_normals().reshape(-1, 3), nan=0.0)
        normals[~self._valid.ravel()] = (0.0, 0.0, 1.0)
        return trimesh.Trimesh(
            vertices=np.nan_to_num(vertices, nan=float(np.nanmean(self.z))),
            faces=faces,
            vertex_normals=normals,
            process=False,
        )

    def save(self, path: str | Path) -> None:
        """Write the ``x``, ``y``, ``z`` arrays to an ``.npz`` file."""
        np.savez_compressed(path, x=self.x, y=self.y, z=self.z)


def interpolating_spline(x: Array, y: Array, z: Array) -> RectBivariateSpline:
    """The bicubic spline through ``z`` (m, n) on axes ``x`` (n,) and ``y`` (m,), mm: scipy's
    ``RectBivariateSpline(y, x, z, kx=3, ky=3)`` (not-a-knot knots, first axis y).

    On evenly spaced axes (every gridded reconstruction) the coefficients are solved along
    each axis with that axis's collocation matrix factorised once per length
    (:func:`_collocation_lu`) by a compiled banded solve: ~0.1 ms on a 120 x 100 grid, where
    FITPACK's fit took ~1 ms a frame, and no BLAS call (OpenBLAS's threads, left spinning
    after a product, slowed the rest of the frame by a third on two cores). The same spline
    to rounding; other axes go to FITPACK.

    Examples
    --------
    >>> import numpy as np
    >>> x, y = np.linspace(0.0, 9.0, 10), np.linspace(0.0, 5.0, 6)
    >>> z = np.sin(x)[None, :] * np.cos(y)[:, None]
    >>> fast = interpolating_spline(x, y, z)
    >>> ref = RectBivariateSpline(y, x, z, kx=3, ky=3)
    >>> bool(np.allclose(fast(2.5, 3.3), ref(2.5, 3.3), rtol=0, atol=1e-12))
    True
    """
    if not (_evenly_spaced(x) and _evenly_spaced(y)):
        return RectBivariateSpline(y, x, z, kx=3, ky=3)
    coeffs = np.array(z, dtype=float, order="C")  # solved in place: along y, then along x
    _banded_solve(*_collocation_lu(y.size), coeffs)
    across = np.ascontiguousarray(coeffs.T)
    _banded_solve(*_collocation_lu(x.size), across)
    # scipy's constructor from knots and coefficients (its own, private but long-standing).
    return RectBivariateSpline._from_tck((_knots(y), _knots(x), across.T.ravel(), 3, 3))


def _evenly_spaced(a: Array) -> bool:
    step = np.diff(a)
    return bool(np.ptp(step) <= 1e-9 * abs(step[0]))


def _knots(a: Array) -> Array:
    """Not-a-knot knots of a cubic interpolating spline on nodes ``a``: FITPACK's choice."""
    return np.concatenate([np.full(4, a[0]), a[2:-2], np.full(4, a[-1])])


_BAND = 3
"""Half-bandwidth of a cubic B-spline collocation matrix (and of its LU factors)."""


@functools.lru_cache(maxsize=32)
def _collocation_lu(n: int) -> tuple[Array, Array]:
    """LU factors (n, n) (unit lower below the diagonal, upper on and above it) of the
    collocation matrix of the cubic not-a-knot B-spline on ``n`` evenly spaced nodes (it does
    not depend on their spacing or origin). A collocation matrix is totally positive, so
    elimination without pivoting is stable and keeps the band (de Boor)."""
    nodes = np.arange(float(n))
    lu = BSpline.design_matrix(nodes, _knots(nodes), 3).toarray()
    for k in range(n - 1):  # within the band: outside it every entry is and stays 0
        end = min(n, k + _BAND + 1)
        lu[k + 1 : end, k] /= lu[k, k]
        lu[k + 1 : end, k + 1 : end] -= np.outer(lu[k + 1 : end, k], lu[k, k + 1 : end])
    lower, upper = np.tril(lu, -1), np.triu(lu)
    lower.setflags(write=False)
    upper.setflags(write=False)
    return lower, upper


@numba.njit(cache=True, nogil=True)
def _banded_solve(lower, upper, rhs):  # pragma: no cover
    """Solve ``(lower + I) upper X = rhs`` (rhs (n, r), overwritten by X) for banded factors
    of half-bandwidth :data:`_BAND`, a row of right-hand sides at a time."""
    n, r = rhs.shape
    for i in range(n):
        for k in range(max(0, i - _BAND), i):
            f = lower[i, k]
            for c in range(r):
                rhs[i, c] -= f * rhs[k, c]
    for i in range(n - 1, -1, -1):
        for k in range(i + 1, min(n, i + _BAND + 1)):
            f = upper[i, k]
            for c in range(r):
                rhs[i, c] -= f * rhs[k, c]
        d = 1.0 / upper[i, i]
        for c in range(r):
            rhs[i, c] *= d


FILL_EXACT_NODES = 2
"""Nodes beyond the known samples that take the tangent-plane continuation of
:func:`continue_surface` as it is (the reach of a cubic spline's support)."""
FILL_BAND_NODES = 6
"""Distance, in grid nodes, at which the continuation has faded into the nearest known
height (a plane extended far would run away)."""


def continue_surface(x: Array, y: Array, z: Array, valid: NDArray[np.bool_]) -> Array:
    """``z`` (m, n) with its unknown samples filled by a smooth continuation of the known ones.

    Each unknown node takes the tangent plane of its nearest known node (slopes by central
    differences, one-sided at the border of the known region) up to
    :data:`FILL_EXACT_NODES` nodes out, faded into that node's height by
    :data:`FILL_BAND_NODES`. The interpolating spline through
    the filled grid then has, next to the border, the slopes of the known surface: filling
    with a constant (the mean) instead bends the spline over the last cells and puts slope
    errors of 0.01-0.1 there, which reflected rays turn into spot errors of 10-30 px and the
    reverse trace into stripes at the edge of the restored view.

    Examples
    --------
    A plane with a hole is continued as the same plane next to the hole:

    >>> import numpy as np
    >>> x = y = np.arange(10.0)
    >>> z = 2.0 + 0.1 * x[None, :] + 0.0 * y[:, None]
    >>> valid = np.ones(z.shape, bool); valid[:, 7:] = False
    >>> filled = continue_surface(x, y, np.where(valid, z, np.nan), valid)
    >>> bool(np.allclose(filled[:, 7:9], z[:, 7:9]))
    True
    """
    from scipy.ndimage import distance_transform_edt

    dist, (jn, inn) = distance_transform_edt(~valid, return_indices=True)
    out = np.array(z, dtype=float)
    _fill_holes(
        np.asarray(x, float), np.asarray(y, float), np.ascontiguousarray(valid), dist, jn, inn,
        float(FILL_EXACT_NODES), float(FILL_BAND_NODES), out,
    )
    return out


@numba.njit(cache=True, nogil=True)
def _slope(z, valid, a, j, i, dj, di):  # pragma: no cover
    """dz/da at known node (j, i) along (dj, di) with node coordinates ``a``: central where
    both neighbours are known, one-sided where one is, 0 where none is (an isolated node)."""
    m, n = z.shape
    k = i if di else j
    lo_ok = k > 0 and valid[j - dj, i - di]
    hi_ok = k < (n if di else m) - 1 and valid[j + dj, i + di]
    if lo_ok and hi_ok:
        return (z[j + dj, i + di] - z[j - dj, i - di]) / (a[k + 1] - a[k - 1])
    if hi_ok:
        return (z[j + dj, i + di] - z[j, i]) / (a[k + 1] - a[k])
    if lo_ok:
        return (z[j, i] - z[j - dj, i - di]) / (a[k] - a[k - 1])
    return 0.0


@numba.njit(cache=True, nogil=True)
def _fill_holes(x, y, valid, dist, jn, inn, exact, band, z):  # pragma: no cover
    """Fill the unknown nodes of ``z`` (m, n) in place as :func:`continue_surface` says: the
    tangent plane of the nearest known node ``(jn, inn)``, at ``dist`` nodes from it, faded
    into its height between ``exact`` and ``band`` nodes."""
    m, n = z.shape
    for j in range(m):
        for i in range(n):
            if valid[j, i]:
                continue
            j0, i0 = jn[j, i], inn[j, i]
            near = z[j0, i0]
            gx = _slope(z, valid, x, j0, i0, 0, 1)
            gy = _slope(z, valid, y, j0, i0, 1, 0)
            plane = near + gx * (x[i] - x[i0]) + gy * (y[j] - y[j0])
            w = min(max((band - dist[j, i]) / (band - exact), 0.0), 1.0)
            z[j, i] = w * plane + (1.0 - w) * near


def grid_faces(n_rows: int, n_cols: int) -> NDArray[np.int64]:
    """Triangles (2 (m-1)(n-1), 3) over a row-major vertex grid, counter-clockwise from above."""
    idx = np.arange(n_rows * n_cols).reshape(n_rows, n_cols)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    # Rows grow with +y and columns with +x, so (a, b, d) and (a, d, c) turn counter-clockwise.
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def load_heightfield(path: str | Path) -> Heightfield:
    """Read and check a heightfield ``.npz`` file (see the module docstring for the format).

    Raises
    ------
    WaiInputError
        In one line naming the file: missing, not an ``.npz`` archive (e.g. a text file), an
        array missing, not numeric, of the wrong shape, holding NaN or inf.
    """
    path = Path(path)
    if not path.is_file():
        raise WaiInputError(f"heightfield file not found: {path}")
    try:
        with path.open("rb") as f:
            magic = f.read(4)
    except OSError as exc:
        raise WaiInputError(f"heightfield {path} cannot be read: {exc.strerror}") from None
    if magic != b"PK\x03\x04":  # an .npz is a zip archive; anything else np.load would try to
        # read as a pickle (and report "pickled data")
        raise WaiInputError(
            f"heightfield {path} is not an .npz archive (numpy.savez of arrays x, y, z)"
        )
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in ("x", "y", "z") if k not in data]
            if missing:
                raise WaiInputError(f"heightfield {path}: missing array '{missing[0]}'")
            arrays = {k: data[k] for k in ("x", "y", "z")}
    except WaiInputError:
        raise
    except Exception as exc:  # corrupt zip, object arrays...
        raise WaiInputError(f"heightfield {path} cannot be read: {exc}") from None
    for name, arr in arrays.items():
        if arr.dtype.kind not in "iuf":
            raise WaiInputError(
                f"heightfield {path}: array '{name}' is not numeric (dtype {arr.dtype})"
            )
    if not np.all(np.isfinite(arrays["z"])):
        raise WaiInputError(f"heightfield {path}: z holds NaN or inf")
    try:
        return Heightfield(arrays["x"], arrays["y"], arrays["z"])
    except WaiInputError as exc:
        why = str(exc).removeprefix("heightfield: ")
        raise WaiInputError(f"heightfield {path}: {why}") from None


def _unit_normals(gx: Array, gy: Array) -> Array:
    """Unit normals (..., 3), pointing up, of a surface with slopes ``dz/dx = gx``,
    ``dz/dy = gy`` (...,)."""
    inv = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
    return np.stack([-gx * inv, -gy * inv, inv], axis=-1)
