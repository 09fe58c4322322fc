"""Degradations in the renders: motion blur's sub-frames and the sensor's images."""

import json
import math

import cv2
import numpy as np
import pytest

from mitsuba_wai.degrade import (
    SUBFRAME_SEED_STRIDE,
    motion_rates,
    render_exposure,
    subframe_plan,
)
from mitsuba_wai.render import FrameRenderer, render_folder, render_seed
from mitsuba_wai.surface_sampling import moving_surface
from mitsuba_wai.waves import sea_surface
from wai_core.io import read_exr
from wai_core.sensor import full_scale_dn


@pytest.fixture(scope="module")
def renderer(small_cfg):
    return FrameRenderer(small_cfg, moving_surface(small_cfg)(small_cfg.waves.time_s))


def test_no_exposure_renders_todays_image(small_cfg, renderer):
    surface = moving_surface(small_cfg)(small_cfg.waves.time_s)
    seed = render_seed(small_cfg)
    sharp = renderer.render(surface, seed)
    same = render_exposure(renderer, small_cfg, surface, seed,
                           surface_at=moving_surface(small_cfg))
    for key in ("pattern", "view"):
        assert np.array_equal(same[key], sharp[key])


def test_a_blurred_image_is_the_mean_of_its_subframes(small_cfg, renderer):
    cfg = small_cfg.replace("motion", exposure_s=0.002, max_subframes=3)
    plan = subframe_plan(cfg)
    assert plan.n == 3 and plan.capped
    at = moving_surface(cfg)
    seed = render_seed(cfg)
    blurred = render_exposure(renderer, cfg, at(cfg.waves.time_s), seed, surface_at=at)
    subs = [
        renderer.render(at(t), (seed + k * SUBFRAME_SEED_STRIDE) % 2**32,
                        spp={"pattern": math.ceil(cfg.render.spp_pattern / 3),
                             "view": math.ceil(cfg.render.spp_view / 3)})
        for k, t in enumerate(plan.times_s)
    ]
    for key in ("pattern", "view"):
        mean = np.mean([s[key].astype(np.float64) for s in subs], axis=0)
        assert np.allclose(blurred[key], mean, rtol=1e-6, atol=1e-7)
        # and it differs from the sharp frame: the surface moved
        sharp = renderer.render(at(cfg.waves.time_s), seed)[key]
        assert not np.allclose(blurred[key], sharp, rtol=1e-3, atol=1e-4)


def test_the_subframe_count_follows_the_rule(paper_cfg):
    rates = motion_rates(paper_cfg)
    fastest = max(rates["pattern"], rates["view"])
    for exposure in (1e-4, 5e-4, 1e-3, 0.05):
        cfg = paper_cfg.replace("motion", exposure_s=exposure, max_shift_px=1.0,
                                max_subframes=32)
        plan = subframe_plan(cfg)
        wanted = math.ceil(exposure * fastest / 1.0)
        assert plan.n == min(max(wanted, 1), 32) and plan.capped == (wanted > 32)
        # the midpoints of equal slices, centred on the frame's time
        t = np.asarray(plan.times_s)
        assert np.mean(t) == pytest.approx(paper_cfg.waves.time_s)
        assert np.ptp(t) == pytest.approx(exposure * (1 - 1 / plan.n))
    assert subframe_plan(paper_cfg).times_s == (paper_cfg.waves.time_s,)  # off: one frame
    # steeper waves move faster, in proportion
    steeper = paper_cfg.replace("waves", height_scale=2.0)
    assert motion_rates(steeper)["view"] == pytest.approx(2 * rates["view"])


def test_the_rule_bounds_the_surface_s_actual_slope_rate(paper_cfg):
    # The rule's slope rate (3 r.m.s.) against finite differences of the wave model's exact
    # slopes over the observed patch: above the largest seen, but of its order.
    from wai_core.layout import observed_patch

    sea = sea_surface(paper_cfg.waves)
    patch = observed_patch(paper_cfg)
    rng = np.random.default_rng(0)
    x = rng.uniform(*patch[0], 4000)
    y = rng.uniform(*patch[1], 4000)
    t, dt = paper_cfg.waves.time_s, 1e-4
    s0 = np.stack(sea.slopes(x, y, t))
    s1 = np.stack(sea.slopes(x, y, t + dt))
    actual = np.linalg.norm(s1 - s0, axis=0) / dt
    bound = motion_rates(paper_cfg)["slope_rate_1_s"]
    assert actual.max() < bound < 4 * actual.max()


def test_a_sensor_render_writes_adc_images_and_restores(paper_cfg, tmp_path):
    from restoration import restore_folder

    cfg = paper_cfg.replace("render", spp_pattern=4, spp_view=4)
    cfg = cfg.replace("sensor", enabled=True, bits=12, reference_frames=4)
    out = tmp_path / "frame"
    record = render_folder(cfg, out, progress=False).record
    sensor = record["config"]["sensor"]
    assert sensor["enabled"] and sensor["electrons_per_unit_s"] > 0
    assert record["degradations"]["sensor"]["full_scale_dn"] == 4095
    for name in ("pattern", "pattern_flat", "view", "view_truth"):
        raw = cv2.imread(str(out / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16
        exr = read_exr(out / f"{name}.exr")
        assert exr.min() >= 0 and exr.max() <= 1
        assert np.allclose(raw[..., ::-1] / 65535, exr, atol=1 / 131070 + 1e-7)
        if name in ("pattern", "view"):  # one frame of noise: whole DN
            dn = exr * full_scale_dn(cfg.sensor)
            assert np.allclose(dn, np.rint(dn), atol=1e-3)
    # The exposure is the flat reference's: its 99.9th percentile at half the well.
    flat = read_exr(out / "view_truth.exr")
    assert np.percentile(flat, 99.9) == pytest.approx(0.5, rel=0.01)
    # The restoration reads the integer images alone (the EXRs removed) and restores them.
    for exr in out.glob("*.exr"):
        exr.unlink()
    done = restore_folder(out, write=False)
    assert done.result.status == "ok", done.result.summary()
    assert done.metrics["wai_rmse_mm"] < 0.5
    assert json.loads((out / "scene.json").read_text())["config"]["sensor"]["bits"] == 12


def test_a_sequence_fixes_the_exposure_and_draws_noise_per_frame(small_cfg, tmp_path):
    from mitsuba_wai.sequence import render_sequence

    cfg = small_cfg.replace("sensor", enabled=True, bits=8, reference_frames=0)
    cfg = cfg.replace("motion", exposure_s=0.002, max_subframes=2)
    record = render_sequence(cfg, tmp_path / "seq", 2, 1000.0, progress=False).record
    exposure = record["config"]["sensor"]["electrons_per_unit_s"]
    assert exposure > 0
    frames = []
    for name in ("frame000", "frame001"):
        scene = json.loads((tmp_path / "seq" / name / "scene.json").read_text())
        assert scene["config"]["sensor"]["electrons_per_unit_s"] == exposure
        assert scene["degradations"]["motion"]["subframes"] == 2
        raw = cv2.imread(str(tmp_path / "seq" / name / "pattern.png"), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint8
        frames.append(read_exr(tmp_path / "seq" / name / "view.exr"))
    # Each frame draws its own noise (and its surface moved 1 ms).
    assert not np.array_equal(frames[0], frames[1])
