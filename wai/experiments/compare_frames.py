"""``wai experiment compare``'s frames by condition: each per-frame method's statuses and
surface errors, frame by frame, against the same frames without the condition.

A case row of :mod:`wai.experiments.compare` carries its frames' statuses and surface RMSEs
(:func:`frame_columns`, two space-separated columns, so that they travel in the sweep's CSV
and Parquet tables). :func:`by_condition` tallies them per condition and method: how many
frames say ``ok``, and how many of those lie within :data:`ADDED_MM` of the same frame's RMSE
on the condition's baseline (the same waves, seed and frame seen without the effect:
``speckle`` for a condition seen through the speckle object, ``none`` otherwise). That is the
error budget's bar (:data:`wai.experiments.budget.ADDED_LIMIT_MM`) met frame by frame; a
condition that changes the waves (capillary, steeper) has no baseline of the same surface.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from wai.experiments.budget import ADDED_LIMIT_MM, OK_SHARE

__all__ = ["ADDED_MM", "by_condition", "condition_report", "frame_columns"]

ADDED_MM = ADDED_LIMIT_MM
"""Surface RMSE (mm) a frame may add to the same frame's on its condition's baseline and
still count as right under the condition (the error budget's bar)."""


def frame_columns(statuses: Sequence[str], rmse_mm: Sequence[float | None]) -> dict[str, str]:
    """A case's frames as two table columns: ``frame_statuses`` (the status of each frame)
    and ``frame_rmse_mm`` (its surface RMSE, ``nan`` where it has none), space-separated.

    Examples
    --------
    >>> frame_columns(["ok", "sparse"], [0.0123456, None])
    {'frame_statuses': 'ok sparse', 'frame_rmse_mm': '0.0123456 nan'}
    """
    return {"frame_statuses": " ".join(str(s) for s in statuses),
            "frame_rmse_mm": " ".join("nan" if v is None else f"{float(v):.6g}"
                                      for v in rmse_mm)}


def _frames(row: Mapping[str, Any]) -> tuple[list[str], np.ndarray] | None:
    """A row's frames (statuses, RMSEs (F,) mm); None where it has none (a video method, a
    failed case, a table written before the columns)."""
    statuses = row.get("frame_statuses")
    if not isinstance(statuses, str) or not statuses.strip():
        return None
    status = statuses.split()
    text = row.get("frame_rmse_mm")
    rmse = (np.array([float(v) for v in text.split()]) if isinstance(text, str) and text.strip()
            else np.full(len(status), np.nan))
    return (status, rmse) if rmse.size == len(status) else None


def _baseline(condition: str, conditions: Mapping[str, Mapping[str, Any]]) -> str | None:
    """The condition whose frames show the same surface without ``condition``'s effect: None
    for a baseline itself, an unknown condition, and one that changes the waves."""
    keys = conditions.get(condition)
    if keys is None or condition in ("none", "speckle"):
        return None
    if any(k.startswith("waves.") for k in keys):
        return None
    return "speckle" if keys.get("object.texture") == "speckle" else "none"


def _case_key(row: Mapping[str, Any], degradation: str) -> tuple:
    return (float(row["wind"]), int(float(row["seed"])), str(row.get("case_frames", "")),
            str(row["method"]), degradation)


def by_condition(rows: Sequence[Mapping[str, Any]],
                 conditions: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per condition and per-frame method with surfaces, summed over the cases: ``frames``,
    ``ok`` (frames that say ``ok``), ``ok_share``, ``median_rmse_mm`` (over its frames with a
    surface), and against the condition's baseline (``baseline``; None where it has none):
    ``compared`` (frames whose baseline frame has a surface) and ``ok_within`` (of those, the
    ``ok`` frames within :data:`ADDED_MM` of the baseline frame's RMSE).

    ``rows``: compare's case rows (``wind``, ``seed``, ``degradation``, ``method``,
    ``case_frames``, :func:`frame_columns`' columns); ``conditions``: the conditions' keys
    (:data:`wai.experiments.compare.DEGRADATIONS`).

    Examples
    --------
    >>> rows = [dict(wind=1, seed=0, method="m", degradation=d, case_frames=2,
    ...              **frame_columns(s, r))
    ...         for d, s, r in (("speckle", ["ok", "ok"], [0.01, 0.02]),
    ...                         ("rough", ["ok", "sparse"], [0.09, 0.5]))]
    >>> [(e["condition"], e["ok"], e["ok_within"]) for e in by_condition(
    ...     rows, {"speckle": {"object.texture": "speckle"},
    ...            "rough": {"water.roughness": 0.01, "object.texture": "speckle"}})]
    [('speckle', 2, None), ('rough', 1, 0)]
    """
    frames = {}
    for row in rows:
        got = _frames(row)
        if got is not None and np.isfinite(got[1]).any():
            frames[_case_key(row, str(row["degradation"]))] = got
    out: dict[tuple[str, str], dict[str, Any]] = {}
    for key, (status, rmse) in frames.items():
        method, condition = key[3], key[4]
        base_name = _baseline(condition, conditions)
        entry = out.setdefault((condition, method), {
            "condition": condition, "method": method, "baseline": base_name, "frames": 0,
            "ok": 0, "compared": 0 if base_name else None,
            "ok_within": 0 if base_name else None, "_rmse": []})
        ok = np.array([s == "ok" for s in status])
        entry["frames"] += len(status)
        entry["ok"] += int(ok.sum())
        entry["_rmse"].extend(rmse[np.isfinite(rmse)].tolist())
        base = frames.get(key[:4] + (base_name,)) if base_name else None
        if base is not None and base[1].size == rmse.size:
            have = np.isfinite(base[1])
            entry["compared"] += int(have.sum())
            within = ok & have & (rmse <= np.where(have, base[1], np.inf) + ADDED_MM)
            entry["ok_within"] += int(within.sum())
    result = []
    for entry in out.values():
        values = entry.pop("_rmse")
        entry["ok_share"] = entry["ok"] / entry["frames"] if entry["frames"] else None
        entry["median_rmse_mm"] = float(np.median(values)) if values else None
        result.append(entry)
    order = list(conditions)
    return sorted(result, key=lambda e: (order.index(e["condition"])
                                         if e["condition"] in order else len(order),
                                         e["method"]))


def condition_report(entries: Sequence[Mapping[str, Any]]) -> list[str]:
    """:func:`by_condition`'s entries as a Markdown section (no lines where there are none)."""
    if not entries:
        return []

    def f(v: Any, spec: str) -> str:
        return "-" if v is None else format(v, spec)

    lines = ["", "## Frames by condition", "",
             f"| condition | method | ok / frames | ok share | ok within baseline + "
             f"{ADDED_MM:g} mm | baseline | median RMSE mm |",
             "|" + " --- |" * 7]
    for e in entries:
        within = ("-" if e["ok_within"] is None
                  else f"{e['ok_within']} / {e['compared']}")
        lines.append(f"| {e['condition']} | {e['method']} | {e['ok']} / {e['frames']} | "
                     f"{f(e['ok_share'], '.0%')} | {within} | {e['baseline'] or '-'} | "
                     f"{f(e['median_rmse_mm'], '.4f')} |")
    lines += ["", f"Frame by frame: a frame is within the bar where it says `ok` and its surface "
              f"RMSE is at most {ADDED_MM:g} mm above the same frame's (same waves, seed and "
              "method) on its baseline, the condition without its effect; a condition that "
              "changes the waves has none. The error budget's reach asks "
              f"{OK_SHARE:.0%} of frames `ok`."]
    return lines
