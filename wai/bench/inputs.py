"""``wai bench inputs``: wrong inputs that restore without an error, against the truth-free
status.

Two frames of one sea, 0.5 s apart, are rendered through the paper's rig; folders of "one's
own captures" are made from the first (its images and ``scene.json``, no truth), each with one
mistake a user makes: the two patterns swapped, a ``pattern.png`` of another moment beside the
``pattern.exr``, the view turned by 180° or taken at another moment (with and without the rig's
flat-water view ``view_flat``). Each is restored by :func:`restoration.restore_folder`; the
status, and the figures it was decided on, are reported.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from wai_core.io import read_exr, write_exr, write_json, write_png

__all__ = ["CASES", "bench_inputs", "print_inputs"]

OWN_FILES = ("scene.json", "pattern.exr", "pattern_flat.exr", "view.exr")


def _swap_patterns(d: Path, other: Path) -> None:
    (d / "pattern.exr").rename(d / "wavy.exr")
    (d / "pattern_flat.exr").rename(d / "pattern.exr")
    (d / "wavy.exr").rename(d / "pattern_flat.exr")


def _foreign_png(d: Path, other: Path) -> None:
    write_png(d / "pattern.png", read_exr(other / "pattern.exr"))


def _turned_view(d: Path, other: Path) -> None:
    write_exr(d / "view.exr", read_exr(d / "view.exr")[::-1, ::-1])


def _other_view(d: Path, other: Path) -> None:
    shutil.copy(other / "view.exr", d / "view.exr")


def _nothing(d: Path, other: Path) -> None:
    pass


@dataclass(frozen=True)
class Case:
    """One wrong input: the mistake made to a copy of the first frame's folder, whether the
    folder holds the rig's flat-water view, and a rig applied over the folder's own (a
    calibration that is off: configuration keys, :func:`restoration.with_rig`)."""

    mistake: Callable[[Path, Path], None] = _nothing
    flat_view: bool = False
    rig: dict[str, Any] = field(default_factory=dict)


def _off(device: str, key: str, value: Any) -> Case:
    return Case(rig={f"{device}.{key}": value})


CASES: dict[str, Case] = {
    "right images": Case(),
    "right images, with view_flat": Case(flat_view=True),
    "patterns swapped": Case(_swap_patterns),
    "pattern.png of another moment": Case(_foreign_png),
    "view turned 180 deg": Case(_turned_view),
    "view turned 180 deg, with view_flat": Case(_turned_view, True),
    "view 0.5 s later": Case(_other_view),
    "view 0.5 s later, with view_flat": Case(_other_view, True),
    "camera s focal length +0.1 %": _off("camera_s", "focal_mm", 1.001),
    "camera s focal length -0.1 %": _off("camera_s", "focal_mm", 0.999),
    "camera s focal length +1 %": _off("camera_s", "focal_mm", 1.01),
    "camera s principal point +1 px": _off("camera_s", "principal_offset_px", [1.0, 0.0]),
    "camera s principal point +3 px": _off("camera_s", "principal_offset_px", [3.0, 0.0]),
    "camera v principal point +1 px": _off("camera_v", "principal_offset_px", [1.0, 0.0]),
}
"""Case name -> :class:`Case`. A rig's ``focal_mm`` is a factor on the scene's own."""


def _rig_keys(cfg: Any, rig: dict[str, Any]) -> dict[str, Any]:
    """``rig`` with each ``focal_mm`` factor made the focal length it stands for, mm."""
    out = {}
    for key, value in rig.items():
        device, _, name = key.partition(".")
        out[key] = getattr(cfg, device).focal_mm * value if name == "focal_mm" else value
    return out


def bench_inputs(config: str | Path, out: Path) -> dict[str, Any]:
    """Restore every case of :data:`CASES` and write ``inputs.json`` into ``out``.

    Parameters
    ----------
    config : str or Path
        The scene (packaged name or TOML).
    out : Path
        Folder for ``inputs.json``.

    Returns
    -------
    dict
        ``config`` and ``rows``: per case its status, message, the flat-water reference's RMS
        distance from the calibrated prediction in spot spacings, the view match (NCC of the
        restored and of the distorted view with the reference, when there was one), and what
        the truth of the first frame says of the restoration: surface RMSE (mm) and corner
        STD (px), None where nothing was restored.
    """
    import numpy as np

    import restoration as rs
    from mitsuba_wai import render_folder
    from restoration import Truth
    from wai_core.system import load_rig

    cfg = load_rig(config)
    rows = []
    with tempfile.TemporaryDirectory(prefix="wai-inputs-") as tmp:
        frames = []
        for t in (cfg.waves.time_s, cfg.waves.time_s + 0.5):
            frames.append(Path(tmp) / f"t{t:g}")
            render_folder(cfg.replace("waves", time_s=t), frames[-1], progress=False)
        for name, case in tqdm(CASES.items(), desc="cases", leave=False):
            folder = Path(tmp) / "case"
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            for file in OWN_FILES:
                shutil.copy(frames[0] / file, folder / file)
            if case.flat_view:
                shutil.copy(frames[0] / "view_truth.exr", folder / "view_flat.exr")
            case.mistake(folder, frames[1])
            done = rs.restore_folder(folder, write=False, rig=_rig_keys(cfg, case.rig))
            result = done.result
            ref = done.cal.reference
            match = result.view_match
            scores = None
            if result.has_view:
                truth = Truth.from_folder(frames[0], done.cal)
                scores = rs.score(result, done.distorted, done.cal, truth)
            rows.append({
                "case": name,
                "status": result.status,
                "message": result.message,
                "reference_rms_spacings": float(ref.rms_px / np.nanmedian(ref.spacing_px)),
                "view_ncc_restored": None if match is None else match.ncc_restored,
                "view_ncc_distorted": None if match is None else match.ncc_distorted,
                "rmse_mm": None if scores is None else scores.rmse_mm,
                "corner_std_px": None if scores is None else scores.corner_std_restored_px,
            })
    res = {"config": str(config), "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "inputs.json", res)
    return res


def print_inputs(res: dict[str, Any]) -> None:
    """One line per case: status, reference RMS (spacings), view NCC restored / distorted,
    and the truth's verdict (surface RMSE, corner STD)."""
    def num(v: Any, spec: str) -> str:
        return "-" if v is None else format(v, spec)

    print(f"{'case':38s} {'status':16s} {'ref RMS':>8s} {'RMSE mm':>8s} {'STD px':>7s}  "
          "view NCC restored / distorted")
    for r in res["rows"]:
        ncc = ("-" if r["view_ncc_restored"] is None
               else f"{r['view_ncc_restored']:.3f} / {r['view_ncc_distorted']:.3f}")
        print(f"{r['case']:38s} {r['status']:16s} {r['reference_rms_spacings']:8.3f} "
              f"{num(r.get('rmse_mm'), '8.3f'):>8s} {num(r.get('corner_std_px'), '7.3f'):>7s}  "
              f"{ncc}")
