"""What a new user sees: progress bars that name their steps, help that shows defaults and only
an experiment's own options, figures that label what they show, examples that install."""

from __future__ import annotations

import numpy as np
import pytest


class _Bar:
    """A stand-in for tqdm that records every label a bar shows."""

    made: list[_Bar] = []

    def __init__(self, iterable=None, *args, **kwargs):
        self.iterable, self.labels = iterable, []
        _Bar.made.append(self)

    def set_postfix_str(self, text, refresh=True):
        self.labels.append(text)

    def update(self, n=1):
        pass

    def close(self):
        pass

    def __iter__(self):
        return iter(self.iterable)


@pytest.fixture
def bars(monkeypatch):
    import tqdm

    _Bar.made = []
    monkeypatch.setattr(tqdm, "tqdm", _Bar)
    return _Bar.made


def test_render_and_restore_bars_name_each_step(small_cfg, tmp_path, bars):
    from mitsuba_wai.render import render_folder
    from restoration import restore_folder

    render_folder(small_cfg, tmp_path / "f", progress=True)
    restore_folder(tmp_path / "f", progress=True)
    render, restore = bars
    for bar in (render, restore):
        assert len(bar.labels) >= 4  # the first step, one per step finished
        assert len(set(bar.labels)) == len(bar.labels)  # every step has its own name


def _integrator_rows() -> list[dict]:
    """Two seeds of the integrator chart: the last integrator inconsistent on both."""
    from wai.experiments.tradeoffs import integrator_names

    names = integrator_names()
    rows = []
    for seed in (0, 1):
        row = {"chart": "integrator", "seed": seed, "status": "ok",
               "frame_status": "inconsistent"}
        for k, name in enumerate(names):
            row.update({f"variant_status_{name}": "ok" if name != names[-1] else "inconsistent",
                        f"wai_rmse_mm_{name}": 0.1 * (k + 1) + 0.01 * seed,
                        f"ms_surface_{name}": 5.0 + seed})
        rows.append(row)
    return rows


def test_tradeoff_chart_shows_spread_and_names_what_it_leaves_out(tmp_path):
    from wai.experiments.tradeoffs import (
        chart_series,
        dropped_variants,
        integrator_names,
        not_ok_summary,
        report_markdown,
        tradeoff_figure,
    )

    names = integrator_names()
    series = chart_series(_integrator_rows())
    first = series["integrator"][0]
    assert first["rmse_mm_min"] < first["rmse_mm"] < first["rmse_mm_max"]
    assert first["ms_max"] - first["ms_min"] == pytest.approx(1.0)
    dropped = dropped_variants(series["integrator"], "rmse_mm")
    assert len(dropped) == 1 and names[-1] in dropped[0] and "inconsistent 2" in dropped[0]
    line = not_ok_summary(series)
    assert "inconsistent 2" in line and names[-1] in line
    defaults = {"spacing": 28.0, "integrator": names[0], "spp": 4, "warp": 8,
                "refinement": "default"}
    md = report_markdown(series, defaults, "wai experiment tradeoffs")
    assert any(names[-1] in ln and "inconsistent" in ln for ln in md.splitlines()
               if ln.startswith("Not in the chart"))
    tradeoff_figure(series, defaults, tmp_path / "t.png")
    assert (tmp_path / "t.png").stat().st_size > 0


def test_accuracy_axis_is_not_narrower_than_the_seed_spread():
    from wai.experiments.tradeoffs import MIN_SPAN, _y_limits

    series = [{"ssim": m, "ssim_min": m - 2e-4, "ssim_max": m + 2e-4} for m in (0.9888, 0.9891)]
    lo, hi = _y_limits(series, "ssim")
    assert hi - lo >= MIN_SPAN["ssim"] and hi <= 1.0
    assert lo <= min(s["ssim_min"] for s in series) and hi >= max(s["ssim_max"] for s in series)
    wide = [{"rmse_mm": 0.02, "rmse_mm_min": 0.0, "rmse_mm_max": 0.05}]
    lo, hi = _y_limits(wide, "rmse_mm")
    assert lo >= 0.0 and hi - lo >= 3 * 0.05


def test_side_by_side_frame_labels_halves_and_marks_unrestored_pixels():
    from restoration.figures import NOT_RESTORED_GREY
    from restoration.sequence import side_by_side_frame

    h, w = 60, 80
    distorted = np.zeros((h, w, 3))
    restored = np.zeros((h, w, 3))
    valid = np.zeros((h, w), bool)
    valid[:, : w // 2] = True
    frame = side_by_side_frame(distorted, restored, valid)
    assert frame.dtype == np.uint8 and frame.shape[1] == 2 * w and frame.shape[0] > h
    strip = (frame.shape[0] - h) // 2
    body = frame[strip: strip + h]
    right = body[:, w:]
    assert np.all(right[:, : w // 2] == 0)  # restored black stays black
    assert set(np.unique(right[:, w // 2:])) <= set(NOT_RESTORED_GREY)  # not black
    assert (frame[:strip] < 128).any() and (frame[strip + h:] < 128).any()  # text drawn


def _subparsers(parser):
    """Every (name, parser) below ``parser``, depth first."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield name, sub
                yield from ((f"{name} {n}", p) for n, p in _subparsers(sub))


def test_every_option_that_takes_a_value_says_its_default():
    from wai.cli import build_parser

    commands = dict(_subparsers(build_parser()))
    assert {"render", "restore", "experiment paper", "experiment tradeoffs"} <= set(commands)
    missing = []
    for name, parser in commands.items():
        formatter = parser._get_formatter()
        for action in parser._actions:
            if not action.option_strings or action.nargs == 0 or action.dest == "help":
                continue
            if action.required:  # no default to state; argparse's usage shows it is needed
                continue
            text = formatter._get_help_string(action) or ""
            if "default" not in text:
                missing.append(f"{name} {action.option_strings[0]}")
    assert not missing


def test_each_experiment_offers_only_its_own_options():
    from wai.cli import build_parser, main
    from wai.experiments import EXPERIMENTS

    commands = dict(_subparsers(build_parser()))
    for name, exp in EXPERIMENTS.items():
        options = {o for a in commands[f"experiment {name}"]._actions for o in a.option_strings}
        assert ("--workers" in options) == ("--scheduler" in options) == exp.sweep, name
        assert ("--seeds" in options) == (exp.seeds is not None), name
        text = commands[f"experiment {name}"].format_help()
        assert "Writes" in text and "--quick" in text and "Takes" in text, name
    assert "--workers" not in commands["experiment paper"].format_help()
    assert main(["experiment", "paper", "--workers", "2"]) == 2


def test_experiment_offers_seeds_exactly_when_its_code_reads_them():
    import importlib
    import inspect

    from wai.experiments import EXPERIMENTS

    for name, exp in EXPERIMENTS.items():
        module = importlib.import_module(f"wai.experiments.{name}")
        runner = getattr(module, f"run_{name}", None) or module.seawater_snr
        assert ("seeds" in inspect.signature(runner).parameters) == (exp.seeds is not None), name
