"""``wai experiment validate``: is the renderer right, and does the geometric model agree with it?

**Renderer vs Mitsuba reference** (:func:`reference_table`): the default renderer (dots drawn
directly, the view traced directly, the one-branch water BSDF) against renders made of
Mitsuba's stock plugins and integrators only (:mod:`mitsuba_wai.reference`: ``ptracer`` +
``projector`` + ``dielectric``, ``path`` + ``dielectric``, independent sampler, high spp), for
flat water and U = 1 m/s: spot centres by windowed centroids (none of the restoration's
detector), the light in the spots and in all of camera s's image, the view's mean and RMS
difference.

**Geometric model vs render**, for flat water and for waves at several wind speeds and seeds:

- spot centres detected in the pattern render against the chief rays of the geometric model
  (:func:`wai.forward.predict_spots`): median and 95th percentile offset, pixels;
- the rendered view against the geometric view (:func:`wai.forward.predict_view`): SSIM on
  the pixels whose rays reach the object (TIR and off-board pixels masked).

Then the testbed's own speed against accuracy, for both ``[render].sampling`` choices: spot
agreement against samples per pixel and render time (camera s), and the view's noise against a
256-spp render (camera v), from which the defaults ``spp_pattern`` / ``spp_view`` are picked.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from tqdm import tqdm

from wai.experiments.outputs import output_folder
from wai_core.config import SAMPLINGS, SystemConfig
from wai_core.heightfield import Heightfield
from wai_core.io import atomic_write_bytes, write_json
from wai_core.system import load_rig

# A detection farther than this from a predicted spot is another dot, not an offset.
MATCH_RADIUS_PX = 3.0


def spot_agreement(
    cfg: SystemConfig, surface: Heightfield | None, pattern: NDArray
) -> dict[str, float]:
    """Offsets (px) between detected spots and the model's chief rays."""
    from restoration import detect_spots
    from wai_core.forward import predict_spots

    _, px = predict_spots(cfg, surface)
    spots = detect_spots(np.nan_to_num(pattern, nan=0.0, posinf=0.0))
    dist, _ = cKDTree(spots.centres_px).query(px)
    found = dist < MATCH_RADIUS_PX
    d = dist[found]
    return {
        "median_px": float(np.median(d)) if d.size else float("nan"),
        "p95_px": float(np.percentile(d, 95)) if d.size else float("nan"),
        "n_predicted": int(px.shape[0]),
        "n_found": int(found.sum()),
    }


def view_agreement(
    cfg: SystemConfig, surface: Heightfield | None, view: NDArray, texture: NDArray
) -> dict[str, float]:
    """SSIM/PSNR of the path-traced view against the geometric one, outside TIR and the board."""
    from restoration import image_metrics
    from wai_core.forward import predict_view

    predicted, ok = predict_view(cfg, surface, texture)
    rendered = view / cfg.water.n_water**2
    mask = ok & (predicted.mean(axis=2) > 0.01)
    m = image_metrics(rendered, predicted, mask)
    return {"ssim": m["ssim"], "psnr_db": m["psnr_db"], "n_pixels": m["n_pixels"]}


SPOT_WINDOW_PX = 6
"""Half side of the windows in which spot centroids are compared with the reference, px."""


def reference_row(
    cfg: SystemConfig, surface: Heightfield, images: dict[str, NDArray],
    reference: dict[str, NDArray],
) -> dict[str, float]:
    """The default renderer's ``images`` against the stock-Mitsuba ``reference``: spot
    offsets (windowed centroids about the model's spots, the same windows in both images),
    light in the spots and in the whole image (ratio default / reference), view mean ratio and
    RMS difference (radiance, white = 1)."""
    from mitsuba_wai import windowed_centroids
    from wai_core.forward import predict_spots

    flat = bool(np.ptp(surface.z) == 0)
    _, px = predict_spots(cfg, None if flat else surface)
    start, _ = windowed_centroids(images["pattern"], px, SPOT_WINDOW_PX)
    ours, e_ours = windowed_centroids(images["pattern"], start, SPOT_WINDOW_PX, iterations=1)
    theirs, e_ref = windowed_centroids(reference["pattern"], start, SPOT_WINDOW_PX, iterations=1)
    d = np.linalg.norm(ours - theirs, axis=1)
    d = d[np.isfinite(d)]
    gain = cfg.water.n_water**2
    view, ref_view = images["view"] / gain, reference["view"] / gain
    return {
        "spots": int(d.size),
        "spot_median_px": float(np.median(d)) if d.size else float("nan"),
        "spot_p95_px": float(np.percentile(d, 95)) if d.size else float("nan"),
        "spot_light_ratio": float(np.nansum(e_ours) / np.nansum(e_ref)),
        "image_light_ratio": float(images["pattern"].sum() / reference["pattern"].sum()),
        "view_mean_ratio": float(view.mean() / ref_view.mean()),
        "view_rms": float(np.sqrt(np.mean((view - ref_view) ** 2))),
    }


