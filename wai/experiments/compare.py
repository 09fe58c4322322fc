"""``wai experiment compare``: every method on the same rendered sequences, with truth.

The field's two families side by side: methods that restore each frame from a rig
(structured light; any method of one's own through :class:`restoration.Method`, given as
``--method SPEC``), and methods that restore a still scene from video alone
(:mod:`restoration.video`: the temporal mean, registration by optical flow, lucky-region
fusion). Each case (sea state, seed, degradation) is one rendered sequence; every method runs
on it. Scores against the truth: the view's SSIM and PSNR against the flat-water view (on the
pixels the method restored and the object covers), corner STD against the truth's corners,
surface RMSE where the method gives a surface; and its cost: ms per frame and the frames it
needs (1 for a per-frame method, the sequence for a video method). Beside them, a score that
needs no truth (what a real capture allows): how far the view's checkerboard corners lie from
the map of a regular grid seen through flat water (:func:`restoration.video.grid_score`), and
whether it ranks the methods as corner STD does (Kendall's tau). The cases run as a sweep
(:mod:`wai.sweep`): locally, on a Dask cluster, resumable.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from wai.experiments.compare_frames import (
    WRONG_OK_MM,
    by_condition,
    condition_report,
    frame_columns,
    rescue_report,
    rescues,
)
from wai.experiments.outputs import output_folder, publish, sweep_command, sweep_rows
from wai.sweep import SweepOptions, is_error
from wai_core.config import with_keys
from wai_core.errors import WaiInputError
from wai_core.io import write_json
from wai_core.sequence import DEFAULT_FPS
from wai_core.system import load_rig

VIDEO_METHODS = ("mean", "registration", "lucky")
"""The image-only baselines (:mod:`restoration.video`)."""
FRAME_METHODS = ("structured-light", "structured-light-view", "schlieren", "schlieren-sl",
                 "wai.examples.plugin_method:AsSeen")
"""The per-frame methods compared by default: the paper's, the paper's with its level pinned
by camera v's view, synthetic Schlieren on camera v's view (at the gauge's level and at the
structured light's), and the unrestored view as a method of one's own (its floor)."""
_SPECKLE = {"object.texture": "speckle"}
DEGRADATIONS: dict[str, dict[str, Any]] = {
    "none": {},
    "speckle": _SPECKLE,
    "sensor": {"sensor.enabled": True},
    # Where the geometric method is weak (the error budget's rows), seen through the speckle
    # object so that Schlieren, which does not look at the pattern, has its texture.
    "rough_0.01": {"water.roughness": 0.01, "render.spp_pattern": 64, **_SPECKLE},
    "rough_0.02": {"water.roughness": 0.02, "render.spp_pattern": 64, **_SPECKLE},
    "capillary_4": {"waves.dispersion": "capillary", "waves.omega_max_rel": 4.0, **_SPECKLE},
    "capillary_5": {"waves.dispersion": "capillary", "waves.omega_max_rel": 5.0, **_SPECKLE},
    "capillary_6": {"waves.dispersion": "capillary", "waves.omega_max_rel": 6.0, **_SPECKLE},
    "steep_2": {"waves.height_scale": 2.0, **_SPECKLE},
    "defocus_2mm": {"projector.aperture_mm": 2.0, "projector.focus_mm": 400.0, **_SPECKLE},
    # Only when named (--condition): micro-roughness with 4x the pattern's samples, where the
    # spots' Monte Carlo noise no longer adds to the halo's.
    "rough_0.01_256": {"water.roughness": 0.01, "render.spp_pattern": 256, **_SPECKLE},
}
"""The cases' conditions, as configuration keys: the paper's scene (``none``), its object a
lab tank's speckle (``speckle``: what Schlieren needs; no corners to score), the sensor's
noise, and where the geometric method is weak: micro-roughness (GGX alpha, 64 pattern
samples as the budget takes), gravity-capillary waves to 4, 5 and 6 omega_p, waves twice as
high and steep as the fully developed sea (towards eq. 35's ordering limit), a defocused
projector (2 mm aperture focused at 400 mm); and, run only when named (:data:`ON_REQUEST`),
micro-roughness 0.01 at 256 pattern samples."""
QUICK_DEGRADATIONS = ("none", "speckle")
"""The conditions of ``--quick``."""
ON_REQUEST = ("rough_0.01_256",)
"""Conditions run only when named with ``--condition`` (four times the render of their
64-sample case)."""
DEFAULT_DEGRADATIONS = tuple(d for d in DEGRADATIONS if d not in ON_REQUEST)
"""The conditions of a run without ``--quick`` or ``--condition``."""
SCORES = ("ssim", "psnr_db", "corner_std_px", "rmse_mm", "rmse_demeaned_mm", "grid_px",
          "grid_fraction", "rig_px", "rig_fraction", "ms_per_frame", "reference_ms",
          "frame_per_reference", "frames_needed", "frames_ok", "frames_ok_wrong", "frames")
MIN_CORNERS = 10
"""Fewest corners, found in the truth, the distorted and the restored view alike, for a corner
STD (two corners have a spread, but not one that says much: a blurred view shows few)."""
COUNTS = ("frames_ok", "frames_ok_wrong", "frames")
"""Scores summed over a method's cases, not averaged."""
GRID_FRAMES = 8
"""Frames of a per-frame method the truth-free grid score looks at, evenly spaced (finding a
partial board costs more than a structured-light restoration)."""


FRAMES, QUICK_FRAMES = 30, 8
"""Frames of each case's sequence (one second at 30 frames/s), and with ``--quick``."""
MIN_FRAMES = 2
"""Fewest frames of a case: the video methods register frames against one another."""


def case_name(point: dict[str, Any]) -> str:
    """The case's folder name: sea state, seed, condition and its number of frames (sequences
    of other lengths in one ``--out`` are other cases, each kept)."""
    return (f"U{point['wind']:g}_seed{point['seed']:03d}_{point['degradation']}"
            f"_{point['case_frames']}f")


def compare_points(methods: list[str], seeds: int, quick: bool, frames: int,
                   first_seed: int = 0, conditions: list[str] | None = None
                   ) -> list[dict[str, Any]]:
    """Every (case, method): sea states, seeds ``first_seed`` .. ``first_seed + seeds - 1``
    and conditions crossed with the methods, each case a sequence of ``frames``.

    ``conditions``: keys of :data:`DEGRADATIONS` (None: :data:`DEFAULT_DEGRADATIONS`, with
    ``quick`` :data:`QUICK_DEGRADATIONS`).

    Raises
    ------
    WaiInputError
        An unknown condition, or a negative ``first_seed``.
    """
    if first_seed < 0:
        raise WaiInputError(f"--first-seed must be 0 or more, not {first_seed}")
    unknown = [c for c in conditions or [] if c not in DEGRADATIONS]
    if unknown:
        raise WaiInputError(f"--condition {unknown[0]!r}: not a condition of compare (one of "
                            f"{', '.join(DEGRADATIONS)})")
    winds = (1.0,) if quick else (1.0, 1.5)
    if conditions:
        degradations = tuple(dict.fromkeys(conditions))
    else:
        degradations = QUICK_DEGRADATIONS if quick else DEFAULT_DEGRADATIONS
    seed_range = range(first_seed, first_seed + seeds)
    return [{"wind": w, "seed": s, "degradation": d, "method": m, "case_frames": frames}
            for w in winds for s in seed_range for d in degradations for m in methods]


def render_case(config: str, point: dict[str, Any], root: Path) -> Path:
    """The case's sequence of ``point['case_frames']``, rendered into ``root/cases/NAME`` unless it
    is there."""
    from mitsuba_wai import render_sequence
    from wai_core.sequence import is_sequence, read_sequence

    folder = root / "cases" / case_name(point)
    frames = int(point["case_frames"])
    if is_sequence(folder) and len(read_sequence(folder).frames) == frames:
        return folder
    cfg = load_rig(config).replace("waves", wind_speed_m_s=point["wind"], seed=point["seed"])
    cfg = with_keys(cfg, DEGRADATIONS[point["degradation"]])
    render_sequence(cfg, folder, frames, DEFAULT_FPS, progress=False, overwrite=True)
    return folder


def _view_scores(result: Any, distorted: np.ndarray, cal: Any, truth: Any) -> dict[str, Any]:
    from restoration import score

    s = score(result, distorted, cal, truth)
    out = {"ssim": s.restored["ssim"], "psnr_db": s.restored["psnr_db"],
           "corner_std_px": _corner_std(s.corner_std_restored_px, s.corners_common)}
    out["rmse_mm"] = s.rmse_mm if s.surface is not None else None
    out["rmse_demeaned_mm"] = None if s.surface is None else s.surface.get("rmse_demeaned_mm")
    return out


def _rig(image: np.ndarray, valid: np.ndarray, cal: Any) -> dict[str, Any]:
    """The truth-free score against the calibrated rig's flat-water corners: spread px
    (None under its corner minimum) and the share of the expected corners found."""
    from restoration import rig_grid_score

    s = rig_grid_score(image, cal.cfg, valid)
    return {"rig_px": s.std_px if np.isfinite(s.std_px) else None, "rig_fraction": s.fraction}


def _grid(image: np.ndarray, valid: np.ndarray, cal: Any) -> dict[str, Any]:
    """The truth-free grid score of one view: residual px (None where no board was found)
    and the share of the board's inner corners it scored."""
    from restoration import video

    nx, ny = cal.cfg.object.squares
    g = video.grid_score(image, (nx - 1, ny - 1), valid, n_water=cal.cfg.water.n_water)
    return {"grid_px": g.rms_px if np.isfinite(g.rms_px) else None,
            "grid_fraction": g.fraction}


def _corner_std(std_px: float | None, corners: int) -> float | None:
    """A view's corner STD, None on fewer than :data:`MIN_CORNERS` corners."""
    return std_px if corners >= MIN_CORNERS else None


def _frame_method(folder: Path, spec: str) -> dict[str, Any]:
    """A per-frame method over the sequence: means over its frames with a view."""
    from restoration import LevelTrack, get_method, restore_frame, sequence_frames
    from wai_core.sequence import read_sequence

    seq = read_sequence(folder)
    method = get_method(spec)
    cal, _ = sequence_frames(folder, method)  # the method's calibration; frames read below
    track = LevelTrack()
    rows = []
    n = len(seq.frame_dirs)
    gridded = set(np.linspace(0, n - 1, min(n, GRID_FRAMES)).round().astype(int).tolist())
    for k, frame in enumerate(seq.frame_dirs):
        done = restore_frame(frame, cal, method, track, flat_from=[folder])
        rows.append(frame_row(done, cal, grid=k in gridded))
    mean = {key: _mean([r.get(key) for r in rows])
            for key in ("ssim", "psnr_db", "corner_std_px", "rmse_mm", "rmse_demeaned_mm",
                        "grid_px", "grid_fraction", "rig_px", "rig_fraction")}
    return {**mean, "ms_per_frame": float(np.median([r["ms"] for r in rows if r["ms"]])),
            "frames_needed": 1, "frames_ok": sum(r["ok"] for r in rows),
            "frames_ok_wrong": _ok_but_wrong(rows), "frames": len(rows),
            "method_name": method.name,
            **frame_columns([r["status"] for r in rows], [r.get("rmse_mm") for r in rows])}


def frame_row(done: Any, cal: Any, grid: bool = False) -> dict[str, Any]:
    """One restored frame's row of a per-frame method (``done``: what
    :func:`restoration.restore_frame` returns): its status and time, the view's scores where
    the view was scored, the surface's RMSE wherever the truth scored the surface (a frame
    whose view restores too few pixels to score still has a surface its status vouches for),
    and the truth-free grid score where ``grid``."""
    res, m = done.result, done.metrics
    row = {"ok": res.ok, "status": str(res.status), "ms": res.timings_ms.get("end_to_end")}
    if res.has_view:
        row.update(_rig(res.view.image, res.view.valid, cal))
        if grid:
            row.update(_grid(res.view.image, res.view.valid, cal))
    if done.scores is not None and done.scores.restored is not None:
        row.update(ssim=done.scores.restored["ssim"],
                   psnr_db=done.scores.restored["psnr_db"],
                   corner_std_px=_corner_std(m.get("corner_std_restored_px"),
                                             m.get("corners_common", 0)))
    row.update(rmse_mm=m.get("wai_rmse_mm"), rmse_demeaned_mm=m.get("wai_rmse_demeaned_mm"))
    return row


def _ok_but_wrong(rows: list[dict[str, Any]]) -> int | None:
    """Frames of ``rows`` that say ``ok`` with a surface RMSE past :data:`WRONG_OK_MM`; None
    where no frame has a surface to score (a method of the view alone)."""
    scored = [r for r in rows if r.get("rmse_mm") is not None]
    if not scored:
        return None
    return sum(bool(r["ok"] and r["rmse_mm"] > WRONG_OK_MM) for r in scored)


def _video_method(folder: Path, name: str) -> dict[str, Any]:
    """A video method over the sequence's views: one fused image, scored against the truth
    of the first frame (the flat-water view is every frame's)."""
    from restoration import RestoredView, RestoreResult, Truth, load_sequence, video
    from wai_core.sequence import read_sequence

    cal, images = load_sequence(folder)
    views = np.stack([cal.radiance(im["view"]) for im in images]).astype(np.float32)
    run = {"mean": video.temporal_mean, "registration": video.register_frames,
           "lucky": video.lucky_fusion}[name]
    fused = run(np.clip(views, 0.0, 1.0))
    truth = Truth.from_folder(read_sequence(folder).frame_dirs[0], cal)
    result = RestoreResult(name, view=RestoredView(fused.image, fused.valid))
    return {**_view_scores(result, views[0], cal, truth), **_grid(fused.image, fused.valid, cal),
            **_rig(fused.image, fused.valid, cal),
            "ms_per_frame": fused.ms_per_frame,
            "frames_needed": len(views), "frames_ok": len(views), "frames": len(views),
            "method_name": name}


def _mean(values: list[Any]) -> float | None:
    v = np.array([x for x in values if x is not None], float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else None


def _sd(values: list[Any]) -> float | None:
    """The sample standard deviation over the cases (None under two)."""
    v = np.array([x for x in values if x is not None], float)
    v = v[np.isfinite(v)]
    return float(v.std(ddof=1)) if v.size > 1 else None


def evaluate(point: dict[str, Any]) -> dict[str, Any]:
    """One sweep point: the method on its case's sequence (rendered beforehand), and the
    reference workload timed after it in the same process (``reference_ms``): a point's
    ``ms_per_frame`` over it (``frame_per_reference``, the frame's cost in reference
    workloads) compares across machines, loads and a cluster's workers."""
    from wai.bench.timing import reference_workload

    folder = Path(point["folder"])
    if point["method"] in VIDEO_METHODS:
        scores = _video_method(folder, point["method"])
    else:
        scores = _frame_method(folder, point["method"])
    reference = reference_workload()["median_ms"]
    ms = scores.get("ms_per_frame")
    return {**scores, "reference_ms": reference,
            "frame_per_reference": None if ms is None else ms / reference}


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per method: the means of its scores over the cases, its frames (``frames_ok``,
    ``frames_ok_wrong`` and ``frames`` summed over the cases: a failed frame is counted, not
    averaged away), its cases, and the cases it failed on (``failed_cases``; ``error``: the
    first one's status, e.g. a method of one's own that raised)."""
    out = []
    for method in dict.fromkeys(r["method"] for r in rows):
        part = [r for r in rows if r["method"] == method and not is_error(r.get("status"))]
        failed = [r["status"] for r in rows if r["method"] == method and is_error(r.get("status"))]
        entry = {"method": method, "name": part[0]["method_name"] if part else method,
                 "cases": len(part), "failed_cases": len(failed),
                 "error": failed[0] if failed else None}
        entry.update({k: _mean([r.get(k) for r in part]) for k in SCORES})
        entry.update({f"{k}_sd": _sd([r.get(k) for r in part])
                      for k in ("corner_std_px", "ssim", "rmse_demeaned_mm")})
        for k in COUNTS:  # None where no case has the count (frames_ok_wrong: no surface)
            have = [float(r[k]) for r in part if r.get(k) not in (None, "")]
            have = [v for v in have if np.isfinite(v)]
            entry[k] = int(sum(have)) if have else None
        out.append(entry)
    return out


def _figure(summary: list[dict[str, Any]], path: Path) -> list[str]:
    """Speed against accuracy: one marker and colour per method, named in a legend below the
    panels (labels beside the points overlapped where methods cluster), the spread over the
    sequences as error bars. Returns the legend's names: every method with a time, whichever
    panels it has a point in."""
    import os

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import NullFormatter

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), layout="constrained")
    markers = "osD^vP*Xh<>"
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    legend: list[Line2D] = []
    for i, e in enumerate(x for x in summary if x["ms_per_frame"] is not None):
        style = {"marker": markers[i % len(markers)], "color": colours[i % len(colours)],
                 "linestyle": "none", "markersize": 7}
        legend.append(Line2D([], [], label=e["name"], **style))
        for ax, key in zip(axes, ("corner_std_px", "ssim", "rmse_demeaned_mm"), strict=True):
            if e[key] is not None:
                spread = e.get(f"{key}_sd")
                ax.errorbar(e["ms_per_frame"], e[key], yerr=spread, label=e["name"],
                            capsize=3, **style)
    axes[0].set_ylabel("corner STD against the truth, px (lower is better)")
    axes[1].set_ylabel("view SSIM against the flat-water view (higher is better)")
    axes[2].set_ylabel("surface RMSE, de-meaned, mm (lower is better)")
    axes[2].set_ylim(bottom=0.0)
    ms = [e["ms_per_frame"] for e in summary if e["ms_per_frame"]]
    # Whole decades, with at least a factor of 2 to spare: no marker sits on an edge.
    decades = (10.0 ** np.floor(np.log10(min(ms) / 2)), 10.0 ** np.ceil(np.log10(2 * max(ms)))) \
        if ms else None
    for ax in axes:
        ax.set_xscale("log")
        if decades is not None:  # whole decades: each panel shows its powers of ten
            ax.set_xlim(*decades)
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(f"ms per frame ({os.cpu_count()} cores, this run)")
        ax.grid(alpha=0.3, which="both")
    if legend:
        fig.legend(handles=legend, loc="outside lower center", ncol=min(len(legend), 5),
                   fontsize=8, frameon=False)
    fig.suptitle("Speed against accuracy, every method on the same rendered sequences "
                 "(means over the sequences; bars: their standard deviation)")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return [h.get_label() for h in legend]


def rank_agreement(summary: list[dict[str, Any]], key: str = "grid_px"
                   ) -> tuple[float | None, int]:
    """Kendall's tau between a truth-free score (``"grid_px"``: the free flat-water grid, what
    an uncalibrated capture allows; ``"rig_px"``: the calibrated rig's corners) and corner STD
    over the methods that have both (1: the same order, -1: reversed; None under 3
    methods), and their count."""
    from scipy.stats import kendalltau

    pairs = [(e[key], e["corner_std_px"]) for e in summary
             if e.get(key) is not None and e.get("corner_std_px") is not None]
    if len(pairs) < 3:
        return None, len(pairs)
    tau = kendalltau(*np.array(pairs).T).statistic
    return (float(tau) if np.isfinite(tau) else None), len(pairs)


def case_agreement(rows: list[dict[str, Any]]) -> list[float | None]:
    """:func:`rank_agreement` within each case (sea state, seed, degradation): the methods
    compared on the same sequence."""
    cases: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        if not is_error(r.get("status")):
            cases.setdefault((r["wind"], r["seed"], r["degradation"]), []).append(r)
    return [rank_agreement(part)[0] for part in cases.values()]


def report(summary: list[dict[str, Any]], command: str,
           case_taus: list[float | None] | None = None,
           conditions: list[dict[str, Any]] | None = None,
           rescued: list[dict[str, Any]] | None = None) -> str:
    def f(v: Any, spec: str) -> str:
        return "-" if v is None else format(v, spec)

    lines = [f"# Methods compared (`{command}`)", "",
             "| method | frames needed | ok / frames | ok but wrong | view SSIM | PSNR dB | "
             "corner STD px | surface RMSE mm | de-meaned mm | grid px (no truth) | "
             "corners found | rig px (no truth) | ms per frame | x reference |",
             "|" + " --- |" * 14]
    for e in summary:
        lines.append(
            f"| {e['name']} | {f(e['frames_needed'], '.0f')} | {f(e['frames_ok'], '.0f')} / "
            f"{f(e['frames'], '.0f')} | {f(e.get('frames_ok_wrong'), '.0f')} | "
            f"{f(e['ssim'], '.4f')} | {f(e['psnr_db'], '.2f')} | "
            f"{f(e['corner_std_px'], '.3f')} | {f(e['rmse_mm'], '.4f')} | "
            f"{f(e.get('rmse_demeaned_mm'), '.4f')} | "
            f"{f(e.get('grid_px'), '.3f')} | {f(e.get('grid_fraction'), '.0%')} | "
            f"{f(e.get('rig_px'), '.3f')} | {f(e['ms_per_frame'], '.1f')} | "
            f"{f(e.get('frame_per_reference'), '.2f')} |")
    failed = [e for e in summary if e.get("failed_cases")]
    if failed:
        lines.append("")
    for e in failed:
        lines.append(f"- {e['name']} failed on {e['failed_cases']} of "
                     f"{e['failed_cases'] + e['cases']} cases: {e['error']}")
    tau, count = rank_agreement(summary)
    lines += ["", f"Ok but wrong: frames that said `ok` with a surface RMSE over {WRONG_OK_MM:g} "
              "mm (a status that should have flagged them; - for methods without a surface). "
              f"Corner STD: over the views that show at least {MIN_CORNERS} of the truth's "
              "corners. Grid px: RMS distance of the view's checkerboard corners from the best "
              "map of a regular grid seen through flat water (no truth read); corners found: "
              "the share of the board's inner corners it scored. Rig px: spread of the "
              "corners about the calibrated rig's flat-water corners, less a common shift "
              "(no truth read; restoration.rig_grid_score)."]
    refs = [e["reference_ms"] for e in summary if e.get("reference_ms") is not None]
    if refs:
        lines.append(
            "Ms per frame: the median over a case's frames (a video method: its fused image's "
            "time over the frames), the mean over the cases. x reference: each case's ms per "
            "frame over the reference workload (a 1000 x 1000 float64 matmul, median of 5) "
            "timed after it in the same process, "
            f"{min(refs):.1f}-{max(refs):.1f} ms in this run's cases (methods' means).")
    if tau is None:
        lines.append(f"Too few methods with both scores ({count}) to compare their rankings.")
    else:
        verdict = ("orders the methods as corner STD does" if np.isclose(tau, 1.0)
                   else "and corner STD rank the methods")
        lines.append(f"The truth-free score {verdict}: Kendall tau = {tau:.2f} over {count} "
                     "methods (1: the same order, -1: reversed).")
    rig_tau, rig_count = rank_agreement(summary, "rig_px")
    if rig_tau is not None:
        lines.append(f"Against the calibrated rig's corners: Kendall tau = {rig_tau:.2f} over "
                     f"{rig_count} methods.")
    if case_taus:
        each = ", ".join("-" if t is None else f"{t:.2f}" for t in case_taus)
        lines.append(f"Within each case: tau = {each}.")
    lines += condition_report(conditions or [])
    lines += rescue_report(rescued or [])
    return "\n".join(lines) + "\n"


def run_compare(config: str | Path, out: str | Path, seeds: int, quick: bool,
                sweep: SweepOptions | None = None, methods: list[str] | None = None,
                frames: int | None = None, first_seed: int = 0,
                conditions: list[str] | None = None) -> list[dict[str, Any]]:
    """The experiment into ``out``: renders, the sweep's table, the summary, chart, report.

    ``frames``: of each case's sequence (None: :data:`FRAMES`, with ``quick``
    :data:`QUICK_FRAMES`). Rows and cases are kept per frame count: a rerun with another
    count renders and restores its own. ``first_seed`` and ``conditions``: see
    :func:`compare_points` (seeds a run has not looked at, a few conditions).

    Raises
    ------
    WaiInputError
        A method that does not resolve, an unknown condition, a negative ``first_seed``, or
        fewer than :data:`MIN_FRAMES` frames, before any render.
    """
    from tqdm import tqdm

    from restoration import method_class

    default = QUICK_FRAMES if quick else FRAMES
    frames = default if frames is None else int(frames)
    if frames < MIN_FRAMES:
        raise WaiInputError(f"--frames must be at least {MIN_FRAMES} (the video methods "
                            f"register frames against one another), not {frames}")
    specs = [*FRAME_METHODS, *(methods or []), *VIDEO_METHODS]
    for spec in specs:  # a bad name fails here, before any render
        if spec not in VIDEO_METHODS:
            method_class(spec)
    points = compare_points(list(dict.fromkeys(specs)), seeds, quick, frames, first_seed,
                            conditions)
    out = output_folder(out)
    cases = {case_name(p): p for p in points}
    sweep = SweepOptions() if sweep is None else sweep
    for name, p in tqdm(cases.items(), desc="render", unit="case", disable=not sweep.progress):
        folder = render_case(str(config), p, out)
        for q in points:
            if case_name(q) == name:
                q["folder"] = str(folder)
    rows = sweep_rows(points, evaluate, out / "compare.csv", sweep,
                      key=("wind", "seed", "degradation", "method", "case_frames"))
    summary = summarize(rows)
    command = sweep_command("compare", seeds, quick)
    if frames != default:
        command += f" --frames {frames}"
    if first_seed:
        command += f" --first-seed {first_seed}"
    command += "".join(f" --condition {c}" for c in dict.fromkeys(conditions or []))
    case_taus = case_agreement(rows)
    by_case = by_condition(rows, DEGRADATIONS)
    rescued = rescues(rows)
    text = report(summary, command, case_taus, by_case, rescued)
    tau, _ = rank_agreement(summary)
    write_json(out / "compare_summary.json",
               {"command": command, "methods": summary, "kendall_tau_grid_corner_std": tau,
                "kendall_tau_rig_corner_std": rank_agreement(summary, "rig_px")[0],
                "kendall_tau_per_case": case_taus, "conditions": by_case,
                "rescues": rescued})
    _figure(summary, out / "compare.png")
    publish(out / "compare.md", text)
    return summary

