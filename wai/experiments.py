"""Dispatch of ``wai experiment NAME``."""

from __future__ import annotations

import argparse
from pathlib import Path


def run_experiment(args: argparse.Namespace) -> None:
    """Run one experiment into ``args.out`` (default ``renders/<name>``) and print its tables."""
    if args.out is None:
        args.out = Path("renders") / args.name
    if args.name == "validate":
        from wai.validate import print_validate, run_validate

        print_validate(run_validate(args))
    elif args.name == "paper":
        from wai.paper import run_paper

        run_paper(args)
