# The two device calls of 2026-11-28 (H200, 16 cores; one machine start; 604 s and 94 s of the 900 s held).
# Call 1, carry [".gpukit", ".whl"], timeout 600 s: `bash scripts/gpu-session.sh record` (404d281 with its step boxes
# cut to 180/100/170/120 s), that is, after `source .gpukit/prefix.sh` and the fast-simplification wheel:
timeout -s INT -k 15 180 python3 benchmarks/record_speed.py --no-end-to-end --workers 16 --writers 8 16 --episodes 8 \
  --num-objects 5 --vcodec h264 --out "$R/record_speed_cuda_h264.json"              # stopped by its box: no file
timeout -s INT -k 15 100 python3 benchmarks/eval_speed.py --workers 16 --num-envs 1 --episodes 64 --filmed 64 \
  --out "$R/eval_speed_scripted_cuda.json"                                            # eval_speed_scripted_cuda.json
timeout -s INT -k 15 170 python3 -m vla_ladder.cli record --out /tmp/long --episodes 800 --workers 16 --num-objects 5
timeout -s INT -k 15 120 python3 benchmarks/train_speed.py --dataset /tmp/long --models smolvla-scratch act \
  --device cuda --batch-size 64 --steps 100 --log-freq 20 --num-workers 10 --keep /tmp/gpu-runs \
  --out "$R/train_speed_cuda.json"                  # stopped during ACT: the SmolVLA-scratch row from its log
# Call 2, the same warm machine (its /tmp/long still there), timeout 190 s: the ACT row.
timeout -s INT 170 python3 benchmarks/train_speed.py --dataset /tmp/long --models act --device cuda --batch-size 64 \
  --steps 100 --log-freq 20 --num-workers 10 --out $OUT/train_speed_act.json
