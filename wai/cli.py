"""The ``wai`` command: render, restore, benchmark and run experiments.

Bad input ends with one line on stderr naming the problem and exit code 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from wai_core.errors import WaiInputError
from wai_core.sequence import DEFAULT_FPS

EXIT_BAD_INPUT = 2
SCENE_HELP = "scene: a packaged name (paper, alterman, schlieren) or a TOML file"


class _Parser(argparse.ArgumentParser):
    """A parser whose usage errors are bad input like any other: one line, exit code 2.

    ``default_subcommand``: the subcommand run when none is named (``wai bench`` is ``wai
    bench all``, options included: ``wai bench --runs 3``).
    """

    def __init__(self, *args: Any, default_subcommand: str | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.default_subcommand = default_subcommand

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        args = sys.argv[1:] if args is None else list(args)
        if self.default_subcommand and (not args or (
                args[0].startswith("-") and args[0] not in ("-h", "--help"))):
            args = [self.default_subcommand, *args]
        return super().parse_known_args(args, namespace)

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
    from restoration import COMPARISON_INTEGRATORS, INTEGRATORS

    return [name for name in INTEGRATORS if name not in COMPARISON_INTEGRATORS]


def _cmd_render(args: argparse.Namespace) -> int:
    from wai.render_cli import run_render

    run_render(args)
    return 0


def _cmd_restore(args: argparse.Namespace) -> int:
    from wai.restore_cli import run_restore

    run_restore(args)
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from wai.bench import show

    bench: _Bench = args.bench
    result, printer, written = bench.run(args)
    show(result, printer, as_json=args.json, written=written)
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
        methods=getattr(args, "method", None), frames=getattr(args, "frames", None),
        first_seed=getattr(args, "first_seed", None),
        conditions=getattr(args, "condition", None),
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
            q.add_argument("--seeds", type=int, default=None,
                           help=f"seeds 0..K-1 (default: {exp.seeds}; with --quick: "
                           f"{exp.quick_seeds})")
        q.add_argument("--quick", action="store_true",
                       help=f"a small version, for CI and a first look: {exp.quick}")
        if exp.sweep:
            from wai.sweep import add_sweep_arguments

            add_sweep_arguments(q)
        if exp.methods:
            q.add_argument("--method", action="append", metavar="SPEC",
                           help="a method of one's own to compare too: module:Class, "
                           "path/to/file.py:Class or an installed entry point (repeatable; "
                           "'wai guide methods') (default: the built-in ones only)")
        if exp.frames is not None:
            q.add_argument("--frames", type=int, default=None, metavar="N",
                           help=f"frames of each case's sequence (default: {exp.frames}; with "
                           f"--quick: {exp.quick_frames}); fewer make room for a slow method "
                           "over every case (--method inverse-rendering)")
        if exp.conditions:
            q.add_argument("--first-seed", type=int, default=None, metavar="S",
                           help="seeds S..S+K-1 with --seeds K: seeds a run has not looked at "
                           "(default: 0)")
            q.add_argument("--condition", action="append", choices=exp.conditions,
                           metavar="NAME",
                           help="only this condition (repeatable): "
                           f"{', '.join(exp.conditions)} (default: all but "
                           "rough_0.01_256; with --quick: none, speckle)")
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
    p.add_argument("--fps", type=float, default=DEFAULT_FPS,
                   help="frames per second of a sequence")
    p.add_argument(
        "--checkerboards", type=int, default=0, metavar="N",
        help="instead of a frame: N views of a checkerboard per camera through the scene's "
        "true lenses, in air (and through a camera's port in the water where it has one), "
        "for 'wai calibrate' ('wai guide rig')",
    )
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
    p.add_argument("dir", type=Path, help="the folder to restore (a video file or a folder "
                   "of frames too, for the video methods)")
    p.add_argument(
        "--integrator", default=None, choices=_integrators(),
        help="slope integrator (paper: the paper's central differences, eq. 10-13); default: "
        "the method's (fourth_order)",
    )
    p.add_argument(
        "--refine", type=int, default=None,
        help="most refinement passes of the surface samples, stopping once converged "
        "(0 = the paper's q on z = h0); default: the method's (8)",
    )
    p.add_argument(
        "--method",
        default="structured-light",
        help="restoration method: structured-light, alterman (the sun-and-pinhole baseline, on "
        "a folder rendered from the alterman scene), schlieren (synthetic Schlieren from the "
        "view and its flat-water view; an object with texture, [object] texture = "
        "\"speckle\"), inverse-rendering (the structured light's surface refitted to the "
        "whole pattern image), structured-light-view (its level pinned by the view), "
        "schlieren-sl (Schlieren at that structured light's level, or at the level camera s's "
        "spots show where it gives none), inverse-rendering-view "
        "(the refit started from structured-light-view's surface), "
        "inverse-rendering-schlieren (from schlieren-sl's where structured-light-view is not "
        "ok, its dots labelled by the spots that surface predicts), the video methods "
        "registration, lucky "
        "and mean (from a video file, a folder of frames or a sequence; no scene.json), a "
        "method of one's own as module:Class, "
        "or the name an installed package registers (entry points 'wai.methods'; "
        "'wai guide methods') (default: structured-light)",
    )
    p.add_argument(
        "--anchor",
        default=None,
        choices=["integrability", "gauge"],
        help="absolute height: from the slopes' integrability (structured light's default), or "
        "the gauge's h0 (the paper; alterman's and schlieren's only anchor); default: the "
        "method's",
    )
    p.add_argument(
        "--rig", type=Path, default=None,
        help="rig file written by 'wai calibrate': its devices' intrinsics replace the folder's "
        "(default: none, the folder's scene.json as it is)",
    )
    p.add_argument(
        "--fit", action="store_true",
        help="structured light: fit the surface and its level to the spots through the exact "
        "model (restoration.fit_level.fit_level): ~0.3-1 s more per frame, no more accurate "
        "than the "
        "default on the mean of the paper's rig ('wai guide results')",
    )
    p.add_argument(
        "--spot-bias", action=argparse.BooleanOptionalAction, default=None,
        help="structured light: correct each spot for where its light's centre lies off its "
        "dot's centre ray on the surface (Fresnel's reflectance across the dot, the water's "
        "roughness; on rough water by the share of it the flat reference's spots show) and "
        "estimate the surface again, ~0.1 s more per frame on smooth water, "
        "0.2-1.2 s on rough (default: on where the scene's water is rough, off on smooth "
        "water, where it takes about a third off the error but moves a few levels the wrong "
        "way; 'wai guide results', \"Where a spot's light centre lies\")",
    )
    p.add_argument(
        "--as-detected", action="store_true",
        help="structured light: take the spots as detected, not referred to the flat reference; "
        "the level then comes from the data alone, not from the reference's water.h0_mm "
        "(default: referred, which cancels the rig's common errors; 'wai guide rig')",
    )
    p.add_argument("--out", type=Path, default=None,
                   help="video methods: output folder (default: DIR/restore_METHOD, or "
                   "renders/NAME_restore_METHOD for a video file NAME: one folder per method)")
    p.add_argument("--board", default=None,
                   help="video methods: score the restored view of a planar checkerboard with "
                   "COLSxROWS inner corners (default: none)")
    p.add_argument("--track", action="store_true",
                   help="structured light, sequences: label each frame's spots by tracking the "
                   "previous frames' (full matching where that fails its checks) and start the "
                   "warp at the previous frame's (default: every frame matched in full, cold; "
                   "tracking needs spots that move under a tenth of the dot spacing per frame)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_restore)


_BenchRun = tuple[dict[str, Any], Callable[[dict[str, Any]], None], list[Path]]
"""A benchmark's result, the function that prints it, and the files it wrote."""


