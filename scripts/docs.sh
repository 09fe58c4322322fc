#!/usr/bin/env bash
# Build the documentation site into docs/_build/html: the user guide (docs/*.md), the API
# reference of the four packages, and the gallery (docs/gallery/*.py, run at build time: about
# a minute). Warnings are errors. Then check what the site must hold (scripts/check_docs.py).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/python -c 'import sphinx, myst_parser, sphinx_gallery, furo' 2>/dev/null \
  || .venv/bin/python -m pip install -q -e '.[docs]'
.venv/bin/python -m sphinx -W --keep-going -q -b html docs docs/_build/html "$@"
.venv/bin/python scripts/check_docs.py docs/_build/html
echo "docs: docs/_build/html/index.html"
