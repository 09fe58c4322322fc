"""The ``wai`` command: render, restore, benchmark and run experiments.

Bad input ends with one line on stderr naming the problem and exit code 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from wai_core.errors import WaiInputError

EXIT_BAD_INPUT = 2
SCENE_HELP = "scene: a packaged name (paper, alterman) or a TOML file"


class _Parser(argparse.ArgumentParser):
    """A parser whose usage errors are bad input like any other: one line, exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise WaiInputError(f"{self.prog}: {message} (see '{self.prog} --help')")


class _Help(argparse.HelpFormatter):
    """Help that shows each option's default (where it has a value to show: 0 is one, an
    unset flag is not)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        unset = default is None or default is False or default is argparse.SUPPRESS
        if (not unset and action.option_strings and "%(default)" not in text
                and "default" not in text):
            text += " (default: %(default)s)"
        return text


class _DescribedHelp(_Help, argparse.RawDescriptionHelpFormatter):
    """:class:`_Help` that keeps a description's paragraphs as written."""


def _version() -> str:
    """The installed package's version (the source tree's when not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("wavy-water-testbed")
    except PackageNotFoundError:  # a checkout run without installing
        return "unknown (not installed)"


def _integrators() -> list[str]:
    """The integrators ``wai restore`` offers: those that restore the paper's frames ``ok``
    (the grid integrators stay in the library and the sweeps, for comparison)."""
    from restoration.integrate import COMPARISON_INTEGRATORS, INTEGRATORS

    return [name for name in INTEGRATORS if name not in COMPARISON_INTEGRATORS]


def _methods() -> list[str]:
    from restoration import METHODS

    return list(METHODS)


def _cmd_render(args: argparse.Namespace) -> int:
    from wai.render_cli import run_render

    run_render(args)
    return 0


def _cmd_restore(args: argparse.Namespace) -> int:
    from wai.restore_cli import run_restore

    run_restore(args)
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from wai.bench import run_bench

    run_bench(
        args.what, config=args.config, out=args.out, runs=args.runs, as_json=args.json,
        variant=args.variant, render_dir=args.dir, seeds=args.seeds, wind=args.wind,
        surface=args.surface, camera=args.camera, spp=args.spp, phi=args.phi,
        workers=args.workers, frames=args.frames, sequence=args.sequence,
    )
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from wai.demo import run_demo

    run_demo(args)
    return 0


def _cmd_experiment(args: argparse.Namespace) -> int:
    from wai.experiments import EXPERIMENTS, run_experiment
    from wai.sweep import SweepOptions

    exp = EXPERIMENTS[args.name]
    run_experiment(
        args.name, args.config, args.out, seeds=args.seeds if exp.seeds is not None else None,
        quick=args.quick, sweep=SweepOptions.from_args(args) if exp.sweep else None,
    )
    return 0


def _add_experiment(sub: argparse._SubParsersAction) -> None:
    """``wai experiment NAME``: one subcommand per experiment, each with only its own options
    (:data:`wai.experiments.EXPERIMENTS`)."""
    from wai.experiments import EXPERIMENTS, describe

    p = sub.add_parser(
        "experiment", formatter_class=_Help,
        help="experiments that write reports, tables and charts",
        description="Experiments that write reports, tables and charts; 'wai experiment NAME "
        "--help' says what NAME writes and how long it takes.",
    )
    names = p.add_subparsers(dest="name", required=True, metavar="NAME")
    for name, exp in EXPERIMENTS.items():
        q = names.add_parser(name, help=exp.summary, description=describe(name),
                             formatter_class=_DescribedHelp)
        q.add_argument("--config", default="paper", help=SCENE_HELP)
        q.add_argument("--out", type=Path, default=Path("renders") / name, help="output folder")
        if exp.seeds is not None:
            q.add_argument("--seeds", type=int, default=exp.seeds, help="seeds 0..K-1")
        q.add_argument("--quick", action="store_true",
                       help=f"a small version, for CI and a first look: {exp.quick}")
        if exp.sweep:
            from wai.sweep import add_sweep_arguments

            add_sweep_arguments(q)
        q.set_defaults(func=_cmd_experiment)


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="render and restore the paper's configuration", formatter_class=_Help
    )
    p.add_argument("--config", default="paper", help=SCENE_HELP)
    p.add_argument("--out", type=Path, default=Path("renders/demo"), help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_demo)


def _add_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render", help="render both optical systems for one sea state (or a sequence)",
        formatter_class=_Help,
    )
    from wai_core.config import load_config
    from wai_core.scenes import scene_path

    # Options left out keep the scene's values; the help quotes the packaged paper scene's.
    paper = load_config(scene_path("paper"))
    p.add_argument("config", help=SCENE_HELP)
    p.add_argument("--out", type=Path, default=Path("renders/latest"), help="output folder")
    p.add_argument("--wind", type=float,
                   help="wind speed U at 19.5 m, m/s (default: the scene's [waves] "
                   f"wind_speed_m_s; paper: {paper.waves.wind_speed_m_s:g})")
    p.add_argument("--time", type=float,
                   help="time t, s (default: the scene's [waves] time_s; paper: "
                   f"{paper.waves.time_s:g})")
    p.add_argument("--seed", type=int,
                   help="random seed of the wave phases and the renders (default: the scene's "
                   f"[waves] seed; paper: {paper.waves.seed})")
    p.add_argument("--heightfield", type=Path,
                   help="surface file (.npz with x, y, z in mm; default: none, the scene's "
                   "[waves] model makes the surface)")
    p.add_argument("--surface", choices=["dielectric", "mirror"],
                   help="water surface material (default: the scene's [water] surface; paper: "
                   f"{paper.water.surface})")
    p.add_argument("--spp", type=int,
                   help="samples per pixel of both renders (default: the scene's [render] "
                   f"spp_pattern and spp_view; paper: {paper.render.spp_pattern} and "
                   f"{paper.render.spp_view})")
    p.add_argument(
        "--variant", default="auto", help="Mitsuba variant: auto, llvm_ad_rgb or cuda_ad_rgb"
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --out folder that is not a previous render (never a file)",
    )
    p.add_argument(
        "--frames", type=int, default=1,
        help="frames of a sequence of the same sea state, 1/FPS s apart from --time; more "
        "than 1 writes a sequence folder (one flat-water reference, a folder per frame)",
    )
    p.add_argument("--fps", type=float, default=30.0, help="frames per second of a sequence")
    p.add_argument(
        "--workers", type=int, default=0,
        help="sequence: Dask worker processes rendering frames (0: here, in order; default: 0)",
    )
    p.add_argument(
        "--scheduler", metavar="ADDRESS",
        help="sequence: a running Dask scheduler (tcp://host:8786) whose workers share --out's "
        "file system (default: none; --workers decides)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_render)


def _add_restore(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "restore",
        help="reconstruct the surface and undistort the view",
        formatter_class=_Help,
        description="Restore a folder: a render of 'wai render', or one's own captures (scene.json "
        "with the rig's config, and pattern, pattern_flat, view as EXR, PNG or TIFF). Scores are "
        "computed where the folder holds truth (heightfield.npz, view_truth.*), else skipped.",
    )
    p.add_argument("dir", type=Path, help="the folder to restore")
    p.add_argument(
        "--integrator", default="fourth_order", choices=_integrators(),
        help="slope integrator (paper: the paper's central differences, eq. 10-13)",
    )
    p.add_argument(
        "--refine", type=int, default=8,
        help="most refinement passes of the reflection points, stopping once converged "
        "(0 = the paper's q on z = h0; RestoreOptions.n_refine)",
    )
    p.add_argument(
        "--method",
        default="structured-light",
        choices=_methods(),
        help="surface sensing method: structured-light, or alterman (the sun-and-pinhole "
        "baseline, on a folder rendered from the alterman scene)",
    )
    p.add_argument(
        "--anchor",
        default=None,
        choices=["integrability", "gauge"],
        help="absolute height: from the slopes' integrability (structured light's default), or "
        "the gauge's h0 (the paper; alterman's only anchor); default: the method's",
    )
    p.add_argument(
        "--fit", action="store_true",
        help="structured light: fit the surface and its level to the spots through the exact "
        "model (restoration.fit.fit_level): ~0.3-1 s more per frame, no more accurate than the "
        "default on the mean of the paper's rig (docs/results.md)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_restore)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmarks that print figures", formatter_class=_Help)
    p.add_argument(
        "what",
        nargs="?",
        default="all",
        choices=["all", "render", "restore", "accuracy", "video", "surfaces", "inputs"],
        help="all (default): time every stage, write bench.json and bench.png to --out; "
        "render/restore: wall time of one part, printed; "
        "accuracy: scores over seeds with an error budget; "
        "surfaces: analytic steep and sharp-crested surfaces; "
        "inputs: wrong inputs (swapped patterns, a turned view, ...) and the status each gets; "
        "video: latency and multi-process throughput over a rendered frame sequence",
    )
    p.add_argument("--config", default="paper", help=SCENE_HELP)
    p.add_argument("--dir", type=Path, help="render folder to restore (default: render one)")
    p.add_argument("--runs", type=int, default=5, help="measured runs (after a warm-up)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--variant", default="auto", help="Mitsuba variant (auto: GPU, else LLVM)")
    p.add_argument("--seeds", type=int, default=10, help="accuracy: seeds 0..K-1")
    p.add_argument(
        "--out", type=Path, help="all: renders/bench (default); accuracy: renders/bench_accuracy; "
        "surfaces, inputs, video: renders/bench_NAME"
    )
    scenes = " (default: the scene's)"
    p.add_argument("--wind", type=float, help="accuracy: wind speed U, m/s" + scenes)
    p.add_argument("--surface", choices=["dielectric", "mirror"],
                   help="accuracy: water surface" + scenes)
    p.add_argument("--camera",
                   help="accuracy: both cameras' pixels, WIDTHxHEIGHT (same sensors)" + scenes)
    p.add_argument("--spp", type=int,
                   help="accuracy: samples per pixel of both renders" + scenes)
    p.add_argument(
        "--phi", type=float, default=0.8,
        help="surfaces: scale each surface to at most this fraction of eq. 35's slope bound",
    )
    p.add_argument("--workers", type=int, default=2, help="video: worker processes (and 1)")
    p.add_argument("--frames", type=int, default=60, help="video: frames restored per count")
    p.add_argument("--sequence", type=int, default=6, help="video: distinct frames rendered")
    p.set_defaults(func=_cmd_bench)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``wai``."""
    parser = _Parser(
        prog="wai", description="Wavy water-air interface testbed (Jian et al. 2022)."
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_render, _add_restore, _add_bench, _add_demo, _add_experiment):
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code.

    Bad input: one line on stderr, exit code 2. SIGINT / SIGTERM: one line, exit code 130 /
    143, temporary outputs removed (:func:`wai_core.io.catch_signals` turns both into
    exceptions); an error that follows a signal (a library that swallowed it) counts as it.
    """
    from wai_core.io import Terminated, catch_signals

    with catch_signals() as caught:
        try:
            args = build_parser().parse_args(argv)
            func: Callable[[argparse.Namespace], int] = args.func
            code = func(args)
            if caught.signum is None:
                return code
        except WaiInputError as exc:
            if caught.signum is None:
                print(f"wai: error: {exc}", file=sys.stderr)
                return EXIT_BAD_INPUT
        except (KeyboardInterrupt, Terminated):
            pass
        except Exception:
            if caught.signum is None:
                raise
        print(f"wai: {caught.message}", file=sys.stderr)
        return caught.exit_code


if __name__ == "__main__":
    sys.exit(main())
