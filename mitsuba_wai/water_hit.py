"""The water mesh's first hit along steep rays, found on its grid instead of through Embree.

The water is a regular grid of vertices with two triangles per cell
(:func:`wai_core.heightfield.grid_faces`), so along a ray ``o + t d`` the height of the mesh
under the ray is a continuous, piecewise-linear function of ``t``. Where the ray climbs faster
than any facet, ``d_z > s |d_xy|`` with ``s`` the steepest facet's slope, the difference
``f(t) = o_z + t d_z - z_mesh(t)`` strictly increases: the ray meets the mesh at most once,
and Newton's method on ``f`` jumps from facet to facet straight to that crossing (each step is
the intersection with the plane of the facet under the current point; once the point lies in
the facet whose plane gave it, it is the mesh's hit). The hit is then what Mitsuba's mesh makes
of Embree's: the point, the facet's geometric normal ``normalize(cross(p1 - p0, p2 - p0))``
and the shading normal interpolated from the vertex normals by the hit's barycentrics.

Rays this cannot settle (not steep enough, no settled facet after the steps, or a crossing off
the grid, where the mesh may or may not lie in the way) are left to Embree, so the answer is
the mesh's for every ray: the grid only saves Embree's traversal for the rays it can settle,
in the repository's scenes nearly all of them.

:class:`WaterGeometry` holds the water's mesh in a scene of its own: the one acceleration
structure the direct tracers of both systems ask (:mod:`mitsuba_wai.particles`,
:mod:`mitsuba_wai.view_tracer`), so a new surface costs one Embree build, not one per scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mitsuba_wai.mesh import set_mesh_buffers, to_mitsuba
from mitsuba_wai.variant import mitsuba
from wai_core.heightfield import grid_faces

__all__ = ["SceneWater", "WaterGeometry", "WaterGrid", "slope_bound", "water_grid",
           "water_intersect"]

# Newton steps before the last facet's (each a facet's plane): the paper's steep rays settle
# in one and the last; the few others go to Embree.
_STEPS = 1


@dataclass(frozen=True)
class WaterGrid:
    """The regular grid of a water mesh (:func:`water_grid`).

    Attributes
    ----------
    x0, y0 : float
        Lab position of vertex ``(0, 0)``, mm.
    dx, dy : float
        Vertex spacing along x (columns) and y (rows), mm.
    nx, ny : int
        Columns and rows of vertices.
    """

    x0: float
    y0: float
    dx: float
    dy: float
    nx: int
    ny: int


def water_grid(mesh: Any) -> WaterGrid | None:
    """The grid of a Mitsuba mesh whose vertices are a regular row-major grid (rows along y,
    columns along x, uniformly spaced) and whose faces are :func:`grid_faces`'s, all of them;
    None for any other mesh (one with holes, say), which Embree alone intersects.

    Parameters
    ----------
    mesh : mitsuba.Mesh
        The water mesh, its buffers evaluated (read back here: ~20k vertices).

    Returns
    -------
    WaterGrid or None
    """
    positions = np.asarray(mesh.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
    if positions.shape[0] < 4:
        return None
    x, y = positions[:, 0], positions[:, 1]
    nx = int(np.argmax(x[1:] <= x[:-1]) + 1) if np.any(x[1:] <= x[:-1]) else x.size
    if nx < 2 or x.size % nx or x.size // nx < 2:
        return None
    ny = x.size // nx
    xs, ys = x.reshape(ny, nx), y.reshape(ny, nx)
    gx, gy = xs[0], ys[:, 0]
    dx, dy = (gx[-1] - gx[0]) / (nx - 1), (gy[-1] - gy[0]) / (ny - 1)
    tol = 1e-5 * max(1.0, float(np.abs(positions[:, :2]).max()))
    regular = (
        dx > 0 and dy > 0
        and np.abs(xs - gx[None, :]).max() <= tol and np.abs(ys - gy[:, None]).max() <= tol
        and np.abs(gx - (gx[0] + dx * np.arange(nx))).max() <= tol
        and np.abs(gy - (gy[0] + dy * np.arange(ny))).max() <= tol
    )
    if not regular:
        return None
    faces = np.asarray(mesh.faces_buffer())
    if not np.array_equal(faces, grid_faces(ny, nx).ravel()):
        return None
    return WaterGrid(float(gx[0]), float(gy[0]), float(dx), float(dy), nx, ny)


def _facet(grid: WaterGrid, heights: Any, px: Any, py: Any) -> tuple[Any, ...]:
    """The facet under lab points ``(px, py)`` (cells clamped to the grid): its first vertex
    index, whether it is the cell's upper triangle ``(a, d, c)`` (else ``(a, b, d)``), the
    cell's local coordinates ``u, v`` (in cell widths) and the facet's plane as the height at
    vertex ``a``, its lab position and the slopes ``dz/dx``, ``dz/dy``."""
    import drjit as dr

    mi = mitsuba()
    fu = (px - grid.x0) * (1.0 / grid.dx)
    fv = (py - grid.y0) * (1.0 / grid.dy)
    col = dr.clip(mi.Int32(dr.floor(fu)), 0, grid.nx - 2)
    row = dr.clip(mi.Int32(dr.floor(fv)), 0, grid.ny - 2)
    u, v = fu - mi.Float(col), fv - mi.Float(row)
    upper = v > u
    a = mi.UInt32(row * grid.nx + col)
    za = dr.gather(mi.Float, heights, a)
    zd = dr.gather(mi.Float, heights, a + grid.nx + 1)
    zo = dr.gather(mi.Float, heights, dr.select(upper, a + grid.nx, a + 1))  # c or b
    gu = dr.select(upper, zd - zo, zo - za) * (1.0 / grid.dx)
    gv = dr.select(upper, zo - za, zd - zo) * (1.0 / grid.dy)
    xa = grid.x0 + mi.Float(col) * grid.dx
    ya = grid.y0 + mi.Float(row) * grid.dy
    return a, upper, u, v, za, xa, ya, gu, gv


def water_intersect(scene: Any, mesh: Any, grid: WaterGrid | None, ray: Any, slope: Any,
                    active: Any) -> Any:
    """The first hit of ``ray`` on the water mesh, as ``scene.ray_intersect`` (minimal flags and
    the shading frame) gives it where the water is the scene's only shape in the rays' way.

    Parameters
    ----------
    scene : mitsuba.Scene
        Holds ``mesh``; Embree intersects it for the rays the grid cannot settle.
    mesh : mitsuba.Mesh
        The water mesh (vertex normals).
    grid : WaterGrid or None
        Its grid (:func:`water_grid`); None: Embree for every ray.
    ray : mitsuba.Ray3f, (n,)
        Lab, mm; unit directions.
    slope : mitsuba.Float, (1,)
        A bound of the facets' slopes ``|grad z|`` (:func:`slope_bound`).
    active : mitsuba.Bool, (n,)

    Returns
    -------
    mitsuba.SurfaceInteraction3f, (n,)
        ``t`` (inf where nothing is hit), ``p``, ``n`` (the facet's), ``sh_frame``, ``wi``,
        ``time``, ``wavelengths``; ``shape`` the water where hit.
    """
    import drjit as dr

    mi = mitsuba()
    flags = mi.RayFlags.Minimal | mi.RayFlags.ShadingFrame
    if grid is None:
        return scene.ray_intersect(ray, flags, True, active)
    o, d = ray.o, ray.d
    steep = active & (d.z > slope * dr.norm(mi.Vector2f(d.x, d.y)))
    positions = mesh.vertex_positions_buffer()
    heights = dr.gather(mi.Float, positions, dr.arange(mi.UInt32, grid.nx * grid.ny) * 3 + 2)
    # Start where the ray meets the plane of the mean vertex height.
    t = (dr.mean(heights) - o.z) / d.z
    for _ in range(_STEPS):
        px, py = dr.fma(d.x, t, o.x), dr.fma(d.y, t, o.y)
        _, _, _, _, za, xa, ya, gu, gv = _facet(grid, heights, px, py)
        t = (za + gu * (o.x - xa) + gv * (o.y - ya) - o.z) / (d.z - gu * d.x - gv * d.y)
    # The last facet under the point, by its own vertices (Mitsuba's float32 geometry).
    px, py = dr.fma(d.x, t, o.x), dr.fma(d.y, t, o.y)
    a, upper, u, v, *_ = _facet(grid, heights, px, py)
    i1 = dr.select(upper, a + grid.nx + 1, a + 1)
    i2 = dr.select(upper, a + grid.nx, a + grid.nx + 1)
    p0, p1, p2 = (dr.gather(mi.Point3f, positions, i) for i in (a, i1, i2))
    n = dr.normalize(dr.cross(p1 - p0, p2 - p0))
    t_hit = dr.dot(p0 - o, n) / dr.dot(d, n)
    px, py = dr.fma(d.x, t_hit, o.x), dr.fma(d.y, t_hit, o.y)
    a_hit, upper_hit, u, v, *_ = _facet(grid, heights, px, py)
    fu = (px - grid.x0) * (1.0 / grid.dx)
    fv = (py - grid.y0) * (1.0 / grid.dy)
    on_grid = ((fu >= 0.0) & (fv >= 0.0) & (fu <= grid.nx - 1) & (fv <= grid.ny - 1))
    # Settled: the hit lies on the facet whose plane gave it (a point on an edge between two
    # facets may not settle; Embree takes it).
    resolved = steep & on_grid & (a_hit == a) & (upper_hit == upper) & (t_hit > 0.0)
    # Barycentrics of (p0, p1, p2): (a, b, d) has b1 = u - v, b2 = v; (a, d, c) b1 = u, b2 = v - u.
    b1 = dr.clip(dr.select(upper, u, u - v), 0.0, 1.0)
    b2 = dr.clip(dr.select(upper, v - u, v), 0.0, 1.0 - b1)
    b0 = 1.0 - b1 - b2
    normals = mesh.vertex_normals_buffer()
    n0, n1, n2 = (dr.gather(mi.Normal3f, normals, i) for i in (a, i1, i2))
    ns = dr.normalize(dr.fma(n2, b2, dr.fma(n1, b1, n0 * b0)))
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(t_hit))
    si.t = dr.select(resolved, t_hit, dr.inf)
    si.p = dr.fma(d, t_hit, o)
    si.n = mi.Normal3f(n)
    # Mitsuba's shading frame: its s the first edge p1 - p0 (the mesh's dp/du) made normal to ns.
    e1 = p1 - p0
    s_axis = dr.normalize(dr.fma(-ns, dr.dot(ns, e1), e1))
    si.sh_frame = mi.Frame3f(s_axis, dr.cross(ns, s_axis), ns)
    si.wi = si.to_local(-d)
    si.time = ray.time
    si.wavelengths = ray.wavelengths
    si.shape = mi.ShapePtr(mesh)
    # Embree for the rest (rays flatter than a facet, crossings off the grid, unsettled ones).
    rest = scene.ray_intersect(ray, flags, True, active & ~resolved)
    return dr.select(resolved, si, rest)


def slope_bound(mesh: Any) -> Any:
    """Steepest facet slope ``|grad z|`` of a mesh, a little over it (a bound of every
    triangle's), as a one-element Dr.Jit array: computed where the mesh is, no read-back."""
    import drjit as dr

    mi = mitsuba()
    faces = dr.unravel(mi.Vector3u, mesh.faces_buffer())
    positions = mesh.vertex_positions_buffer()
    a, b, c = (dr.gather(mi.Point3f, positions, k) for k in faces)
    normal = dr.cross(b - a, c - a)
    slope = dr.norm(mi.Vector2f(normal.x, normal.y)) / dr.abs(normal.z)
    return dr.max(dr.select(dr.isfinite(slope), slope, 0.0)) * 1.01 + 1e-6


class WaterGeometry:
    """The water's mesh and the scene the direct tracers ask for its hits and for whether it
    lies in a ray's way (:func:`water_intersect`, ``ray_test``).

    A system's scene holds the water beside other shapes (the diffuser below it, the object
    above it), and every new surface rebuilds each scene's acceleration structure: on a fine
    mesh (640 000 triangles) one build takes longer than a render. The direct tracers ask
    only about the water (their rays start past the diffuser, and the object is met on its
    own plane), so one scene holding the water alone answers both systems, built once a
    surface (:meth:`own`, :meth:`update`); :meth:`of` borrows a system's scene and mesh as
    they are.

    Attributes
    ----------
    scene : mitsuba.Scene
        Holds :attr:`mesh` (and, when borrowed, the system's other shapes).
    mesh : mitsuba.Mesh
        The water, its vertex normals the surface's.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core.heightfield import Heightfield
    >>> x = y = np.linspace(-100.0, 100.0, 5)
    >>> water = WaterGeometry.own(Heightfield(x, y, np.full((5, 5), 150.0)).to_trimesh())
    >>> (water.grid.nx, water.grid.ny)
    (5, 5)
    """

    def __init__(self, scene: Any, mesh: Any, owned: bool = False) -> None:
        self.scene = scene
        self.mesh = mesh
        self._params = mitsuba().traverse(scene) if owned else None
        self._grid: tuple[WaterGrid | None] | None = None
        self._slope: Any = None

    @classmethod
    def own(cls, tm: Any) -> WaterGeometry:
        """The water of the ``trimesh`` ``tm`` in a scene of its own."""
        mesh = to_mitsuba(tm, "water", {"type": "diffuse"})  # never shaded: the systems' BSDFs
        return cls(mitsuba().load_dict({"type": "scene", "water": mesh}), mesh, owned=True)

    @classmethod
    def of(cls, scene: Any) -> WaterGeometry:
        """A system's scene and its ``water`` mesh, as they are."""
        return cls(scene, {shape.id(): shape for shape in scene.shapes()}["water"])

    def update(self, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray | None
               ) -> None:
        """New buffers (:func:`mitsuba_wai.mesh.set_mesh_buffers`) for an owned geometry."""
        if self._params is None:
            raise ValueError("a borrowed water geometry changes with its own scene")
        set_mesh_buffers(self._params, vertices, normals, faces, prefix="water.")
        self._grid = None
        self._slope = None

    @property
    def grid(self) -> WaterGrid | None:
        """The mesh's grid (:func:`water_grid`), found once a surface."""
        if self._grid is None:
            self._grid = (water_grid(self.mesh),)
        return self._grid[0]

    @property
    def slope(self) -> Any:
        """:func:`slope_bound` of the mesh, once a surface."""
        if self._slope is None:
            import drjit as dr

            self._slope = slope_bound(self.mesh)
            dr.eval(self._slope)
        return self._slope

    def intersect(self, ray: Any, active: Any) -> Any:
        """The water's first hit along ``ray`` (:func:`water_intersect`)."""
        return water_intersect(self.scene, self.mesh, self.grid, ray, self.slope, active)

    def occluded(self, ray: Any, active: Any) -> Any:
        """Whether the water (and, when borrowed, the scene's other shapes) lies on ``ray``
        before its ``maxt``."""
        return self.scene.ray_test(ray, active)


class SceneWater:
    """The water of a renderer's scenes, swapped per surface: the shared :class:`WaterGeometry`
    at once, each system's scene only when a render goes through it (Mitsuba's integrators,
    the general tracers), so a frame whose renders all take the direct tracers rebuilds one
    acceleration structure.

    Parameters
    ----------
    params : dict
        Each scene's ``mitsuba.traverse`` (its water's buffers ``water.*``), by key.
    geometry : WaterGeometry, optional
        The direct tracers' water; None: every scene is updated with each surface.
    """

    def __init__(self, params: dict[str, Any], geometry: WaterGeometry | None) -> None:
        self._params = params
        self.geometry = geometry
        self._buffers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._faces: dict[str | None, np.ndarray] = {}  # the faces each holds (None: geometry)
        self._stale: set[str] = set()

    def set(self, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> None:
        """A new surface's flat buffers (:func:`mitsuba_wai.mesh.surface_buffers`)."""
        self._buffers = (vertices, normals, faces)
        self._stale = set(self._params)
        if self.geometry is None:
            self.sync(self._params)
            return
        self.geometry.update(vertices, normals, self._new_faces(None, faces))

    def sync(self, keys: Any) -> None:
        """Bring the scenes ``keys`` to the last surface."""
        for key in [k for k in keys if k in self._stale]:
            vertices, normals, faces = self._buffers
            set_mesh_buffers(self._params[key], vertices, normals, self._new_faces(key, faces),
                             prefix="water.")
            self._stale.discard(key)

    def _new_faces(self, key: str | None, faces: np.ndarray) -> np.ndarray | None:
        """``faces`` where they differ from those ``key`` holds (a surface's holes), else
        None: the grid's stay."""
        same = key in self._faces and np.array_equal(faces, self._faces[key])
        self._faces[key] = faces
        return None if same else faces
