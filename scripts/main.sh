#!/usr/bin/env bash
# The main job on embedded defaults (CPU, a few minutes on 2 cores): set up (idempotent), then
#   1. sample the placement ladder and draw the paper's Figure 1,
#   2. render both cameras of one episode per regime,
#   3. run the spatial ladder for the reference policies (scripted expert, nearest, layout-prior, random),
#      20 seeded episodes per regime, and write the HTML report.
# Outputs go to outputs/ (or the directory given as $1); the last line is the report's path.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1 MS_SKIP_ASSET_DOWNLOAD_PROMPT=1 WANDB_MODE=disabled
OUT=${1:-outputs}
EPISODES=${VLA_LADDER_EPISODES:-20}
mkdir -p "$OUT"
.venv/bin/vla-ladder placements --regimes all --n 500 --first-seed 0 --json "$OUT/placements.json" \
  --plot "$OUT/placements.png"
.venv/bin/vla-ladder render --regimes all --seed 0 --out "$OUT/renders"
.venv/bin/vla-ladder experiment ladder --policy scripted nearest layout-prior random \
  --episodes "$EPISODES" --videos 1 --out "$OUT/ladder"
echo "report: $(cd "$OUT/ladder" && pwd)/report.html"
