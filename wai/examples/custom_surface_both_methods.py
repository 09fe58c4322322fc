"""A surface of one's own, from a file, through both methods, scored on the same truth.

    python -m wai.examples custom_surface_both_methods [--quick] [--amplitude 3] [--out DIR]

Both methods: the structured light and Alterman's sun sensor. Everything (the surface file and
both render folders, each with its restore/) goes to ``--out``, by default a fresh temporary
folder whose path is printed.

The surface here is analytic (two crossing swells), written to a ``.npz`` with ``x``, ``y`` (mm)
and ``z`` (absolute heights, mm), the format ``wai render --heightfield`` reads.
"""

import argparse
from pathlib import Path

import numpy as np

import mitsuba_wai as mw
import restoration as rs
from wai.examples import output_folder
from wai_core import AltermanSystem, Heightfield, load_heightfield, load_system


def swells(h0_mm: float, amplitude_mm: float) -> Heightfield:
    """Two crossing sinusoidal swells of 140 and 190 mm wavelength about h0."""
    x = np.linspace(-200.0, 800.0, 501)
    y = np.linspace(-400.0, 400.0, 401)
    xx, yy = np.meshgrid(x, y)
    z = h0_mm + amplitude_mm * (
        0.6 * np.sin(2 * np.pi * xx / 140.0) + 0.4 * np.cos(2 * np.pi * (xx + yy) / 190.0)
    )
    return Heightfield(x, y, z)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 samples per pixel")
    parser.add_argument("--amplitude", type=float, default=2.0, help="swell amplitude, mm")
    parser.add_argument("--out", type=Path,
                        help="folder of the surface file and both renders (default: a fresh "
                        "temporary folder)")
    args = parser.parse_args()

    sensor = load_system("alterman")
    cfg = sensor.base
    work = output_folder(args.out, "custom_surface")
    print(f"writing into {work}")
    swells(cfg.water.h0_mm, args.amplitude).save(work / "swells.npz")
    surface = load_heightfield(work / "swells.npz")
    spp = 2 if args.quick else None
    if spp:
        cfg = cfg.replace("render", spp_pattern=spp, spp_view=spp)
        sensor = AltermanSystem(cfg, sensor.sensor.replace("render", spp=spp))

    mw.render_folder(cfg, work / "structured", heightfield=surface, progress=False)
    mw.render_alterman_folder(sensor, work / "sun", heightfield=surface, progress=False)
    for name, folder, method in (("structured light", "structured", "structured-light"),
                                 ("Alterman (sun)", "sun", "alterman")):
        done = rs.restore_folder(work / folder, method)
        s = done.scores
        print(f"{name:17s} status {done.result.status:8s} RMSE {s.rmse_mm:.3f} mm "
              f"(de-meaned {s.surface['rmse_demeaned_mm']:.3f}) SSIM {s.restored['ssim']:.3f}")
    print(f"folders in {work}")


if __name__ == "__main__":
    main()
