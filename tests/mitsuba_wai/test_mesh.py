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