def _bench_all(args: argparse.Namespace) -> _BenchRun:
    from wai.bench.report import bench_all, print_report, write_report

    result = bench_all(args.config, args.runs, args.dir, args.variant)
    return result, print_report, write_report(result, args.out)


def _bench_render(args: argparse.Namespace) -> _BenchRun:
    from wai.bench.render import bench_render, print_render

    return bench_render(args.config, args.runs, args.variant), print_render, []


def _bench_restore(args: argparse.Namespace) -> _BenchRun:
    from wai.bench.restore import bench_restore, print_restore

    return (bench_restore(args.config, args.runs, args.dir, args.variant, args.workers,
                          method=args.method), print_restore, [])


def _bench_sizes(args: argparse.Namespace) -> _BenchRun:
    from wai.bench.sizes import bench_sizes, parse_sizes, print_sizes

    sizes = parse_sizes(args.sizes)
    return bench_sizes(args.config, args.out, args.runs, sizes), print_sizes, []


def _bench_capture(args: argparse.Namespace) -> _BenchRun:
    from wai.bench.capture import bench_capture, parse_board, print_capture

    return bench_capture(args.video, parse_board(args.board)), print_capture, []


def _capture_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--video", type=Path, required=True,
                   help="a video file or a folder of frames of a planar checkerboard seen "
                   "through water, such as Tian & Narasimhan's CMU capture ('wai guide results', "
                   "\"A real capture\")")
    p.add_argument("--board", default="8x6",
                   help="the board's inner corners, COLSxROWS (default: 8x6, the CMU board)")