def reference_table(cfg: SystemConfig, quick: bool) -> list[dict[str, Any]]:
    """Renderer vs Mitsuba reference, flat water and U = 1 m/s (seed 0): :func:`reference_row`
    at the default spp, the reference at 64 / 16 spp (``quick``) or 256 / 64."""
    from mitsuba_wai import FrameRenderer, flat_like, render_reference, render_seed, wave_surface

    spp = (64, 16) if quick else (256, 64)
    c = cfg.replace("waves", wind_speed_m_s=1.0, seed=0)
    grid = wave_surface(c)
    renderer = FrameRenderer(c, grid)
    rows = []
    for wind in tqdm((0.0, 1.0), desc="validate: renderer vs Mitsuba reference", leave=True):
        surface = flat_like(grid, c.water.h0_mm) if wind == 0 else grid
        images = renderer.render(surface, render_seed(c))
        reference = render_reference(c, surface, *spp, seed=render_seed(c) + 17)
        rows.append({"wind_m_s": wind, "reference_spp_pattern": spp[0],
                     "reference_spp_view": spp[1],
                     **reference_row(c, surface, images, reference)})
    return rows


def _cases(quick: bool) -> list[tuple[float, int]]:
    winds = [0.0, 1.0] if quick else [0.0, 0.5, 1.0, 1.5]
    seeds = [0] if quick else [0, 1]
    return [(0.0, 0)] + [(u, s) for u in winds if u > 0 for s in seeds]


def agreement_table(cfg: SystemConfig, quick: bool) -> list[dict[str, Any]]:
    """Spot and view agreement for flat water and each (wind, seed) case at the default spp."""
    from mitsuba_wai import FrameRenderer, flat_like, object_texture, render_seed, wave_surface

    texture = object_texture(cfg.object)
    default_grid = wave_surface(cfg)
    renderers: dict[tuple[int, ...], FrameRenderer] = {}
    rows = []
    for wind, seed in tqdm(_cases(quick), desc="validate: model against render", leave=True):
        c = cfg.replace("waves", wind_speed_m_s=wind, seed=seed)
        surface = wave_surface(c) if wind > 0 else None
        grid = default_grid if surface is None else surface
        if grid.z.shape not in renderers:  # one loaded scene per mesh size
            renderers[grid.z.shape] = FrameRenderer(c, grid)
        shown = flat_like(grid, cfg.water.h0_mm) if surface is None else surface
        images = renderers[grid.z.shape].render(shown, render_seed(c))
        spots = spot_agreement(c, surface, images["pattern"])
        view = view_agreement(c, surface, images["view"], texture)
        rows.append(
            {
                "wind_m_s": wind,
                "seed": seed,
                "spp_pattern": cfg.render.spp_pattern,
                "spp_view": cfg.render.spp_view,
                **{f"spot_{k}": v for k, v in spots.items()},
                **{f"view_{k}": v for k, v in view.items()},
            }
        )
    return rows


def spp_sweep(cfg: SystemConfig, spps: list[int], runs: int = 2) -> list[dict[str, Any]]:
    """Spot agreement and render time of the pattern against spp, for each ``[render].sampling``
    (U from cfg, seed 0)."""
    from mitsuba_wai import FrameRenderer, wave_surface

    surface = wave_surface(cfg)
    rows = []
    for sampling in SAMPLINGS:
        c = cfg.replace("render", sampling=sampling)
        renderer = FrameRenderer(c, surface, systems=("pattern",))
        renderer.render(surface, 0, ("pattern",), spp=1)  # compile the kernels before timing
        for spp in tqdm(spps, desc=f"validate: pattern spp ({sampling})", leave=True):
            times, medians, p95s = [], [], []
            for run in range(runs):
                t0 = time.perf_counter()
                img = renderer.render(surface, 1000 + run, ("pattern",), spp=spp)["pattern"]
                times.append(time.perf_counter() - t0)
                agree = spot_agreement(c, surface, img)
                medians.append(agree["median_px"])
                p95s.append(agree["p95_px"])
            rows.append(
                {
                    "sampling": sampling,
                    "spp": spp,
                    "render_s": float(np.median(times)),
                    "spot_median_px": float(np.median(medians)),
                    "spot_p95_px": float(np.median(p95s)),
                }
            )
    return rows


