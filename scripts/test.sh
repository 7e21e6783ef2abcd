#!/usr/bin/env bash
# Set up (idempotent) and run the test suite. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1 MS_SKIP_ASSET_DOWNLOAD_PROMPT=1 WANDB_MODE=disabled
exec .venv/bin/python -m pytest "$@"
