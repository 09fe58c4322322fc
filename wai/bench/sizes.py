"""``wai bench sizes``: the restoration's cost against its work, camera size by camera size.

The bench scene is rendered with both cameras at each size (the same sensors, so the same
fields of view with finer pixels; :func:`wai.bench.accuracy.parse_camera`) and each render is
restored as ``wai bench restore`` does it (:func:`wai.bench.restore.bench_restore`). The table
gives ms per frame and per megapixel of camera s, whose image the costliest stages read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tqdm import tqdm

from wai.bench.accuracy import parse_camera
from wai.bench.timing import check_runs, machine, reference_workload

SIZES = ("640x480", "800x600", "1280x960", "1600x1200")
"""The camera sizes of the table (both cameras)."""
STAGES = ("features", "surface", "grid", "view", "consistency")
"""The stages whose medians the table lists beside the end to end."""


def parse_sizes(text: str) -> list[str]:
    """``"640x480,800x600"`` as its sizes, each checked (one-line error naming ``--sizes``)."""
    from wai_core.errors import WaiInputError

    sizes = [s.strip() for s in text.split(",") if s.strip()]
    if not sizes:
        raise WaiInputError("--sizes: give at least one WIDTHxHEIGHT")
    for s in sizes:
        try:
            parse_camera(s)
        except WaiInputError as exc:
            raise WaiInputError(str(exc).replace("--camera", "--sizes", 1)) from None
    return sizes


def render_size(config: str | Path, size: str, out: Path) -> Path:
    """The bench scene with both cameras at ``size``, rendered into ``out/size`` unless it
    holds a render already."""
    folder = out / size
    if not (folder / "scene.json").is_file():
        from mitsuba_wai import render_folder
        from wai_core.system import load_rig

        w, h = parse_camera(size)
        cfg = load_rig(config)
        cfg = cfg.replace("camera_s", width_px=w, height_px=h).replace(
            "camera_v", width_px=w, height_px=h)
        render_folder(cfg, folder, progress=False)
    return folder


def bench_sizes(config: str | Path, out: str | Path, runs: int,
                sizes: list[str] | tuple[str, ...] = SIZES) -> dict[str, Any]:
    """Restore the bench scene at every size in ``sizes``; medians of ``runs`` runs each.

    Returns
    -------
    dict
        ``rows``: per size its ``megapixels`` (camera s), ``end_to_end_ms``, ``ms_per_mp``,
        ``stages_ms`` (medians of :data:`STAGES`) and ``fps``; ``reference``: the
        reference workload, timed before and after the rows (its median over both).
    """
    from wai.bench.restore import bench_restore

    check_runs(runs)
    out = Path(out)
    before = reference_workload()
    rows = []
    for size in tqdm(sizes, desc="sizes", unit="size", leave=False):
        folder = render_size(config, size, out)
        res = bench_restore(config, runs, folder)
        w, h = parse_camera(size)
        mp = w * h / 1e6
        e2e = res["end_to_end_ms"]
        rows.append({
            "size": size, "megapixels": mp, "end_to_end_ms": e2e, "ms_per_mp": e2e / mp,
            "fps": res["fps"], "end_to_end_per_reference": res["end_to_end_per_reference"],
            "stages_ms": {s: res["stages"][s]["median_ms"] for s in STAGES
                          if s in res["stages"]},
        })
    after = reference_workload()
    ref_ms = sorted([before["median_ms"], after["median_ms"]])
    return {"config": str(config), "machine": machine(), "runs": runs, "rows": rows,
            "reference": {"workload": before["workload"], "median_ms": sum(ref_ms) / 2,
                          "before_ms": before["median_ms"], "after_ms": after["median_ms"]}}


def print_sizes(res: dict[str, Any]) -> None:
    """The table of :func:`bench_sizes`."""
    ref = res["reference"]
    print(f"restoration cost against camera size ({res['runs']} runs each, medians; "
          f"{res['machine']['cores']} cores; reference workload {ref['workload']}: "
          f"{ref['before_ms']:.1f} ms before, {ref['after_ms']:.1f} ms after)")
    head = ["size", "MP", "end to end ms", "ms / MP", "frames/s", "x ref", *STAGES]
    print("  ".join(f"{h:>12}" for h in head))
    for r in res["rows"]:
        cells = [r["size"], f"{r['megapixels']:.2f}", f"{r['end_to_end_ms']:.1f}",
                 f"{r['ms_per_mp']:.1f}", f"{r['fps']:.1f}",
                 f"{r['end_to_end_per_reference']:.2f}",
                 *(f"{r['stages_ms'].get(s, float('nan')):.2f}" for s in STAGES)]
        print("  ".join(f"{c:>12}" for c in cells))
