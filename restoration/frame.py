"""One frame restored from its folder's images with a calibration already read: the images
loaded, the method run (:func:`~restoration.protocol.run_method`), the result flagged by what
the folder shows beyond them, scored against the folder's truth where it has some, and the
restore folder's files and the summary a person reads first. :func:`restoration.restore_folder`
restores one folder, :func:`restoration.restore_sequence` every frame of a sequence, each
through :func:`restore_frame`."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from restoration.calibration import LevelTrack, RigCalibration
from restoration.protocol import Method, run_method
from restoration.result import RestoreResult, Status
from restoration.scoring import Scores, Truth, score, surface_profile
from restoration.view_check import match_flat_view
from wai_core.config import with_keys
from wai_core.errors import WaiInputError
from wai_core.images import image_conflict, locate_image, read_image
from wai_core.io import write_exr, write_json, write_png

RESTORE_REMEDY = "move what is not the tool's elsewhere: a restore replaces only its own outputs"
"""What a refused restore folder's message tells the user (``wai restore`` has no --overwrite:
it never replaces a folder it did not write)."""

CalibrationT = TypeVar("CalibrationT", bound=RigCalibration)


@dataclass
class FolderRestore:
    """One folder restored: the result, its scores (None without truth) and what was written.

    Attributes
    ----------
    folder : Path
        The folder read.
    out : Path or None
        Where the outputs were written (None when ``write=False``, and from
        :func:`restore_frame`).
    cal : RigCalibration
        The calibration read (with its per-rig caches, e.g. the flat-water reference).
    images : dict of str to ndarray
        The images read, as stored (the view not yet divided by the gain).
    result : RestoreResult
    truth : Truth or None
        The folder's truth, when it has some and scoring was asked.
    scores : Scores or None
    metrics : dict
        What ``metrics.json`` holds: the result's summary, the scores, options and seed.
    """

    folder: Path
    out: Path | None
    cal: RigCalibration
    images: dict[str, Any]
    result: RestoreResult
    truth: Truth | None
    scores: Scores | None
    metrics: dict[str, Any]

    @property
    def distorted(self) -> NDArray:
        """(H, W, 3) ndarray: the frame's view on the object's radiance scale (what the scores
        compare the restored view with)."""
        return self.cal.radiance(self.images["view"])

    def summary_lines(self) -> list[str]:
        """The figures a person reads first, one line each."""
        return summary_lines(self.metrics)

    def write_files(self, tmp: Path, *, figures: bool = True) -> None:
        """This frame's restore files into an open temporary folder ``tmp`` (see
        :func:`write_restore_files`)."""
        write_restore_files(tmp, self.cal, self.images, self.result, self.scores, self.truth,
                            self.metrics, figures=figures)


def check_rig_geometry(cal: RigCalibration, source: Path) -> None:
    """Refuse, before any work, a structured-light rig (a :class:`Calibration`'s) whose
    geometry cannot work through flat water (:func:`wai_core.rig_checks.check_rig`), naming
    ``source``, the ``scene.json`` it came from."""
    from restoration.calibration import Calibration
    from wai_core.rig_checks import check_rig

    if isinstance(cal, Calibration):
        check_rig(cal.cfg, str(source))


def with_rig(cal: CalibrationT, rig: Mapping[str, Any] | str | Path | None) -> CalibrationT:
    """``cal`` with a rig applied: the configuration keys of ``rig`` (a mapping, or a rig
    file's path, read by :func:`~restoration.rig_calibration.read_rig`), checked, and
    recorded in :attr:`~restoration.calibration.RigCalibration.rig`; ``cal`` itself when there
    are none."""
    if rig is None or (isinstance(rig, Mapping) and not rig):
        return cal
    source = None
    if not isinstance(rig, Mapping):
        from restoration.rig_calibration import read_rig

        source, rig = str(Path(rig).resolve()), read_rig(rig)
    keys = dict(rig)
    return replace(cal, cfg=with_keys(cal.cfg, keys),
                   rig={"file": source, "config_keys": keys})


def default_out(record: Mapping[str, Any], method: str) -> str:
    """The name of a render folder's restore output for ``method``: ``restore`` for the method
    its images were made for (a sun-sensor render's ``alterman``, else ``structured-light``),
    ``restore_METHOD`` for any other (Schlieren on the same render, a method of one's own).

    Examples
    --------
    >>> default_out({"config": {}}, "structured-light"), default_out({"config": {}}, "schlieren")
    ('restore', 'restore_schlieren')
    """
    own = "alterman" if "alterman" in record else "structured-light"
    return "restore" if method == own else f"restore_{method}"


def restore_frame(
    folder: str | Path,
    cal: RigCalibration,
    method: Method,
    track: LevelTrack | None = None,
    *,
    flat_from: Sequence[str | Path] = (),
    scored: bool = True,
    seed: Any = None,
    step: Callable[[str], None] | None = None,
) -> FolderRestore:
    """Restore one frame's folder with a calibration already read, and score it; nothing is
    written (:meth:`FolderRestore.write_files` does).

    What :func:`~restoration.folder.restore_folder` and a sequence's restore do for each
    frame: load the images, run ``method``, flag the result by the folder's other files
    (:func:`check_inputs`), score it against the folder's truth, and assemble
    ``metrics.json``.

    Parameters
    ----------
    folder : str or Path
        Holds the method's images (see :func:`~restoration.folder.restore_folder`); for
        scores, the truth.
    cal : RigCalibration
        The rig's calibration (of ``method.calibration_type``); one serves every frame of a
        rig, keeping its per-rig caches.
    method : Method
        A configured method object (:func:`~restoration.methods.as_method`).
    track : LevelTrack, optional
        A sequence's level (see :class:`~restoration.calibration.LevelTrack`).
    flat_from : sequence of str or Path
        Folders searched after ``folder`` for the rig's flat-water view ``view_flat.*``
        (a sequence's own folder).
    scored : bool
        Score against the folder's truth when it has some (default True).
    seed : optional
        The render's seed, recorded in ``metrics.json``.
    step : callable, optional
        Called with the name of the next step once restoring is done (a progress bar's).

    Returns
    -------
    FolderRestore
        With ``out`` None.
    """
    folder = Path(folder)
    images = cal.load_images(folder)
    view_flat = load_view_flat(cal, folder, *flat_from)
    t0 = time.perf_counter()
    result = run_method(method, images, cal, track)
    # A method of one's own may time nothing: the call's wall time is its end to end.
    result.timings_ms.setdefault("end_to_end", 1e3 * (time.perf_counter() - t0))
    check_inputs(folder, cal, images, result, view_flat)
    if step is not None:
        step("score" if scored else "score (skipped)")
    truth = Truth.from_folder(folder, cal) if scored and result.has_view else None
    scores = None if truth is None else score(result, cal.radiance(images["view"]), cal, truth)
    metrics = folder_metrics(method, result, scores, scored, seed, rig=cal.rig)
    return FolderRestore(folder, None, cal, images, result, truth, scores, metrics)


def load_view_flat(cal: RigCalibration, *folders: str | Path) -> Any:
    """The rig's flat-water view (``view_flat.*``, optional) from the first of ``folders``
    holding one, or None; its size is checked like the view's."""
    for folder in folders:
        path = locate_image(folder, "view_flat")
        if path is None:
            continue
        img = read_image(path)
        h, w = cal.image_size("view")
        if img.shape[:2] != (h, w):
            raise WaiInputError(
                f"{path} is {img.shape[1]}x{img.shape[0]} but the calibration says {w}x{h}"
            )
        return cal.to_pinhole("view_flat", img)
    return None


def check_inputs(
    folder: str | Path, cal: RigCalibration, images: dict[str, Any], result: RestoreResult,
    view_flat: Any = None,
) -> None:
    """Flag ``result`` by what the folder shows beyond the frame's own images: two differing
    files of one image (``ambiguous_input``), and a restored view that disagrees with the
    rig's flat-water view (``view_mismatch``, see :mod:`restoration.view_check`)."""
    check_files(cal.image_files(folder), cal, images, result, view_flat)


def check_files(
    files: Mapping[str, Path], cal: RigCalibration, images: dict[str, Any],
    result: RestoreResult, view_flat: Any = None,
) -> None:
    """:func:`check_inputs` for the frame's images read from ``files`` (name: path): another
    file of one image beside it (same stem) that differs, and the flat-water view."""
    for name, path in files.items():
        image = images[name]
        if cal.resamples(name):  # compare the file as it was read
            image = read_image(path)
        conflict = image_conflict(path.parent, path.stem, image)
        if conflict is not None:
            result.warnings.append(conflict)
            result.flag(Status.AMBIGUOUS_INPUT, conflict)
    if view_flat is not None and result.has_view:
        match = match_flat_view(result.view.image, result.view.valid,
                                cal.radiance(images["view"]), view_flat)
        result.view_match = match
        if not match.consistent:
            result.flag(Status.VIEW_MISMATCH, match.message)


def folder_metrics(
    method: Method, result: RestoreResult, scores: Scores | None, scored: bool, seed: Any,
    rig: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """``metrics.json``: the truth-free summary, the scores (or why there are none), the
    options (``spot_bias`` left to the scene: whether the spots were corrected), the render's
    ``seed`` (from its ``scene.json``) and the ``rig`` applied, if any
    (:func:`with_rig`)."""
    metrics = result.summary()
    if scores is not None:
        metrics.update(scores.to_dict())
    metrics["scored"] = scores is not None
    if scores is None:
        metrics["scores_skipped"] = (
            "not asked" if not scored
            else "no restoration" if not result.has_view
            else "no truth in the folder (heightfield.npz, view_truth.*)"
        )
    metrics["options"] = method.options.to_dict()
    if metrics["options"].get("spot_bias", False) is None:  # by the scene: say whether it ran
        metrics["options"]["spot_bias"] = result.spot_bias_gain is not None
    metrics["seed"] = seed
    if rig is not None:
        metrics["rig"] = rig
    return metrics


def write_restore_files(
    tmp: Path,
    cal: RigCalibration,
    images: dict[str, Any],
    result: RestoreResult,
    scores: Scores | None,
    truth: Truth | None,
    metrics: dict[str, Any],
    *,
    figures: bool = True,
) -> None:
    """The restore folder's files, into an open temporary folder ``tmp`` (renamed into place
    by the caller's :func:`~wai_core.outputs.atomic_dir`): surface, restored view, figures (unless
    ``figures=False``) and ``metrics.json``; only ``metrics.json`` when there is no
    restoration."""
    _write_arrays(tmp, result)
    if figures:
        _write_figures(tmp, cal, images, result, scores, truth)
    write_json(tmp / "metrics.json", metrics)


def _write_arrays(tmp: Path, result: RestoreResult) -> None:
    """The surface (when the method gives one), the restored view, its mask and the
    confidence arrays."""
    if not result.has_view:
        return
    if result.surface is not None:
        est = result.surface.heightfield
        est.save(tmp / "heightfield_est.npz")
        est.to_trimesh().export(tmp / "surface_est.ply")
    write_exr(tmp / "restored.exr", result.view.image)
    write_png(tmp / "restored.png", result.view.image, exposure=1.0)
    write_png(tmp / "restored_mask.png", (result.view.valid * np.uint8(255)).astype(np.uint8))
    if result.consistency is not None:
        check = result.consistency
        np.savez_compressed(
            tmp / "confidence.npz", x=est.x, y=est.y,
            residual_px=check.residual_map_px, confidence=check.confidence,
        )


def _write_figures(
    tmp: Path, cal: RigCalibration, images: dict[str, Any], result: RestoreResult,
    scores: Scores | None, truth: Truth | None,
) -> None:
    """The views with the mask, the confidence map and, with truth, error map, profile and
    corners."""
    from restoration import figures

    if not result.has_view:
        return
    figures.views_figure(_view_panels(cal, images, result, scores, truth), result.view.valid,
                         tmp / "distorted_vs_restored.png",
                         None if scores is None else scores.view_restored_fraction)
    if result.surface is None:
        return _write_corners(tmp, scores)
    est = result.surface.heightfield
    if result.consistency is not None:
        check = result.consistency
        figures.confidence_figure(est, check.residual_map_px, check.threshold_px,
                                  tmp / "confidence.png")
    reference = getattr(cal, "reference", None)
    if reference is not None and getattr(reference, "pred_px", None) is not None:
        cam_s = cal.cfg.camera_s
        figures.flat_reference_figure(reference, (cam_s.height_px, cam_s.width_px),
                                      tmp / "flat_reference.png")
    if scores is not None and scores.error_map_mm is not None:
        figures.error_map_figure(est, scores.error_map_mm, tmp / "error_map.png")
        y0 = float(np.nanmedian(result.surface.points_mm[:, 1]))
        figures.profile_figure(*surface_profile(est, truth.surface, y0), y0, tmp / "profile.png")
    _write_corners(tmp, scores)


def _write_corners(tmp: Path, scores: Scores | None) -> None:
    from restoration import figures

    if scores is not None and scores.corner_points_px:
        figures.corner_scatter_figure(
            scores.corner_points_px,
            {"distorted": scores.corner_std_distorted_px,
             "restored": scores.corner_std_restored_px},
            tmp / "corners.png",
        )


def _view_panels(
    cal: RigCalibration, images: dict[str, Any], result: RestoreResult, scores: Scores | None,
    truth: Truth | None,
) -> list[tuple[str, Any]]:
    """(title, image) of the truth (if any), distorted and restored views, scores in titles."""
    def scored(name: str) -> str:
        part = None if scores is None else getattr(scores, name)
        if part is None:
            return name
        return f"{name}: SSIM {_num(part['ssim'], '.3f')}, PSNR {_num(part['psnr_db'], '.1f')} dB"

    return [
        ("truth (flat water)", None if truth is None else truth.view),
        (scored("distorted"), cal.radiance(images["view"])),
        (scored("restored"), result.view.image),
    ]


def _num(value: Any, spec: str, unit: str = "") -> str:
    """``value`` formatted, or ``n/a`` when it is missing or not finite (never ``nan``)."""
    if value is None or not np.isfinite(value):
        return "n/a"
    return f"{value:{spec}}{unit}"


STATUS_DOCS = '`wai guide outputs`, "Frame status"'
"""Where a frame's statuses are explained."""


def status_line(status: str, message: str) -> str:
    """The frame's truth-free status, in words."""
    if status == Status.OK:
        return f"status ok: every truth-free check passed ({STATUS_DOCS})"
    return f"status {status}: {message} ({STATUS_DOCS})"


def summary_lines(m: dict[str, Any]) -> list[str]:
    """The figures of a ``metrics.json`` a person reads first, one line each: the status
    first, the end-to-end time last, each term said in words where it appears."""
    status = m.get("status", Status.OK)
    if "features_used" not in m and "view_valid_fraction" not in m:
        return [f"{m['method']}: cannot run ({status}): {m['message']}"]
    lines = [status_line(status, m.get("message", ""))]
    if "wai_rmse_mm" in m:
        lines.append(
            f"surface RMSE {_num(m['wai_rmse_mm'], '.3f', ' mm')} against the true surface "
            f"(de-meaned {_num(m['wai_rmse_demeaned_mm'], '.3f', ' mm')}, max "
            f"{_num(m['wai_max_abs_mm'], '.3f', ' mm')}) from {m['features_used']} features "
            f"({m['features_rejected']} rejected)"
        )
    elif "features_used" in m:
        lines.append(
            f"surface from {m['features_used']} features ({m['features_rejected']} rejected); "
            f"scores skipped: {m.get('scores_skipped', 'no truth')}"
        )
    else:
        skipped = "" if m.get("scored") else f"; scores skipped: {m.get('scores_skipped')}"
        lines.append(f"{m['method']}: a restored view without a surface{skipped}")
    if "corner_std_restored_px" in m:
        lines.append(
            f"corner STD {_num(m['corner_std_distorted_px'], '.2f', ' px')} -> "
            f"{_num(m['corner_std_restored_px'], '.2f', ' px')} on {m['corners_common']} corners "
            "(the spread of the checkerboard's corners about their flat-water positions, a "
            "common shift not counted; 0 is perfect)"
        )
    if "restored" in m:
        d, r = m["distorted"], m["restored"]
        lines.append(
            f"SSIM {_num(d['ssim'], '.4f')} -> {_num(r['ssim'], '.4f')}, "
            f"PSNR {_num(d['psnr_db'], '.2f')} -> {_num(r['psnr_db'], '.2f')} dB, "
            f"MSE {_num(d['mse'], '.4f')} -> {_num(r['mse'], '.4f')} on the restored "
            f"{m['view_restored_fraction']:.0%} of the object's pixels (those the flat-water "
            "view sees)"
        )
    if "anchor" in m:
        lines.append(anchor_line(m["anchor"]))
    if "flat_reference" in m:
        lines.append(flat_reference_line(m["flat_reference"]))
    if m.get("rig"):
        lines.append(rig_line(m["rig"]))
    lines.append(f"restoration {m['timings_ms']['end_to_end']:.1f} ms end to end (this frame's "
                 "features, surface and view; reading and writing files not counted)")
    return lines


def flat_reference_line(ref: dict[str, Any]) -> str:
    """The flat-water reference's residual (the calibration's check, docs/rig.md), in words."""
    return (f"flat-water reference {ref['rms_px']:.2f} px RMS from the calibration "
            f"({ref['rms_of_spacing']:.1%} of the dot spacing: the flat-water spots against "
            "where the rig predicts them; `wai guide rig`)")


def rig_line(rig: dict[str, Any]) -> str:
    """Which rig was applied over the folder's configuration."""
    keys = ", ".join(sorted(rig["config_keys"]))
    source = f"rig file {rig['file']}" if rig.get("file") else "a rig"
    return f"{source} applied: {keys}"


def anchor_line(anchor: dict[str, Any]) -> str:
    """How the absolute water level was set, in words."""
    level = f"mean level {_num(anchor.get('anchor_mm'), '.2f', ' mm')}"
    sigma = anchor.get("sigma_mm")
    if anchor.get("method") == "integrability":
        return (f"{level} from integrability (+- {_num(sigma, '.2f', ' mm')}: the level at "
                "which the measured slopes fit one surface best)")
    if anchor.get("method") == "gauge_fallback":
        why = "not pinned" if sigma is None or not np.isfinite(sigma) else f"+- {sigma:.2f} mm"
        return f"{level} from the gauge (integrability {why}: too little curvature)"
    if anchor.get("method") == "view":
        return (f"{level} from camera v's view (+- {_num(sigma, '.3f', ' mm')}: the level at "
                "which the surface sends the view's lines of sight where the flow puts them)")
    if anchor.get("method") == "structured_light":
        return (f"{level} from the structured light's surface (the two differ by "
                f"{_num(anchor.get('source_difference_mm'), '.3f', ' mm')} RMS where both "
                "reach, once levelled)")
    if anchor.get("method") == "pattern":
        return (f"{level} from camera s's spots (another level fits "
                f"{_num(anchor.get('pattern_alias_ratio'), '.2f', '')} as well; the matched "
                f"spots miss by {_num(anchor.get('pattern_residual_px'), '.2f', ' px')})")
    return f"{level} from the gauge"
