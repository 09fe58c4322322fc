#!/usr/bin/env bash
# The pictures in README.md and docs/: made by `wai demo` (the paper's configuration, seed 0)
# and copied into docs/images/. Rerun after a change that alters them.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/wai demo --out renders/readme --quiet
mkdir -p docs/images
for f in rig.png pattern_flat_vs_wavy.png view_flat_vs_wavy.png fig10_surface.png; do
  cp "renders/readme/$f" docs/images/
done
for f in distorted_vs_restored.png error_map.png profile.png; do
  cp "renders/readme/restore/$f" docs/images/
done
.venv/bin/wai dataset --frames 4 --size 160x120 --spp 1 --seed 7 --out renders/readme_dataset --quiet
cp renders/readme_dataset/preview.png docs/images/dataset_preview.png
echo "readme images: docs/images/"
