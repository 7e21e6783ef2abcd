#!/usr/bin/env bash
# One device call: issue 10's GPU measurements still to run (docs/gpu.md), each step time-boxed.
# Results and logs go to W and are re-packed into $OUT/session.tgz after every step (a killed call keeps them).
cd "$(dirname "$0")/.."
T0=$(date +%s)
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
W=/tmp/w; rm -rf $W; mkdir -p $W/logs $W/results
SCALE=${SCALE:-1}   # SCALE=0: a local dry run of every command at tiny sizes, in .venv
if [ "$SCALE" = 1 ]; then
  source .gpukit/prefix.sh > $W/logs/prefix.log 2>&1 || { cat $W/logs/prefix.log; exit 1; }
  python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl >> $W/logs/prefix.log 2>&1
else
  source .venv/bin/activate
fi
n() { [ "$SCALE" = 1 ] && echo "$1" || echo "$2"; }
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; nproc; free -g; lscpu | grep 'Model name'; } > $W/logs/machine.txt 2>&1
cat $W/logs/machine.txt
pack() { tar czf $OUT/.session.tgz -C $W logs results && mv $OUT/.session.tgz $OUT/session.tgz; }
step() {  # step NAME TIMEOUT_S CMD...
  local name=$1 t=$2; shift 2
  echo "=== $name start at +$(( $(date +%s) - T0 )) s"
  timeout -s INT -k 15 "$t" "$@" > $W/logs/$name.log 2>&1
  local rc=$?
  pkill -9 -f 'vla_ladder|benchmarks/' 2>/dev/null; sleep 1
  echo "=== $name rc=$rc at +$(( $(date +%s) - T0 )) s"
  grep -v 'it/s\]\|s/it\]' $W/logs/$name.log | tail -n 14
  pack
}
step record_speed $(n 220 400) python3 benchmarks/record_speed.py --workers $(n 16 2) --writers $(n 8 2) \
  --episodes $(n 128 4) --stage-episodes $(n 8 2) --num-objects 5 --encoder-threads 1 0 --out $W/results/record_speed_cuda.json
step record_h264_norebuild $(n 80 300) python3 -m vla_ladder.cli record --out /tmp/rec-h264 --episodes $(n 160 4) \
  --workers $(n 16 2) --writers $(n 8 2) --encoder-threads 1 --vcodec h264 --no-rebuild-scenes --num-objects 5
step eval_speed_scripted $(n 150 400) python3 benchmarks/eval_speed.py --workers $(n 16 2) --num-envs 1 \
  --episodes $(n 64 4) --filmed $(n 64 2) --out $W/results/eval_speed_scripted_cuda.json
cp benchmarks/results/policy_latency_$(n cuda cpu).json $W/results/policy_latency.json 2>/dev/null
step policy_latency_amp $(n 110 300) bash -c "python3 benchmarks/policy_latency.py $(n --full '') --device $(n cuda cpu) \
  --use-amp --batch 1 --out $W/results/policy_latency.json && python3 benchmarks/policy_latency.py $(n --full '') \
  --device $(n cuda cpu) --use-amp --batch 16 --out $W/results/policy_latency.json"
echo "=== all done at +$(( $(date +%s) - T0 )) s"
