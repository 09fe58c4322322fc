"""Restore a sequence folder: every frame with the level tracked, per-frame and temporal scores,
the restored movie and a distorted/restored side-by-side one.

One calibration serves the whole sequence (the flat-water reference is detected once); a
:class:`~restoration.tracking.SequenceState` starts each frame's level search at the previous
frame's level, labels its spots by tracking the previous frames' (full matching where that
fails its checks) and starts its warp solve at the previous frame's. Temporal scores say
whether the restoration is stable in time: the view of a still object should not move, so the
mean absolute change between consecutive restored frames
(on pixels restored in both) is compared with the same for the distorted frames.

A folder of one's own captures (numbered images or frame folders, :mod:`wai_core.sequence`)
restores the same way, without truth: its frames are read where they are, and every output,
each frame's included (``restore/<frame>/``), goes under ``folder/restore/``; nothing else in
the folder is written.
"""

from __future__ import annotations

import contextlib
import csv
import io
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from restoration.calibration import LevelTrack, RigCalibration, read_scene_record
from restoration.frame import (
    RESTORE_REMEDY,
    FolderRestore,
    check_files,
    check_rig_geometry,
    default_out,
    flat_reference_line,
    folder_metrics,
    load_view_flat,
    restore_frame,
    rig_line,
    with_rig,
)
from restoration.methods import as_method
from restoration.options import SurfaceOptions
from restoration.protocol import Method, run_method
from restoration.result import Status
from restoration.tracking import SequenceState
from restoration.view_check import match_sequence
from wai_core.io import atomic_write_bytes, to_srgb8, write_json
from wai_core.outputs import atomic_dir, check_output_dir
from wai_core.sequence import SequenceRecord, read_sequence

__all__ = [
    "SequenceRestore",
    "frame_change",
    "load_sequence",
    "restore_captured_frame",
    "restore_sequence",
    "sequence_frames",
    "write_movie",
]

COLUMNS = (
    "frame", "time_s", "status", "wai_rmse_mm", "wai_rmse_demeaned_mm", "distorted_ssim",
    "restored_ssim", "corner_std_restored_px", "residual_median_px", "anchor_mm",
    "features_used", "tracked", "end_to_end_ms", "change_distorted", "change_restored", "view_ncc",
)
"""Columns of ``frames.csv``: one row per frame (the change columns compare with the previous
frame; ``view_ncc`` is the restored view's agreement with ``view_flat`` or the sequence's median
restored view, see :mod:`restoration.view_check`)."""


@dataclass
class SequenceRestore:
    """A restored sequence.

    Attributes
    ----------
    sequence : SequenceRecord
    rows : list of dict
        One per frame (see :data:`COLUMNS`).
    summary : dict
        Means over ``ok`` frames, status counts, temporal stability, timings.
    out : Path or None
        Where the outputs were written.
    """

    sequence: SequenceRecord
    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    out: Path | None

    def summary_lines(self) -> list[str]:
        """What a person reads first."""
        s = self.summary
        lines = [f"{s['frames']} frames at {s['fps']:g} fps: statuses {s['statuses']}"]
        if s.get("wai_rmse_mm") is not None:
            lines.append(f"surface RMSE {s['wai_rmse_mm']:.3f} mm, restored SSIM "
                         f"{s['restored_ssim']:.4f} (means over ok frames)")
        lines.append(
            f"frame-to-frame change: distorted {s['change_distorted']:.4f}, restored "
            f"{s['change_restored']:.4f} (mean |difference|, 1 = white)"
        )
        lines.append(f"restoration {s['end_to_end_ms']:.1f} ms per frame (median)")
        if s.get("flat_reference"):
            lines.append(flat_reference_line(s["flat_reference"]))
        if s.get("rig"):
            lines.append(rig_line(s["rig"]))
        if s.get("tracking"):
            lines.append(
                f"labels tracked from the previous frames on {s['frames_tracked']} frames, "
                f"matched in full on {s['frames_matched']} ({s['track_fallbacks']} where "
                f"tracking failed its checks, {s['track_skipped']} not tried after failures)"
            )
        return lines


def frame_change(a: NDArray, b: NDArray, mask: NDArray | None = None) -> float:
    """Mean absolute difference of two images (H, W, 3) or grey (H, W) over ``mask`` (H, W)
    (all pixels by default), on the object's radiance scale; NaN when nothing is compared."""
    diff = np.abs(np.asarray(a, float) - np.asarray(b, float))
    diff = diff.mean(axis=-1) if diff.ndim == 3 else diff
    sel = diff if mask is None else diff[mask]
    return float(sel.mean()) if sel.size else float("nan")


