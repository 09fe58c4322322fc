"""A restoration method of one's own, in its own file, run through the testbed.

``AsSeen`` takes the distorted view as the restored one: the floor every method must beat,
written the way any method joins (:class:`restoration.Method`): a name, the calibration type
it reads frames with, its options type, and ``method(images, cal, track) -> RestoreResult``.
It gives a view and no surface, so it is scored on the view alone.

    python -m wai.examples plugin_method [--quick] [--seed 3]

renders one frame in memory and scores this method beside the structured light on it. The CLI
takes it by its file (or ``module:Class``, or an installed package's entry point in the
group ``wai.methods``)::

    wai restore renders/demo --method wai.examples.plugin_method:AsSeen
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

import mitsuba_wai as mw
import restoration as rs
from restoration import Calibration, LevelTrack, RestoredView, RestoreResult, SurfaceOptions
from wai_core import load_system


class AsSeen:
    """The distorted view, unrestored, valid everywhere."""

    name = "as-seen"
    calibration_type = Calibration
    options_type = SurfaceOptions

    def __init__(self, options: SurfaceOptions | None = None) -> None:
        self.options = options or SurfaceOptions()

    def __call__(self, images: dict[str, Any], cal: Calibration,
                 track: LevelTrack | None = None) -> RestoreResult:
        view = cal.radiance(images["view"])
        return RestoreResult(self.name, view=RestoredView(view, np.ones(view.shape[:2], bool)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 samples per pixel (seconds)")
    parser.add_argument("--seed", type=int, default=0, help="wave phases and render noise")
    args = parser.parse_args()

    cfg = load_system("paper").replace("waves", seed=args.seed)
    frame = mw.render_frame(cfg, spp=2 if args.quick else None)
    cal = rs.Calibration(cfg, frame.view_gain)
    truth = rs.Truth(frame.surface, cal.radiance(frame.images["view_truth"]))
    for method in (AsSeen(), rs.StructuredLight()):
        result = method(frame.images, cal)
        scores = rs.score(result, cal.radiance(frame.images["view"]), cal, truth)
        surface = "no surface" if scores.surface is None else f"RMSE {scores.rmse_mm:.3f} mm"
        print(f"{method.name}: status {result.status}; view SSIM {scores.restored['ssim']:.3f},"
              f" corner STD {scores.corner_std_restored_px:.2f} px; {surface}")


if __name__ == "__main__":
    main()
