"""``python -m wai.examples [NAME [ARGS...]]``: list the examples, or run one with ARGS."""

from __future__ import annotations

import ast
import importlib
import sys
from pathlib import Path

from wai.examples import NAMES

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    """List the examples (no NAME) or run example NAME with the arguments after it; returns
    the exit code."""
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m wai.examples NAME [--help] [ARGS...]\n\nexamples:")
        for name in NAMES:
            # Read, not imported: listing should not load the renderer.
            doc = ast.get_docstring(ast.parse((HERE / f"{name}.py").read_text())) or ""
            print(f"  {name:28s} {doc.splitlines()[0]}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in NAMES:
        print(f"python -m wai.examples: no example {name!r} (one of {', '.join(NAMES)})",
              file=sys.stderr)
        return 2
    module = importlib.import_module(f"wai.examples.{name}")
    sys.argv = [f"python -m wai.examples {name}", *rest]  # the example's usage line
    module.main()
    return 0


if __name__ == "__main__":
    sys.exit(main())
