"""Heightfield meshes: orientation and exactness at the vertices."""

import numpy as np

from mitsuba_wai.mesh import heightfield_mesh
from wai_core.heightfield import Heightfield


def test_faces_point_up_into_the_air():
    x = np.linspace(0, 50, 11)
    y = np.linspace(0, 30, 7)
    xx, yy = np.meshgrid(x, y)
    hf = Heightfield(x, y, 150 + 2 * np.sin(xx / 9) * np.cos(yy / 7))
    m = heightfield_mesh(hf)
    assert (m.face_normals[:, 2] > 0).all()
    assert (m.vertex_normals[:, 2] > 0).all()
    assert np.allclose(m.vertices[:, 2], hf.z.ravel())
    # Vertex normals are the surface's analytic ones, not the facets' average.
    assert np.allclose(m.vertex_normals, hf.normal(m.vertices[:, 0], m.vertices[:, 1]))


def test_surface_buffers_are_the_trimesh_meshs(paper_cfg):
    # The renderer's per-frame buffers are the mesh heightfield_mesh builds, bit for bit,
    # holes (cells left out, heights at the mean, normals up) included.
    from mitsuba_wai.mesh import heightfield_mesh, surface_buffers
    from mitsuba_wai.surface_sampling import wave_surface
    from wai_core.heightfield import Heightfield

    surface = wave_surface(paper_cfg)
    z = surface.z.copy()
    z[3:7, 10:12] = np.nan
    for surf in (surface, Heightfield(surface.x, surface.y, z)):
        tm = heightfield_mesh(surf)
        vertices, normals, faces = surface_buffers(surf)
        assert vertices.tobytes() == np.asarray(tm.vertices, np.float32).tobytes()
        assert normals.tobytes() == np.asarray(tm.vertex_normals, np.float32).tobytes()
        assert faces.tobytes() == np.asarray(tm.faces, np.uint32).tobytes()
