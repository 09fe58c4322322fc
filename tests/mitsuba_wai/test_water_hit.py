"""The water's hit found on its grid (mitsuba_wai.water_hit) against Embree's on the same mesh."""

import numpy as np
import pytest

from mitsuba_wai import particles
from mitsuba_wai.mesh import flat_like
from mitsuba_wai.render import FrameRenderer
from mitsuba_wai.surface_sampling import wave_surface
from mitsuba_wai.water_hit import slope_bound, water_grid, water_intersect
from tests.conftest import shrink


@pytest.fixture(scope="module")
def renderer(paper_cfg):
    cfg = shrink(paper_cfg, factor=8, spp=2)
    return cfg, FrameRenderer(cfg, wave_surface(cfg), systems=("pattern",))


def _rays(mi, n, seed):
    """Rays from between the diffuser (z = 60 mm) and the water, up to 80 degrees off the
    vertical: nearly all steeper than any facet, a few flatter (left to Embree)."""
    rng = np.random.default_rng(seed)
    origin = np.stack([rng.uniform(100, 400, n), rng.uniform(-150, 150, n),
                       rng.uniform(61, 130, n)])
    theta = np.radians(rng.uniform(0, 80, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    return mi.Ray3f(mi.Point3f(*origin.astype(np.float32)), mi.Vector3f(*d.astype(np.float32)))


@pytest.mark.parametrize("wavy", [True, False])
def test_grid_hit_is_the_meshs(renderer, wavy):
    import drjit as dr

    mi = particles.mitsuba()
    cfg, fr = renderer
    surface = wave_surface(cfg)
    fr._set_surface(surface if wavy else flat_like(surface, cfg.water.h0_mm))
    scene = fr.scene("pattern")
    mesh = {s.id(): s for s in scene.shapes()}["water"]
    grid = water_grid(mesh)
    assert grid is not None and (grid.ny, grid.nx) == surface.z.shape
    ray = _rays(mi, 20000, 3)
    flags = mi.RayFlags.Minimal | mi.RayFlags.ShadingFrame
    embree = scene.ray_intersect(ray, flags, True, True)
    mine = water_intersect(scene, mesh, grid, ray, slope_bound(mesh), mi.Bool(True))
    dr.eval(embree, mine)
    a, b = embree.is_valid().numpy(), mine.is_valid().numpy()
    assert a.mean() > 0.5
    # Embree's triangles are not watertight: a ray exactly on a facet's edge may slip through.
    assert (a != b).sum() <= 2 and not (a & ~b).any()
    both = a & b
    assert np.abs(embree.p.numpy() - mine.p.numpy())[:, both].max() < 1e-4  # mm
    assert np.abs(embree.t.numpy()[both] - mine.t.numpy()[both]).max() < 2e-4
    # Normals and frames: the same facet's (a ray on an edge may take either facet).
    for field in ("n", "wi"):
        diff = np.abs(getattr(embree, field).numpy() - getattr(mine, field).numpy())[:, both]
        assert (diff.max(axis=0) > 1e-5).sum() <= 2
    diff = np.abs(embree.sh_frame.n.numpy() - mine.sh_frame.n.numpy())[:, both]
    assert diff.max() < 1e-5


def test_grid_of_other_meshes_is_none(renderer):
    import drjit as dr

    mi = particles.mitsuba()
    _, fr = renderer
    mesh = {s.id(): s for s in fr._scenes["pattern"].shapes()}["water"]
    m = mi.Mesh("holes", vertex_count=mesh.vertex_count(), face_count=mesh.face_count() - 1,
                has_vertex_normals=True)
    params = mi.traverse(m)
    params["vertex_positions"] = mi.Float(mesh.vertex_positions_buffer())
    faces = np.asarray(mesh.faces_buffer())[3:]
    params["faces"] = mi.UInt32(faces)
    params.update()
    dr.eval()
    assert water_grid(m) is None


def test_the_shared_water_gives_the_scenes_own_images(paper_cfg):
    # A renderer's direct tracers ask one scene holding the water alone (one acceleration
    # structure a surface); each system's scene, brought up to date, gives the same bits.
    from mitsuba_wai.dots import DotEmitter
    from mitsuba_wai.particles import render_particles
    from mitsuba_wai.scenes import pattern_depth
    from mitsuba_wai.view_tracer import render_view

    cfg = shrink(paper_cfg, factor=8, spp=2)
    first = wave_surface(cfg)
    fr = FrameRenderer(cfg, first)
    assert fr._direct == {"pattern", "view"}
    later = wave_surface(cfg.replace("waves", time_s=cfg.waves.time_s + 3.0))
    shared = fr.render(later, seed=5)
    own = {
        "pattern": render_particles(fr.scene("pattern"), cfg.render.spp_pattern, 5,
                                    pattern_depth(cfg), True, DotEmitter(cfg))[0],
        "view": render_view(fr.scene("view"), cfg.render.spp_view, 5)[0],
    }
    for key in ("pattern", "view"):
        assert shared[key].tobytes() == own[key].tobytes(), key
    # The two surfaces' images differ: the equality is no scene left holding the first.
    other = fr.render(first, seed=5)
    assert all(other[k].tobytes() != shared[k].tobytes() for k in ("pattern", "view"))
