"""The rig and the light paths: derived once, written once, and right by facts of geometry."""

import numpy as np
import pytest

from wai_core.geometry import intersect_plane_z, pinhole_of
from wai_core.heightfield import Heightfield
from wai_core.light_paths import (
    dot_rays,
    flat_pixel_of,
    pack_camera,
    reflected_spot_px,
    spots_from_hits,
    spots_through,
)
from wai_core.optics import trace_to_object


def test_the_rig_is_derived_once_per_configuration(paper_cfg):
    rig = paper_cfg.rig
    assert paper_cfg.rig is rig and rig.camera_s is rig.camera_s
    assert rig.flat_spots is rig.flat_spots and rig.lit is rig.lit
    # Its devices are the configuration's pinholes; a changed configuration has its own rig.
    np.testing.assert_array_equal(rig.camera_v.pose.R, pinhole_of(paper_cfg.camera_v).pose.R)
    moved = paper_cfg.replace("diffuser", z_mm=50.0)
    assert moved.rig is not rig
    assert moved.rig.flat_spots.diffuser_mm[0, 2] == pytest.approx(50.0)
    # A pickled configuration (a sweep's worker) derives its rig again.
    import pickle

    copy = pickle.loads(pickle.dumps(paper_cfg))
    assert copy == paper_cfg and "rig" not in copy.__dict__
    np.testing.assert_array_equal(copy.rig.lit, rig.lit)


def test_flat_water_is_a_mirror_between_projector_and_diffuser(paper_cfg):
    """Through flat water the reflected dot lands where the projector's mirror image (its
    centre reflected in the plane z = h0) sends it straight: a fact of plane mirrors."""
    rig = paper_cfg.rig
    h0, zh = paper_cfg.water.h0_mm, paper_cfg.diffuser.z_mm
    o, d = dot_rays(rig, rig.dot_panel_px)
    mirror = o * [1, 1, -1] + [0, 0, 2 * h0]
    straight, _ = intersect_plane_z(mirror, d * [1, 1, -1], zh)
    flat = rig.flat_spots
    ok = flat.upward & np.isfinite(flat.diffuser_mm[:, 0])
    np.testing.assert_allclose(flat.diffuser_mm[ok], straight[ok], atol=1e-9)
    assert ok.sum() > 500


def test_the_compiled_step_follows_the_vectorised_one(paper_cfg):
    """The per-frame check's compiled reflection and the vectorised path agree to rounding,
    on tilted normals."""
    rig = paper_cfg.rig
    rng = np.random.default_rng(0)
    o, d = dot_rays(rig, rig.dot_panel_px[::7])
    q, _ = intersect_plane_z(o, d, paper_cfg.water.h0_mm)
    keep = np.isfinite(q[:, 0])
    q, d = q[keep], d[keep]
    slopes = rng.normal(0.0, 0.05, (len(q), 2))
    n = np.column_stack([-slopes, np.ones(len(q))])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    want = spots_from_hits(rig, q, d, n).px
    camera = pack_camera(rig.camera_s)
    got = np.array([reflected_spot_px(*q[k], *d[k], *slopes[k], paper_cfg.diffuser.z_mm, camera)
                    for k in range(len(q))])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9, equal_nan=True)


def test_spots_through_flat_water_given_as_a_surface_are_the_flat_spots(paper_cfg):
    rig = paper_cfg.rig
    x = np.linspace(-200.0, 700.0, 181)
    y = np.linspace(-400.0, 400.0, 161)
    flat = Heightfield(x, y, np.full((161, 181), paper_cfg.water.h0_mm))
    panel = rig.dot_panel_px[rig.lit]
    through = spots_through(rig, flat, panel)
    plane = spots_through(rig, None, panel)
    ok = np.isfinite(through[:, 0])
    assert ok.mean() > 0.9
    np.testing.assert_allclose(through[ok], plane[ok], atol=1e-6)


def test_flat_pixel_of_inverts_the_traced_view(paper_cfg):
    rig = paper_cfg.rig
    cols, rows = np.meshgrid(np.linspace(0, 799, 9), np.linspace(0, 599, 7))
    tr = trace_to_object(rig.camera_v, None, paper_cfg.water.h0_mm, paper_cfg.water.n_water,
                         paper_cfg.object_z_mm, cols, rows)
    ok = tr.ok
    c, r = flat_pixel_of(rig, tr.object_mm[ok])
    np.testing.assert_allclose(c, cols[ok], atol=1e-6)
    np.testing.assert_allclose(r, rows[ok], atol=1e-6)