def _bench_accuracy(args: argparse.Namespace) -> _BenchRun:
    from wai.bench.accuracy import print_accuracy, run_accuracy

    result = run_accuracy(args.config, args.out, args.seeds, args.wind, args.surface,
                          args.camera, args.spp)
    return result, print_accuracy, []


def _bench_surfaces(args: argparse.Namespace) -> _BenchRun:
    from wai.bench.surfaces import bench_surfaces, print_surfaces

    return bench_surfaces(args.config, args.out, args.phi), print_surfaces, []


def _bench_inputs(args: argparse.Namespace) -> _BenchRun:
    from wai.bench.inputs import bench_inputs, print_inputs

    return bench_inputs(args.config, args.out), print_inputs, []


def _bench_video(args: argparse.Namespace) -> _BenchRun:
    from wai.bench.video import bench_video, print_video

    result = bench_video(args.config, args.out, args.runs, args.workers, args.frames,
                         args.sequence, track=args.track, fps=args.fps)
    return result, print_video, []


def _timed_options(p: argparse.ArgumentParser, *, restores: bool = False,
                   renders: bool = True) -> None:
    """``--runs`` of the wall-time benchmarks; ``--variant`` of those that render, ``--dir`` of
    those that restore a render folder."""
    if restores:
        p.add_argument("--dir", type=Path,
                       help="render folder to restore (default: renders/bench, rendered there "
                       "unless it holds one)")
    p.add_argument("--runs", type=int, default=5, help="measured runs (after a warm-up)")
    if renders:
        p.add_argument("--variant", default="auto",
                       help="Mitsuba variant (auto: GPU, else LLVM)")


def _accuracy_options(p: argparse.ArgumentParser) -> None:
    scenes = " (default: the scene's)"
    p.add_argument("--seeds", type=int, default=10, help="seeds 0..K-1")
    p.add_argument("--wind", type=float, help="wind speed U, m/s" + scenes)
    p.add_argument("--surface", choices=["dielectric", "mirror"], help="water surface" + scenes)
    p.add_argument("--camera", help="both cameras' pixels, WIDTHxHEIGHT (same sensors)" + scenes)
    p.add_argument("--spp", type=int, help="samples per pixel of both renders" + scenes)


def _sizes_options(p: argparse.ArgumentParser) -> None:
    from wai.bench.sizes import SIZES

    _timed_options(p, renders=False)
    p.add_argument("--sizes", default=",".join(SIZES),
                   help="both cameras' sizes, WIDTHxHEIGHT, comma-separated (default: "
                   f"{','.join(SIZES)})")


def _surfaces_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--phi", type=float, default=0.8,
                   help="scale each surface to at most this fraction of eq. 35's slope bound")


def _restore_options(p: argparse.ArgumentParser) -> None:
    _timed_options(p, restores=True)
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes restoring the frame side by side for the throughput "
                   "(1: latency only; a frame is serial) (default: one per core, as memory "
                   "allows; the structured light's only)")
    p.add_argument("--method", default="structured-light",
                   help="the method timed: any per-frame method of 'wai restore --method' "
                   "(inverse-rendering adds its loss evaluations and their time, against the "
                   "37.6 ms a GPU iteration of Mitsuba's caustic-design tutorial takes)")


def _video_options(p: argparse.ArgumentParser) -> None:
    _timed_options(p, renders=False)
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes (and 1) (default: one per core, as memory allows)")
    p.add_argument("--frames", type=int, default=60, help="frames restored per count")
    p.add_argument("--sequence", type=int, default=6, help="distinct frames rendered")
    p.add_argument("--fps", type=float, default=DEFAULT_FPS,
                   help="frame rate of the rendered sequence, frames/s (the camera's)")
    p.add_argument("--track", action="store_true",
                   help="labels tracked from the previous frames, the warp started at the "
                   "previous frame's (default: every frame restored on its own)")


