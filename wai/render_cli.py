"""``wai render``: configuration plus command-line overrides, then one rendered frame.

Every option is checked before the renders start, and a bad one ends the command with one line
that names it (exit code 2): numbers that are not finite, a seed out of Mitsuba's range, a
variant this machine cannot run, an output location that cannot or may not be written (the
output policy of :mod:`wai_core.outputs`), a rig that sees nothing through flat water
(:func:`wai_core.rig_checks.check_rig`), a frame too large for the memory available
(:mod:`mitsuba_wai.memory`), a surface file that is not one, a surface outside the rig.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

from wai_core.alterman import AltermanSystem, is_alterman_file, load_alterman
from wai_core.config import SystemConfig, load_config
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield, load_heightfield
from wai_core.outputs import check_output_dir
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


def _folder_options(args: argparse.Namespace, given: Heightfield | None) -> dict[str, Any]:
    """The keyword arguments a render folder (a frame's, a sun-sensor frame's) takes from the
    command line: the surface given, the progress bar, ``--overwrite``, the surface's label."""
    return {"heightfield": given, "progress": not args.quiet,
            "overwrite": getattr(args, "overwrite", False),
            "surface_label": _surface_label(args)}


def _prepare(args: argparse.Namespace, cfg: SystemConfig | None = None
             ) -> tuple[Heightfield | None, str]:
    """The checks every render makes before its long work: the output location, ``cfg``'s rig
    geometry and the memory its frame needs, the surface file, the variant. Returns the surface
    given (or None) and the variant's name."""
    from mitsuba_wai import OUTPUT_COMMAND, select_variant

    check_output_dir(
        args.out, OUTPUT_COMMAND, getattr(args, "overwrite", False), label=f"--out {args.out}"
    )
    if cfg is not None:
        from mitsuba_wai import check_render_memory
        from wai_core.rig_checks import check_rig

        check_rig(cfg, str(args.config))
        check_render_memory(cfg, str(args.config))
    given = load_heightfield(args.heightfield) if args.heightfield else None
    try:
        variant = select_variant(args.variant)
    except WaiInputError as exc:
        raise WaiInputError(f"--variant {exc}") from None
    return given, variant


def run_render(args: argparse.Namespace) -> None:
    """Render the configured frame (or ``--frames`` of them) into ``args.out`` and print a
    one-line summary."""
    from mitsuba_wai import render_folder

    scene = resolve_scene(args.config)  # a packaged scene's name, or a TOML file
    sequence = getattr(args, "frames", 1) != 1
    if scene.is_file() and is_alterman_file(scene):
        if sequence:
            raise WaiInputError("--frames: sequences of the sun sensor are not supported")
        run_render_alterman(args)
        return
    cfg = apply_overrides(load_config(scene), args)
    if getattr(args, "checkerboards", 0):
        from wai.calibrate_cli import run_checkerboards

        if args.checkerboards < 1 or sequence:
            raise WaiInputError("--checkerboards N needs N >= 1 and no --frames")
        run_checkerboards(args, cfg)
        return
    if sequence:
        run_render_sequence(cfg, args)
        return
    given, variant = _prepare(args, cfg)
    total = render_folder(cfg, args.out, **_folder_options(args, given)).seconds
    print(
        f"rendered {args.out} ({variant}, U={cfg.waves.wind_speed_m_s} m/s, "
        f"t={cfg.waves.time_s} s, seed={cfg.waves.seed}) in {total:.1f} s"
    )


