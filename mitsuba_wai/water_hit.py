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
the grid, where the mesh may or may not lie in the way) are left to Embree, or march over the
grid's cells (:func:`_march`), so the answer is the mesh's for every ray: the grid saves
Embree's traversal for the rays it can settle, in the repository's scenes nearly all of them.

:class:`WaterGeometry` answers the direct tracers of both systems (:mod:`mitsuba_wai.particles`,
:mod:`mitsuba_wai.view_tracer`) on the grid alone, the rays the facets do not settle marched
over its cells (:func:`_march`): a new surface then costs no Embree build.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mitsuba_wai.mesh import set_mesh_buffers, to_mitsuba
from mitsuba_wai.variant import mitsuba
from wai_core.heightfield import grid_faces

__all__ = ["WaterGeometry", "WaterGrid", "slope_bound", "water_grid", "water_intersect"]

# Newton steps before the last facet's (each a facet's plane): with two, all but a few in 10^4
# of the paper's steep rays settle on the finest meshes (with one, up to 5 % did not); the rest
# go to Embree or the march.
_STEPS = 2


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
    scene : mitsuba.Scene or None
        Holds ``mesh``; Embree intersects it for the rays the grid's facets cannot settle.
        None: those rays march over the grid's cells (:func:`_march`), no Embree.
    mesh : mitsuba.Mesh
        The water mesh (vertex normals).
    grid : WaterGrid or None
        Its grid (:func:`water_grid`); None: Embree for every ray (``scene`` needed).
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
    heights = _heights(grid, positions)
    # Start where the ray meets the plane of the mean vertex height.
    t = (dr.mean(heights) - o.z) / d.z
    for _ in range(_STEPS):
        px, py = dr.fma(d.x, t, o.x), dr.fma(d.y, t, o.y)
        _, _, _, _, za, xa, ya, gu, gv = _facet(grid, heights, px, py)
        t = (za + gu * (o.x - xa) + gv * (o.y - ya) - o.z) / (d.z - gu * d.x - gv * d.y)
    # The last facet under the point, by its own vertices (Mitsuba's float32 geometry).
    px, py = dr.fma(d.x, t, o.x), dr.fma(d.y, t, o.y)
    a, upper, *_ = _facet(grid, heights, px, py)
    hit = _facet_hit(grid, positions, a, upper, o, d)
    a_hit, upper_hit, *_ = _facet(grid, heights, hit.px, hit.py)
    on_grid = ((hit.fu >= 0.0) & (hit.fv >= 0.0) & (hit.fu <= grid.nx - 1)
               & (hit.fv <= grid.ny - 1))
    # Settled: the hit lies on the facet whose plane gave it (a point on an edge between two
    # facets may not settle; Embree or the march takes it).
    resolved = steep & on_grid & (a_hit == a) & (upper_hit == upper) & (hit.t > 0.0)
    if scene is not None:
        si = _interaction(mesh, hit, a, upper, ray, resolved)
        # Embree for the rest (rays flatter than a facet, crossings off the grid, unsettled).
        rest = scene.ray_intersect(ray, flags, True, active & ~resolved)
        return dr.select(resolved, si, rest)
    # The rest marched over the grid's cells: the first facet each meets.
    found, a_m, upper_m = _march(grid, positions, heights, o, d, dr.inf, active & ~resolved,
                                 steep)
    a, upper = dr.select(resolved, a, a_m), dr.select(resolved, upper, upper_m)
    hit = _facet_hit(grid, positions, a, upper, o, d)
    return _interaction(mesh, hit, a, upper, ray, resolved | (found & (hit.t > 0.0)))


def _heights(grid: WaterGrid, positions: Any) -> Any:
    """The heights (mm) of a grid mesh's vertices, from its flat position buffer."""
    import drjit as dr

    mi = mitsuba()
    return dr.gather(mi.Float, positions, dr.arange(mi.UInt32, grid.nx * grid.ny) * 3 + 2)


@dataclass
class _FacetHit:
    """A ray's hit on the plane of a given facet: its vertices, unit normal, distance, lab
    point ``(px, py)``, grid coordinates ``(fu, fv)`` (in cell widths) and the point's
    coordinates ``(u, v)`` in the facet's cell."""

    p0: Any
    p1: Any
    p2: Any
    i1: Any
    i2: Any
    n: Any
    t: Any
    px: Any
    py: Any
    fu: Any
    fv: Any
    u: Any
    v: Any


