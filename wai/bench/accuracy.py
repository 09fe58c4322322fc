"""``wai bench accuracy``: the paper's scores over several seeds, and where the error comes from.

For each seed a frame is rendered and restored; the surface error is then split by re-running
the surface stage with one source of error removed at a time (scoring only — these reruns read
the truth and never feed the restoration):

``paper``       the paper's method (q_k on z = h0, eq. 10-13 differences, cubic gridding,
                mean height anchored at the gauge's h0);
``no_refine``   our integrator and gridding, q_k ≈ h0 kept, gauge anchor;
``gauge_anchor``  ours with refinement, but anchored at the gauge's h0 as in the paper;
``ours``        the default restoration (anchored by integrability);
``trapezoid``   ours with the trapezoid rule instead of the fourth-order one, in the level
                search and the integration (the former default);
``fit``         ours, then the surface and its level fitted to the spots through the exact model
                (``StructuredLightOptions(fit_spots=True)``,
                :func:`restoration.fit_level.fit_level`);
``spot_bias``   ours, then each spot less its light centre's modelled bias on that surface
                and the surface estimated again (``StructuredLightOptions(spot_bias=True)``,
                :mod:`restoration.spot_bias`; the restoration's own, truth-free);
``oracle_spots``  the default, fed the exact spot positions ray-traced through the true surface
                (what is left is integration, gridding and the anchor);
``oracle_anchor`` the default with the truth's mean height over the samples as anchor instead
                of h0 (what is left is shape error alone).

The corner STD is split the same way: ``corner_floor`` restores the view through the *true*
surface, so what it measures is the reverse trace, the resampling and the corner detector's own
noise on the rendered images: the floor no surface estimate can go below.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from wai.bench import parse_pair
from wai_core.config import SystemConfig
from wai_core.heightfield import Heightfield
from wai_core.io import write_json
from wai_core.system import load_rig


def true_spots(cfg: SystemConfig, truth: Heightfield, ij: NDArray) -> NDArray:
    """Exact camera-s pixels (K, 2) of the dots with grid indices ``ij`` (K, 2) reflected by
    the true surface (geometry only)."""
    from wai_core.light_paths import spots_through

    rig = cfg.rig
    return spots_through(rig, truth, rig.dot_panel_px[rig.dot_index(ij)])


def _surface_variant(
    name: str, features: Any, cal: Any, truth: Heightfield, options: Any
) -> dict[str, float]:
    from restoration import Calibration, estimate_surface, fit_to_spots, surface_errors

    cfg = cal.cfg
    spots = features.spot_px
    extra_ms = 0.0  # a variant's own work before the timed surface stage
    if options.flat_referenced and name != "oracle_spots":
        # Referred once here: the oracle anchor's calibration below has no reference of its own.
        spots = spots - cal.reference.flat_shift_at(features.ij)
    if name == "paper":
        options = replace(
            options, integrator="paper", n_refine=0, gridder="clough_tocher", anchor="gauge"
        )
    elif name == "no_refine":
        options = replace(options, n_refine=0, anchor="gauge")
    elif name == "gauge_anchor":
        options = replace(options, anchor="gauge")
    elif name == "trapezoid":
        options = replace(options, integrator="trapezoid")
    elif name == "oracle_spots":
        spots = true_spots(cfg, truth, features.ij)
    elif name == "spot_bias":
        # The default's surface, then each spot less its modelled bias on it (truth-free).
        from restoration.spot_bias import SpotBiasModel, spot_correction_px

        t_first = time.perf_counter()
        est = estimate_surface(cal.observe(features.ij, spots), cal, options)
        spots = spots - spot_correction_px(cal, features.ij, est,
                                           SpotBiasModel.of_scene(cfg))
        extra_ms = 1e3 * (time.perf_counter() - t_first)
    elif name == "oracle_anchor":
        # The gauge reading replaced by the truth's mean height over the samples.
        obs = cal.observe(features.ij, spots)
        est = estimate_surface(obs, cal, replace(options, anchor="gauge"))
        pts = est.points_mm
        mean = float(np.mean(truth.height(pts[:, 0], pts[:, 1])))
        cal = Calibration(cfg.replace("water", h0_mm=mean))
        options = replace(options, anchor="gauge")
    t0 = time.perf_counter()
    obs = cal.observe(features.ij, spots)
    est = estimate_surface(obs, cal, options)
    if name == "fit":
        est = fit_to_spots(est, obs.take(obs.rows_of(est.ij)))
    elapsed_ms = 1e3 * (time.perf_counter() - t0) + extra_ms
    err = surface_errors(est.heightfield, truth)
    return {**{k: float(err[k]) for k in ("rmse_mm", "rmse_demeaned_mm", "max_abs_mm")},
            "surface_ms": elapsed_ms}


VARIANTS = (
    "paper", "no_refine", "gauge_anchor", "trapezoid", "ours", "fit", "spot_bias",
    "oracle_spots", "oracle_anchor",
)


def spot_noise_px(cfg: SystemConfig, features: Any, truth: Heightfield) -> dict[str, float]:
    """Detected minus ray-traced spot centres, pixels: median and 95th percentile of |d|."""

    exact = true_spots(cfg, truth, features.ij)
    d = np.linalg.norm(features.spot_px - exact, axis=1)
    d = d[np.isfinite(d)]
    return {"median_px": float(np.median(d)), "p95_px": float(np.percentile(d, 95))}


def run_seed(cfg: SystemConfig, seed: int, out: Path) -> dict[str, Any]:
    """Render, restore and dissect one seed (the restoration runs once; the budget's variants
    rerun only the surface stage on its features)."""
    from mitsuba_wai import render_folder
    from restoration import restore_folder

    frame = out / f"seed{seed:03d}"
    if not (frame / "scene.json").is_file():
        render_folder(cfg.replace("waves", seed=seed), frame, progress=False)
    done = restore_folder(frame)
    metrics, cal, result = done.metrics, done.cal, done.result
    options = result_options(done)
    truth = done.truth.surface
    others = [v for v in VARIANTS if v != "ours"]
    budget = {v: _surface_variant(v, result.features, cal, truth, options) for v in others}
    budget["ours"] = {
        "rmse_mm": metrics["wai_rmse_mm"],
        "rmse_demeaned_mm": metrics["wai_rmse_demeaned_mm"],
        "max_abs_mm": metrics["wai_max_abs_mm"],
        "surface_ms": metrics.get("timings_ms", {}).get("surface", float("nan")),
    }
    return {
        "seed": seed,
        "metrics": {k: v for k, v in metrics.items() if not k.startswith("timings")},
        "verdict": truth_verdict(done),
        "error_budget": budget,
        "corner_floor_px": corner_floor_px(done, truth),
        "spot_noise": spot_noise_px(cal.cfg, result.features, truth),
    }


WRONG_CORNER_STD_PX = 0.3
"""A restored view whose corner STD exceeds this (px) is wrong somewhere."""
WRONG_SURFACE_MM = 0.5
"""A surface node off the truth by more than this (mm) is restored wrongly."""
RIGHT_SHARE = 0.99
"""A frame is right where it restored when at least this share of its surface nodes is within
:data:`WRONG_SURFACE_MM` and its corner STD within :data:`WRONG_CORNER_STD_PX`."""


def truth_verdict(done: Any) -> dict[str, Any]:
    """What the truth says of ``done`` (a FolderRestore) beside its truth-free status: the
    share of its surface nodes within :data:`WRONG_SURFACE_MM` of the truth, its corner STD,
    and whether it is right where it restored (:data:`RIGHT_SHARE`); ``right`` is False for a
    frame that restored nothing."""
    status = str(done.result.status.value)
    scores = done.scores
    if scores is None or scores.error_map_mm is None:
        return {"status": status, "within_mm_share": None, "corner_std_px": None,
                "right": False}
    err = np.abs(scores.error_map_mm)
    err = err[np.isfinite(err)]
    share = float(np.mean(err <= WRONG_SURFACE_MM)) if err.size else 0.0
    std = scores.corner_std_restored_px
    right = share >= RIGHT_SHARE and (std is None or not std > WRONG_CORNER_STD_PX)
    return {"status": status, "within_mm_share": share, "corner_std_px": std,
            "right": bool(right)}


def verdict_counts(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """How the truth-free statuses of ``runs`` agree with the truth (:func:`truth_verdict`):
    the statuses, the ``ok`` frames that are wrong somewhere, and the right frames flagged."""
    statuses: dict[str, int] = {}
    for r in runs:
        statuses[r["verdict"]["status"]] = statuses.get(r["verdict"]["status"], 0) + 1
    ok = [r for r in runs if r["verdict"]["status"] == "ok"]
    right = [r for r in runs if r["verdict"]["right"]]
    return {
        "frames": len(runs), "statuses": statuses,
        "ok_but_wrong": [r["seed"] for r in ok if not r["verdict"]["right"]],
        "right_but_flagged": [r["seed"] for r in right if r["verdict"]["status"] != "ok"],
        "right": len(right),
    }


def result_options(done: Any) -> Any:
    """The options ``done`` (a FolderRestore) was restored with."""
    from restoration import StructuredLightOptions

    return StructuredLightOptions(**done.metrics["options"])


def corner_floor_px(done: Any, truth: Heightfield) -> Any:
    """Restored corner STD (px) of ``done`` (a FolderRestore) with its view restored through
    the true surface."""
    from restoration import score

    cal, result = done.cal, done.result
    distorted = done.images["view"] / cal.view_gain
    view = cal.restore_view(distorted, truth, result_options(done).warp_step_px)
    return score(replace(result, view=view), distorted, cal, done.truth).corner_std_restored_px


def _mean_std(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    return {"mean": float(np.nanmean(a)), "std": float(np.nanstd(a)), "n": int(a.size)}


def summarize_runs(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean ± std over seeds of the headline scores and of every error-budget entry."""

    def col(path: tuple[str, ...]) -> list[float]:
        out = []
        for r in runs:
            v: Any = r
            for p in path:
                v = v[p]
            out.append(np.nan if v is None else v)
        return out

    keys = {
        "wai_rmse_mm": ("metrics", "wai_rmse_mm"),
        "wai_rmse_demeaned_mm": ("metrics", "wai_rmse_demeaned_mm"),
        "wai_max_abs_mm": ("metrics", "wai_max_abs_mm"),
        "corner_std_distorted_px": ("metrics", "corner_std_distorted_px"),
        "corner_std_restored_px": ("metrics", "corner_std_restored_px"),
        "ssim_distorted": ("metrics", "distorted", "ssim"),
        "ssim_restored": ("metrics", "restored", "ssim"),
        "psnr_distorted_db": ("metrics", "distorted", "psnr_db"),
        "psnr_restored_db": ("metrics", "restored", "psnr_db"),
        "mse_distorted": ("metrics", "distorted", "mse"),
        "mse_restored": ("metrics", "restored", "mse"),
        "view_restored_fraction": ("metrics", "view_restored_fraction"),
        "features_used": ("metrics", "features_used"),
        "features_rejected": ("metrics", "features_rejected"),
        "spot_noise_median_px": ("spot_noise", "median_px"),
        "corner_std_floor_px": ("corner_floor_px",),
    }
    keys["corner_std_restored_px800"] = ("metrics", "corner_std_restored_px800")
    summary = {k: _mean_std(col(p)) for k, p in keys.items()}
    for v in VARIANTS:
        for m in ("rmse_mm", "rmse_demeaned_mm", "surface_ms"):
            summary[f"budget.{v}.{m}"] = _mean_std(col(("error_budget", v, m)))
    return summary


