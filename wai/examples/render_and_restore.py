"""Render one frame of the paper's system in memory, restore it and score it.

    python -m wai.examples render_and_restore [--quick] [--wind 1.5] [--seed 3]

The ten-line core of a render -> restore -> score script (docs/api.md shows it alone). It
works in memory and writes no file.
"""

import argparse

import mitsuba_wai as mw
import restoration as rs
from wai_core import load_system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 samples per pixel (seconds)")
    parser.add_argument("--wind", type=float, default=1.0, help="wind speed U, m/s")
    parser.add_argument("--seed", type=int, default=0, help="wave phases and render noise")
    args = parser.parse_args()

    cfg = load_system("paper").replace("waves", wind_speed_m_s=args.wind, seed=args.seed)
    frame = mw.render_frame(cfg, spp=2 if args.quick else None)
    cal = rs.Calibration(cfg, frame.view_gain)
    result = rs.StructuredLight()(frame.images, cal)
    truth = rs.Truth(frame.surface, cal.radiance(frame.images["view_truth"]))
    scores = rs.score(result, cal.radiance(frame.images["view"]), cal, truth)
    print(f"status {result.status}; {len(result.features)} features matched")
    demeaned = scores.surface["rmse_demeaned_mm"]
    print(f"surface RMSE {scores.rmse_mm:.3f} mm (de-meaned {demeaned:.3f} mm)")
    print(f"SSIM {scores.distorted['ssim']:.3f} -> {scores.restored['ssim']:.3f}; corner STD "
          f"{scores.corner_std_distorted_px:.2f} -> {scores.corner_std_restored_px:.2f} px")
    print(f"restored in {result.timings_ms['end_to_end']:.0f} ms")


if __name__ == "__main__":
    main()
