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


CASES: dict[str, tuple[Callable[[Path, Path], None], bool]] = {
    "right images": (_nothing, False),
    "right images, with view_flat": (_nothing, True),
    "patterns swapped": (_swap_patterns, False),
    "pattern.png of another moment": (_foreign_png, False),
    "view turned 180 deg": (_turned_view, False),
    "view turned 180 deg, with view_flat": (_turned_view, True),
    "view 0.5 s later": (_other_view, False),
    "view 0.5 s later, with view_flat": (_other_view, True),
}
"""Case name -> (the mistake, applied to a copy of the first frame; whether the folder holds
the rig's flat-water view)."""


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
        distance from the calibrated prediction in spot spacings, and the view match (NCC of
        the restored and of the distorted view with the reference, when there was one).
    """
    import numpy as np

    import restoration as rs
    from mitsuba_wai.render import render_folder
    from wai_core.system import load_rig

    cfg = load_rig(config)
    rows = []
    with tempfile.TemporaryDirectory(prefix="wai-inputs-") as tmp:
        frames = []
        for t in (cfg.waves.time_s, cfg.waves.time_s + 0.5):
            frames.append(Path(tmp) / f"t{t:g}")
            render_folder(cfg.replace("waves", time_s=t), frames[-1], progress=False)
        for name, (mistake, flat_view) in tqdm(CASES.items(), desc="cases", leave=False):
            case = Path(tmp) / "case"
            shutil.rmtree(case, ignore_errors=True)
            case.mkdir()
            for file in OWN_FILES:
                shutil.copy(frames[0] / file, case / file)
            if flat_view:
                shutil.copy(frames[0] / "view_truth.exr", case / "view_flat.exr")
            mistake(case, frames[1])
            done = rs.restore_folder(case, write=False)
            result = done.result
            ref = done.cal.reference
            match = result.view_match
            rows.append({
                "case": name,
                "status": result.status,
                "message": result.message,
                "reference_rms_spacings": float(ref.rms_px / np.nanmedian(ref.spacing_px)),
                "view_ncc_restored": None if match is None else match.ncc_restored,
                "view_ncc_distorted": None if match is None else match.ncc_distorted,
            })
    res = {"config": str(config), "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "inputs.json", res)
    return res


def print_inputs(res: dict[str, Any]) -> None:
    """One line per case: status, reference RMS (spacings), view NCC restored / distorted."""
    print(f"{'case':38s} {'status':16s} {'ref RMS':>8s}  view NCC restored / distorted")
    for r in res["rows"]:
        ncc = ("-" if r["view_ncc_restored"] is None
               else f"{r['view_ncc_restored']:.3f} / {r['view_ncc_distorted']:.3f}")
        print(f"{r['case']:38s} {r['status']:16s} {r['reference_rms_spacings']:8.3f}  {ncc}")