def restore_sequence(
    folder: str | Path | SequenceRecord,
    method: str | Method = "structured-light",
    options: SurfaceOptions | None = None,
    *,
    write: bool = True,
    movie: bool = True,
    progress: bool = False,
    rig: Mapping[str, Any] | str | Path | None = None,
    track: bool = False,
) -> SequenceRestore:
    """Restore every frame of a sequence folder (any layout of :mod:`wai_core.sequence`),
    each as :func:`~restoration.frame.restore_frame` with the sequence's one calibration and
    level.

    Parameters
    ----------
    folder : str, Path or SequenceRecord
        The sequence folder, or its description (:func:`~wai_core.sequence.read_sequence`).
    method, options
        As :func:`restoration.restore_folder`.
    write : bool
        Write ``folder/restore/`` (``frames.csv``, ``summary.json``, ``temporal.png``, the
        movies) and each frame's own restore files (surface, restored view, ``metrics.json``;
        no per-frame figures): a render's in each frame folder's ``restore/``, captures' in
        ``folder/restore/<frame>/``; ``restore_METHOD`` in place of ``restore`` for a method
        other than the sequence's own (:func:`~restoration.frame.default_out`).
    movie : bool
        Write ``restored.mp4`` and ``side_by_side.mp4`` (animated GIFs where no MP4 encoder
        is present).
    progress : bool
        A progress bar over the frames.
    rig : mapping of str to value, or str or Path, optional
        Configuration keys that replace the sequence's, or a rig file's path, as
        :func:`restoration.restore_folder`'s (a rig file's calibrated intrinsics).
    track : bool
        Reuse the previous frames (:class:`~restoration.tracking.SequenceState`): labels
        tracked from their spots (full matching where tracking fails its checks), the warp
        solve started at the previous frame's; False (the default) restores every frame on
        its own, the level search's start aside. Tracking takes only where spots move by
        under a tenth of the dot spacing between frames (a fast camera; docs/results.md).

    Returns
    -------
    SequenceRestore
    """
    from tqdm import tqdm

    seq = folder if isinstance(folder, SequenceRecord) else read_sequence(folder)
    meth = as_method(method, options)
    cal = with_rig(_calibration(seq, meth), rig)
    check_rig_geometry(cal, seq.scene_dir / "scene.json")
    name = default_out(seq.record or {}, meth.name)  # another method's results stay
    out = seq.folder / name
    if write:  # every output checked before the first frame is restored
        frame_outs = () if seq.captured else (d / name for d in seq.frame_dirs)
        for target in (out, *frame_outs):
            check_output_dir(target, "restore", remedy=RESTORE_REMEDY)
    track = SequenceState(track=track)
    rows, restored, distorted, masks, results, staged = [], [], [], [], [], []
    # Each frame's restore/ is written to a temporary folder and all are renamed into place
    # together at the end: an interrupted run leaves every old output as it was.
    with contextlib.ExitStack() as stack:
        out_tmp = None  # captures' frames are written inside it, so it is open from the start
        if write and seq.captured:
            out_tmp = stack.enter_context(atomic_dir(out, command="restore",
                                                     remedy=RESTORE_REMEDY))
        bar = tqdm(seq.frame_dirs, desc="restore frames", disable=not progress, leave=False,
                   unit="frame")
        for k, frame_dir in enumerate(bar):
            if seq.captured:
                done = restore_captured_frame(seq, k, cal, meth, track)
            else:
                done = restore_frame(frame_dir, cal, meth, track, flat_from=(seq.folder,),
                                     seed=seq.record.get("seed"))
            result = done.result
            if write:
                if out_tmp is not None:
                    tmp = out_tmp / seq.frames[k]
                    tmp.mkdir()
                else:
                    tmp = stack.enter_context(atomic_dir(
                        frame_dir / name, command="restore", remedy=RESTORE_REMEDY))
                done.write_files(tmp, figures=False)
                staged.append((tmp, done.metrics))
            view = done.distorted
            image = result.view.image if result.has_view else np.zeros_like(view)
            valid = result.view.valid if result.has_view else np.zeros(view.shape[:2], bool)
            rows.append(_row(k, seq.times_s[k], result, done.scores, view, image, valid,
                             distorted[-1:], restored[-1:], masks[-1:]))
            distorted.append(view)
            restored.append(image.astype(np.float32))
            masks.append(valid)
            results.append(result)
            bar.set_postfix_str(f"frame {k}: {result.status}", refresh=False)
        bar.close()
        _flag_moving_views(results, rows, restored, masks, distorted, staged)
        summary = _summary(seq, rows)
        summary.update(tracking=track.track, frames_tracked=track.tracked,
                       frames_matched=track.matched, track_fallbacks=track.fallbacks,
                       track_skipped=track.skipped)
        # The rig's own check, the same for every frame (one reference per calibration).
        reference = next((r.summary().get("flat_reference") for r in results
                          if r.reference_rms_px is not None), None)
        if reference is not None:
            summary["flat_reference"] = reference
        if cal.rig is not None:
            summary["rig"] = cal.rig
        if write:
            tmp = out_tmp if out_tmp is not None else stack.enter_context(
                atomic_dir(out, command="restore", remedy=RESTORE_REMEDY))
            atomic_write_bytes(tmp / "frames.csv", _csv(rows).encode())
            write_json(tmp / "summary.json", summary)
            _temporal_figure(rows, tmp / "temporal.png")
            if movie:
                write_movie(tmp / "restored", restored, seq.fps, masks)
                sides = [side_by_side_frame(d, r, m)
                         for d, r, m in zip(distorted, restored, masks, strict=True)]
                write_movie(tmp / "side_by_side", sides, seq.fps)
    return SequenceRestore(seq, rows, summary, out if write else None)


