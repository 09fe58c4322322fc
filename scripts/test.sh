#!/usr/bin/env bash
# The test suite: set up, lint, then pytest. Exits non-zero when any test fails.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check .
# The slow tier (whole experiments, the example scripts, renders against stock Mitsuba at
# scale) runs with --all, as CI does; without it the suite keeps to about 3 minutes.
tier=(-m "not slow")
if [[ "${1:-}" == "--all" ]]; then
    tier=()
    shift
fi
# Two processes, whole files each (module fixtures render once per file).
.venv/bin/python -m pytest -q -n 2 --dist loadfile "${tier[@]}" "$@"
