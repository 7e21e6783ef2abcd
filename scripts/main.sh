#!/usr/bin/env bash
# The main job on embedded defaults: set up (idempotent), sample the placement ladder and draw the
# paper's Figure 1, render both cameras for one episode per regime. Outputs go to outputs/ (or $1).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1 MS_SKIP_ASSET_DOWNLOAD_PROMPT=1 WANDB_MODE=disabled
OUT=${1:-outputs}
mkdir -p "$OUT"
.venv/bin/vla-ladder placements --regime all --n 500 --seed 0 --json "$OUT/placements.json" --plot "$OUT/placements.png"
.venv/bin/vla-ladder render --regime all --seed 0 --out "$OUT/renders"
echo "done: $OUT/placements.png, $OUT/renders/"