def parse_camera(text: str) -> tuple[int, int]:
    """``"1600x1200"`` as (width, height) px; one-line error naming ``--camera`` otherwise."""
    return parse_pair(text, "--camera", "WIDTHxHEIGHT in pixels", 16, "pixels")


def run_accuracy(config: str | Path, out: str | Path, seeds: int, wind: float | None = None,
                 surface: str | None = None, camera: str | None = None,
                 spp: int | None = None) -> dict[str, Any]:
    """``wai bench accuracy``: seeds 0..K-1 of a configuration; writes ``accuracy.json``.

    Parameters
    ----------
    config : str or Path
        The scene: a packaged name or a TOML file.
    out : str or Path
        The output folder.
    seeds : int
        Seeds 0..seeds-1.
    wind : float or None
        Wind speed U, m/s; None: the scene's.
    surface : str or None
        Water surface (``dielectric``, ``mirror``); None: the scene's.
    camera : str or None
        Both cameras' pixels, ``WIDTHxHEIGHT`` (:func:`parse_camera`); None: the scene's.
    spp : int or None
        Samples per pixel of both renders; None: the scene's.
    """
    cfg = load_rig(config)
    if wind is not None:
        cfg = cfg.replace("waves", wind_speed_m_s=wind)
    if surface:
        cfg = cfg.replace("water", surface=surface)
    if camera:
        w, h = parse_camera(camera)
        cfg = cfg.replace("camera_s", width_px=w, height_px=h).replace(
            "camera_v", width_px=w, height_px=h
        )
    if spp:
        cfg = cfg.replace("render", spp_pattern=spp, spp_view=spp)
    out = Path(out)
    runs = [run_seed(cfg, s, out) for s in tqdm(range(seeds), desc="seeds", leave=False)]
    result = {
        "config": str(config),
        "wind_speed_m_s": cfg.waves.wind_speed_m_s,
        "surface": cfg.water.surface,
        "camera_px": [cfg.camera_s.width_px, cfg.camera_s.height_px],
        "spp": [cfg.render.spp_pattern, cfg.render.spp_view],
        "seeds": list(range(seeds)),
        "summary": summarize_runs(runs),
        "verdicts": verdict_counts(runs),
        "runs": runs,
    }
    write_json(out / "accuracy.json", result)
    return result


def print_accuracy(res: dict[str, Any]) -> None:
    """Mean ± std table of :func:`run_accuracy`."""
    s = res["summary"]
    print(f"{len(res['seeds'])} seeds, U = {res['wind_speed_m_s']} m/s, {res['surface']} surface")
    for k, v in s.items():
        print(f"  {k:38s} {v['mean']:10.4f} ± {v['std']:.4f}")
    v = res.get("verdicts")
    if v:
        print(f"statuses {v['statuses']}; right where restored (truth: corner STD <= "
              f"{WRONG_CORNER_STD_PX:g} px, {RIGHT_SHARE:.0%} of the surface within "
              f"{WRONG_SURFACE_MM:g} mm): {v['right']} of {v['frames']}; ok but wrong: "
              f"{len(v['ok_but_wrong'])} {v['ok_but_wrong']}; right but flagged: "
              f"{len(v['right_but_flagged'])} {v['right_but_flagged']}")


