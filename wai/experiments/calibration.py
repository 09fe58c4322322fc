"""``wai experiment calibration``: what calibrating a real rig's cameras buys.

For each seed the paper's scene is rendered twice: with ideal lenses, and with real ones
(:data:`LENS`: barrel distortion and a principal point off the centre, on camera s and camera
v). The real-lens frame is restored three ways: with the ideal rig (the pinholes the scene
names), with the true rig (the keys it was rendered with), with the rig that ``wai calibrate``
finds from rendered checkerboards (:mod:`restoration.rig_calibration`), and with that rig's
camera s refined on the flat-water pattern (``wai calibrate --flat``); the ideal-lens frame
restored with the ideal rig is the accuracy to get back. Each restoration runs twice: with
the spots referred to the flat reference (the default,
:attr:`restoration.StructuredLightOptions.flat_referenced`) and as detected. Writes
``calibration.csv`` (one row per frame and rig), ``calibration.json`` (the run record with the
calibrated intrinsics against the truth), ``calibration.png`` and ``calibration.md``.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from wai.experiments.outputs import output_folder, publish
from wai_core.config import SystemConfig, with_keys
from wai_core.io import atomic_write_bytes, write_json
from wai_core.system import load_system

DEVICES = ("camera_v", "camera_s")
"""The cameras given real lenses (the projector stays ideal)."""
DISTORTION = (-0.2, 0.05, 0.0, 0.0, 0.0)
PRINCIPAL_OFFSET_PX = (15.0, -10.0)
LENS: dict[str, Any] = {
    **{f"{d}.distortion": list(DISTORTION) for d in DEVICES},
    **{f"{d}.principal_offset_px": list(PRINCIPAL_OFFSET_PX) for d in DEVICES},
}
"""The real lenses: OpenCV's (k1, k2, p1, p2, k3) and the principal point minus the centre."""
IDEAL: dict[str, Any] = {
    **{f"{d}.distortion": [0.0] * 5 for d in DEVICES},
    **{f"{d}.principal_offset_px": [0.0, 0.0] for d in DEVICES},
}
"""The ideal rig's keys: what restoring as if the lenses were pinholes assumes."""
CHECKERBOARD_VIEWS = 15
SPOTS = {"flat-referenced": True, "as detected": False}
"""The two ways of taking the spots, and their ``flat_referenced`` option."""
COLUMNS = ("seed", "lens", "rig", "spots", "status", "wai_rmse_mm", "wai_rmse_demeaned_mm",
           "corner_std_restored_px", "restored_psnr_db", "features_used")


def calibrated_rig(real: SystemConfig, out: Path, views: int) -> tuple[dict[str, Any], dict]:
    """The rig keys ``wai calibrate`` finds for the real lenses from ``views`` rendered
    checkerboards per camera, and the fits' summary (each value beside its truth)."""
    from mitsuba_wai import Board, render_checkerboards
    from restoration import calibrate_device

    keys: dict[str, Any] = {}
    fits: dict[str, Any] = {}
    board = Board()
    for k, device in enumerate(DEVICES):
        dev = getattr(real, device)
        images = render_checkerboards(real, device, views, seed=100 + k, board=board)
        fit = calibrate_device(images, board, (dev.height_px, dev.width_px))
        keys.update(fit.to_config_keys(device, dev))
        cx0, cy0 = (dev.width_px - 1) / 2.0, (dev.height_px - 1) / 2.0
        fits[device] = {
            "fx_px": fit.fx_px, "fx_true_px": dev.focal_mm * dev.width_px / dev.sensor_width_mm,
            "cx_px": fit.cx_px, "cx_true_px": cx0 + dev.principal_offset_px[0],
            "cy_px": fit.cy_px, "cy_true_px": cy0 + dev.principal_offset_px[1],
            "k1": float(fit.distortion[0]), "k1_true": dev.distortion[0],
            "k2": float(fit.distortion[1]), "k2_true": dev.distortion[1],
            "rms_px": fit.rms_px, "views_used": fit.n_used, "views_rejected": fit.n_rejected,
        }
    return keys, fits


