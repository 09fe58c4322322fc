"""``wai experiment stability``: where each method breaks, against the bound eq. 35 predicts.

Sweeps, each over seeds (frames by :func:`wai.frame_eval.evaluate_frame`, on Dask):

- sea state: wind speed U from calm to where everything fails, and the wave heights scaled at
  fixed U = 1 m/s (steeper waves of the same shape);
- pattern spacing D, diffuser height z_h;
- the field's degradations: the sensor's signal (electrons at the flat reference's 99.9th
  percentile; shot and read noise, full well, 12-bit ADC: ``[sensor]``) and the exposure time
  (motion blur: ``[motion]``);
- daylight on the structured light (``ambient_level``: sky radiance, object white = 1, and a sun
  ten times brighter at 30 deg zenith: ``[ambient]``) and murky water (``turbidity``, the
  scattering's scale, half of it arriving as a glow: ``[water_optics]``), both read by a
  10000 e- sensor;
- Alterman's sun sensor: the sun's zenith angle (:func:`evaluate_sun`).

Each panel marks the sweep's failure point (:func:`failure_point`): walking from its mildest
value to its harshest, the first value at which under half the frames end ok, after one at
which at least half did.

Every frame reports its fraction of correct correspondences (against the geometric model's
spot for each label), surface RMSE, restored SSIM and a status; a failed frame is a row with
its status, never left out of a mean. The summary chart puts every structured-light frame's
fraction of correct correspondences against its effective slope amplitude Φ (eq. 35's 2Φ is
the largest inclination change between neighbouring dots) divided by the Φ that eq. 35 allows
for its geometry: the bound predicts failure beyond 1.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from wai.experiments.frame_eval import evaluate_frame  # noqa: E402
from wai.experiments.outputs import (  # noqa: E402
    output_folder,
    publish,
    sweep_command,
    sweep_rows,
)
from wai.figures import save_figure  # noqa: E402
from wai.sweep import SweepOptions  # noqa: E402
from wai_core.io import write_json  # noqa: E402
from wai_core.scenes import scene_path  # noqa: E402

SWEEPS: dict[str, tuple[str, tuple[float, ...]]] = {
    "wind": ("wind_mps", (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0)),
    "amplitude": ("amplitude", (0.25, 0.5, 1.0, 2.0, 3.0, 4.0, 6.0)),
    "spacing": ("spacing_px", (12.0, 16.0, 20.0, 28.0, 40.0, 56.0)),
    "z_h": ("z_h_mm", (20.0, 40.0, 60.0, 80.0, 100.0, 120.0)),
    "noise": ("signal_e", (30000.0, 10000.0, 3000.0, 1000.0, 300.0, 100.0, 30.0)),
    "exposure": ("exposure_s", (0.0, 0.002, 0.005, 0.01, 0.02, 0.04)),
    "ambient": ("ambient_level", (0.0, 0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0)),
    "turbidity": ("turbidity", (1.0, 30.0, 100.0, 300.0, 1000.0, 3000.0)),
    "sun": ("theta_sun_deg", (0.0, 15.0, 30.0, 45.0, 60.0)),
}
QUICK: dict[str, tuple[float, ...]] = {
    "wind": (0.5, 1.0, 3.0),
    "amplitude": (1.0, 4.0),
    "spacing": (16.0, 28.0),
    "z_h": (60.0,),
    "noise": (10000.0, 100.0),
    "exposure": (0.0, 0.01),
    "ambient": (0.0, 0.01, 0.1),
    "turbidity": (1.0, 300.0),
    "sun": (0.0,),
}
HARSHER: dict[str, int] = {
    "wind": 1, "amplitude": 1, "spacing": -1, "z_h": -1, "noise": -1, "exposure": 1,
    "ambient": 1, "turbidity": 1, "sun": 1,
}
"""Which way each sweep gets harder: +1 towards larger values, -1 towards smaller (denser
dots and a lower diffuser shrink eq. 35's bound; fewer electrons mean more noise)."""
FIXED: dict[str, dict[str, float]] = {
    "ambient": {"signal_e": 10000.0},
    "turbidity": {"signal_e": 10000.0, "forward_fraction": 0.5},
}
"""Point fields a sweep holds fixed: daylight and murky water are seen by a real sensor
(10000 e- at the flat reference's 99.9th percentile, so the background's shot noise counts),
and half of the water's scattered light arrives as a veiling glow."""


CODES = ("none", "colour")
"""The patterns the "coded" sweep runs side by side on the same sea states: the paper's plain
grid (ordering matcher) and the colour-coded one (:mod:`restoration.features.decode`)."""
CODED: tuple[tuple[float, float], ...] = (
    (1.0, 0.5), (1.0, 1.0), (1.0, 1.5), (1.0, 2.0), (1.0, 2.5), (1.0, 3.0), (0.5, 1.0),
)
"""The "coded" sweep's sea states, (U m/s, height scale): amplitude at U = 1, and U = 0.5."""
CODED_QUICK: tuple[tuple[float, float], ...] = ((1.0, 1.0), (1.0, 2.0))


def status_cell(statuses: dict[str, int]) -> str:
    """A table cell of the frames' statuses and their counts, by status.

    Examples
    --------
    >>> status_cell({"sparse": 1, "ok": 3})
    'ok 3, sparse 1'
    """
    return ", ".join(f"{k} {v}" for k, v in sorted(statuses.items()))


def failure_point(entries: list[dict[str, Any]], harsher: int = 1) -> float | None:
    """The first value, from the mildest towards the harshest, at which under half the frames
    ended ok after one at which at least half did; None when the sweep never breaks (or never
    worked)."""
    worked = False
    for e in sorted(entries, key=lambda e: harsher * e["value"]):
        ok = e["ok"] >= 0.5 * max(e["frames"], 1)
        if worked and not ok:
            return e["value"]
        worked = worked or ok
    return None


def evaluate_sun(point: dict[str, Any]) -> dict[str, Any]:
    """Render and restore Alterman's sun sensor at the point's sun zenith angle."""
    from mitsuba_wai import render_alterman_folder
    from restoration import Alterman, restore_folder
    from wai_core.alterman import AltermanSystem, load_alterman
    from wai_core.system import load_rig

    sensor = load_alterman(point["alterman"]).sensor
    sensor = sensor.replace("sun", zenith_deg=float(point["theta_sun_deg"]))
    base = load_rig(point["config"]).replace("waves", seed=int(point["seed"]))
    with tempfile.TemporaryDirectory(prefix="wai-sun-") as tmp:
        frame = Path(tmp) / "frame"
        render_alterman_folder(AltermanSystem(base, sensor), frame, progress=False)
        m = restore_folder(frame, Alterman(), write=False).metrics
    status = m.get("status", "ok")
    row = {"frame_status": status}
    if status == "ok":
        row.update(
            wai_rmse_mm=m["wai_rmse_mm"],
            wai_rmse_demeaned_mm=m["wai_rmse_demeaned_mm"],
            restored_ssim=m["restored"]["ssim"],
            features_used=m["features_used"],
            features_rejected=m["features_rejected"],
        )
    return row


def evaluate_point(point: dict[str, Any]) -> dict[str, Any]:
    """One stability point: the sun sweep's own evaluation, or a structured-light frame."""
    return evaluate_sun(point) if point["sweep"] == "sun" else evaluate_frame(point)


def stability_points(
    config: Path, alterman: Path, seeds: list[int], quick: bool
) -> list[dict[str, Any]]:
    """The sweeps' points: one per swept value and seed."""
    points = []
    for sweep, (field, values) in SWEEPS.items():
        for value in QUICK[sweep] if quick else values:
            for seed in seeds:
                p = {"sweep": sweep, "config": str(config), "seed": seed, field: value,
                     "repeats": 1, **FIXED.get(sweep, {})}
                if sweep == "sun":
                    p["alterman"] = str(alterman)
                points.append(p)
    for wind, amplitude in CODED_QUICK if quick else CODED:
        for code in CODES:
            for seed in seeds:
                points.append({"sweep": "coded", "config": str(config), "seed": seed,
                               "code": code, "wind_mps": wind, "amplitude": amplitude,
                               "repeats": 1})
    return points


def _ok(row: dict) -> bool:
    return row.get("status") == "ok" and row.get("frame_status") == "ok"


def sweep_summary(rows: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Per sweep and value: frames, how many ended ok and how each other one ended, and the
    means over the ok frames (fraction correct is averaged over all frames that ran)."""
    out: dict[str, list[dict[str, Any]]] = {}
    for sweep, (field, _) in SWEEPS.items():
        sel = [r for r in rows if r.get("sweep") == sweep]
        entries = []
        for value in sorted({r[field] for r in sel}):
            group = [r for r in sel if r[field] == value]
            good = [r for r in group if _ok(r)]
            statuses: dict[str, int] = {}
            for r in group:
                s = r.get("frame_status") if r.get("status") == "ok" else r.get("status")
                key = str(s).split(":")[0]
                statuses[key] = statuses.get(key, 0) + 1

            def mean(key: str, rows_: list[dict] = good) -> float:
                vals = [float(r[key]) for r in rows_ if r.get(key) is not None]
                vals = [v for v in vals if np.isfinite(v)]
                return float(np.mean(vals)) if vals else float("nan")

            entries.append({
                "value": value, "frames": len(group), "ok": len(good), "statuses": statuses,
                "fraction_correct": mean("fraction_correct", group),
                "wai_rmse_mm": mean("wai_rmse_mm"), "restored_ssim": mean("restored_ssim"),
                "phi_deg": mean("phi_deg", group), "phi_max_deg": mean("phi_max_deg", group),
            })
        out[sweep] = entries
    return out


BAD_RMSE_MM = 1.0
"""A frame whose surface is off by more than this (RMSE, mm) must not pass as ``ok``."""


def detection_rates(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """How well the truth-free statuses flag bad frames, over the structured-light frames.

    A frame is *bad* when its restoration failed or its surface RMSE exceeds
    :data:`BAD_RMSE_MM`; *flagged* when the method's own status (``method_status``: without
    the sweep's truth-based ``wrong_labels``; ``failed`` when it refused) is not ``ok``.
    Returns the counts,
    the detection rate (bad frames flagged) and the false-alarm rate (good frames flagged),
    with the statuses of both.
    """
    frames = [r for r in rows if r.get("sweep") != "sun" and r.get("status") == "ok"]
    bad, good = [], []
    for r in frames:
        rmse = r.get("wai_rmse_mm")
        failed = rmse is None or not np.isfinite(float(rmse))
        (bad if failed or float(rmse) > BAD_RMSE_MM else good).append(r)

    def own_status(r: dict) -> str:
        return str(r.get("method_status") or r.get("frame_status")).split(":")[0]

    def tally(group: list[dict]) -> dict[str, int]:
        out: dict[str, int] = {}
        for r in group:
            out[own_status(r)] = out.get(own_status(r), 0) + 1
        return out

    flagged_bad = sum(own_status(r) != "ok" for r in bad)
    flagged_good = sum(own_status(r) != "ok" for r in good)
    return {
        "bad_rmse_mm": BAD_RMSE_MM,
        "frames": len(frames), "bad": len(bad), "good": len(good),
        "detection_rate": flagged_bad / len(bad) if bad else float("nan"),
        "false_alarm_rate": flagged_good / len(good) if good else float("nan"),
        "bad_statuses": tally(bad), "good_statuses": tally(good),
    }


def confidence_figure(rows: list[dict[str, Any]], rates: dict[str, Any], path: Path) -> None:
    """True surface RMSE against the truth-free residual (in units of each frame's threshold),
    by the method's own status: the check works when bad frames sit right of 1 and good ones
    left."""
    fig, ax = plt.subplots(figsize=(7, 5))
    pts: dict[str, tuple[list[float], list[float]]] = {}
    for r in rows:
        if r.get("sweep") == "sun" or r.get("residual_median_px") is None:
            continue
        status = str(r.get("method_status") or r.get("frame_status")).split(":")[0]
        x = float(r["residual_median_px"]) / float(r["residual_threshold_px"])
        pts.setdefault(status, ([], []))
        pts[status][0].append(max(x, 1e-3))
        pts[status][1].append(float(r["wai_rmse_mm"]))
    for status, (x, y) in sorted(pts.items()):
        ax.plot(x, y, "o", ms=5, alpha=0.7, label=f"{status} ({len(x)})")
    ax.axvline(1.0, color="gray", ls="--", lw=1, label="threshold (status inconsistent)")
    ax.axhline(BAD_RMSE_MM, color="tab:red", ls=":", lw=1, label=f"RMSE {BAD_RMSE_MM:g} mm")
    ax.set(xscale="log", yscale="log", xlabel="median spot residual / threshold (truth-free)",
           ylabel="surface RMSE (mm, truth)",
           title=f"Detection {rates['detection_rate']:.0%} of {rates['bad']} bad frames, "
                 f"false alarms {rates['false_alarm_rate']:.0%} of {rates['good']} good")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def stability_figure(rows: list[dict], summary: dict[str, list[dict]], path: Path) -> None:
    """Fraction correct against Φ / Φ_max (eq. 35) for every frame, and per sweep the surface
    RMSE and the share of frames that ended ok."""
    fig, axes = plt.subplots(2, 5, figsize=(21, 8))
    ax = axes[0, 0]
    markers = dict(zip(SWEEPS, "osD^vP", strict=False))
    for sweep in ("wind", "amplitude", "spacing", "z_h"):  # the geometry sweeps eq. 35 covers
        pts = [r for r in rows if r.get("sweep") == sweep and r.get("phi_max_deg")
               and r.get("phi_deg") is not None]
        if not pts:
            continue
        x = [r["phi_deg"] / r["phi_max_deg"] for r in pts]
        y = [r.get("fraction_correct") or 0.0 for r in pts]
        ax.plot(x, y, markers[sweep], ms=5, alpha=0.7, label=sweep)
    ax.axvline(1.0, color="gray", ls="--", lw=1, label="eq. 35 bound")
    ax.set(xlabel="Φ / Φ_max (eq. 35)", ylabel="fraction of dots correctly matched",
           title="Correspondence against the bound")
    ax.set_xscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    labels = {"wind": "U (m/s)", "amplitude": "height scale at U = 1", "spacing": "D (px)",
              "z_h": "z_h (mm)", "noise": "signal at the reference's p99.9 (e-)",
              "exposure": "exposure (s)", "ambient": "sky radiance (object white = 1)",
              "turbidity": "scattering x", "sun": "sun zenith (deg)"}
    for ax, sweep in zip(axes.ravel()[1:], SWEEPS, strict=False):
        ent = summary[sweep]
        if not ent:
            ax.set_visible(False)
            continue
        x = [e["value"] for e in ent]
        ax.plot(x, [e["wai_rmse_mm"] for e in ent], "o-", label="surface RMSE (mm, ok frames)")
        ax.set_yscale("log")
        if sweep in ("noise", "turbidity"):
            ax.set_xscale("log")
        elif sweep == "ambient":
            ax.set_xscale("symlog", linthresh=1e-3)
        ax.set(xlabel=labels[sweep], title=sweep)
        fail = failure_point(ent, HARSHER[sweep])
        if fail is not None:
            ax.axvline(fail, color="k", ls="-.", lw=1, label=f"fails at {fail:g}")
        tw = ax.twinx()
        tw.plot(x, [e["ok"] / max(e["frames"], 1) for e in ent], "s--", color="tab:red",
                label="share of frames ok")
        if sweep != "sun":
            tw.plot(x, [e["fraction_correct"] for e in ent], "^:", color="tab:green",
                    label="fraction correct")
        tw.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = tw.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, fontsize=6)
    fig.tight_layout()
    save_figure(fig, path)


def report_markdown(
    summary: dict[str, list[dict]], command: str, rates: dict[str, Any] | None = None
) -> str:
    """Tables of the sweeps with the status of every frame, and the detection rates."""
    lines = ["# Stability: where the methods break", "", f"Command: `{command}`", "",
             "![stability](stability.png)", ""]
    if rates is not None:
        lines += [
            "## Knowing when a frame is wrong", "", "![confidence](confidence.png)", "",
            f"Of {rates['frames']} structured-light frames, {rates['bad']} are bad (failed, or "
            f"surface RMSE over {rates['bad_rmse_mm']:g} mm) and {rates['good']} good. "
            f"Flagged by a truth-free status: **{rates['detection_rate']:.1%}** of the bad "
            f"(statuses {rates['bad_statuses']}), **{rates['false_alarm_rate']:.1%}** of the "
            f"good (statuses {rates['good_statuses']}).", ""]
    lines += ["Status counts per value: `ok`; `wrong_labels` (over 5 % of kept correspondences "
             "wrong); `sparse` (under a quarter of the dots in view matched, their labels "
             "not pinned by the pattern); "
             "`inconsistent` (the surface does not reproduce the spots); "
             "`gauge_level` (integrability did not pin the level: the gauge's h0 was "
             "used, and scores are not averaged in); `uncertain_level` (the level's standard "
             "error over its bound: the shape is the data's, the level may be off); `failed` "
             "(the restoration refused the "
             "frame, e.g. too few features); "
             "`no_sun` (Alterman's sensor without a sun); `error` (an exception, in the table).",
             ""]
    for sweep, entries in summary.items():
        field = SWEEPS[sweep][0]
        fail = failure_point(entries, HARSHER[sweep])
        verdict = f"Fails at **{fail:g}**" if fail is not None else "No failure point"
        lines += [f"## {sweep} ({field})", "",
                  f"{verdict} (the first value, mildest to harshest, with under half the "
                  "frames ok).", "",
                  "| value | frames | statuses | fraction correct | Φ (deg) | Φ_max (deg) | "
                  "RMSE (mm) | SSIM |", "|" + " --- |" * 8]
        for e in entries:
            st = status_cell(e["statuses"])
            lines.append(
                f"| {e['value']:g} | {e['frames']} | {st} | {e['fraction_correct']:.3f} | "
                f"{e['phi_deg']:.2f} | {e['phi_max_deg']:.2f} | {e['wai_rmse_mm']:.3g} | "
                f"{e['restored_ssim']:.3f} |"
            )
        lines.append("")
    return "\n".join(lines)


def run_stability(config: str | Path, out: str | Path, seeds: int, quick: bool = False,
                  sweep: SweepOptions | None = None) -> dict[str, Any]:
    """Run the sweeps into ``out/stability.csv``; write the chart and the report.

    Parameters
    ----------
    config : str or Path
        The scene of the structured light: a packaged name or a TOML file.
    out : str or Path
        The output folder (made if missing).
    seeds : int
        Seeds 0..seeds-1 of every value.
    quick : bool
        2-3 values per sweep, 2 sea states of the coded sweep.
    sweep : SweepOptions or None
        Where and how the sweep's points run; None: :class:`SweepOptions`' defaults.

    Returns
    -------
    dict
        :func:`sweep_summary` of the sweep's rows.
    """
    out = output_folder(out)
    points = stability_points(config, scene_path("alterman"), list(range(seeds)), quick)
    rows = sweep_rows(points, evaluate_point, out / "stability.csv", sweep)
    summary = sweep_summary(rows)
    rates = detection_rates(rows)
    stability_figure(rows, summary, out / "stability.png")
    coded = coded_summary(rows)
    coded_figure(rows, out / "coded.png")
    confidence_figure(rows, rates, out / "confidence.png")
    command = sweep_command("stability", seeds, quick)
    text = report_markdown(summary, command, rates) + coded_markdown(coded)
    # stability.json is the sweep's run record; the summary and the rates go beside it.
    write_json(out / "stability_summary.json",
               {"sweeps": summary, "detection": rates, "coded": coded})
    publish(out / "stability.md", text)
    return summary


def coded_summary(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The "coded" sweep per pattern and sea state: frames, statuses, Φ / Φ_max, the share of
    kept labels that are correct (``label_precision``, over the frames that ran), the share of
    the dots in view correctly labelled, and the surface RMSE over the ok frames."""
    sel = [r for r in rows if r.get("sweep") == "coded"]
    out = []
    for key in sorted({(r["code"], r["wind_mps"], r["amplitude"]) for r in sel}):
        group = [r for r in sel if (r["code"], r["wind_mps"], r["amplitude"]) == key]
        good = [r for r in group if _ok(r)]

        def mean(name: str, rows_: list[dict]) -> float:
            vals = [float(r[name]) for r in rows_ if r.get(name) is not None]
            vals = [v for v in vals if np.isfinite(v)]
            return float(np.mean(vals)) if vals else float("nan")

        statuses: dict[str, int] = {}
        for r in group:
            st = str(r.get("frame_status") if r.get("status") == "ok" else r.get("status"))
            statuses[st.split(":")[0]] = statuses.get(st.split(":")[0], 0) + 1
        out.append({
            "code": key[0], "wind_mps": key[1], "amplitude": key[2], "frames": len(group),
            "ok": len(good), "statuses": statuses,
            "phi_ratio": mean("phi_deg", group) / mean("phi_max_deg", group),
            "label_precision": mean("label_precision", group),
            "fraction_correct": mean("fraction_correct", group),
            "wai_rmse_mm": mean("wai_rmse_mm", good),
            "wai_rmse_all_mm": mean("wai_rmse_mm", group),
        })
    return out


def coded_figure(rows: list[dict[str, Any]], path: Path) -> None:
    """Both patterns on the same sea states against Φ / Φ_max (eq. 35's bound at 1): the share
    of kept labels correct, the share of dots in view correctly labelled, and the surface RMSE
    (filled: frame ok, hollow: any other status)."""
    sel = [r for r in rows if r.get("sweep") == "coded" and r.get("phi_deg") is not None
           and r.get("phi_max_deg")]
    if not sel:
        return
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    style = {"none": ("o", "tab:blue", "plain grid (ordering)"),
             "colour": ("s", "tab:orange", "colour code (decoded)")}
    for code, (marker, colour, label) in style.items():
        pts = [r for r in sel if r.get("code") == code]
        if not pts:
            continue
        x = np.array([r["phi_deg"] / r["phi_max_deg"] for r in pts])
        ok = np.array([_ok(r) for r in pts])
        for ax, key in zip(axes, ("label_precision", "fraction_correct", "wai_rmse_mm"),
                           strict=True):
            y = np.array([np.nan if r.get(key) is None else float(r[key]) for r in pts])
            for mask, face in ((ok, colour), (~ok, "none")):
                ax.plot(x[mask], y[mask], marker, color=colour, mfc=face, ms=6, ls="none",
                        label=label if face != "none" else None)
    titles = ("share of kept labels correct", "dots in view correctly labelled",
              "surface RMSE (mm)")
    for ax, title in zip(axes, titles, strict=True):
        ax.axvline(1.0, color="gray", ls="--", lw=1, label="eq. 35 bound")
        ax.set(xlabel="Φ / Φ_max (eq. 35)", title=title)
        ax.grid(alpha=0.3)
    axes[0].axhline(0.99, color="tab:green", ls=":", lw=1, label="99 %")
    axes[2].set_yscale("log")
    axes[0].legend(fontsize=7)
    fig.suptitle("Coded pattern against the ordering limit (hollow: frame not ok)")
    fig.tight_layout()
    save_figure(fig, path)


def coded_markdown(coded: list[dict[str, Any]]) -> str:
    """The "coded" sweep's table."""
    if not coded:
        return ""
    lines = ["", "## coded: plain grid against the colour code", "", "![coded](coded.png)", "",
             "| pattern | U (m/s) | height scale | Φ/Φ_max | frames | statuses | kept labels "
             "correct | dots correct | RMSE ok (mm) | RMSE all (mm) |", "|" + " --- |" * 10]
    for e in coded:
        st = status_cell(e["statuses"])
        lines.append(
            f"| {e['code']} | {e['wind_mps']:g} | {e['amplitude']:g} | {e['phi_ratio']:.2f} | "
            f"{e['frames']} | {st} | {e['label_precision']:.4f} | {e['fraction_correct']:.3f} "
            f"| {e['wai_rmse_mm']:.3g} | {e['wai_rmse_all_mm']:.3g} |"
        )
    return "\n".join(lines) + "\n"