def _facet_hit(grid: WaterGrid, positions: Any, a: Any, upper: Any, o: Any, d: Any
               ) -> _FacetHit:
    """Where rays ``o + t d`` meet the planes of the facets ``(a, upper)`` (module notes)."""
    import drjit as dr

    mi = mitsuba()
    i1 = dr.select(upper, a + grid.nx + 1, a + 1)
    i2 = dr.select(upper, a + grid.nx, a + grid.nx + 1)
    p0, p1, p2 = (dr.gather(mi.Point3f, positions, i) for i in (a, i1, i2))
    n = dr.normalize(dr.cross(p1 - p0, p2 - p0))
    t = dr.dot(p0 - o, n) / dr.dot(d, n)
    px, py = dr.fma(d.x, t, o.x), dr.fma(d.y, t, o.y)
    fu = (px - grid.x0) * (1.0 / grid.dx)
    fv = (py - grid.y0) * (1.0 / grid.dy)
    u = fu - mi.Float(mi.Int32(a % grid.nx))
    v = fv - mi.Float(mi.Int32(a // grid.nx))
    return _FacetHit(p0, p1, p2, i1, i2, n, t, px, py, fu, fv, u, v)


def _interaction(mesh: Any, hit: _FacetHit, a: Any, upper: Any, ray: Any, valid: Any) -> Any:
    """The surface interaction of rays at their facet hits, as Mitsuba's mesh makes it of
    Embree's (``t`` inf where not ``valid``)."""
    import drjit as dr

    mi = mitsuba()
    u, v = hit.u, hit.v
    # Barycentrics of (p0, p1, p2): (a, b, d) has b1 = u - v, b2 = v; (a, d, c) b1 = u, b2 = v - u.
    b1 = dr.clip(dr.select(upper, u, u - v), 0.0, 1.0)
    b2 = dr.clip(dr.select(upper, v - u, v), 0.0, 1.0 - b1)
    b0 = 1.0 - b1 - b2
    normals = mesh.vertex_normals_buffer()
    n0, n1, n2 = (dr.gather(mi.Normal3f, normals, i) for i in (a, hit.i1, hit.i2))
    ns = dr.normalize(dr.fma(n2, b2, dr.fma(n1, b1, n0 * b0)))
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(hit.t))
    si.t = dr.select(valid, hit.t, dr.inf)
    si.p = dr.fma(ray.d, hit.t, ray.o)
    si.n = mi.Normal3f(hit.n)
    # Mitsuba's shading frame: its s the first edge p1 - p0 (the mesh's dp/du) made normal to ns.
    e1 = hit.p1 - hit.p0
    s_axis = dr.normalize(dr.fma(-ns, dr.dot(ns, e1), e1))
    si.sh_frame = mi.Frame3f(s_axis, dr.cross(ns, s_axis), ns)
    si.wi = si.to_local(-ray.d)
    si.time = ray.time
    si.wavelengths = ray.wavelengths
    si.shape = mi.ShapePtr(mesh)
    return si


# How far (mm) a steep ray must lie below the mesh where it leaves the grid, or above it where
# it enters, to be taken as missing it without a march: well past float32 rounding at 150 mm.
_SIDE_MM = 1e-3


def _slab(lo: float, hi: float, oc: Any, dc: Any) -> tuple[Any, Any]:
    """The distances along rays (origins ``oc``, directions ``dc`` along one axis) between
    which they lie within ``[lo, hi]`` on that axis (infinite for a ray parallel to it)."""
    import drjit as dr

    flat = dr.abs(dc) < 1e-12
    inside = (oc >= lo) & (oc <= hi)
    ta, tb = (lo - oc) / dc, (hi - oc) / dc
    t_in = dr.select(flat, dr.select(inside, -dr.inf, dr.inf), dr.minimum(ta, tb))
    t_out = dr.select(flat, dr.select(inside, dr.inf, -dr.inf), dr.maximum(ta, tb))
    return t_in, t_out


def _above_mesh(grid: WaterGrid, heights: Any, o: Any, d: Any, t: Any) -> Any:
    """How far (mm) the points ``o + t d`` lie above the mesh's facet under them (on the grid:
    the cell clamped at its edges)."""
    import drjit as dr

    px, py = dr.fma(d.x, t, o.x), dr.fma(d.y, t, o.y)
    _, _, _, _, za, xa, ya, gu, gv = _facet(grid, heights, px, py)
    return dr.fma(d.z, t, o.z) - (za + gu * (px - xa) + gv * (py - ya))


# Slack of the march's triangle test, in barycentric units: a ray through an edge or a vertex
# counts on both sides (the first cell's facet is then the hit), so none slips between facets.
_EDGE_SLACK = 1e-5


def _march(grid: WaterGrid, positions: Any, heights: Any, o: Any, d: Any, t_max: Any,
           active: Any, steep: Any = None) -> tuple[Any, Any, Any]:
    """The first facet each ray ``o + t d``, ``0 < t <= t_max``, meets on the grid: the cells
    under the ray's path in the order it crosses them (a 2-D digital differential analyser
    over the span where the ray lies within the grid and the heights' range), each cell's
    two triangles tested (Moller-Trumbore); the first cell with a hit holds the nearest,
    since a facet lies within its cell. A ray of ``steep`` crosses the mesh at most once: one
    below the mesh where it leaves the grid, or above it where it enters, meets nothing.

    Every step, the first one's set-up included, runs inside the loop: a kernel's lanes that
    do not march (nearly all of a render's) cost it nothing but the loop's test.

    Returns ``found`` and the facet ``(a, upper)`` as :func:`_facet` names it.
    """
    import drjit as dr

    mi = mitsuba()
    nx, ny = grid.nx, grid.ny
    x1, y1 = grid.x0 + (nx - 1) * grid.dx, grid.y0 + (ny - 1) * grid.dy
    z0, z1 = dr.min(heights), dr.max(heights)
    steep = dr.zeros(mi.Bool, 1) if steep is None else steep

    def start() -> tuple[Any, ...]:
        """The first cell, its next boundaries along x and y, the span's end, and whether
        the ray has nothing to march."""
        sx, sy = _slab(grid.x0, x1, o.x, d.x), _slab(grid.y0, y1, o.y, d.y)
        sz = _slab(z0 - 1e-3, z1 + 1e-3, o.z, d.z)
        t_in = dr.maximum(dr.maximum(sx[0], sy[0]), dr.maximum(sz[0], 0.0))
        t_out = dr.minimum(dr.minimum(sx[1], sy[1]), dr.minimum(sz[1], t_max))
        box_in = dr.maximum(dr.maximum(sx[0], sy[0]), 0.0)
        box_out = dr.minimum(sx[1], sy[1])
        missed = steep & ((_above_mesh(grid, heights, o, d, box_out) < -_SIDE_MM)
                          | (_above_mesh(grid, heights, o, d, box_in) > _SIDE_MM))
        fu = (dr.fma(d.x, t_in, o.x) - grid.x0) * (1.0 / grid.dx)
        fv = (dr.fma(d.y, t_in, o.y) - grid.y0) * (1.0 / grid.dy)
        col = dr.clip(mi.Int32(dr.floor(fu)), 0, nx - 2)
        row = dr.clip(mi.Int32(dr.floor(fv)), 0, ny - 2)
        edge_x = grid.x0 + mi.Float(col + dr.select(d.x > 0.0, 1, 0)) * grid.dx
        edge_y = grid.y0 + mi.Float(row + dr.select(d.y > 0.0, 1, 0)) * grid.dy
        next_x = dr.select(dr.abs(d.x) < 1e-12, dr.inf, (edge_x - o.x) / d.x)
        next_y = dr.select(dr.abs(d.y) < 1e-12, dr.inf, (edge_y - o.y) / d.y)
        return col, row, next_x, next_y, t_out, missed | (t_in > t_out)

    def triangle(i0: Any, i1: Any, i2: Any) -> tuple[Any, Any]:
        p0, p1, p2 = (dr.gather(mi.Point3f, positions, i) for i in (i0, i1, i2))
        e1, e2 = p1 - p0, p2 - p0
        pv = dr.cross(d, e2)
        det = dr.dot(e1, pv)
        inv = dr.rcp(det)
        tv = o - p0
        b1 = dr.dot(tv, pv) * inv
        qv = dr.cross(tv, e1)
        b2 = dr.dot(d, qv) * inv
        t = dr.dot(e2, qv) * inv
        ok = ((dr.abs(det) > 1e-20) & (b1 >= -_EDGE_SLACK) & (b2 >= -_EDGE_SLACK)
              & (b1 + b2 <= 1.0 + _EDGE_SLACK) & (t > 0.0) & (t <= t_max))
        return ok, t

    def cond(started, col, row, next_x, next_y, t_out, done, found, a_hit, upper_hit):
        return ~done

    def body(started, col, row, next_x, next_y, t_out, done, found, a_hit, upper_hit):
        first = start()
        col, row, next_x, next_y, t_out = (
            dr.select(started, mine, theirs)
            for mine, theirs in zip((col, row, next_x, next_y, t_out), first[:5], strict=True))
        skip = ~started & first[5]
        a = mi.UInt32(row * nx + col)
        low_ok, low_t = triangle(a, a + 1, a + nx + 1)
        up_ok, up_t = triangle(a, a + nx + 1, a + nx)
        here = (low_ok | up_ok) & ~skip
        a_hit = dr.select(here, a, a_hit)
        upper_hit = dr.select(here, up_ok & (~low_ok | (up_t < low_t)), upper_hit)
        found = found | here
        # The ray's distance to the cell's next boundary along x and y, and between them.
        along_x = next_x < next_y
        entry = dr.minimum(next_x, next_y)
        col = dr.select(along_x, col + dr.select(d.x > 0.0, 1, -1), col)
        row = dr.select(along_x, row, row + dr.select(d.y > 0.0, 1, -1))
        next_x = dr.select(along_x, next_x + grid.dx / dr.abs(d.x), next_x)
        next_y = dr.select(along_x, next_y, next_y + grid.dy / dr.abs(d.y))
        done = (skip | here | (entry > t_out) | (col < 0) | (col > nx - 2) | (row < 0)
                | (row > ny - 2))
        return dr.full(mi.Bool, True, dr.width(done)), col, row, next_x, next_y, t_out, done, \
            found, a_hit, upper_hit

    n = max(dr.width(o.x), dr.width(d.x), dr.width(active))
    state = (dr.zeros(mi.Bool, n), dr.zeros(mi.Int32, n), dr.zeros(mi.Int32, n),
             dr.zeros(mi.Float, n), dr.zeros(mi.Float, n), dr.zeros(mi.Float, n),
             ~(active & dr.full(mi.Bool, True, n)), dr.zeros(mi.Bool, n),
             dr.zeros(mi.UInt32, n), dr.zeros(mi.Bool, n))
    *_, found, a_hit, upper_hit = dr.while_loop(state, cond, body)
    return found, a_hit, upper_hit


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
    """The water's mesh as the direct tracers ask it: its first hit along rays
    (:func:`water_intersect`) and whether it lies in a ray's way (:meth:`occluded`).

    A system's scene holds the water beside other shapes (the diffuser below it, the object
    above it), and every new surface rebuilds each scene's acceleration structure: on a fine
    mesh (640 000 triangles) one Embree build takes longer than a render. The direct tracers
    ask only about the water (their rays start past the diffuser, and the object is met on
    its own plane), and a regular grid answers that on its own: steep rays settle on their
    facet in a few Newton steps, the rest march over the cells (:func:`_march`). :meth:`own` holds
    a mesh in no scene, which a new surface costs only its upload (:meth:`update`); :meth:`of`
    borrows a system's scene and its mesh as they are (Embree for the rays the facets do not
    settle, and for every ray on a mesh with holes).

    Attributes
    ----------
    mesh : mitsuba.Mesh
        The water, its vertex normals the surface's.
    scene : mitsuba.Scene or None
        The borrowed scene holding :attr:`mesh`; None for an owned mesh.

    Examples
    --------
    >>> import numpy as np
    >>> from wai_core.heightfield import Heightfield
    >>> x = y = np.linspace(-100.0, 100.0, 5)
    >>> water = WaterGeometry.own(Heightfield(x, y, np.full((5, 5), 150.0)).to_trimesh())
    >>> (water.grid.nx, water.grid.ny)
    (5, 5)
    """

    def __init__(self, mesh: Any, scene: Any = None) -> None:
        self.mesh = mesh
        self.scene = scene
        self._grid: tuple[WaterGrid | None] | None = None
        self._slope: Any = None

    @classmethod
    def own(cls, tm: Any) -> WaterGeometry:
        """The water of the ``trimesh`` ``tm``, in no scene."""
        return cls(to_mitsuba(tm, "water", {"type": "diffuse"}))  # never shaded: the systems'

    @classmethod
    def of(cls, scene: Any) -> WaterGeometry:
        """A system's scene and its ``water`` mesh, as they are."""
        return cls({shape.id(): shape for shape in scene.shapes()}["water"], scene)

    def update(self, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray | None
               ) -> None:
        """New buffers (:func:`mitsuba_wai.mesh.set_mesh_buffers`) for an owned mesh."""
        if self.scene is not None:
            raise ValueError("a borrowed water geometry changes with its own scene")
        set_mesh_buffers(self.mesh, vertices, normals, faces)
        self._grid = self._slope = None

    @property
    def grid(self) -> WaterGrid | None:
        """The mesh's grid (:func:`water_grid`; None where it has holes), once a surface."""
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
        if self.scene is None and self.grid is None:
            raise ValueError("a water mesh with holes is intersected through its scene")
        return water_intersect(self.scene, self.mesh, self.grid, ray, self.slope, active)

    def occluded(self, ray: Any, active: Any) -> Any:
        """Whether the water (and, when borrowed, the scene's other shapes) lies on ``ray``
        before its ``maxt``."""

        if self.scene is not None:
            return self.scene.ray_test(ray, active)
        if self.grid is None:
            raise ValueError("a water mesh with holes is intersected through its scene")
        positions = self.mesh.vertex_positions_buffer()
        return _march(self.grid, positions, _heights(self.grid, positions), ray.o, ray.d,
                      ray.maxt, active)[0]