def _flag_moving_views(
    results: list[Any], rows: list[dict[str, Any]], restored: list[NDArray],
    masks: list[NDArray], distorted: list[NDArray], staged: list[tuple[Path, dict]],
) -> None:
    """A still object's restored views agree from frame to frame: frames without a
    flat-water view's verdict are compared with the sequence's median restored view
    (:func:`~restoration.view_check.match_sequence`), and those that disagree become
    ``view_mismatch`` (their staged ``metrics.json`` rewritten)."""
    for k, match in enumerate(match_sequence(restored, masks, distorted)):
        result = results[k]
        if match is None or result.view_match is not None:
            continue
        result.view_match = match
        rows[k]["view_ncc"] = match.ncc_restored
        if match.consistent:
            continue
        result.flag(Status.VIEW_MISMATCH, match.message)
        rows[k]["status"] = result.status.value
        if staged:
            tmp, metrics = staged[k]
            metrics.update(status=result.status.value, message=result.message,
                           view_match=match.summary())
            write_json(tmp / "metrics.json", metrics)


def _row(
    k: int, time_s: float, result: Any, scores: Any, view: NDArray, image: NDArray,
    valid: NDArray, prev_view: list, prev_image: list, prev_mask: list,
) -> dict[str, Any]:
    """One ``frames.csv`` row."""
    row: dict[str, Any] = {c: None for c in COLUMNS}
    row.update(frame=k, time_s=time_s, status=result.status.value)
    if result.has_view:
        row["end_to_end_ms"] = result.timings_ms.get("end_to_end")
    if result.restored:
        row.update(
            anchor_mm=result.surface.anchor.anchor_mm,
            features_used=len(result.surface.ij),
            tracked=int(result.features.counts.get("tracked", 0)
                        if result.features is not None else 0),
        )
        if result.consistency is not None:
            row["residual_median_px"] = result.consistency.median_px
        if result.view_match is not None:
            row["view_ncc"] = result.view_match.ncc_restored
    if scores is not None and scores.surface is not None:
        row.update(wai_rmse_mm=scores.rmse_mm,
                   wai_rmse_demeaned_mm=scores.surface["rmse_demeaned_mm"])
    if scores is not None and scores.restored is not None:
        row.update(distorted_ssim=scores.distorted["ssim"], restored_ssim=scores.restored["ssim"],
                   corner_std_restored_px=scores.corner_std_restored_px)
    if prev_view:
        both = valid & prev_mask[0]
        row["change_distorted"] = frame_change(view, prev_view[0], both)
        row["change_restored"] = frame_change(image, prev_image[0], both)
    return row