def refined_on_flat_water(cfg: SystemConfig, boards: dict[str, Any], frame: Path) -> Any:
    """Camera s refined on the rig's flat-water pattern
    (:func:`restoration.rig_calibration.refine_on_flat_water`), starting from the
    checkerboards' intrinsics."""
    from restoration import refine_on_flat_water
    from wai_core.images import find_image, read_image

    return refine_on_flat_water(with_keys(cfg, boards), read_image(find_image(frame,
                                                                              "pattern_flat")))


def _row(seed: int, lens: str, rig: str, spots: str, metrics: dict[str, Any]
         ) -> dict[str, Any]:
    row = {"seed": seed, "lens": lens, "rig": rig, "spots": spots}
    for key in COLUMNS[4:]:
        row[key] = metrics.get(key)
    return row


def render_seed(cfg: SystemConfig, seed: int, out: Path) -> dict[str, Path]:
    """The seed's ideal-lens and real-lens frames, rendered into ``out`` (a rerun reuses
    them)."""
    from mitsuba_wai import render_folder

    cfg = cfg.replace("waves", seed=seed)
    folders = {"ideal": out / f"seed{seed:03d}" / "ideal_lens",
               "real": out / f"seed{seed:03d}" / "real_lens"}
    for lens, folder in folders.items():
        if not (folder / "scene.json").is_file():
            render_folder(cfg if lens == "ideal" else with_keys(cfg, LENS), folder,
                          progress=False)
    return folders


