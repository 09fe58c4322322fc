"""The error budget's points and summary (the sweep itself runs in CI: ``.ci/run``)."""

import json
from pathlib import Path

import pytest

from wai.experiments.budget import EFFECTS, budget_points, budget_summary
from wai_core import load_system
from wai_core.config import RENDERER_EFFECTS, renderer_effects, with_keys
from wai_core.errors import WaiInputError


def test_every_effect_is_a_valid_renderer_only_change():
    cfg = load_system("paper")
    known = {f"{s}.{k}" for s, keys in RENDERER_EFFECTS.items() for k in keys}
    for name, effect in EFFECTS.items():
        for m in effect.values + effect.quick:
            changed = with_keys(cfg, effect.overrides(m))  # a checked configuration
            on = renderer_effects(changed)
            # Each effect turns on renderer-only keys (the index sweep changes the render's n,
            # which the budget keeps from the restoration) and never a restoration setting.
            assert set(on) <= known, name
            assert on or name == "index", name
            assert changed.water.n_water != cfg.water.n_water or name != "index"
            assert changed.water.index_model == "quan_fry" or name != "real_rig"


def test_points_carry_the_overrides_and_a_baseline_per_seed():
    points = budget_points(Path("scenes/paper.toml"), [0, 1], quick=True)
    base = [p for p in points if p["effect"] == "none"]
    assert [p["seed"] for p in base] == [0, 1] and all("render_overrides" not in p for p in base)
    k1 = [p for p in points if p["effect"] == "k1_s"]
    # A lens the restoration can be told: each frame restored without and with it.
    assert len(k1) == 2 * 2 * len(EFFECTS["k1_s"].quick)
    assert sum(bool(p.get("modelled")) for p in k1) == len(k1) // 2
    assert json.loads(k1[0]["render_overrides"])["camera_s.distortion"][0] < 0
    aperture = [p for p in points if p["effect"] == "aperture"]  # nothing to be told
    assert aperture and not any(p.get("modelled") for p in aperture)
    # Rough water and the whole real rig, told, take their level from the view (a textured
    # object); every other point restores as the paper does.
    for name in ("real_rig", "roughness"):
        real = [p for p in points if p["effect"] == name]
        assert {p.get("method") for p in real if p.get("modelled")} == {"structured-light-view"}
        assert all(json.loads(p["render_overrides"])["object.texture"] == "speckle"
                   for p in real)
        assert not any(p.get("method") for p in real if not p.get("modelled"))
    assert not any(p.get("method") for p in points
                   if p["effect"] not in ("real_rig", "roughness"))


def test_a_point_names_a_method_of_the_structured_light_or_is_refused():
    from wai.experiments.frame_eval import method_class

    assert method_class(None).name == "structured-light"
    assert method_class("structured-light-view").name == "structured-light-view"
    with pytest.raises(WaiInputError, match="method must be one of"):
        method_class("schlieren")


def test_summary_finds_where_rmse_passes_each_limit_and_counts_flags():
    def row(effect, m, rmse, status="ok"):
        return {"effect": effect, "magnitude": m, "seed": 0, "status": "ok",
                "frame_status": status, "method_status": status, "wai_rmse_mm": rmse,
                "wai_rmse_demeaned_mm": rmse / 2, "corner_std_restored_px": 0.1,
                "residual_median_px": 0.05}

    rows = [row("none", 0.0, 0.03), row("k1_s", 0.05, 0.04), row("k1_s", 0.1, 0.2),
            row("k1_s", 0.2, 3.0, "inconsistent"), row("k1_s", 0.3, 5.0),
            row("k1_s", 0.2, 0.05) | {"modelled": "True"}]
    s = budget_summary(rows)
    k1 = s["effects"]["k1_s"]
    assert k1["passes_mm"] == {"+0.05": 0.1, "1": 0.2}  # 0.03 + 0.05 mm, then 1 mm
    # The modelled frame is its own column, not part of the unmodelled means.
    assert [e["rmse_mm"] for e in k1["modelled"]] == [pytest.approx(0.05)]
    assert next(e for e in k1["entries"] if e["magnitude"] == 0.2)["rmse_mm"] == 3.0
    from wai.experiments.budget import budget_markdown

    text = budget_markdown(s, "cmd")
    assert "| 0.2 (modelled) | 1 | 100% |" in text
    assert "| k1_s | 0.2 | 0% of 1 | 3.0000 | 100% | 0.0500 | 0.100 | yes |" in text
    assert s["baseline"]["rmse_mm"] == pytest.approx(0.03)
    # Two ruined frames, one flagged.
    assert s["detection"]["bad"] == 2 and s["detection"]["detection_rate"] == 0.5


def test_summary_counts_the_frames_that_fail_beside_the_mean_of_those_that_did_not():
    """A magnitude where one frame of two fails has a fine mean RMSE over the frame that gave
    a surface: its ok share (50 %) says what the mean hides, and the reach stops before it."""
    def row(m, seed, rmse, status="ok"):
        return {"effect": "capillary", "magnitude": m, "seed": seed, "status": "ok",
                "method_status": status, "wai_rmse_mm": rmse, "wai_rmse_demeaned_mm": rmse,
                "corner_std_restored_px": 0.1, "residual_median_px": 0.05}

    rows = [row(0.0, 0, 0.02) | {"effect": "none"}, row(0.0, 1, 0.02) | {"effect": "none"},
            row(3.0, 0, 0.03), row(3.0, 1, 0.03), row(4.0, 0, 0.04),
            row(4.0, 1, None, "failed"), row(6.0, 0, None, "sparse"), row(6.0, 1, 0.05)]
    eff = budget_summary(rows)["effects"]["capillary"]
    at = {e["magnitude"]: e for e in eff["entries"]}
    assert at[4.0]["rmse_mm"] == pytest.approx(0.04)  # the mean of the frame with a surface
    assert (at[3.0]["ok_fraction"], at[4.0]["ok_fraction"], at[4.0]["failed_fraction"]) == (
        1.0, 0.5, 0.5)
    assert at[6.0]["sparse_fraction"] == 0.5
    assert eff["reach"] == 3.0
    from wai.experiments.budget import budget_markdown

    text = budget_markdown(budget_summary(rows), "cmd")
    assert "| 4 | 2 | 50% | 50% | 0% |" in text


def test_with_keys_names_an_unknown_key():
    with pytest.raises(WaiInputError, match="water.nope"):
        with_keys(load_system("paper"), {"water.nope": 1})
    with pytest.raises(WaiInputError, match="roughness"):
        with_keys(load_system("paper"), {"water.roughness": 2.0})