def _mean(rows: list[dict], key: str) -> float | None:
    vals = [float(r[key]) for r in rows if r.get(key) is not None]
    vals = [v for v in vals if np.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def _summary(seq: SequenceRecord, rows: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in rows if r["status"] == Status.OK]
    statuses: dict[str, int] = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    times = [r["end_to_end_ms"] for r in rows if r["end_to_end_ms"] is not None]
    return {
        "frames": len(rows), "fps": seq.fps, "statuses": statuses, "ok": len(ok),
        "wai_rmse_mm": _mean(ok, "wai_rmse_mm"),
        "wai_rmse_demeaned_mm": _mean(ok, "wai_rmse_demeaned_mm"),
        "restored_ssim": _mean(ok, "restored_ssim"),
        "distorted_ssim": _mean(ok, "distorted_ssim"),
        "corner_std_restored_px": _mean(ok, "corner_std_restored_px"),
        # Over every consecutive pair (a failed frame's black image counts: it is what a
        # viewer would see).
        "change_distorted": _mean(rows, "change_distorted") or float("nan"),
        "change_restored": _mean(rows, "change_restored") or float("nan"),
        "end_to_end_ms": float(np.median(times)) if times else float("nan"),
        "seed": seq.record.get("seed"),
    }


def _csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(COLUMNS))
    writer.writeheader()
    for r in rows:
        writer.writerow({k: "" if v is None else v for k, v in r.items()})
    return buf.getvalue()


def _temporal_figure(rows: list[dict[str, Any]], path: Path) -> None:
    """Per frame against time: the scores against the truth where there is one (surface RMSE,
    SSIM), the truth-free checks always (spots used, forward residual), and the
    frame-to-frame change; a panel with nothing to draw is left out."""
    from restoration.figures import plt, save_figure

    t = [r["time_s"] for r in rows]

    def col(key: str) -> list[float]:
        return [np.nan if r.get(key) in (None, "") else float(r[key]) for r in rows]

    def has(*keys: str) -> bool:
        return any(np.isfinite(col(k)).any() for k in keys)

    panels = []
    if has("wai_rmse_mm"):
        panels.append(("surface error (truth)", "surface RMSE (mm)",
                       [("wai_rmse_mm", "o-", None)]))
    if has("distorted_ssim", "restored_ssim"):
        panels.append(("view quality (truth)", "SSIM", [("distorted_ssim", "s--", "distorted"),
                                                        ("restored_ssim", "o-", "restored")]))
    if has("features_used", "residual_median_px"):
        panels.append(("truth-free checks", "spots used", [("features_used", "o-", None)]))
    panels.append(("stability in time (a still object)", "mean |frame - previous|",
                   [("change_distorted", "s--", "distorted"),
                    ("change_restored", "o-", "restored")]))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.7 * len(panels), 3.6), squeeze=False)
    for ax, (title, ylabel, series) in zip(axes[0], panels, strict=True):
        for key, style, label in series:
            ax.plot(t, col(key), style, label=label)
        ax.set(xlabel="t (s)", ylabel=ylabel, title=title)
        if title == "truth-free checks" and has("residual_median_px"):
            twin = ax.twinx()
            twin.plot(t, col("residual_median_px"), "^:", color="tab:red")
            twin.set_ylabel("forward residual, median (px)", color="tab:red")
        if any(label for _, _, label in series):
            ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def side_by_side_frame(distorted: NDArray, restored: NDArray, valid: NDArray) -> NDArray:
    """One frame of ``side_by_side.mp4``: the distorted and the restored view, each under its
    label, the pixels not restored hatched grey, and a legend line saying so.

    Parameters
    ----------
    distorted, restored : (H, W, 3) ndarray
        Linear views on the object's radiance scale (1 = white).
    valid : (H, W) ndarray of bool
        The restored pixels.

    Returns
    -------
    (H', W', 3) ndarray of uint8
        sRGB, taller than the views by a label strip above and a legend strip below.
    """
    import cv2

    from restoration.figures import as_rgb8, mark_not_restored

    left = as_rgb8(to_srgb8(distorted, 1.0))
    right = mark_not_restored(to_srgb8(restored, 1.0), valid)
    h, w = left.shape[:2]
    scale = max(0.4, w / 800)  # text in proportion to the view
    strip = int(round(28 * scale)) & ~1  # even heights keep the MPEG-4 encoder happy
    thick = max(1, int(round(scale)))
    font = cv2.FONT_HERSHEY_SIMPLEX

    def labelled(img: NDArray, text: str) -> NDArray:
        top = np.full((strip, w, 3), 255, np.uint8)
        cv2.putText(top, text, (int(8 * scale), int(strip * 0.72)), font, 0.7 * scale,
                    (0, 0, 0), thick, cv2.LINE_AA)
        return np.concatenate([top, img], axis=0)

    body = np.concatenate([labelled(left, "distorted"), labelled(right, "restored")], axis=1)
    legend = np.full((strip, 2 * w, 3), 255, np.uint8)
    swatch = mark_not_restored(legend[: strip - 8, : strip * 2], np.zeros((strip - 8,
                                                                          strip * 2), bool))
    x0 = int(8 * scale)
    legend[4: strip - 4, x0: x0 + strip * 2] = swatch
    cv2.putText(legend, "hatched grey: not restored; black: no object seen",
                (x0 + strip * 2 + x0, int(strip * 0.72)), font, 0.55 * scale, (0, 0, 0), thick,
                cv2.LINE_AA)
    return np.concatenate([body, legend], axis=0)


