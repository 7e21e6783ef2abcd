#!/usr/bin/env bash
# One device call of issue 10's GPU measurements still to run (docs/gpu.md, "Still to run"), each step in a time
# box. A session has 15 minutes of device time and a call at most 10, so the work is cut into parts of about 9
# minutes, one a session, in the order that gives the most per minute:
#
#   policy  a learned LeRobot policy evaluated by 16 workers against one acting on a batch of 16 envs, and through
#           a GPU policy server (`serve-policy`); trains its checkpoint first where /tmp/gpu-runs has none
#   record  H.264's stage bound and 16 writers; filming in one process; which decoder training uses there (the
#           SmolVLA-scratch run is kept in /tmp/gpu-runs for `policy`)
#   ppo     the few-env PPO run on the easiest condition, in a time box of LIMIT seconds (default 540); it resumes
#           a run carried in runs/ppo16 (unpack the previous session's $OUT/ppo16.tgz at the repository root and
#           carry runs/ppo16; leave all of benchmarks/results out of that call so that the kit and it fit 64 MiB)
#
#   here:   bash ../shared/gpu/make-kit.sh; then leave the study folders out of the call (docs/gpu.md)
#   device: `bash scripts/gpu-session.sh PART` with carry [".gpukit", ".whl"] (.whl: fast-simplification's wheel;
#           add "runs/ppo16" to resume PPO)
#   dry run here, every command at tiny sizes in .venv: SCALE=0 OUT=/tmp/out bash scripts/gpu-session.sh PART
#
# Results and logs are packed into $OUT/session.tgz after every step, so a call stopped at its limit keeps what
# the finished steps wrote: unpack it at the repository root (benchmarks/results/..., logs/).
set -uo pipefail
PART=${1:-policy}
case "$PART" in record|policy|ppo) ;; *) echo "unknown part '$PART'; allowed: record, policy, ppo" >&2; exit 2 ;; esac
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

RUNS=/tmp/gpu-runs  # training runs kept for a later part on the same warm machine
CKPT=$RUNS/smolvla-scratch/checkpoints/last/pretrained_model

if [ "$PART" = record ]; then
  rm -rf "$RUNS" /tmp/small
  # 1. H.264's stage bound beside AV1's 9.9 demos/s (record_speed_cuda.json), and 16 writers against 8 (2026-11-28:
  # 8 H.264 writers alone 13.7 demos/s; the 16 writers' spawn, each importing torch and LeRobot, outlasted a 180 s box).
  # The stage rows are written before the writer runs, and the file again after each.
  step record_stages_h264 "$(n 280 600)" python3 benchmarks/record_speed.py --no-end-to-end --workers "$(n 16 2)" \
    --writers $(n "8 16" 2) --episodes "$(n 8 2)" --num-objects 5 --vcodec h264 \
    --out "$R/record_speed_cuda_h264.json"
  # 2. Filming in one process, against 2.59 s an episode in each of 16 (eval_speed_scripted_cuda.json, 2026-11-28).
  step eval_filmed_alone "$(n 60 600)" python3 benchmarks/eval_speed.py --workers 1 --num-envs 1 \
    --episodes "$(n 16 2)" --filmed "$(n 16 2)" --out "$R/eval_speed_scripted_alone_cuda.json"
  # 3. Which decoder LeRobot's training uses there (`vla-ladder train` restarts itself for torchcodec on PyAV's
  # FFmpeg; train_speed.py's rows now say which), on a small H.264 recording; the run is kept for `policy`.
  step record_small "$(n 100 600)" python3 -m vla_ladder.cli record --out /tmp/small --episodes "$(n 96 4)" \
    --workers "$(n 16 2)" --num-objects 5 --vcodec h264 --no-rebuild-scenes
  cp benchmarks/results/train_speed_cuda.json "$R/" 2>/dev/null  # its rows of other models and settings stay
  step train_speed "$(n 120 900)" python3 benchmarks/train_speed.py --dataset /tmp/small --models smolvla-scratch \
    --device "$(n cuda cpu)" --batch-size "$(n 64 2)" --steps "$(n 100 4)" --log-freq "$(n 20 1)" \
    --num-workers "$(n 10 0)" --keep "$RUNS" --out "$R/train_speed_cuda.json"
fi

