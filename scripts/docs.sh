#!/usr/bin/env bash
# Build the documentation site into docs/_build/html: the user guide (docs/*.md), the API
# reference of the packages, and the gallery (docs/gallery/*.py, run at build time: about a
# minute). Warnings are errors. Then check what the site must hold (scripts/check_docs.py), and
# load every kind of run's index.html in headless Chromium (scripts/check_reports.py; the
# chromium package is installed when missing, as scripts/setup.sh installs libLLVM).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/python -c 'import sphinx, myst_parser, sphinx_gallery, furo' 2>/dev/null \
  || .venv/bin/python -m pip install -q -e '.[docs]'
.venv/bin/python -m sphinx -W --keep-going -q -b html docs docs/_build/html "$@"
.venv/bin/python scripts/check_docs.py docs/_build/html
if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
  echo "docs: installing chromium (the pages' check)"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null
fi
.venv/bin/python scripts/check_reports.py
echo "docs: docs/_build/html/index.html"
