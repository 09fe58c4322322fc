"""``wai bench surfaces``: the restoration on analytic surfaces it was not tuned on.

Each surface of :data:`wai_core.surfaces.SURFACES` (sharp-crested trochoidal waves, a Stokes
wave, crossing swells, a bump) is scaled so that its effective slope amplitude is at most
``--phi`` times eq. 35's bound, rendered through the paper's rig and restored with the
default refinement and with the Gauss-Newton fit to the spots; surface RMSE (absolute and
de-meaned), the consistency residual and the status are reported per surface.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tqdm import tqdm

from wai_core.io import write_json

__all__ = ["bench_surfaces", "print_surfaces"]


def _restore(frame: Any, cal: Any, fit: bool) -> dict[str, Any]:
    import restoration as rs

    result = rs.StructuredLight(rs.StructuredLightOptions(fit_spots=fit))(frame.images, cal)
    if not result.restored:
        return {"status": result.status, "message": result.message}
    truth = rs.Truth(frame.surface, cal.radiance(frame.images["view_truth"]))
    s = rs.score(result, cal.radiance(frame.images["view"]), cal, truth)
    return {
        "status": result.status,
        "rmse_mm": s.rmse_mm,
        "rmse_demeaned_mm": s.surface["rmse_demeaned_mm"],
        "residual_median_px": result.consistency.median_px,
        "restored_ssim": (s.restored or {}).get("ssim"),  # None: restored nowhere
        "surface_ms": result.timings_ms["surface"],
    }


def bench_surfaces(config: str | Path, out: str | Path, phi: float) -> dict[str, Any]:
    """Render and restore every analytic surface; writes ``surfaces.json`` into ``out``.

    Parameters
    ----------
    config, out : str or Path
        The scene (a packaged name or a TOML file) and the output folder (made if missing), as
        :func:`wai.experiments.run_experiment` takes them.
    phi : float
        Each surface is scaled to at most this fraction of eq. 35's slope bound.
    """
    import mitsuba_wai as mw
    import restoration as rs
    from wai_core.limits import correspondence_limit, effective_phi_deg
    from wai_core.surfaces import SURFACES, scaled
    from wai_core.system import load_rig

    cfg = load_rig(config)
    phi_max = correspondence_limit(cfg)["phi_max_deg"]
    rows = []
    for name, make in tqdm(SURFACES.items(), desc="surfaces", leave=False):
        surface = make(cfg.water.h0_mm)
        factor = min(1.0, phi * phi_max / effective_phi_deg(surface, cfg))
        surface = scaled(surface, cfg.water.h0_mm, factor)
        frame = mw.render_frame(cfg, surface)
        cal = rs.Calibration(cfg, frame.view_gain)
        rows.append({
            "surface": name,
            "height_scale": factor,
            "phi_ratio": effective_phi_deg(frame.surface, cfg) / phi_max,
            "default": _restore(frame, cal, fit=False),
            "fit": _restore(frame, cal, fit=True),
        })
    res = {"config": str(config), "phi_target": phi, "rows": rows}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "surfaces.json", res)
    return res


def print_surfaces(res: dict[str, Any]) -> None:
    """One line per surface: RMSE / de-meaned (mm), residual (px) and status, both variants."""
    def cell(r: dict) -> str:
        if "rmse_mm" not in r:
            return f"{r['status']}"
        return (f"{r['rmse_mm']:.3f} / {r['rmse_demeaned_mm']:.3f} mm, resid "
                f"{r['residual_median_px']:.3f} px, {r['status']}")

    print(f"{'surface':18s} {'phi/phi_max':>11s}  default | with the fit to the spots")
    for r in res["rows"]:
        print(f"{r['surface']:18s} {r['phi_ratio']:11.2f}  {cell(r['default'])} | {cell(r['fit'])}")
