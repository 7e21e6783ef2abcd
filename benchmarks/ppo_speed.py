"""Env-steps/s of PPO expert training (rollout + update, the training loop only), and optionally the
wall-clock a finished training run took to reach a success rate.

    .venv/bin/python benchmarks/ppo_speed.py                        # CPU: 1 env, then 2 (one process each)
    python benchmarks/ppo_speed.py --num-envs 16                     # GPU machine: 16 CPU envs, networks on CUDA
    python benchmarks/ppo_speed.py --sim-backend physx_cuda --num-envs 1024 4096 --from-run runs/ppo
                                                                     # needs SAPIEN's PhysX GPU library (docs/gpu.md)

Each measurement is `vla-ladder train-expert` for --iterations iterations (50 steps per env each) from scratch
with the paper's settings otherwise, on full_random with 5 objects. Writes benchmarks/results/ppo_speed_cpu.json,
or ppo_speed_cuda.json when the networks run on a CUDA GPU (--out elsewhere).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

from vla_ladder import files
from vla_ladder.conditions import ConditionGrid
from vla_ladder.contract import EPISODE_STEPS
from vla_ladder.machine import cores
from vla_ladder.ppo.config import Args as PPOArgs
from vla_ladder.ppo.train import train

RESULTS = Path(__file__).parent / "results"


@dataclass
class Args:
    """Env-steps/s of PPO expert training, and time to a success rate of a finished run."""

    sim_backend: str = "physx_cpu"
    """physx_cpu (one process per env) or physx_cuda (GPU-parallel envs)"""
    num_envs: tuple[int, ...] = ()
    """env counts to measure (default: 1 2 on physx_cpu, 1024 on physx_cuda)"""
    iterations: int = 3
    """training iterations (50 steps per env) per measurement"""
    cuda: bool = True
    """run the networks on CUDA when there is a GPU"""
    from_run: Path | None = None
    """also report the time a finished run (its evals.json) took to reach --target success"""
    target: float = 0.9
    """evaluation success rate for --from-run"""
    out: Path | None = None
    """result JSON (default: benchmarks/results/ppo_speed_<cpu|cuda>.json)"""


def ppo_args(args: Args, num_envs: int, out: Path) -> PPOArgs:
    """`iterations` PPO iterations from scratch with the paper's settings otherwise (checked as it is made), into
    `out` (made empty)."""
    out.mkdir()
    return PPOArgs(out=out, sim_backend=args.sim_backend, num_envs=num_envs, cuda=args.cuda, progress=False,
                   total_timesteps=args.iterations * num_envs * EPISODE_STEPS, eval_freq=10**9, eval_episodes=1,
                   grid=ConditionGrid(regimes=("full_random",), num_objects=(5,)))


def measure(args: Args, ppo: PPOArgs) -> dict:
    """Train the run `ppo` describes."""
    t0 = time.perf_counter()
    state = train(ppo)
    total = time.perf_counter() - t0
    num_envs = ppo.num_envs
    row = {"sim_backend": args.sim_backend, "num_envs": num_envs, "iterations": args.iterations,
           "env_steps": state["global_step"], "train_loop_s": round(state["wall_s"], 2),
           "env_steps_per_s": round(state["global_step"] / state["wall_s"], 1),
           "last_iteration_env_steps_per_s": round(state["sps"], 1),
           "wall_s_including_startup_and_final_eval": round(total, 1)}
    print(json.dumps(row), flush=True)
    return row


def time_to_success(run: Path, target: float) -> dict:
    """Training-loop seconds and env steps at the first evaluation reaching `target` success."""
    evals = json.loads((run / "evals.json").read_text())
    hit = next((e for e in evals if e["all"]["success"] >= target), None)
    return {"run": str(run), "target_success": target, "reached": hit is not None,
            "train_loop_s": hit["wall_s"] if hit else None, "env_steps": hit["global_step"] if hit else None,
            "final": {"global_step": evals[-1]["global_step"], "wall_s": evals[-1]["wall_s"],
                      **{m: evals[-1]["all"][m] for m in ("success", "grasp_any", "reach")}} if evals else None}


def main(args: Args) -> None:
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    load_before = os.getloadavg()[0]
    counts = args.num_envs or ((1, 2) if args.sim_backend == "physx_cpu" else (1024,))
    with tempfile.TemporaryDirectory() as tmp:
        # every count's settings checked before the first trains: a count this machine cannot run (more physx_cpu
        # envs than cores) failed only after the smaller ones had trained, and nothing was written
        runs = [ppo_args(args, n, Path(tmp) / f"envs-{n}") for n in counts]
        rows = [measure(args, ppo) for ppo in runs]
    network = "cuda" if gpu and (args.cuda or args.sim_backend == "physx_cuda") else "cpu"
    result = {"benchmark": "ppo_speed", "network_device": network, "rows": rows,
              "machine": {"cores": cores(), "cpu_count": os.cpu_count(), "gpu": gpu,
                          "load_average_1min": [load_before, os.getloadavg()[0]]},
              "provenance": files.provenance()}
    if args.from_run:
        result["time_to_success"] = time_to_success(args.from_run, args.target)
        print(json.dumps(result["time_to_success"]))
    # A physx_cpu run and a physx_cuda run on one GPU machine each keep their file.
    backend = "" if args.sim_backend == "physx_cpu" else f"_{args.sim_backend}"
    out = args.out or RESULTS / f"ppo_speed{backend}_{network}.json"
    files.write_json(out, result)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
