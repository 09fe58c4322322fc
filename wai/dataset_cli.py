"""``wai dataset --frames N --out DIR``: a dataset of rendered frames with their truth for
learned methods (:mod:`wai.dataset`, 'wai guide dataset')."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from wai_core.errors import WaiInputError


def parse_size(text: str) -> tuple[int, int]:
    """``WxH`` pixels (each >= 16) as ``(width, height)``.

    Examples
    --------
    >>> parse_size("160x120")
    (160, 120)
    """
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if m is None or int(m[1]) < 16 or int(m[2]) < 16:
        raise WaiInputError(f"--size must be WxH pixels, each >= 16, not {text!r}")
    return int(m[1]), int(m[2])


def add_dataset(sub: argparse._SubParsersAction, formatter: type, scene_help: str) -> None:
    """The ``dataset`` subcommand."""
    p = sub.add_parser(
        "dataset", help="render a dataset of random sea states with their truth (HDF5)",
        formatter_class=formatter,
        description="Frame i draws wind speed, direction, time and wave seed from "
        "default_rng([SEED, i]) and stores the distorted and true views, the patterns, the "
        "true heightfield and normals and the exact warp between the views in DIR/dataset.h5 "
        "(with DIR/manifest.csv). A rerun with the same seed, config and options continues "
        "from the frames stored. See 'wai guide dataset'.",
    )
    p.add_argument("--frames", type=int, required=True, help="frames the dataset holds")
    p.add_argument("--out", type=Path, required=True, help="dataset folder")
    p.add_argument("--config", default="paper", help=scene_help)
    p.add_argument("--seed", type=int, default=0, help="the dataset's seed")
    p.add_argument("--spp", type=int,
                   help="samples per pixel of every render (default: the scene's)")
    p.add_argument("--size", metavar="WxH",
                   help="both cameras' pixels at the scene's field of view (default: the "
                   "scene's)")
    p.add_argument("--degrade", action="store_true",
                   help="sensor noise, exposure and read noise drawn per frame")
    p.add_argument("--workers", type=int, default=0,
                   help="processes rendering frames (0: here)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://host:8786) whose workers render the "
                   "frames (default: none; --workers decides)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_dataset)


def _cmd_dataset(args: argparse.Namespace) -> int:
    run_dataset(args)
    return 0


def run_dataset(args: argparse.Namespace) -> None:
    """Write the dataset ``args`` describes and print how fast its new frames came."""
    import h5py

    from wai.dataset import DatasetSpec, write_dataset

    if args.spp is not None and args.spp < 1:
        raise WaiInputError(f"--spp must be >= 1, not {args.spp}")
    spec = DatasetSpec(
        config=str(args.config), seed=int(args.seed), spp=args.spp,
        size_px=parse_size(args.size) if args.size else None, degrade=bool(args.degrade),
    )
    before = len(_runs_in(args.out))
    path = write_dataset(args.out, args.frames, spec, workers=args.workers,
                         scheduler=args.scheduler, progress=not args.quiet)
    with h5py.File(path, "r") as f:
        total = int(f.attrs["frames"])
    runs = _runs_in(args.out)
    if len(runs) == before:
        print(f"{path}: {total} frames, none made (--frames {args.frames})")
        return
    r = runs[-1]
    print(f"{path}: {total} frames; made {r['frames']} (from frame {r['first_frame']}) in "
          f"{r['seconds']:.1f} s, {r['frames_per_s']:.3g} frames/s, by {r['renderers']} on "
          f"{r['cores']} cores (reference {r['reference']}: {r['reference_ms']:.1f} ms)")


def _runs_in(out: Path) -> list[dict]:
    """The runs an existing store records (none: no store, or unreadable; the writer checks
    it)."""
    from wai.dataset import read_runs

    try:
        return read_runs(out)
    except (OSError, ValueError):
        return []
