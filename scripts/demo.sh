#!/usr/bin/env bash
# The demo: set up, render the paper's configuration, restore it, write figures and scores under
# renders/demo/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/wai demo --out renders/demo "$@"
