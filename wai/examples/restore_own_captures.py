"""Restore a folder of one's own images, with no ground truth.

    python -m wai.examples restore_own_captures --folder MY_CAPTURE
    python -m wai.examples restore_own_captures --quick [--out DIR]   # a stand-in capture

A capture folder holds ``scene.json`` (at least its ``config`` table: the rig's geometry, as in
``wai_core/scenes/paper.toml``) and three images as EXR, PNG or TIFF (8 or 16 bit):
``pattern`` (camera s, wavy water), ``pattern_flat`` (camera s, calm water: the calibration) and
``view`` (camera v). The restoration writes ``FOLDER/restore/`` (surface, restored view,
``metrics.json``) and says that scores were skipped. Without ``--folder`` a stand-in capture
is rendered into ``--out``, by default a fresh temporary folder whose path is printed.
"""

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

import restoration as rs
from wai.examples import output_folder
from wai_core import load_system


def make_capture(folder: Path, spp: int) -> None:
    """A stand-in for a real capture: a render written as 16-bit PNGs with only the config."""
    import mitsuba_wai as mw

    cfg = load_system("paper")
    frame = mw.render_frame(cfg, spp=spp)
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("pattern", "pattern_flat", "view"):
        img = frame.images[name]
        if name == "view":  # a camera's exposure: the brightest object pixel near full scale
            img = img / frame.view_gain
        counts = np.clip(img / max(float(img.max()), 1e-9), 0, 1) * 65535
        cv2.imwrite(str(folder / f"{name}.png"), counts.astype(np.uint16)[..., ::-1])
    (folder / "scene.json").write_text(json.dumps({"config": cfg.to_dict()}, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path, help="a capture folder (default: make one)")
    parser.add_argument("--quick", action="store_true", help="a 2-spp stand-in capture")
    parser.add_argument("--out", type=Path,
                        help="where the stand-in capture is written, without --folder "
                        "(default: a fresh temporary folder)")
    args = parser.parse_args()

    folder = args.folder
    if folder is None:
        folder = output_folder(args.out, "capture")
        make_capture(folder, spp=2 if args.quick else 8)
        print(f"stand-in capture written to {folder}")
    done = rs.restore_folder(folder)
    print("\n".join(done.summary_lines()))
    print(f"status {done.result.status}; scored: {done.metrics['scored']}; outputs: {done.out}")


if __name__ == "__main__":
    main()
