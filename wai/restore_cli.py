"""``wai restore DIR``: restore a render folder, score it, write ``DIR/restore/``."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from wai_core.errors import WaiInputError
from wai_core.io import atomic_dir, write_exr, write_json, write_png


@dataclass
class MethodRun:
    """One method run on a render folder: its calibration, the images it read, and its result,
    or (``result`` None) the status that says why it could not run."""

    cal: Any
    images: dict[str, Any]
    result: Any
    status: str = "ok"
    message: str = ""
    counts: dict[str, int] = field(default_factory=dict)


def run_method(render_dir: Path, method: str, options: Any) -> MethodRun:
    """Load a render folder's calibration and images and run ``method`` on them."""
    from restoration.pipeline import METHODS, load_calibration, load_inputs, restore

    if method not in METHODS:
        raise WaiInputError(f"unknown method {method!r} (known: {', '.join(METHODS)})")
    if not Path(render_dir).is_dir():
        raise WaiInputError(f"render folder not found: {render_dir}")
    if method == "alterman":
        from restoration.alterman import (
            load_alterman_calibration,
            load_alterman_inputs,
            restore_alterman,
        )

        cal = load_alterman_calibration(render_dir)
        images = load_alterman_inputs(render_dir, cal)
        out = restore_alterman(images, cal, options)
        return MethodRun(cal, images, out.result, out.status, out.message, out.counts)
    cal = load_calibration(render_dir)
    images = load_inputs(render_dir, cal)
    return MethodRun(cal, images, restore(images, cal, options))


def restore_folder(
    render_dir: Path, options: Any, progress: bool = True, method: str = "structured-light"
) -> dict[str, Any]:
    """Restore, score and write ``render_dir/restore`` atomically; returns ``metrics.json``.

    ``method`` is ``structured-light`` (the paper's) or ``alterman`` (the sun-sensor baseline,
    on a folder rendered from ``scenes/alterman.toml``). A method that cannot run on this input
    (e.g. no sun) writes only ``metrics.json`` with its ``status``: never a made-up surface.
    """
    from tqdm import tqdm

    from restoration.scoring import load_and_score, surface_profile
    from wai import figures

    bar = tqdm(total=3, desc="restore", disable=not progress, leave=False, unit="step")
    run = run_method(render_dir, method, options)
    if run.result is None:
        bar.close()
        return write_status(render_dir, method, run, options)
    cal, images, result = run.cal, run.images, run.result
    bar.update(1)
    distorted = images["view"] / cal.view_gain
    scores = load_and_score(render_dir, result, cal, distorted)
    bar.update(1)
    error_map = scores.pop("_error_map")
    corner_points = scores.pop("_corner_points")
    metrics = {
        **scores,
        "options": vars(options),
        "timings_ms": {
            **result.timings_ms,
            "features_steps": result.features.timings_ms,
            "surface_steps": result.surface.timings_ms,
            "reverse_trace_steps": result.view.timings_ms,
        },
        "seed": json.loads((Path(render_dir) / "scene.json").read_text()).get("seed"),
    }
    if method != "structured-light":
        metrics.update(method=method, status="ok")
    with atomic_dir(Path(render_dir) / "restore") as tmp:
        est = result.surface.heightfield
        est.save(tmp / "heightfield_est.npz")
        est.to_trimesh().export(tmp / "surface_est.ply")
        write_exr(tmp / "restored.exr", result.view.image)
        write_png(tmp / "restored.png", result.view.image, exposure=1.0)
        figures.error_map_figure(est, error_map, tmp / "error_map.png")
        from wai_core.heightfield import load_heightfield

        truth = load_heightfield(Path(render_dir) / "heightfield.npz")
        y0 = float(np.nanmedian(result.surface.points_mm[:, 1]))
        figures.profile_figure(*surface_profile(est, truth, y0), y0, tmp / "profile.png")
        figures.corner_scatter_figure(
            corner_points,
            {"distorted": scores["corner_std_distorted_px"],
             "restored": scores["corner_std_restored_px"]},
            tmp / "corners.png",
        )
        figures.side_by_side(
            [images["view"] / cal.view_gain, result.view.image],
            ["distorted", "restored"],
            tmp / "distorted_vs_restored.png",
            [1.0, 1.0],
        )
        write_json(tmp / "metrics.json", metrics)
    bar.update(1)
    bar.close()
    return metrics


def write_status(render_dir: Path, method: str, run: MethodRun, options: Any) -> dict[str, Any]:
    """``metrics.json`` alone, for a method that could not run: its status and why."""
    metrics = {
        "method": method,
        "status": run.status,
        "message": run.message,
        "feature_counts": run.counts,
        "options": vars(options),
        "seed": json.loads((Path(render_dir) / "scene.json").read_text()).get("seed"),
    }
    with atomic_dir(Path(render_dir) / "restore") as tmp:
        write_json(tmp / "metrics.json", metrics)
    return metrics


def summary_lines(m: dict[str, Any]) -> list[str]:
    """The scores a person reads first."""
    if m.get("status", "ok") != "ok":
        return [f"{m['method']}: cannot run ({m['status']}): {m['message']}"]
    d, r = m["distorted"], m["restored"]
    return [
        f"surface RMSE {m['wai_rmse_mm']:.3f} mm (de-meaned {m['wai_rmse_demeaned_mm']:.3f} mm, "
        f"max {m['wai_max_abs_mm']:.3f} mm) from {m['features_used']} features "
        f"({m['features_rejected']} rejected)",
        f"corner STD {m['corner_std_distorted_px']:.2f} px -> {m['corner_std_restored_px']:.2f} px "
        f"on {m['corners_common']} corners",
        f"SSIM {d['ssim']:.4f} -> {r['ssim']:.4f}, "
        f"PSNR {d['psnr_db']:.2f} -> {r['psnr_db']:.2f} dB, "
        f"MSE {d['mse']:.4f} -> {r['mse']:.4f} on {m['view_restored_fraction']:.0%} of the view",
        anchor_line(m.get("anchor", {})),
        f"end to end {m['timings_ms']['end_to_end']:.1f} ms",
    ]


def anchor_line(anchor: dict[str, Any]) -> str:
    """How the absolute water level was set, in words."""
    level = f"mean level {anchor.get('anchor_mm', float('nan')):.2f} mm"
    sigma = anchor.get("sigma_mm")
    if anchor.get("method") == "integrability":
        return f"{level} from integrability (+- {sigma:.2f} mm)"
    if anchor.get("method") == "gauge_fallback":
        why = "not pinned" if sigma is None or not np.isfinite(sigma) else f"+- {sigma:.2f} mm"
        return f"{level} from the gauge (integrability {why}: too little curvature)"
    return f"{level} from the gauge"


def run_restore(args: argparse.Namespace) -> None:
    """CLI entry: restore ``args.dir`` and print the summary."""
    from restoration.pipeline import METHODS, RestoreOptions

    if args.method not in METHODS:
        raise WaiInputError(f"unknown method {args.method!r} (known: {', '.join(METHODS)})")
    # The structured light finds the height from integrability; the sun sensor cannot.
    anchor = args.anchor or ("gauge" if args.method == "alterman" else "integrability")
    options = RestoreOptions(integrator=args.integrator, n_refine=args.refine, anchor=anchor)
    metrics = restore_folder(args.dir, options, progress=not args.quiet, method=args.method)
    for line in summary_lines(metrics):
        print(line)
