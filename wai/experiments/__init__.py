"""Dispatch of ``wai experiment NAME``."""

from __future__ import annotations

import argparse
from pathlib import Path

# Seeds 0..K-1 when --seeds is not given: the sun sweep renders six sensors per seed.
DEFAULT_SEEDS = {
    "validate": 10, "paper": 10, "alterman": 3, "tradeoffs": 2, "stability": 2, "seawater": 1,
}


def run_experiment(args: argparse.Namespace) -> None:
    """Run one experiment into ``args.out`` (default ``renders/<name>``) and print its tables."""
    if args.out is None:
        args.out = Path("renders") / args.name
    if args.seeds is None:
        args.seeds = DEFAULT_SEEDS[args.name]
    if args.name == "validate":
        from wai.experiments.validate import print_validate, run_validate

        print_validate(run_validate(args))
    elif args.name == "paper":
        from wai.experiments.paper import run_paper

        run_paper(args)
    elif args.name == "alterman":
        from wai.experiments.alterman import run_alterman

        run_alterman(args)
    elif args.name == "tradeoffs":
        from wai.experiments.tradeoffs import run_tradeoffs

        run_tradeoffs(args)
    elif args.name == "stability":
        from wai.experiments.stability import run_stability

        run_stability(args)
    elif args.name == "seawater":
        from wai.experiments.seawater import format_snr, seawater_snr
        from wai_core.io import write_json

        res = seawater_snr(args.config, seed=0, spp=4 if args.quick else None)
        args.out.mkdir(parents=True, exist_ok=True)
        write_json(args.out / "seawater_snr.json", res)
        print(format_snr(res))
