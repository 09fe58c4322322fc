#!/usr/bin/env bash
# The test suite: set up, lint, then pytest. Exits non-zero when any test fails.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check .
# Two processes, whole files each (module fixtures render once per file).
.venv/bin/python -m pytest -q -n 2 --dist loadfile "$@"
