"""``wai render``: configuration plus command-line overrides, then one rendered frame.

Every option is checked before the renders start, and a bad one ends the command with one line
that names it (exit code 2): numbers that are not finite, a seed out of Mitsuba's range, a
variant this machine cannot run, an output location that cannot or may not be written (the
output policy of :mod:`wai_core.io`), a surface file that is not one, a surface outside the rig.
"""

from __future__ import annotations

import argparse
import math

from wai_core.alterman import AltermanSystem, is_alterman_file, load_alterman
from wai_core.config import SystemConfig, load_config
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield, load_heightfield
from wai_core.io import check_output_dir
from wai_core.scenes import resolve_scene

# Mitsuba's sampler seeds are 32-bit.
MAX_SEED = 2**32 - 1


def _check_number(option: str, value: float | None, unit: str, minimum: float | None) -> None:
    """Refuse a non-finite value (argparse's float() takes 'nan' and 'inf') or one below
    ``minimum``, naming the option."""
    if value is None:
        return
    if not math.isfinite(value):
        raise WaiInputError(f"{option} must be a finite number of {unit}, not {value}")
    if minimum is not None and value < minimum:
        raise WaiInputError(f"{option} must be >= {minimum:g} {unit}, not {value:g}")


def apply_overrides(cfg: SystemConfig, args: argparse.Namespace) -> SystemConfig:
    """The configuration with ``--wind``, ``--time``, ``--seed``, ``--surface``, ``--spp`` set.

    Raises
    ------
    WaiInputError
        Naming the option: ``--wind`` negative or not finite, ``--time`` not finite, ``--seed``
        outside 0 .. 2^32 - 1, ``--spp`` below 1.
    """
    _check_number("--wind", args.wind, "m/s", 0.0)
    _check_number("--time", args.time, "s", None)
    if args.seed is not None and not 0 <= args.seed <= MAX_SEED:
        raise WaiInputError(f"--seed must be between 0 and {MAX_SEED}, not {args.seed}")
    waves = {
        k: v
        for k, v in (("wind_speed_m_s", args.wind), ("time_s", args.time), ("seed", args.seed))
        if v is not None
    }
    if waves:
        cfg = cfg.replace("waves", **waves)
    if args.surface:
        cfg = cfg.replace("water", surface=args.surface)
    if args.spp is not None:
        if args.spp < 1:
            raise WaiInputError("--spp must be at least 1")
        cfg = cfg.replace("render", spp_pattern=args.spp, spp_view=args.spp)
    return cfg


def _surface_label(args: argparse.Namespace) -> str:
    """How a message about the surface names where it came from."""
    if args.heightfield is not None:
        return f"heightfield {args.heightfield}"
    if args.wind is not None:
        return f"--wind {args.wind:g}"
    return f"[waves] of {args.config}"


def _prepare(args: argparse.Namespace) -> tuple[Heightfield | None, str]:
    """The checks every render makes before its long work: the output location, the surface
    file, the variant. Returns the surface given (or None) and the variant's name."""
    from mitsuba_wai.render import OUTPUT_COMMAND
    from mitsuba_wai.variant import select_variant

    check_output_dir(
        args.out, OUTPUT_COMMAND, getattr(args, "overwrite", False), label=f"--out {args.out}"
    )
    given = load_heightfield(args.heightfield) if args.heightfield else None
    try:
        variant = select_variant(args.variant)
    except WaiInputError as exc:
        raise WaiInputError(f"--variant {exc}") from None
    return given, variant


def run_render(args: argparse.Namespace) -> None:
    """Render the configured frame into ``args.out`` and print a one-line summary."""
    from mitsuba_wai.render import render_folder

    scene = resolve_scene(args.config)  # a packaged scene's name, or a TOML file
    if scene.is_file() and is_alterman_file(scene):
        run_render_alterman(args)
        return
    cfg = apply_overrides(load_config(scene), args)
    given, variant = _prepare(args)
    record = render_folder(
        cfg,
        args.out,
        heightfield=given,
        progress=not args.quiet,
        overwrite=getattr(args, "overwrite", False),
        surface_label=_surface_label(args),
    )
    total = sum(record["timings_s"].values())
    print(
        f"rendered {args.out} ({variant}, U={cfg.waves.wind_speed_m_s} m/s, "
        f"t={cfg.waves.time_s} s, seed={cfg.waves.seed}) in {total:.1f} s"
    )


def run_render_alterman(args: argparse.Namespace) -> None:
    """Render a sun-sensor frame (a TOML file with ``[base]``); the same overrides apply to the
    base scene, and ``--spp`` to the sun spots as well."""
    from mitsuba_wai.alterman import render_alterman_folder

    system = load_alterman(resolve_scene(args.config))
    base = apply_overrides(system.base, args)
    sensor = system.sensor
    if args.spp is not None:
        sensor = sensor.replace("render", spp=args.spp)
    system = AltermanSystem(base, sensor)
    given, variant = _prepare(args)
    record = render_alterman_folder(
        system,
        args.out,
        heightfield=given,
        progress=not args.quiet,
        overwrite=getattr(args, "overwrite", False),
        surface_label=_surface_label(args),
    )
    total = sum(record["timings_s"].values())
    sun = sensor.sun
    state = f"sun at {sun.zenith_deg} deg" if sun.enabled else "overcast"
    print(
        f"rendered {args.out} (sun sensor, {state}, {variant}, "
        f"U={system.base.waves.wind_speed_m_s} m/s, seed={system.base.waves.seed}) in {total:.1f} s"
    )
