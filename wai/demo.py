"""``wai demo``: render the paper's configuration, restore it, draw the figures, print scores."""

from __future__ import annotations

import argparse
from pathlib import Path

from wai_core.config import load_config

PAPER = Path(__file__).resolve().parents[1] / "scenes" / "paper.toml"


def overview_figures(render_dir: Path) -> None:
    """Fig. 10 (the simulated surface) and flat-vs-wavy pattern and view, into ``render_dir``."""
    from wai import figures
    from wai_core.heightfield import load_heightfield
    from wai_core.io import read_exr, read_json

    record = read_json(render_dir / "scene.json")
    cfg = load_config(PAPER) if "config" not in record else None
    h0 = record["config"]["water"]["h0_mm"] if cfg is None else cfg.water.h0_mm
    waves = record["config"]["waves"]
    surface = load_heightfield(render_dir / "heightfield.npz")
    figures.surface_figure(
        surface,
        h0,
        f"Simulated sea surface (U = {waves['wind_speed_m_s']} m/s, t = {waves['time_s']} s, "
        f"seed {waves['seed']})",
        render_dir / "fig10_surface.png",
    )
    gain = record["derived"]["view_radiance_gain"]
    img = {n: read_exr(render_dir / f"{n}.exr") for n in ("pattern_flat", "pattern")}
    figures.side_by_side(
        [img["pattern_flat"], img["pattern"]],
        ["pattern, flat water (reference)", "pattern, wavy water"],
        render_dir / "pattern_flat_vs_wavy.png",
        [None, None],
    )
    views = {n: read_exr(render_dir / f"{n}.exr") for n in ("view_truth", "view")}
    figures.side_by_side(
        [views["view_truth"], views["view"]],
        ["view, flat water (ground truth)", "view, wavy water"],
        render_dir / "view_flat_vs_wavy.png",
        [1 / gain, 1 / gain],
    )


def run_demo(args: argparse.Namespace) -> None:
    """Render + restore the paper's setup into ``args.out`` and print the scores."""
    from mitsuba_wai.render import render_folder
    from restoration.pipeline import RestoreOptions
    from wai.restore_cli import restore_folder, summary_lines

    cfg = load_config(args.config)
    out = Path(args.out)
    print(f"rendering {args.config} into {out} ...")
    render_folder(cfg, out, progress=not args.quiet)
    overview_figures(out)
    print("restoring ...")
    metrics = restore_folder(out, RestoreOptions(), progress=not args.quiet)
    for line in summary_lines(metrics):
        print("  " + line)
    print(f"results: {out}/ (renders, figures) and {out}/restore/ (metrics.json, figures)")
