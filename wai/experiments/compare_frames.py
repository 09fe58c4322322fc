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
:func:`rescues` reads every method on the frames where the structured light is weak (not
``ok``, or more than :data:`RIGHT_MM` off): how many of them it restores ``ok`` within it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from wai.experiments.budget import ADDED_LIMIT_MM, OK_SHARE

__all__ = ["ADDED_MM", "REFERENCE_METHOD", "RIGHT_MM", "WRONG_OK_MM", "by_condition",
           "condition_report", "frame_columns", "rescue_report", "rescues"]

ADDED_MM = ADDED_LIMIT_MM
"""Surface RMSE (mm) a frame may add to the same frame's on its condition's baseline and
still count as right under the condition (the error budget's bar)."""
RIGHT_MM = 0.1
"""Surface RMSE (mm) within which a frame counts as right: the structured light's frames
past it (or not ``ok``) are its weak frames, and another method's ``ok`` frame within it
there is one it rescues."""
WRONG_OK_MM = 0.25
"""A frame that says ``ok`` with its surface further than this from the truth (RMSE, mm) is
counted in ``frames_ok_wrong``: a status that should have flagged it (a method is never to say
``ok`` there)."""
REFERENCE_METHOD = "structured-light"
"""The method whose weak frames :func:`rescues` counts (the paper's)."""


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


def _names(rows: Sequence[Mapping[str, Any]]) -> dict[str, str]:
    """Each method spec's name as the methods call themselves (``method_name``; the spec
    where a row has none), as compare's summary table shows them."""
    names: dict[str, str] = {}
    for row in rows:
        spec, name = str(row["method"]), row.get("method_name")
        if isinstance(name, str) and name:
            names.setdefault(spec, name)
    return names


def _case_frames(rows: Sequence[Mapping[str, Any]]
                 ) -> dict[tuple, tuple[list[str], np.ndarray]]:
    """Each row's frames (:func:`_frames`) by its case and method (:func:`_case_key`)."""
    out = {}
    for row in rows:
        got = _frames(row)
        if got is not None:
            out[_case_key(row, str(row["degradation"]))] = got
    return out


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
    names = _names(rows)
    frames = {k: v for k, v in _case_frames(rows).items() if np.isfinite(v[1]).any()}
    out: dict[tuple[str, str], dict[str, Any]] = {}
    for key, (status, rmse) in frames.items():
        method, condition = key[3], key[4]
        base_name = _baseline(condition, conditions)
        entry = out.setdefault((condition, method), {
            "condition": condition, "method": names.get(method, method),
            "baseline": base_name, "frames": 0,
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


def rescues(rows: Sequence[Mapping[str, Any]],
            reference: str = REFERENCE_METHOD) -> list[dict[str, Any]]:
    """Per condition and method, on the frames where ``reference`` is weak (not ``ok``, or
    its surface more than :data:`RIGHT_MM` off, or none): ``weak`` (those frames, each
    matched to the same case and frame of the method), ``rescued`` (of them, the method's
    ``ok`` frames within :data:`RIGHT_MM`), ``rescued_share`` and ``ok_wrong`` (its ``ok``
    frames more than :data:`WRONG_OK_MM` off); then each method's totals over the
    conditions (condition ``all``). Conditions where ``reference`` has no weak frame are
    left out.

    ``rows``: compare's case rows, as for :func:`by_condition`.

    Examples
    --------
    >>> rows = [dict(wind=1, seed=0, method=m, degradation="rough", case_frames=3,
    ...              **frame_columns(s, r))
    ...         for m, s, r in (("structured-light", ["ok", "sparse", "ok"], [0.01, 2.0, 0.3]),
    ...                         ("mine", ["ok", "ok", "ok"], [0.01, 0.05, 0.4]))]
    >>> [(e["condition"], e["weak"], e["rescued"], e["ok_wrong"]) for e in rescues(rows)]
    [('rough', 2, 1, 1), ('all', 2, 1, 1)]
    """
    frames, names = _case_frames(rows), _names(rows)
    out: dict[tuple[str, str], dict[str, Any]] = {}
    for key, (status, rmse) in frames.items():
        method, condition = key[3], key[4]
        base = frames.get(key[:3] + (reference, condition))
        if method == reference or base is None or len(base[0]) != len(status):
            continue
        base_right = np.array([s == "ok" for s in base[0]]) & (base[1] <= RIGHT_MM)
        weak = ~base_right
        if not weak.any():
            continue
        ok = np.array([s == "ok" for s in status])
        for name in (condition, "all"):
            entry = out.setdefault((name, method), {"condition": name,
                                                    "method": names.get(method, method),
                                                    "weak": 0, "rescued": 0, "ok_wrong": 0})
            entry["weak"] += int(weak.sum())
            entry["rescued"] += int((weak & ok & (rmse <= RIGHT_MM)).sum())
            entry["ok_wrong"] += int((weak & ok & (rmse > WRONG_OK_MM)).sum())
    for entry in out.values():
        entry["rescued_share"] = entry["rescued"] / entry["weak"]
    return sorted(out.values(), key=lambda e: (e["condition"] == "all", e["condition"],
                                               e["method"]))


def rescue_report(entries: Sequence[Mapping[str, Any]],
                  reference: str = REFERENCE_METHOD) -> list[str]:
    """:func:`rescues`' entries as a Markdown section (no lines where there are none)."""
    if not entries:
        return []
    lines = ["", f"## Where {reference} is weak", "",
             f"| condition | method | weak frames | `ok` within {RIGHT_MM:g} mm | share | "
             f"`ok` past {WRONG_OK_MM:g} mm |", "|" + " --- |" * 6]
    for e in entries:
        lines.append(f"| {e['condition']} | {e['method']} | {e['weak']} | {e['rescued']} | "
                     f"{e['rescued_share']:.0%} | {e['ok_wrong']} |")
    lines += ["", f"Weak frames: those {reference} does not call `ok`, or calls `ok` with a "
              f"surface more than {RIGHT_MM:g} mm RMSE from the truth; each method is read "
              "on the same frames of the same cases. `all`: every condition together."]
    return lines
