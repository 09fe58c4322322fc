"""``wai render``: configuration plus command-line overrides, then one rendered frame."""

from __future__ import annotations

import argparse

from wai_core.config import SystemConfig, load_config
from wai_core.errors import WaiInputError
from wai_core.heightfield import load_heightfield


def apply_overrides(cfg: SystemConfig, args: argparse.Namespace) -> SystemConfig:
    """The configuration with ``--wind``, ``--time``, ``--seed``, ``--surface``, ``--spp`` set."""
    waves = {
        k: v
        for k, v in (("wind_speed_m_s", args.wind), ("time_s", args.time), ("seed", args.seed))
        if v is not None
    }
    if waves.get("wind_speed_m_s", 0.0) < 0:
        raise WaiInputError("--wind must be >= 0 m/s")
    if waves:
        cfg = cfg.replace("waves", **waves)
    if args.surface:
        cfg = cfg.replace("water", surface=args.surface)
    if args.spp is not None:
        if args.spp < 1:
            raise WaiInputError("--spp must be at least 1")
        cfg = cfg.replace("render", spp_pattern=args.spp, spp_view=args.spp)
    return cfg


def run_render(args: argparse.Namespace) -> None:
    """Render the configured frame into ``args.out`` and print a one-line summary."""
    from mitsuba_wai.render import render_folder
    from mitsuba_wai.variant import select_variant

    cfg = apply_overrides(load_config(args.config), args)
    given = load_heightfield(args.heightfield) if args.heightfield else None
    variant = select_variant(args.variant)
    record = render_folder(cfg, args.out, heightfield=given, progress=not args.quiet)
    total = sum(record["timings_s"].values())
    print(
        f"rendered {args.out} ({variant}, U={cfg.waves.wind_speed_m_s} m/s, "
        f"t={cfg.waves.time_s} s, seed={cfg.waves.seed}) in {total:.1f} s"
    )
