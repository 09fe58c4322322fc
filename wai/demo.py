"""``wai demo``: render the paper's configuration, restore it, draw the figures, print scores."""

from __future__ import annotations

import argparse
from pathlib import Path


def run_demo(args: argparse.Namespace) -> None:
    """Render + restore the paper's setup into ``args.out`` and print the scores."""
    from mitsuba_wai.render import render_folder
    from restoration import Calibration, restore_folder
    from wai import figures
    from wai_core import load_system

    cfg = load_system(args.config)
    out = Path(args.out)
    print(f"rendering {args.config} into {out} ...")
    render_folder(cfg, out, progress=not args.quiet)
    figures.render_overview(out, cfg, Calibration.from_folder(out).view_gain)
    from wai.restore_cli import compile_notice

    print("restoring ...")
    cold = compile_notice(args.quiet)
    done = restore_folder(out, progress=not args.quiet)
    for line in done.summary_lines():
        if cold and line.startswith("end to end"):
            line += " (includes compiling the kernels once)"
        print("  " + line)
    print(f"results: {out}/ (renders, figures) and {out}/restore/ (metrics.json, figures)")