@dataclass(frozen=True)
class _Bench:
    """One ``wai bench NAME``: its help line, its own options (beside ``--config``, ``--json``
    and, where it writes files, ``--out``) and how it runs."""

    summary: str
    options: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], _BenchRun]


_BENCHES = {
    "all": _Bench("time every stage, rendering and restoration; write bench.json and bench.png "
                  "to --out ('wai bench' alone runs it)",
                  lambda p: _timed_options(p, restores=True), _bench_all),
    "render": _Bench("wall time per frame of each scene, printed", _timed_options,
                     _bench_render),
    "restore": _Bench("per-stage and end-to-end time of the restoration of one frame, and "
                      "frames/s with frames in parallel, printed", _restore_options,
                      _bench_restore),
    "sizes": _Bench("the restoration's cost against camera size: ms per frame and per "
                    "megapixel, printed", _sizes_options, _bench_sizes),
    "capture": _Bench("the image-only baselines on a real capture of a checkerboard: the "
                      "corners' residual from a grid, raw frames and temporal mean beside",
                      _capture_options, _bench_capture),
    "accuracy": _Bench("scores over seeds with an error budget", _accuracy_options,
                       _bench_accuracy),
    "surfaces": _Bench("analytic steep and sharp-crested surfaces", _surfaces_options,
                       _bench_surfaces),
    "inputs": _Bench("wrong inputs (swapped patterns, a turned view, ...) and the status each "
                     "gets", lambda p: None, _bench_inputs),
    "video": _Bench("latency and multi-process throughput over a rendered frame sequence",
                    _video_options, _bench_video),
}
"""``wai bench NAME``, in the order of ``wai bench --help``."""


def _add_bench(sub: argparse._SubParsersAction) -> None:
    """``wai bench NAME``: one subcommand per benchmark, each with only its own options;
    ``wai bench`` alone is ``wai bench all``."""
    from wai.bench import DEFAULT_OUT

    p = sub.add_parser(
        "bench", help="benchmarks that print figures", formatter_class=_Help,
        default_subcommand="all",
        description="Benchmarks that print figures; 'wai bench NAME --help' lists NAME's "
        "options. Without NAME: all (its options too: 'wai bench --runs 3').",
    )
    names = p.add_subparsers(dest="what", required=True, metavar="NAME")
    for name, bench in _BENCHES.items():
        q = names.add_parser(name, help=bench.summary, description=bench.summary.capitalize()
                             + ".", formatter_class=_Help)
        q.add_argument("--config", default="paper", help=SCENE_HELP)
        q.add_argument("--json", action="store_true", help="print one JSON object")
        if name in DEFAULT_OUT:
            q.add_argument("--out", type=Path, default=DEFAULT_OUT[name], help="output folder")
        bench.options(q)
        q.set_defaults(func=_cmd_bench, bench=bench)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``wai``."""
    parser = _Parser(
        prog="wai", description="Wavy water-air interface testbed (Jian et al. 2022)."
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_render, _add_restore, _add_bench, _add_demo, _add_experiment):
        add(sub)
    from wai.calibrate_cli import add_calibrate

    add_calibrate(sub, _Help, SCENE_HELP)
    from wai.dataset_cli import add_dataset

    add_dataset(sub, _Help, SCENE_HELP)
    from wai.guide_cli import add_guide

    add_guide(sub, _Help)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code.

    Bad input: one line on stderr, exit code 2; so is a failure of the environment (an
    ``OSError``: a full disk, a read-only folder), the outputs' temporary folders removed.
    SIGINT / SIGTERM: one line, exit code 130 / 143, temporary outputs removed
    (:func:`wai_core.signals.catch_signals` turns both into exceptions); an error that follows a
    signal (a library that swallowed it) counts as it.
    """
    from wai_core.signals import Terminated, catch_signals

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
        except OSError as exc:  # the environment: a full disk, a folder made read-only
            if caught.signum is None:
                where = f"{exc.filename}: " if exc.filename else ""
                print(f"wai: error: {where}{exc.strerror or exc}", file=sys.stderr)
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
