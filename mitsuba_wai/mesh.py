"""Water surface meshes: a heightfield becomes a ``trimesh`` mesh, then a Mitsuba mesh.

The mesh is a regular grid of vertices on the surface with two triangles per cell, wound so that
face normals point up (+z, into the air): Mitsuba's ``dielectric`` takes the side the normals point
to as the exterior (air) and the other side as the interior (water). Vertex normals are the
surface's exact normals, so shading (reflection and refraction directions) follows the smooth
surface that the restoration assumes, not the facets.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh

from wai_core.heightfield import Heightfield, grid_faces


def heightfield_mesh(surface: Heightfield) -> trimesh.Trimesh:
    """Triangle mesh through the heightfield's samples, mm, with exact vertex normals."""
    return surface.to_trimesh()


def surface_buffers(
    surface: Heightfield,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh of :func:`heightfield_mesh` as flat buffers, without building a ``trimesh``.

    Parameters
    ----------
    surface : Heightfield
        The surface, mm.

    Returns
    -------
    vertices : (3 V,) ndarray of float32
        ``x, y, z`` of each grid sample in turn (row-major), mm; unknown heights at the mean.
    normals : (3 V,) ndarray of float32
        The spline's unit normals at the vertices (up where the height is unknown).
    faces : (3 F,) ndarray of uint32
        Triangles counter-clockwise seen from above; cells touching an unknown sample left out.
    """
    m, n = surface.z.shape
    valid = np.isfinite(surface.z).ravel()
    whole = bool(valid.all())
    vertices = np.empty((m * n, 3), dtype=np.float32)
    vertices[:, 0] = np.tile(surface.x, m)
    vertices[:, 1] = np.repeat(surface.y, n)
    vertices[:, 2] = surface.z.ravel() if whole else np.nan_to_num(
        surface.z.ravel(), nan=float(np.nanmean(surface.z)))
    faces = grid_faces(m, n)
    normals = surface.grid_normals().reshape(-1, 3)
    if not whole:  # holes: the cells around them left out, up where the height is unknown
        faces = faces[valid[faces].all(axis=1)]
        normals = np.nan_to_num(normals, nan=0.0)
        normals[~valid] = (0.0, 0.0, 1.0)
    return (vertices.ravel(), normals.astype(np.float32).ravel(),
            faces.astype(np.uint32).ravel())


def flat_like(surface: Heightfield, z_mm: float) -> Heightfield:
    """A flat surface at ``z_mm`` on the same grid (same topology, so a loaded scene can switch
    between flat and wavy by updating vertex positions only)."""
    return Heightfield(surface.x, surface.y, np.full_like(surface.z, z_mm))


PLANE_GRID_POINTS = 4
"""Vertices along each axis of the mesh that renders flat water
(:class:`~mitsuba_wai.render.FrameRenderer`)."""


def flat_level_mm(surface: Heightfield) -> float | None:
    """The height of ``surface`` if it is flat water (every height the same in the float32 a
    mesh holds), else None.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0.0, 10.0, 4)
    >>> flat_level_mm(Heightfield(x, x, np.full((4, 4), 2.5)))
    2.5
    >>> flat_level_mm(Heightfield(x, x, np.add.outer(x, x))) is None
    True
    """
    z = surface.z.astype(np.float32)  # the heights a mesh holds
    z0 = z.flat[0]
    return float(surface.z.flat[0]) if np.isfinite(z0) and bool(np.all(z == z0)) else None


def plane_grid(grid: Heightfield) -> Heightfield:
    """A grid of :data:`PLANE_GRID_POINTS` squared vertices over ``grid``'s span (heights 0)."""
    x = np.linspace(grid.x[0], grid.x[-1], PLANE_GRID_POINTS)
    y = np.linspace(grid.y[0], grid.y[-1], PLANE_GRID_POINTS)
    return Heightfield(x, y, np.zeros((y.size, x.size)))


def to_mitsuba(
    mesh: trimesh.Trimesh, name: str, bsdf: dict, emitter: dict | None = None
) -> object:
    """A Mitsuba ``Mesh`` with the vertices, faces and vertex normals of a ``trimesh`` mesh,
    and optionally an emitter attached to it."""
    import mitsuba as mi

    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    if emitter is not None:
        props["emitter"] = mi.load_dict(emitter)
    m = mi.Mesh(
        name,
        vertex_count=len(mesh.vertices),
        face_count=len(mesh.faces),
        props=props,
        has_vertex_normals=True,
    )
    set_mesh_geometry(m, mesh)
    return m


def set_mesh_geometry(m: object, mesh: trimesh.Trimesh, prefix: str = "") -> None:
    """Write vertex positions, normals and faces into a Mitsuba mesh (or a scene's parameters when
    ``m`` is a ``SceneParameters`` and ``prefix`` names the mesh, e.g. ``'water.'``)."""
    set_mesh_buffers(
        m,
        np.ascontiguousarray(mesh.vertices, dtype=np.float32).ravel(),
        np.ascontiguousarray(mesh.vertex_normals, dtype=np.float32).ravel(),
        np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel(),
        prefix,
    )


def set_mesh_buffers(
    m: object, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray | None,
    prefix: str = "",
) -> None:
    """Write flat vertex positions, normals (3 V,) float32 and faces (3 F,) uint32 into a
    Mitsuba mesh (or scene parameters, as :func:`set_mesh_geometry`); ``faces=None`` keeps the
    mesh's own (the same grid: only the positions, the normals and the BVH change)."""
    import mitsuba as mi

    params = m if prefix else mi.traverse(m)
    params[f"{prefix}vertex_positions"] = mi.Float(vertices)
    params[f"{prefix}vertex_normals"] = mi.Float(normals)
    if faces is not None:
        params[f"{prefix}faces"] = mi.UInt32(faces)
    params.update()


class SceneWater:
    """The water of a renderer's scenes, swapped per surface: the shared
    :class:`~mitsuba_wai.water_hit.WaterGeometry` at once, each system's scene only when a
    render goes through it (Mitsuba's integrators, the general tracers), so a frame whose
    renders all take the direct tracers rebuilds no acceleration structure.

    Parameters
    ----------
    params : dict
        Each scene's ``mitsuba.traverse`` (its water's buffers ``water.*``), by key.
    geometry : mitsuba_wai.water_hit.WaterGeometry, optional
        The direct tracers' water; None: every scene is updated with each surface.
    """

    def __init__(self, params: dict[str, Any], geometry: Any) -> None:
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
        if self.geometry.grid is None:  # holes: each scene's own water, Embree's
            self.sync(self._params)

    @property
    def shared(self) -> Any:
        """The water the direct tracers ask for the last surface: the shared geometry where
        its grid serves (a surface without holes), else None (each scene's own)."""
        if self.geometry is None or self.geometry.grid is None:
            return None
        return self.geometry

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