if [ "$PART" = policy ]; then
  if [ ! -f "$CKPT/config.json" ]; then  # a fresh machine: a small recording and 100 training steps give one
    rm -rf "$RUNS" /tmp/small
    step record_small "$(n 100 600)" python3 -m vla_ladder.cli record --out /tmp/small --episodes "$(n 96 4)" \
      --workers "$(n 16 2)" --num-objects 5 --vcodec h264 --no-rebuild-scenes
    step train_small "$(n 110 900)" python3 benchmarks/train_speed.py --dataset /tmp/small --models smolvla-scratch \
      --device "$(n cuda cpu)" --batch-size "$(n 64 2)" --steps "$(n 100 4)" --log-freq "$(n 20 1)" \
      --num-workers "$(n 10 0)" --keep "$RUNS" --out "$W/logs/train_speed_small.json"
  fi
  SPEC="lerobot:$CKPT?device=$(n cuda cpu)"
  # 1. 16 policy copies (one a worker process) against one policy acting on a batch of 16 envs; 1 worker as the base.
  step eval_learned "$(n 200 900)" python3 benchmarks/eval_speed.py --policy "$SPEC" --workers 1 "$(n 16 2)" \
    --num-envs "$(n 16 2)" --episodes "$(n 64 4)" --filmed 0 --out "$R/eval_speed_cuda.json"
  # 2. The same through one GPU policy server that batches what arrives together: 16 worker clients, then one client
  # whose 16 envs send a pipelined window a chunk.
  python3 -m vla_ladder.cli serve-policy --policy "$SPEC" --port 8765 > "$W/logs/serve_policy.log" 2>&1 &
  for _ in $(seq 120); do
    python3 -c "import socket; socket.create_connection(('127.0.0.1', 8765), 1)" 2> /dev/null && break
    sleep 1
  done
  step eval_remote "$(n 120 900)" python3 benchmarks/eval_speed.py --policy remote:ws://127.0.0.1:8765 \
    --workers "$(n 16 2)" --num-envs "$(n 16 2)" --episodes "$(n 64 4)" --filmed 0 \
    --out "$R/eval_speed_remote_cuda.json"
  pkill -f 'vla_ladder.cli serve-policy'
  # 3. The protocol's share of a chunk, and 1/4/16-env windows, on the GPU.
  step remote_overhead "$(n 60 600)" python3 benchmarks/remote_overhead.py "$CKPT" --device "$(n cuda cpu)" \
    --out "$R/remote_overhead_cuda.json"
fi

if [ "$PART" = ppo ]; then
  # The settings with which few envs learn the easiest condition (docs/ppo.md), 16 envs x 50 steps a batch; a run
  # carried in runs/ppo16 is resumed. Stopped at LIMIT, it keeps its last checkpoint (every 32k steps).
  resume=()
  [ -f runs/ppo16/state.json ] && resume=(--resume)
  step ppo "${LIMIT:-$(n 540 300)}" python3 -m vla_ladder.cli train-expert --out runs/ppo16 "${resume[@]}" \
    --sim-backend physx_cpu --num-envs "$(n 16 2)" --num-steps "$(n 50 20)" --learning-rate 3e-4 --ent-coef 0 \
    --num-minibatches 8 --update-epochs 8 --regimes small_jitter --num-objects 1 --total-timesteps 600000 \
    --eval-freq "$(n 40 2)" --eval-episodes "$(n 32 2)" --keep-checkpoints 1 --no-progress
  name=$(n physx_cpu16_few_cuda dry_run)
  step ppo_curve 60 python3 benchmarks/ppo_curve.py runs/ppo16 --name "$name" --out "$R/ppo_curve_$name.json"
  # What the next session carries to resume (about 3.8 MB: the kit leaves the tree and the carry about 4 MiB), and
  # apart, what it does not need: the TensorBoard logs (SPS against rollout SPS: the updates' share) and the best model.
  ck=$(python3 -c "import json; print(json.load(open('runs/ppo16/state.json'))['checkpoint'])")
  tar czf "$OUT/ppo16.tgz" runs/ppo16/config.json runs/ppo16/state.json runs/ppo16/evals.json "runs/ppo16/$ck"
  tar czf "$OUT/ppo16_logs.tgz" runs/ppo16/tb runs/ppo16/checkpoints/best 2> /dev/null
  ls -l "$OUT"/ppo16*.tgz
fi
echo "=== all done at +$(( $(date +%s) - T0 )) s"