def run_render_alterman(args: argparse.Namespace) -> None:
    """Render a sun-sensor frame (a TOML file with ``[base]``); the same overrides apply to the
    base scene, and ``--spp`` to the sun spots as well."""
    from mitsuba_wai import render_alterman_folder

    system = load_alterman(resolve_scene(args.config))
    base = apply_overrides(system.base, args)
    sensor = system.sensor
    if args.spp is not None:
        sensor = sensor.replace("render", spp=args.spp)
    system = AltermanSystem(base, sensor)
    given, variant = _prepare(args)
    total = render_alterman_folder(system, args.out, **_folder_options(args, given)).seconds
    sun = sensor.sun
    state = f"sun at {sun.zenith_deg} deg" if sun.enabled else "overcast"
    print(
        f"rendered {args.out} (sun sensor, {state}, {variant}, "
        f"U={system.base.waves.wind_speed_m_s} m/s, seed={system.base.waves.seed}) in {total:.1f} s"
    )


def _check_sequence(args: argparse.Namespace) -> None:
    """``--frames``, ``--fps`` and the runner options of a sequence, before any work."""
    if args.frames < 1:
        raise WaiInputError(f"--frames must be at least 1, not {args.frames}")
    _check_number("--fps", args.fps, "frames/s", None)
    if not args.fps > 0:
        raise WaiInputError(f"--fps must be > 0, not {args.fps:g}")
    if args.heightfield is not None:
        raise WaiInputError("--heightfield: a sequence moves the sea state; give no surface file")
    if args.workers < 0:
        raise WaiInputError(f"--workers must be >= 0, not {args.workers}")


def run_render_sequence(cfg: SystemConfig, args: argparse.Namespace) -> None:
    """``--frames N --fps F``: a sequence folder (:mod:`wai_core.sequence`), its frames
    rendered here or on Dask workers (``--workers``, ``--scheduler``)."""
    from mitsuba_wai import render_sequence

    _check_sequence(args)
    _, variant = _prepare(args, cfg)
    use_dask = args.scheduler is not None or args.workers > 0
    runner = _dask_runner(args) if use_dask else None
    total = render_sequence(
        cfg, args.out, args.frames, args.fps, progress=not args.quiet,
        overwrite=getattr(args, "overwrite", False), runner=runner,
    ).seconds
    print(
        f"rendered {args.out}: {args.frames} frames at {args.fps:g} fps from t = "
        f"{cfg.waves.time_s} s ({variant}, U={cfg.waves.wind_speed_m_s} m/s, "
        f"seed={cfg.waves.seed}) in {total:.1f} s of rendering"
    )


def _dask_runner(args: argparse.Namespace):  # -> mitsuba_wai.sequence.FrameRunner
    """A runner that spreads a sequence's frames over the sweep runner's Dask workers, each
    rendering with its own loaded scenes into the sequence's temporary folder."""
    import json
    import tempfile
    from pathlib import Path

    from wai.sweep import run_sweep

    def runner(cfg: SystemConfig, times: list[float], indices: list[int], folder: Path) -> list:
        points = [
            {"frame": int(k), "config": json.dumps(cfg.to_dict()), "times": json.dumps(times),
             "folder": str(folder)}
            for k in indices
        ]
        with tempfile.TemporaryDirectory(prefix="wai-frames-") as tmp:
            rows = run_sweep(
                points, render_frame_point, Path(tmp) / "frames.csv", scheduler=args.scheduler,
                workers=max(args.workers, 1), progress=not args.quiet, key=["frame"],
            )
        bad = [r for r in rows if r.get("status") != "ok"]
        if bad or len(rows) != len(points):
            why = bad[0].get("status") if bad else "a frame did not finish"
            raise RuntimeError(f"sequence frame failed: {why}")
        return [{"frame": int(r["frame"]), "render_s": float(r["render_s"])} for r in rows]

    return runner


def render_frame_point(point: dict) -> dict:
    """One sequence frame on a worker (a sweep point: frame index, configuration, times and
    the sequence's folder); its render time."""
    import json
    from pathlib import Path

    from mitsuba_wai import render_frames
    from wai_core.config import config_from_dict

    cfg = config_from_dict(json.loads(point["config"]))
    row = render_frames(cfg, json.loads(point["times"]), [int(point["frame"])],
                        Path(point["folder"]))[0]
    return {"render_s": row["render_s"]}
