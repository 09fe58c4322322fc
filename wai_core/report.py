"""A run's report: ``index.html`` in every output folder, gathering what the run made.

One self-contained page (no server, no script, no file from elsewhere): the command that made
the folder, every figure (``*.png`` of the folder and of the folders it holds, by relative
links, each with its name as caption), its Markdown report as written, the run's summary (the
scalar values of its record, ``metrics.json``, ``*_summary.json``, ``bench.json`` or
``scene.json``), and a list of its other files. Opening the file in a browser is all it
takes.

Examples
--------
>>> import tempfile, pathlib, json
>>> folder = pathlib.Path(tempfile.mkdtemp())
>>> _ = (folder / "metrics.json").write_text(json.dumps({"status": "ok", "rmse_mm": 0.02}))
>>> page = write_report(folder, "wai restore DIR")
>>> "rmse_mm" in page.read_text() and page.name
'index.html'
"""

from __future__ import annotations

import html
import json
import math
import shlex
import sys
from pathlib import Path
from typing import Any

from wai_core.io import atomic_write_bytes

__all__ = ["REPORT_FILE", "command_line", "write_report"]

REPORT_FILE = "index.html"

_RECORDS = ("metrics.json", "bench.json", "scene.json")
"""The run's record, first found first: its scalar values make the summary table (with any
``*_summary.json``)."""

_MAX_FIGURES = 120
_MAX_ROWS = 80

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.4em; } h2 { font-size: 1.15em; margin-top: 1.6em; }
code, pre { background: #f4f4f4; } pre { padding: 0.8em; overflow-x: auto; }
table { border-collapse: collapse; } td, th { padding: 2px 10px; border-bottom: 1px solid #ddd;
  text-align: left; font-size: 0.92em; }
figure { display: inline-block; margin: 0.5em; vertical-align: top; }
figure img { max-width: 520px; max-height: 420px; border: 1px solid #ccc; }
figcaption { font-size: 0.85em; color: #555; }
"""


def command_line(argv: list[str] | None = None) -> str:
    """The command as typed (``wai`` and its arguments, shell-quoted)."""
    argv = list(sys.argv if argv is None else argv)
    if argv and Path(argv[0]).name in ("wai", "__main__.py", "cli.py"):
        argv[0] = "wai"
    return " ".join(shlex.quote(a) for a in argv)


def _scalars(record: Any, prefix: str = "", depth: int = 0) -> list[tuple[str, str]]:
    """The scalar values of a JSON record, nested keys joined by dots (two levels deep)."""
    rows: list[tuple[str, str]] = []
    if not isinstance(record, dict):
        return rows
    for key, value in record.items():
        name = f"{prefix}{key}"
        if isinstance(value, bool) or value is None or isinstance(value, str):
            if isinstance(value, str) and len(value) > 200:
                continue
            rows.append((name, str(value)))
        elif isinstance(value, int | float):
            text = f"{value:.6g}" if isinstance(value, float) and math.isfinite(value) else str(
                value)
            rows.append((name, text))
        elif isinstance(value, dict) and depth < 1:
            rows += _scalars(value, name + ".", depth + 1)
    return rows


def _summary(folder: Path) -> tuple[str | None, list[tuple[str, str]]]:
    records = [folder / n for n in _RECORDS if (folder / n).is_file()][:1]
    records += sorted(folder.glob("*_summary.json"))
    for path in records:
        try:
            rows = _scalars(json.loads(path.read_text()))
        except (OSError, ValueError):
            continue
        if rows:
            return path.name, rows[:_MAX_ROWS]
    return None, []


def _shown(path: Path, folder: Path) -> bool:
    """Whether ``path`` in ``folder`` belongs on the page: no part of it hidden (a run's
    temporary files, the output marker)."""
    return not any(part.startswith(".") for part in path.relative_to(folder).parts)


def _figures(folder: Path) -> list[Path]:
    found = sorted(folder.glob("*.png")) + sorted(folder.glob("*/*.png"))
    return [p for p in found if _shown(p, folder)][:_MAX_FIGURES]


def write_report(folder: str | Path, command: str | None = None,
                 title: str | None = None) -> Path:
    """Write ``folder/index.html`` (atomically) gathering the folder's run; its path.

    Parameters
    ----------
    folder : str or Path
        The output folder, complete (its figures and records written).
    command : str, optional
        The command that made it (default: this process's, :func:`command_line`).
    title : str, optional
        The page's heading (default: the folder's name).
    """
    folder = Path(folder)
    command = command_line() if command is None else command
    esc = html.escape
    parts = [f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
             f"<title>{esc(title or folder.name)}</title><style>{_STYLE}</style></head><body>",
             f"<h1>{esc(title or folder.name)}</h1>",
             f"<p>Made by <code>{esc(command)}</code></p>"]
    figures = _figures(folder)
    if figures:
        parts.append("<h2>Figures</h2>")
        for fig in figures:
            rel = fig.relative_to(folder).as_posix()
            parts.append(f"<figure><a href=\"{esc(rel)}\"><img src=\"{esc(rel)}\" "
                         f"alt=\"{esc(rel)}\"></a>"
                         f"<figcaption>{esc(rel)}</figcaption></figure>")
    for md in sorted(folder.glob("*.md")):
        parts.append(f"<h2>{esc(md.name)}</h2><pre>{esc(md.read_text(errors='replace'))}</pre>")
    source, rows = _summary(folder)
    if rows:
        parts.append(f"<details open><summary><b>Summary</b> ({esc(source or '')}: its "
                     f"values)</summary><table>")
        parts += [f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in rows]
        parts.append("</table></details>")
    page = folder / REPORT_FILE
    others = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                    if p.is_file() and p.suffix != ".png" and p != page and _shown(p, folder))
    nested = [o for o in others if o.endswith("/" + REPORT_FILE)]
    if nested:
        parts.append("<h2>Reports inside</h2><ul>")
        parts += [f"<li><a href=\"{esc(o)}\">{esc(o)}</a></li>" for o in nested]
        parts.append("</ul>")
    if others:
        parts.append("<h2>Files</h2><ul>")
        parts += [f"<li><a href=\"{esc(o)}\">{esc(o)}</a></li>" for o in others[:400]]
        parts.append("</ul>")
    parts.append("</body></html>\n")
    atomic_write_bytes(page, "\n".join(parts).encode())
    return page