def run_seed(cfg: SystemConfig, seed: int, out: Path, calibrated: dict[str, dict[str, Any]]
             ) -> list[dict[str, Any]]:
    """Restore the seed's frames (:func:`render_seed`) with each rig: ideal, true, the
    checkerboards' and the checkerboards' refined on flat water; each with the spots
    flat-referenced and as detected."""
    from restoration import StructuredLightOptions, restore_folder

    folders = render_seed(cfg, seed, out)
    runs = (("ideal", "ideal", None), ("real", "ideal", IDEAL), ("real", "true", None),
            ("real", "checkerboards", calibrated["checkerboards"]),
            ("real", "calibrated", calibrated["flat_water"]))
    return [_row(seed, lens, rig, spots, restore_folder(
                folders[lens], options=StructuredLightOptions(flat_referenced=referenced),
                write=False, rig=keys).metrics)
            for lens, rig, keys in runs for spots, referenced in SPOTS.items()]


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per (lens, rig, spots): mean and spread of the RMSE and corner STD, and the
    statuses."""
    out: dict[str, Any] = {}
    for lens, rig, spots in sorted({(r["lens"], r["rig"], r["spots"]) for r in rows}):
        part = [r for r in rows if (r["lens"], r["rig"], r["spots"]) == (lens, rig, spots)]
        ok = [r for r in part if r["status"] == "ok"]

        def stat(key: str, part: list[dict[str, Any]] = ok) -> dict[str, float | None]:
            v = np.array([r[key] for r in part if r[key] is not None], float)
            if not v.size:
                return {"mean": None, "max": None}
            return {"mean": float(v.mean()), "max": float(v.max())}

        out[f"{lens}_lens/{rig}_rig/{spots}"] = {
            "lens": lens, "rig": rig, "spots": spots, "frames": len(part), "ok": len(ok),
            "statuses": sorted({str(r["status"]) for r in part}),
            "wai_rmse_mm": stat("wai_rmse_mm"),
            "corner_std_restored_px": stat("corner_std_restored_px"),
        }
    return out


def _csv(rows: list[dict[str, Any]]) -> bytes:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue().encode()


def _figure(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    cases = [("ideal", "ideal", "ideal lens, ideal rig"), ("real", "true", "real lens, true rig"),
             ("real", "checkerboards", "real lens, checkerboards' rig"),
             ("real", "calibrated", "real lens, checkerboards + flat water")]
    for ax, spots in zip(axes, SPOTS, strict=True):
        for k, (lens, rig, label) in enumerate(cases):
            part = [r for r in rows if (r["lens"], r["rig"], r["spots"]) == (lens, rig, spots)]
            seeds = np.array([r["seed"] for r in part], float) + (k - 1.5) * 0.15
            rmse = [r["wai_rmse_mm"] if r["status"] == "ok" else np.nan for r in part]
            ax.plot(seeds, rmse, "o", label=label)
        flagged = [r for r in rows if (r["lens"], r["rig"], r["spots"]) == ("real", "ideal",
                                                                             spots)]
        ax.set_xlabel("seed")
        ax.set_yscale("log")
        ax.set_title(f"spots {spots}; real lenses with the ideal rig:\n"
                     f"{sum(r['status'] != 'ok' for r in flagged)} of {len(flagged)} flagged",
                     fontsize=9)
    axes[0].set_ylabel("surface RMSE, mm (status ok)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(rows: list[dict[str, Any]], fits: dict[str, Any]) -> str:
    """The run as Markdown: the calibration against the truth, then the restorations."""
    lines = ["# What calibrating the cameras buys", "",
             "| camera | fx (true) px | cx (true) | cy (true) | k1 (true) | k2 (true) | RMS px |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for device, f in fits.items():
        lines.append(
            f"| {device} | {f['fx_px']:.2f} ({f['fx_true_px']:.2f}) | {f['cx_px']:.2f} "
            f"({f['cx_true_px']:.2f}) | {f['cy_px']:.2f} ({f['cy_true_px']:.2f}) | "
            f"{f['k1']:.4f} ({f['k1_true']:.2f}) | {f['k2']:.4f} ({f['k2_true']:.2f}) | "
            f"{f['rms_px']:.3f} |")
    lines += ["", "| lens | rig | spots | ok / frames | RMSE mm (mean, max) | "
              "corner STD px (mean) |", "| --- | --- | --- | --- | --- | --- |"]
    for s in summarize(rows).values():
        lens, rig, spots = s["lens"], s["rig"], s["spots"]
        r, c = s["wai_rmse_mm"], s["corner_std_restored_px"]
        rmse = "-" if r["mean"] is None else f"{r['mean']:.4f}, {r['max']:.4f}"
        corner = "-" if c["mean"] is None else f"{c['mean']:.3f}"
        lines.append(f"| {lens} | {rig} | {spots} | {s['ok']} / {s['frames']} | {rmse} | "
                     f"{corner} |")
    return "\n".join(lines) + "\n"


def _versions() -> dict[str, str]:
    import platform

    import cv2
    import mitsuba

    return {"mitsuba": mitsuba.__version__, "numpy": np.__version__, "opencv": cv2.__version__,
            "python": platform.python_version()}


def run_calibration(config: str | Path, out: Path, seeds: int | None, quick: bool) -> None:
    """The experiment: seeds 0..seeds-1 (10 when None), written into ``out``; ``quick``: 8
    checkerboard views per camera."""
    cfg = load_system(config)
    out = output_folder(out)
    views = 8 if quick else CHECKERBOARD_VIEWS
    boards, fits = calibrated_rig(with_keys(cfg, LENS), out, views)
    flat = refined_on_flat_water(cfg, boards, render_seed(cfg, 0, out)["real"])
    fits["camera_s"]["flat_water"] = {"config_keys": flat.config_keys,
                                      "rms_before_px": flat.rms_before_px,
                                      "rms_after_px": flat.rms_after_px}
    calibrated = {"checkerboards": boards, "flat_water": {**boards, **flat.config_keys}}
    n = int(seeds or 10)
    rows: list[dict[str, Any]] = []
    for seed in tqdm(range(n), desc="calibration", unit="seed"):
        rows += run_seed(cfg, seed, out, calibrated)
    atomic_write_bytes(out / "calibration.csv", _csv(rows))
    write_json(out / "calibration.json", {
        "versions": _versions(), "config": str(config), "seeds": list(range(n)), "lens": LENS,
        "calibrated_rig": calibrated, "fits": fits, "summary": summarize(rows),
    })
    _figure(rows, out / "calibration.png")
    publish(out / "calibration.md", report(rows, fits))
