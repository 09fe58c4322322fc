"""``wai restore DIR``: restore a folder (a render, or one's own captures), score it where truth
exists, write ``DIR/restore/`` (``DIR/restore_METHOD/`` for a method other than the folder's own:
:func:`restoration.folder.default_out`) and print the summary."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from restoration import SurfaceOptions, get_method, restore_folder


def run_restore(args: argparse.Namespace) -> None:
    """CLI entry: restore ``args.dir``, print the summary, and warn on a frame whose status is
    not ``ok``."""
    from wai.restore_video_cli import VIDEO_METHODS, run_restore_video
    from wai_core.errors import WaiInputError

    if args.method in VIDEO_METHODS:
        run_restore_video(args)
        return
    if args.out is not None or args.board is not None:
        raise WaiInputError(f"--out and --board are for the video methods "
                            f"({', '.join(VIDEO_METHODS)}), not {args.method}")
    if not args.dir.is_dir():
        raise WaiInputError(f"restore folder not found: {args.dir}")
    if args.refine is not None and args.refine < 0:
        raise WaiInputError(f"--refine must be 0 or more passes, got {args.refine}")
    options = method_options(args)
    rig = None
    if getattr(args, "rig", None) is not None:  # read before any work: a bad file stops here
        from restoration import read_rig

        read_rig(args.rig)
        rig = args.rig
    from wai_core.sequence import is_sequence

    cold = compile_notice(args.quiet)
    if is_sequence(args.dir):
        run_restore_sequence(args, options, rig)
        return
    done = restore_folder(args.dir, args.method, options, progress=not args.quiet, rig=rig)
    for line in done.summary_lines():
        if cold and line.startswith("restoration "):
            line += " (includes compiling the kernels once)"
        print(line)
    status = done.result.status
    if status != "ok":
        print(f"wai: warning: {args.dir}: frame status {status}: {done.result.message}",
              file=sys.stderr)


def method_options(args: argparse.Namespace) -> SurfaceOptions:
    """The method's options with the flags given, the rest at the method's defaults."""
    from wai_core.errors import WaiInputError

    anchor = args.anchor
    if args.method == "alterman":
        # The sun sensor's normals do not depend on the height: its level is the gauge's.
        if anchor == "integrability" or args.fit or args.as_detected or args.spot_bias:
            flag = ("--fit" if args.fit else "--as-detected" if args.as_detected
                    else "--spot-bias" if args.spot_bias else "--anchor integrability")
            raise WaiInputError(
                f"{flag}: alterman's normals do not depend on the height, so its level is "
                "always the gauge's (--anchor gauge)"
            )
        anchor = None
    choices = {"integrator": args.integrator, "n_refine": args.refine, "anchor": anchor,
               "fit_spots": True if args.fit else None,
               "flat_referenced": False if args.as_detected else None,
               "spot_bias": args.spot_bias}
    try:
        return get_method(args.method, **choices).options
    except WaiInputError as exc:
        if str(exc).startswith("--"):
            raise
        if str(exc).startswith("unknown method"):
            from restoration import method_names
            from wai.restore_video_cli import VIDEO_METHODS

            raise WaiInputError(
                f"--method: unknown method {args.method!r}: per frame "
                f"{', '.join(method_names())}; from video {', '.join(VIDEO_METHODS)}; or one's "
                "own as module:Class or path/to/file.py:Class ('wai guide methods')"
            ) from None
        raise WaiInputError(f"--method: {exc}") from None


def compile_notice(quiet: bool) -> bool:
    """Say so (unless ``quiet``) when this run compiles the kernels; whether it will."""
    from restoration import COMPILE_NOTICE, kernels_cached

    cold = not kernels_cached()
    if cold and not quiet:
        print(f"wai: {COMPILE_NOTICE}", file=sys.stderr)
    return cold


def run_restore_sequence(
    args: argparse.Namespace, options: SurfaceOptions, rig: Any = None
) -> None:
    """A sequence folder: every frame, the per-frame table, the movies and temporal scores."""
    from restoration import restore_sequence

    done = restore_sequence(args.dir, args.method, options, progress=not args.quiet, rig=rig,
                            track=getattr(args, "track", False))
    for line in done.summary_lines():
        print(line)
    print(f"per-frame table, movies and figures: {done.out}")
    bad = {k: v for k, v in done.summary["statuses"].items() if k != "ok"}
    if bad:
        print(f"wai: warning: {args.dir}: frames with status {bad}", file=sys.stderr)
