"""Water surface meshes: a heightfield becomes a ``trimesh`` mesh, then a Mitsuba mesh.

The mesh is a regular grid of vertices on the surface with two triangles per cell, wound so that
face normals point up (+z, into the air): Mitsuba's ``dielectric`` takes the side the normals point
to as the exterior (air) and the other side as the interior (water). Vertex normals are the
surface's exact normals, so shading (reflection and refraction directions) follows the smooth
surface that the restoration assumes, not the facets.
"""

from __future__ import annotations

import numpy as np
import trimesh

from wai_core.heightfield import Heightfield


def heightfield_mesh(surface: Heightfield) -> trimesh.Trimesh:
    """Triangle mesh through the heightfield's samples, mm, with exact vertex normals."""
    return surface.to_trimesh()


def flat_like(surface: Heightfield, z_mm: float) -> Heightfield:
    """A flat surface at ``z_mm`` on the same grid (same topology, so a loaded scene can switch
    between flat and wavy by updating vertex positions only)."""
    return Heightfield(surface.x, surface.y, np.full_like(surface.z, z_mm))


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
    import mitsuba as mi

    params = m if prefix else mi.traverse(m)
    params[f"{prefix}vertex_positions"] = mi.Float(
        np.ascontiguousarray(mesh.vertices, dtype=np.float32).ravel()
    )
    params[f"{prefix}vertex_normals"] = mi.Float(
        np.ascontiguousarray(mesh.vertex_normals, dtype=np.float32).ravel()
    )
    params[f"{prefix}faces"] = mi.UInt32(np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel())
    params.update()