def write_movie(
    stem: Path, frames: list[NDArray], fps: float, masks: list[NDArray] | None = None
) -> Path:
    """Write frames (H, W, 3) or grey (H, W) as ``stem.mp4`` (OpenCV's MPEG-4 writer), or
    ``stem.gif`` where no MP4 encoder is present: linear frames are tone-mapped, 8-bit ones
    (already drawn, as by :func:`side_by_side_frame`) written as they are; pixels outside
    ``masks`` are hatched grey (:func:`restoration.figures.mark_not_restored`).

    Returns
    -------
    Path
        The file written.
    """
    import cv2

    from restoration.figures import as_rgb8, mark_not_restored

    frames8 = []
    for k, f in enumerate(frames):
        img = as_rgb8(f if f.dtype == np.uint8 else to_srgb8(f, 1.0))
        if masks is not None:
            img = mark_not_restored(img, masks[k])
        frames8.append(img)
    h, w = frames8[0].shape[:2]
    path = stem.with_suffix(".mp4")
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if writer.isOpened():
        for img in frames8:
            writer.write(np.ascontiguousarray(img[..., ::-1]))
        writer.release()
        if path.is_file() and path.stat().st_size > 0:
            return path
    from PIL import Image

    path = stem.with_suffix(".gif")
    pics = [Image.fromarray(img) for img in frames8]
    pics[0].save(path, save_all=True, append_images=pics[1:], duration=int(1000 / fps), loop=0)
    return path


def load_sequence(
    folder: str | Path, method: str | Method = "structured-light"
) -> tuple[RigCalibration, list[dict[str, NDArray]]]:
    """The calibration and every frame's images of a sequence folder, in order (what a video
    benchmark restores in a loop)."""
    cal, frames = sequence_frames(folder, method)
    return cal, list(frames)


def sequence_frames(
    folder: str | Path, method: str | Method = "structured-light"
) -> tuple[RigCalibration, Iterator[dict[str, NDArray]]]:
    """:func:`load_sequence` one frame at a time: the calibration, and the frames' images in
    order, each read when the iterator reaches it."""
    seq = read_sequence(folder)
    cal = _calibration(seq, as_method(method))
    if not seq.captured:
        return cal, (cal.load_images(d) for d in seq.frame_dirs)
    return cal, (cal.load_files(_frame_files(seq, k, cal)) for k in range(len(seq.frames)))


def restore_captured_frame(
    seq: SequenceRecord, k: int, cal: RigCalibration, method: Method,
    track: LevelTrack | None = None,
) -> FolderRestore:
    """Restore frame ``k`` of a capture sequence from its files where they are: what
    :func:`~restoration.frame.restore_frame` does for a frame folder (load, restore, flag
    differing files of one image and a view that disagrees with ``view_flat``, assemble
    ``metrics.json``), without truth (a capture has none); nothing is written.

    Parameters
    ----------
    seq : SequenceRecord
        A capture sequence (``seq.captured``).
    k : int
        The frame's index, 0-based.
    cal : RigCalibration
        The rig's calibration (of ``method.calibration_type``).
    method : Method
        A configured method object.
    track : LevelTrack, optional
        The sequence's level.

    Returns
    -------
    FolderRestore
        With ``folder`` the frame's folder (the sequence folder for numbered images), ``out``
        None, no truth and no scores.
    """
    files = _frame_files(seq, k, cal)
    images = cal.load_files(files)
    view_flat = load_view_flat(cal, *dict.fromkeys((seq.frame_dirs[k], seq.folder)))
    result = run_method(method, images, cal, track)
    check_files(files, cal, images, result, view_flat)
    metrics = folder_metrics(method, result, None, True, seq.record.get("seed"), rig=cal.rig)
    return FolderRestore(seq.frame_dirs[k], None, cal, images, result, None, None, metrics)


def _frame_files(seq: SequenceRecord, k: int, cal: RigCalibration) -> dict[str, Path]:
    """The file of each of the method's images for frame ``k``."""
    return {name: seq.image_path(k, name) for name in cal.IMAGES}


def _calibration(seq: SequenceRecord, method: Method) -> RigCalibration:
    """The one calibration of a sequence (a capture's ``scene.json``, or a render's first
    frame's: every frame's has the same rig)."""
    return method.calibration_type.from_record(read_scene_record(seq.scene_dir))
