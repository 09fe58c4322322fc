"""Scripts to start from, installed with the package.

Run one with ``python -m wai.examples NAME [--quick] [--out DIR]`` (``python -m wai.examples``
lists them), or as a file from a checkout (``python examples/NAME.py``: ``examples/`` links
here). Each runs with ``--quick`` in seconds; the ones that write files write them to
``--out``, by default a fresh temporary folder whose path they print.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

NAMES = ("render_and_restore", "restore_own_captures", "custom_surface_both_methods",
         "small_sweep", "plugin_method")
"""The examples, simplest first."""


def output_folder(out: Path | None, name: str) -> Path:
    """``out``, created, or a fresh temporary folder for example ``name`` (never the current
    folder, which may be anything)."""
    if out is None:
        return Path(tempfile.mkdtemp(prefix=f"wai-{name}-"))
    out.mkdir(parents=True, exist_ok=True)
    return out
