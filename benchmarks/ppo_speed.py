"""Env-steps/s of PPO expert training (rollout + update, the training loop only), and optionally the
wall-clock a finished training run took to reach a success rate.

    .venv/bin/python benchmarks/ppo_speed.py                                      # CPU: 1 env, then 2
    .venv/bin/python benchmarks/ppo_speed.py --sim-backend physx_cuda --num-envs 1024 4096
    .venv/bin/python benchmarks/ppo_speed.py --sim-backend physx_cuda --from-run runs/ppo

Writes benchmarks/results/ppo_speed_cpu.json (or _cuda.json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import torch

from vla_ladder import io
from vla_ladder.experts import ppo

RESULTS = Path(__file__).parent / "results"


def measure(sim_backend: str, num_envs: int, iterations: int) -> dict:
    """Train `iterations` PPO iterations from scratch with the paper's settings otherwise."""
    with tempfile.TemporaryDirectory() as tmp:
        args = ppo.Args(out=tmp, sim_backend=sim_backend, num_envs=num_envs, progress=False,
                        total_timesteps=iterations * num_envs * 50, eval_freq=10**9, eval_episodes=1,
                        regimes=("full_random",), num_objects=(5,))
        t0 = time.perf_counter()
        state = ppo.train(args)
        total = time.perf_counter() - t0
    return {"sim_backend": sim_backend, "num_envs": num_envs, "iterations": iterations,
            "env_steps": state["global_step"], "train_loop_s": round(state["wall_s"], 2),
            "env_steps_per_s": round(state["global_step"] / state["wall_s"], 1),
            "last_iteration_env_steps_per_s": round(state["sps"], 1),
            "wall_s_including_startup_and_final_eval": round(total, 1)}


def time_to_success(run: Path, target: float) -> dict:
    """Training-loop seconds and env steps at the first evaluation reaching `target` success."""
    evals = json.loads((run / "evals.json").read_text())
    hit = next((e for e in evals if e["all"]["success"] >= target), None)
    return {"run": str(run), "target_success": target, "reached": hit is not None,
            "train_loop_s": hit["wall_s"] if hit else None, "env_steps": hit["global_step"] if hit else None,
            "final": {"global_step": evals[-1]["global_step"], "wall_s": evals[-1]["wall_s"],
                      **{m: evals[-1]["all"][m] for m in ("success", "grasp_any", "reach")}} if evals else None}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sim-backend", default="physx_cpu", choices=ppo.SIM_BACKENDS)
    p.add_argument("--num-envs", type=int, nargs="+", default=None,
                   help="env counts to measure (default: 1 2 on CPU, 1024 on GPU)")
    p.add_argument("--iterations", type=int, default=3, help="training iterations (50 steps per env) each")
    p.add_argument("--from-run", type=Path, help="also report time to --target success of this finished run")
    p.add_argument("--target", type=float, default=0.9)
    a = p.parse_args()
    counts = a.num_envs or ([1, 2] if a.sim_backend == "physx_cpu" else [1024])
    rows = []
    for n in counts:
        rows.append(measure(a.sim_backend, n, a.iterations))
        print(json.dumps(rows[-1]))
    result = {"benchmark": "ppo_speed", "rows": rows,
              "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                          "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
                          "load_average_1min": round(os.getloadavg()[0], 2)},
              "provenance": io.provenance()}
    if a.from_run:
        result["time_to_success"] = time_to_success(a.from_run, a.target)
        print(json.dumps(result["time_to_success"]))
    kind = "cpu" if a.sim_backend == "physx_cpu" else "cuda"
    io.write_json(RESULTS / f"ppo_speed_{kind}.json", result)
    print(f"wrote {RESULTS / f'ppo_speed_{kind}.json'}")


if __name__ == "__main__":
    main()
