#!/usr/bin/env bash
# One device call of issue 10's GPU measurements still to run (docs/gpu.md, "Still to run"), each step in a time
# box, in the order that gives the most per minute. A session has 15 minutes of device time and a call at most 10:
# the steps below take about 9.
#
#   here:   bash ../shared/gpu/make-kit.sh; then leave the study folders out of the call (docs/gpu.md)
#   device: run `bash scripts/gpu-session.sh` with carry [".gpukit", ".whl"] (.whl: fast-simplification's wheel)
#   dry run here, every command at tiny sizes in .venv: SCALE=0 OUT=/tmp/out bash scripts/gpu-session.sh
#
# Results and logs are packed into $OUT/session.tgz after every step, so a call stopped at its limit keeps what
# the finished steps wrote: unpack it at the repository root (benchmarks/results/..., logs/).
set -uo pipefail
cd "$(dirname "$0")/.."
T0=$(date +%s)
OUT=${OUT:-/tmp/out}
W=$(mktemp -d)
mkdir -p "$OUT" "$W/logs" "$W/benchmarks/results"
SCALE=${SCALE:-1}
if [ "$SCALE" = 1 ]; then
  source .gpukit/prefix.sh > "$W/logs/prefix.log" 2>&1 || { cat "$W/logs/prefix.log"; exit 1; }
  if ls .whl/*.whl > /dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl >> "$W/logs/prefix.log" 2>&1
  fi
else
  source .venv/bin/activate
  export HF_HUB_OFFLINE=1 MS_SKIP_ASSET_DOWNLOAD_PROMPT=1 PYTHONUNBUFFERED=1
fi
n() { [ "$SCALE" = 1 ] && echo "$1" || echo "$2"; }  # full size, or the dry run's
R=$W/benchmarks/results
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; nproc; lscpu | grep 'Model name'; } \
  > "$W/logs/machine.txt" 2>&1
cat "$W/logs/machine.txt"

pack() { tar czf "$OUT/.session.tgz" -C "$W" logs benchmarks && mv "$OUT/.session.tgz" "$OUT/session.tgz"; }
step() {  # step NAME SECONDS COMMAND...: its output in logs/NAME.log, its tail here
  local name=$1 limit=$2 rc
  shift 2
  echo "=== $name (at most ${limit} s) from +$(( $(date +%s) - T0 )) s"
  timeout -s INT -k 15 "$limit" "$@" > "$W/logs/$name.log" 2>&1
  rc=$?
  # A stopped step's worker processes would keep their cores from the next one.
  pkill -9 -f 'vla_ladder.cli|benchmarks/' 2>/dev/null
  sleep 1
  echo "=== $name rc=$rc at +$(( $(date +%s) - T0 )) s"
  grep -v 'it/s\]\|s/it\]' "$W/logs/$name.log" | tail -n 12
  pack
}

# 1. H.264's stage bound beside AV1's 9.9 demos/s (record_speed_cuda.json), and 16 writers against 8.
step record_stages_h264 "$(n 200 600)" python3 benchmarks/record_speed.py --no-end-to-end --workers "$(n 16 2)" \
  --writers $(n "8 16" 2) --episodes "$(n 8 2)" --num-objects 5 --vcodec h264 \
  --out "$R/record_speed_cuda_h264.json"
# 2. Filming apart from encoding (one phase in eval_speed_scripted_cuda.json), with the veryfast preset.
step eval_filmed "$(n 120 600)" python3 benchmarks/eval_speed.py --workers "$(n 16 2)" --num-envs 1 \
  --episodes "$(n 64 4)" --filmed "$(n 64 2)" --out "$R/eval_speed_scripted_cuda.json"
# 3. A long recording with record's defaults (AV1, scenes rebuilt): its steady rate, which 128 demos could not show.
step record_long "$(n 180 600)" python3 -m vla_ladder.cli record --out /tmp/long --episodes "$(n 800 4)" \
  --workers "$(n 16 2)" --num-objects 5
# 4. Training speed on that recording (torchcodec on PyAV's FFmpeg now; the H100's figures had PyAV decoding).
cp benchmarks/results/train_speed_cuda.json "$R/" 2>/dev/null  # its rows of other models and settings stay
step train_speed "$(n 150 900)" python3 benchmarks/train_speed.py --dataset /tmp/long --models smolvla-scratch act \
  --device "$(n cuda cpu)" --batch-size "$(n 64 2)" --steps "$(n 100 4)" --log-freq "$(n 20 1)" \
  --num-workers "$(n 10 0)" --out "$R/train_speed_cuda.json"
echo "=== all done at +$(( $(date +%s) - T0 )) s"