def view_spp_sweep(
    cfg: SystemConfig, spps: list[int], reference_spp: int = 256, runs: int = 2
) -> list[dict[str, Any]]:
    """The view's noise against spp, for each ``[render].sampling``: RMS difference from a
    ``reference_spp`` render (two independent ones averaged), on the radiance scale (1 = white),
    and render time (U from cfg, seed 0)."""
    from mitsuba_wai import FrameRenderer, wave_surface

    surface = wave_surface(cfg)
    reference = None
    rows = []
    for sampling in ("independent", "stratified"):
        c = cfg.replace("render", sampling=sampling)
        renderer = FrameRenderer(c, surface, systems=("view",))
        if reference is None:
            reference = np.mean(
                [renderer.render(surface, 500 + k, ("view",), spp=reference_spp)["view"]
                 for k in range(2)], axis=0)
        renderer.render(surface, 0, ("view",), spp=1)
        for spp in tqdm(spps, desc=f"validate: view spp ({sampling})", leave=True):
            times, errors = [], []
            for run in range(runs):
                t0 = time.perf_counter()
                img = renderer.render(surface, 1000 + run, ("view",), spp=spp)["view"]
                times.append(time.perf_counter() - t0)
                errors.append(float(np.sqrt(np.mean((img - reference) ** 2))))
            rows.append({"sampling": sampling, "spp": spp, "render_s": float(np.median(times)),
                         "rms_vs_reference": float(np.mean(errors))})
    return rows


