"""``wai demo``: render the paper's configuration, restore it, draw the figures, print scores."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def run_demo(args: argparse.Namespace) -> None:
    """Render + restore the paper's setup into ``args.out`` and print the scores."""
    from mitsuba_wai import render_folder
    from restoration import Calibration, restore_folder
    from wai import figures
    from wai_core import load_system

    cfg = load_system(args.config)
    out = Path(args.out)
    t0 = time.perf_counter()
    print(f"rendering {args.config} into {out} ...")
    render_folder(cfg, out, progress=not args.quiet)
    figures.render_overview(out, cfg, Calibration.from_folder(out).view_gain)
    from wai.restore_cli import compile_notice

    t1 = time.perf_counter()
    print("restoring ...")
    cold = compile_notice(args.quiet)
    done = restore_folder(out, progress=not args.quiet)
    t2 = time.perf_counter()
    for line in done.summary_lines():
        if cold and line.startswith("restoration "):
            line += " (includes compiling the kernels once)"
        print("  " + line)
    print(f"results: {out}/ (renders, figures) and {out}/restore/ (metrics.json, figures)")
    print(f"the demo took {t2 - t0:.1f} s: rendering and figures {t1 - t0:.1f} s, restoring, "
          f"scoring and writing {t2 - t1:.1f} s{' (with the kernels compiled)' if cold else ''}")
