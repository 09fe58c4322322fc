"""The figures a run writes: what a reader could misread in them, checked on the drawn artists
(colour scales, which markers lie on top, overlapping labels), not on pixels."""

import numpy as np

from restoration import figures
from restoration.figures import plt
from wai.bench.report import CHART_MIN_MS, chart_rows
from wai_core.heightfield import Heightfield


def _surface(n=40):
    x = np.linspace(-50.0, 50.0, n)
    return Heightfield(x, x.copy(), np.zeros((n, n)))


def test_one_outlier_does_not_set_the_error_maps_scale():
    est = _surface()
    rng = np.random.default_rng(0)
    err = np.abs(rng.normal(0.0, 0.01, est.z.shape))
    err[3, 3] = 0.085  # one outlier at the edge, 8x the rest
    fig = figures.draw_error_map(est, err)
    ax = fig.axes[0]
    mesh = ax.collections[0]
    assert mesh.norm.vmax < 0.04  # the bulk of the map uses the colours
    rmse = np.sqrt(np.mean(err**2))
    assert f"RMSE {rmse:.3f} mm" in ax.get_title() and "max 0.085" in ax.get_title()
    plt.close(fig)


def test_restored_corners_are_drawn_over_hollow_truth_rings():
    pts = np.array([[10.0, 20.0], [30.0, 40.0]])
    fig = figures.draw_corners({"truth": pts, "distorted": pts + 3, "restored": pts},
                               {"distorted": 2.0, "restored": 0.1})
    by_label = {c.get_label().split(" ")[0]: c for c in fig.axes[0].collections}
    assert by_label["restored"].get_zorder() > by_label["truth"].get_zorder()
    assert by_label["truth"].get_facecolors().size == 0  # hollow: the cross inside shows
    plt.close(fig)


def test_the_profile_has_a_residual_panel_and_shades_what_is_not_estimated():
    x = np.linspace(0.0, 300.0, 61)
    true = np.sin(x / 30.0)
    est = np.where(x < 210.0, true + 0.01, np.nan)
    fig = figures.draw_profile(x, est, true, 12.0)
    top, res = fig.axes
    assert "residual: RMS 0.010 mm" in res.get_title()
    assert len(top.patches) == 2  # the part beyond x = 210 mm shaded (and the empty left)
    plt.close(fig)


def test_the_views_are_cropped_to_the_restored_region():
    mask = np.zeros((100, 200), bool)
    mask[30:60, 50:150] = True
    rows, cols = figures.crop_box(mask, margin=0.0)
    assert (rows, cols) == (slice(30, 60), slice(50, 150))
    assert figures.crop_box(np.zeros((4, 5), bool)) == (slice(0, 4), slice(0, 5))


def test_the_bench_chart_nests_parts_under_their_stage_and_drops_zero_bars():
    stages = {"surface": {"median_ms": 20.0}, "surface.normals": {"median_ms": 0.01},
              "surface.integrate": {"median_ms": 9.0}, "view": {"median_ms": 5.0}}
    rows = chart_rows(stages)
    assert [r[0] for r in rows] == ["surface", "surface.integrate", "view"]
    assert rows[1][2] and rows[1][1].strip().endswith("integrate")
    assert all(stages[r[0]]["median_ms"] >= CHART_MIN_MS for r in rows)


def test_the_zoom_box_sits_on_the_images_light():
    img = np.zeros((100, 200), np.float32)
    img[60:70, 150:160] = 1.0
    rows, cols = figures.zoom_box(img, 0.2)
    assert (rows.stop - rows.start, cols.stop - cols.start) == (20, 40)
    assert rows.start <= 60 and rows.stop >= 70 and cols.start <= 150 and cols.stop >= 160


def test_the_rig_diagram_puts_each_device_where_the_configuration_does(tmp_path):
    from unittest import mock

    from wai import figures as wai_figures
    from wai_core import load_system

    cfg = load_system("paper")
    drawn = {}
    with mock.patch.object(wai_figures, "save_figure", lambda fig, path: drawn.update(fig=fig)):
        wai_figures.rig_figure(cfg, tmp_path / "rig.png")
    ax = drawn["fig"].axes[0]
    squares = [line.get_xydata()[0] for line in ax.lines if line.get_marker() == "s"]
    for name, point in zip(("projector", "camera_s", "camera_v"), squares, strict=True):
        c = cfg.rig.device(name).pose.center_lab_mm
        np.testing.assert_allclose(point, [c[0], c[2]], atol=1e-9)
    assert abs(np.mean([t.get_position()[1] for t in ax.texts if "water level" in t.get_text()])
               - cfg.water.h0_mm) < 10
    plt.close(drawn["fig"])


def test_the_flat_reference_figure_draws_each_spots_residual_from_the_calibration():
    from types import SimpleNamespace
    from unittest import mock

    pred = np.array([[100.0, 100.0], [200.0, 150.0], [300.0, 200.0]])
    ref = SimpleNamespace(pred_px=pred, ref_px=pred + [[0.1, 0.0], [0.0, -0.2], [0.0, 0.0]],
                          observed=np.array([True, True, False]), rms_px=0.158)
    drawn = {}
    with mock.patch.object(figures, "save_figure", lambda fig, path: drawn.update(fig=fig)):
        figures.flat_reference_figure(ref, (600, 800), "unused.png")
    ax = drawn["fig"].axes[0]
    arrows = ax.collections[0]
    np.testing.assert_allclose(arrows.U, [0.1, 0.0])  # the observed spots only
    np.testing.assert_allclose(arrows.V, [0.0, -0.2])
    assert "RMS 0.158 px" in ax.get_title()
    plt.close(drawn["fig"])
