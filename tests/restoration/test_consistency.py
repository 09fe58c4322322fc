"""The forward-consistency check against spots the exact geometric model puts there.

Spots come from :func:`wai_core.light_paths.spots_through` on a known analytic surface (no renderer,
no detector): the true surface must reproduce them to rounding, a wrong one must not.
"""

import numpy as np
import pytest

from restoration import Calibration
from restoration.consistency import INCONSISTENT_FRACTION, spot_consistency
from restoration.normals import projector_rays
from wai_core.heightfield import Heightfield
from wai_core.light_paths import spots_through

SPACING_PX = 13.0  # the paper rig's median dot spacing in camera s


def _swell(cfg, amplitude_mm=2.0, offset_mm=0.0, wavelength_mm=160.0):
    x = np.linspace(-100.0, 700.0, 401)
    y = np.linspace(-350.0, 350.0, 351)
    xx, yy = np.meshgrid(x, y)
    phase = 2 * np.pi * (xx + 0.5 * yy) / wavelength_mm
    z = cfg.water.h0_mm + offset_mm + amplitude_mm * np.sin(phase)
    return Heightfield(x, y, z)


def _check(cfg, truth, surface, patches=None):
    ij = np.array([[i, j] for i in range(-12, 13) for j in range(-12, 13)])
    panel = Calibration(cfg).panel_px(ij)
    spots = spots_through(cfg.rig, truth, panel)
    keep = np.isfinite(spots).all(axis=1)
    origin, dirs = projector_rays(panel[keep], cfg.rig.projector)
    # The samples: where each ray meets the true surface (what a good reconstruction gives).
    hits, _ = truth.intersect(np.broadcast_to(origin, dirs.shape),
                              dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    return spot_consistency(surface, hits, origin, dirs, spots[keep], cfg.rig.camera_s,
                            cfg.diffuser.z_mm, SPACING_PX, patches=patches)


def test_the_true_surface_reproduces_its_spots(paper_cfg):
    truth = _swell(paper_cfg)
    check = _check(paper_cfg, truth, truth)
    assert check.n_predicted > 400
    assert check.median_px < 1e-3 and check.p95_px < 1e-2
    assert check.consistent
    assert check.threshold_px == pytest.approx(INCONSISTENT_FRACTION * SPACING_PX)


@pytest.mark.parametrize("wrong", ["level", "shape"])
def test_a_wrong_surface_is_inconsistent(paper_cfg, wrong):
    truth = _swell(paper_cfg)
    # 1 mm too high everywhere, or the right level with a 30 % weaker swell.
    surface = _swell(paper_cfg, offset_mm=1.0) if wrong == "level" else _swell(paper_cfg, 1.4)
    check = _check(paper_cfg, truth, surface)
    assert not check.consistent
    assert check.median_px > 3 * check.threshold_px


def test_the_confidence_map_follows_the_residuals(paper_cfg):
    truth = _swell(paper_cfg)
    good, bad = _check(paper_cfg, truth, truth), _check(paper_cfg, truth, _swell(paper_cfg, 1.4))
    known = np.isfinite(good.confidence)
    assert known.any() and np.nanmin(good.confidence) > 0.99
    assert np.nanmedian(bad.confidence) < 0.5


def _numpy_prediction(surface, origin, dirs, start, camera_s, z_h_mm, steps=3):
    """The forward prediction by NumPy steps (the oracle of the compiled kernel)."""
    from restoration.reverse_trace import SplinePatches
    from wai_core.geometry import intersect_plane_z, reflect

    patches = SplinePatches(surface)
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    t = (start[:, 2] - origin[2]) / d[:, 2]
    for _ in range(steps):
        p = origin + t[:, None] * d
        h, gx, gy = patches.jet(p[:, 0], p[:, 1])[:3]
        t = t - (p[:, 2] - h) / (d[:, 2] - gx * d[:, 0] - gy * d[:, 1])
    p = origin + t[:, None] * d
    _, gx, gy = patches.jet(p[:, 0], p[:, 1])[:3]
    normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    s, _ = intersect_plane_z(p, reflect(d, normal), z_h_mm)
    cols, rows, front = camera_s.project(s)
    px = np.stack([cols, rows], axis=1)
    px[~front] = np.nan
    return px


def test_compiled_prediction_is_the_numpy_steps(paper_cfg):
    from restoration.consistency import predict_spots_px

    truth = _swell(paper_cfg)
    z = truth.z.copy()
    z[150:170, 200:230] = np.nan  # a hole: rays through it leave the known surface
    surface = Heightfield(truth.x, truth.y, z)
    ij = np.array([[i, j] for i in range(-14, 15) for j in range(-14, 15)])
    origin, dirs = projector_rays(Calibration(paper_cfg).panel_px(ij), paper_cfg.rig.projector)
    # Starts off the surface by up to 3 mm; unnormalised directions.
    start = origin + ((paper_cfg.water.h0_mm - origin[2]) / dirs[:, 2])[:, None] * dirs
    start[:, 2] += np.linspace(-3.0, 3.0, len(start))
    args = (surface, origin, 2.0 * dirs, start, paper_cfg.rig.camera_s,
            paper_cfg.diffuser.z_mm)
    got, want = predict_spots_px(*args), _numpy_prediction(*args)
    assert np.isnan(want).any() and np.isfinite(want).sum() > 500
    # The projection's 3 x 3 product may be summed in another order by NumPy's matmul.
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_a_passed_spline_table_gives_the_same_check(paper_cfg):
    """The frame's one :class:`SplinePatches` (shared with its view) checks exactly what the
    check builds for itself; a table of another surface object is refused."""
    from restoration.reverse_trace import SplinePatches
    from wai_core.errors import WaiInputError

    truth, surface = _swell(paper_cfg), _swell(paper_cfg, 1.4)
    own = _check(paper_cfg, truth, surface)
    shared = _check(paper_cfg, truth, surface, patches=SplinePatches(surface))
    np.testing.assert_array_equal(shared.residual_px, own.residual_px)
    assert not own.consistent
    with pytest.raises(WaiInputError, match="another surface"):
        _check(paper_cfg, truth, surface, patches=SplinePatches(truth))


@pytest.fixture(scope="module")
def frame(paper_cfg, tmp_path_factory):
    from mitsuba_wai.render import render_folder

    folder = tmp_path_factory.mktemp("frame") / "f"
    render_folder(paper_cfg.replace("render", spp_pattern=4, spp_view=4), folder,
                  progress=False)
    return folder


def _mislabelled(monkeypatch, n_wrong):
    """Give ``n_wrong`` side-by-side spots of one lattice row their neighbour's label (what a
    matcher that lost its place in a row does): each dot's ray then meets another dot's spot."""
    import dataclasses

    import restoration.structured_light as sl

    real = sl.match_features

    def wrong(*args, **kwargs):
        f = real(*args, **kwargs)
        row = f.ij[:, 1] == 2
        order = np.flatnonzero(row)[np.argsort(f.ij[row, 0])]
        mid = len(order) // 2
        take = order[mid:mid + n_wrong]
        spots = f.spot_px.copy()
        spots[take] = f.spot_px[order[mid + 1:mid + 1 + n_wrong]]
        return dataclasses.replace(f, spot_px=spots)

    monkeypatch.setattr(sl, "match_features", wrong)


def _errors_mm(done):
    e = np.abs(done.scores.error_map_mm)
    return e[np.isfinite(e)]


def test_spots_the_surface_cannot_reproduce_are_left_out_and_the_frame_stays_right(
        frame, monkeypatch):
    """Five wrong labels side by side: the surface built with them misses their spots by
    pixels; estimated again without them (and without the unchecked spots beside them) it is
    right everywhere it restored. Kept, they put the surface off by over half a millimetre
    there, which the frame's median residual alone does not show."""
    import restoration.structured_light as sl
    from restoration import restore_folder

    _mislabelled(monkeypatch, 5)
    done = restore_folder(frame, write=False)
    counts = done.result.features.counts
    assert counts["rejected_inconsistent"] >= 5
    assert done.result.status == "ok", done.result.message
    assert np.mean(_errors_mm(done) <= 0.5) >= 0.99 and done.metrics["wai_max_abs_mm"] < 0.5
    assert done.metrics["corner_std_restored_px"] <= 0.3
    monkeypatch.setattr(sl, "MAX_REJECTION_ROUNDS", 0)
    kept = restore_folder(frame, write=False)
    assert kept.metrics["wai_max_abs_mm"] > 0.5
    assert kept.result.consistency.consistent  # the median does not see it ...
    assert kept.result.status == "inconsistent"  # ... the spots missed by pixels do
    assert "spots around" in kept.result.message
