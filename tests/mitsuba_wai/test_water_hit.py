"""The water's hit found on its grid (mitsuba_wai.water_hit) against Embree's on the same mesh."""

import numpy as np
import pytest

from mitsuba_wai import particles
from mitsuba_wai.mesh import flat_like
from mitsuba_wai.render import FrameRenderer
from mitsuba_wai.surface_sampling import wave_surface
from mitsuba_wai.water_hit import WaterGeometry, slope_bound, water_grid, water_intersect
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


@pytest.mark.parametrize("marched", [False, True])
@pytest.mark.parametrize("wavy", [True, False])
def test_grid_hit_is_the_meshs(renderer, wavy, marched):
    # The rays the facets do not settle go to Embree (a scene given) or march over the grid's
    # cells (none): either way the mesh's own first hit.
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
    mine = water_intersect(None if marched else scene, mesh, grid, ray, slope_bound(mesh),
                           mi.Bool(True))
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
    mesh = {s.id(): s for s in fr.scene("pattern").shapes()}["water"]
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
    # A renderer's direct tracers ask the water alone, on its grid (no acceleration structure
    # to build a surface); each system's scene, brought up to date, gives the same image.
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
        # The rays the facets do not settle march over the grid instead of Embree: their hits
        # agree to float rounding, which can move a sample across a pixel or a texel border.
        moved = np.abs(shared[key] - own[key]).sum() / own[key].sum()
        assert moved < 1e-4, key
    # The two surfaces' images differ: the equality is no scene left holding the first.
    other = fr.render(first, seed=5)
    assert all(other[k].tobytes() != shared[k].tobytes() for k in ("pattern", "view"))


def test_the_march_meets_what_embree_meets(paper_cfg):
    # Rays in every direction up to grazing (89.5 degrees off the vertical) from between the
    # diffuser and the water, most flatter than the steepest facet of a windy sea: the march's
    # first hits and its occlusion tests against Embree's on the same mesh.
    import drjit as dr

    mi = particles.mitsuba()
    cfg = shrink(paper_cfg.replace("waves", wind_speed_m_s=3.0), factor=8, spp=2)
    fr = FrameRenderer(cfg, wave_surface(cfg), systems=("pattern",))
    scene = fr.scene("pattern")
    mesh = {s.id(): s for s in scene.shapes()}["water"]
    rng = np.random.default_rng(1)
    n = 50_000
    origin = np.stack([rng.uniform(-100, 500, n), rng.uniform(-250, 250, n),
                       rng.uniform(61, 130, n)]).astype(np.float32)
    theta, phi = np.radians(rng.uniform(0, 89.5, n)), rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                  np.cos(theta)]).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(*d))
    flat = d[2] <= float(slope_bound(mesh)[0]) * np.hypot(d[0], d[1])
    assert flat.mean() > 0.03
    embree = scene.ray_intersect(ray, mi.RayFlags.Minimal, True, True)
    mine = WaterGeometry(mesh).intersect(ray, mi.Bool(True))
    dr.eval(embree, mine)
    a, b = embree.is_valid().numpy(), mine.is_valid().numpy()
    assert 0.2 < a.mean() < 0.8 and (a != b).sum() <= 2
    both = a & b
    assert np.abs(embree.t.numpy()[both] - mine.t.numpy()[both]).max() < 1e-3
    segment = mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(*d),
                       mi.Float(rng.uniform(10, 400, n).astype(np.float32)), 0.0, [])
    blocked = scene.ray_test(segment, True).numpy()
    assert 0.1 < blocked.mean() < 0.9
    assert (blocked != WaterGeometry(mesh).occluded(segment, mi.Bool(True)).numpy()).sum() <= 2


def test_a_surface_with_holes_takes_each_scenes_own_water(paper_cfg):
    # A mesh with holes is no grid: the direct tracers then ask each scene's own water
    # (Embree), brought up to date, and the grid serves again once the holes are gone.
    from mitsuba_wai.view_tracer import render_view
    from wai_core.heightfield import Heightfield

    cfg = shrink(paper_cfg, factor=8, spp=2)
    surface = wave_surface(cfg)
    fr = FrameRenderer(cfg, surface)
    z = surface.z.copy()
    z[4:7, 5:9] = np.nan
    holes = Heightfield(surface.x, surface.y, z)
    images = fr.render(holes, seed=3)
    assert fr._water.shared is None
    own = render_view(fr.scene("view"), cfg.render.spp_view, 3)[0]
    assert images["view"].tobytes() == own.tobytes()
    fr.render(surface, seed=3)
    assert fr._water.shared is fr._water.geometry
