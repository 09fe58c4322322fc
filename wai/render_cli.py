"""``wai render``: configuration plus command-line overrides, then one rendered frame."""

from __future__ import annotations

import argparse

from wai_core.alterman import AltermanSystem, is_alterman_file, load_alterman
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

    if is_alterman_file(args.config):
        run_render_alterman(args)
        return
    cfg = apply_overrides(load_config(args.config), args)
    given = load_heightfield(args.heightfield) if args.heightfield else None
    variant = select_variant(args.variant)
    record = render_folder(cfg, args.out, heightfield=given, progress=not args.quiet)
    total = sum(record["timings_s"].values())
    print(
        f"rendered {args.out} ({variant}, U={cfg.waves.wind_speed_m_s} m/s, "
        f"t={cfg.waves.time_s} s, seed={cfg.waves.seed}) in {total:.1f} s"
    )


def run_render_alterman(args: argparse.Namespace) -> None:
    """Render a sun-sensor frame (a TOML file with ``[base]``); the same overrides apply to the
    base scene, and ``--spp`` to the sun spots as well."""
    from mitsuba_wai.alterman import render_alterman_folder
    from mitsuba_wai.variant import select_variant

    system = load_alterman(args.config)
    sensor = system.sensor
    if args.spp is not None and args.spp >= 1:
        sensor = sensor.replace("render", spp=args.spp)
    system = AltermanSystem(apply_overrides(system.base, args), sensor)
    given = load_heightfield(args.heightfield) if args.heightfield else None
    variant = select_variant(args.variant)
    record = render_alterman_folder(system, args.out, heightfield=given, progress=not args.quiet)
    total = sum(record["timings_s"].values())
    sun = sensor.sun
    state = f"sun at {sun.zenith_deg} deg" if sun.enabled else "overcast"
    print(
        f"rendered {args.out} (sun sensor, {state}, {variant}, "
        f"U={system.base.waves.wind_speed_m_s} m/s, seed={system.base.waves.seed}) in {total:.1f} s"
    )