def spp_chart(rows: list[dict[str, Any]], view_rows: list[dict[str, Any]], cfg: SystemConfig,
              path: Path) -> None:
    """Spot agreement (left) and view noise (right) against render time, one point per spp and
    one line per sampling; the defaults starred."""
    from wai.figures import plt, save_figure

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.4))
    styles = {"stratified": ("o-", "tab:blue"), "independent": ("s--", "tab:gray")}
    r_ = cfg.render
    for sampling, (style, colour) in styles.items():
        sel = [r for r in rows if r["sampling"] == sampling]
        t = [r["render_s"] for r in sel]
        ax.plot(t, [r["spot_median_px"] for r in sel], style, color=colour,
                label=f"{sampling}: median")
        ax.plot(t, [r["spot_p95_px"] for r in sel], style, color=colour, alpha=0.45,
                label=f"{sampling}: 95th percentile")
        for r in sel:
            ax.annotate(f"{r['spp']}", (r["render_s"], r["spot_median_px"]), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")
        vsel = [r for r in view_rows if r["sampling"] == sampling]
        bx.plot([r["render_s"] for r in vsel], [r["rms_vs_reference"] for r in vsel], style,
                color=colour, label=sampling)
        for r in vsel:
            bx.annotate(f"{r['spp']}", (r["render_s"], r["rms_vs_reference"]), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")
    d = next((r for r in rows if r["spp"] == r_.spp_pattern and r["sampling"] == r_.sampling),
             None)
    if d is not None:
        ax.plot([d["render_s"]], [d["spot_median_px"]], "r*", ms=16,
                label=f"default ({r_.spp_pattern} spp, {r_.sampling})")
    v = next((r for r in view_rows if r["spp"] == r_.spp_view and r["sampling"] == r_.sampling),
             None)
    if v is not None:
        bx.plot([v["render_s"]], [v["rms_vs_reference"]], "r*", ms=16,
                label=f"default ({r_.spp_view} spp, {r_.sampling})")
    ax.axhline(0.05, color="gray", lw=0.8, ls=":", label="goal 0.05 px")
    for a in (ax, bx):
        a.set_xscale("log")
        a.set_yscale("log")
        a.legend(fontsize=7)
    ax.set_xlabel("pattern render time per frame (s)")
    ax.set_ylabel("spot offset, render vs geometric model (px)")
    ax.set_title("Camera s: spot agreement vs time (labels: spp)")
    bx.set_xlabel("view render time per frame (s)")
    bx.set_ylabel("RMS difference from a 256-spp render")
    bx.set_title("Camera v: view noise vs time (labels: spp)")
    save_figure(fig, path)


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    """Rows of dicts as CSV, atomically."""
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def run_validate(config: str | Path, out: str | Path, quick: bool = False) -> dict[str, Any]:
    """Run both comparisons and the spp sweeps; write JSON, CSV and the chart into ``out``.

    Parameters
    ----------
    config, out : str or Path
        The scene (a packaged name or a TOML file) and the output folder (made if missing), as
        :func:`wai.experiments.run_experiment` takes them.
    quick : bool
        2 wave cases, spp 2/8/32 and 1/4, one run each, the reference at 64 / 16 spp.

    Returns
    -------
    dict
        The tables (``renderer_vs_mitsuba``, ``agreement``, ``spp_sweep``,
        ``view_spp_sweep``), the scene's ``default_spp`` and ``sampling``; as
        ``validate.json``.
    """
    cfg = load_rig(config)
    out = output_folder(out)
    against_mitsuba = reference_table(cfg, quick)
    table = agreement_table(cfg, quick)
    spps = [2, 8, 32] if quick else [1, 2, 3, 4, 8, 16, 32, 64]
    runs = 1 if quick else 3
    sweep = spp_sweep(cfg, spps, runs=runs)
    view_sweep = view_spp_sweep(cfg, [1, 4] if quick else [1, 2, 4, 8, 16, 32],
                                reference_spp=64 if quick else 256, runs=runs)
    write_csv(out / "renderer_vs_mitsuba.csv", against_mitsuba)
    write_csv(out / "agreement.csv", table)
    write_csv(out / "spp_sweep.csv", sweep)
    write_csv(out / "view_spp_sweep.csv", view_sweep)
    spp_chart(sweep, view_sweep, cfg, out / "spp_tradeoff.png")
    result = {"renderer_vs_mitsuba": against_mitsuba, "agreement": table, "spp_sweep": sweep,
              "view_spp_sweep": view_sweep,
              "default_spp": [cfg.render.spp_pattern, cfg.render.spp_view],
              "sampling": cfg.render.sampling}
    write_json(out / "validate.json", result)
    return result


def print_validate(res: dict[str, Any]) -> None:
    """The tables, readable."""
    print("Renderer vs Mitsuba reference (stock ptracer/path + dielectric, independent sampler)")
    print("wind  ref spp   spots  spot median  spot p95  light: spots  image   view mean  "
          "view RMS")
    for r in res["renderer_vs_mitsuba"]:
        print(
            f"{r['wind_m_s']:4.1f} {r['reference_spp_pattern']:4d}/{r['reference_spp_view']:<4d}"
            f" {r['spots']:5d}  {r['spot_median_px']:9.4f} px {r['spot_p95_px']:7.4f} px  "
            f"{r['spot_light_ratio']:11.5f} {r['image_light_ratio']:7.4f}  "
            f"{r['view_mean_ratio']:9.5f}  {r['view_rms']:.4f}"
        )
    print("Geometric model vs render")
    print("wind  seed  spot median  spot p95  found/predicted  view SSIM")
    for r in res["agreement"]:
        print(
            f"{r['wind_m_s']:4.1f} {r['seed']:5d}  {r['spot_median_px']:9.3f} px "
            f"{r['spot_p95_px']:7.3f} px  {r['spot_n_found']:5d}/{r['spot_n_predicted']:<5d}"
            f"     {r['view_ssim']:.4f}"
        )
    print("pattern: sampling      spp   render s  spot median  spot p95")
    for r in res["spp_sweep"]:
        print(
            f"         {r['sampling']:12s} {r['spp']:4d} {r['render_s']:9.2f}  "
            f"{r['spot_median_px']:9.3f} px {r['spot_p95_px']:7.3f} px"
        )
    print("view:    sampling      spp   render s  RMS vs reference")
    for r in res["view_spp_sweep"]:
        print(f"         {r['sampling']:12s} {r['spp']:4d} {r['render_s']:9.2f}  "
              f"{r['rms_vs_reference']:.4f}")
