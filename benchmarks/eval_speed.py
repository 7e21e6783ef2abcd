"""Evaluation throughput against worker processes: episodes/s of `vla-ladder eval`, state only and filmed.

    .venv/bin/python benchmarks/eval_speed.py [--episodes 20] [--filmed 4] [--workers 1 2] [--num-envs 1 2]
                                              [--policy scripted]

For each --workers N, and each --num-envs N > 1 (one policy acting on N env processes in lockstep, as a batch),
it times `run_evaluation` (what `vla-ladder eval` runs) on one condition with the policy (default: the scripted
expert; `lerobot:CKPT?device=cuda` measures a learned policy's batched GPU inference):
  state  - state-only episodes (no renderer);
  filmed - every episode filmed: both 256x256 cameras rendered every step (on the GPU when there is one,
           else lavapipe) and encoded to MP4.
Wall time includes starting the N processes (imports, building the env); the start-up is also timed alone
(one episode per process) so that the steady rate, (episodes - N) / (wall - start-up), can be given. Each row
also keeps the run's summary.json `timing`: seconds in resets, the policy, the env's steps and filming, and
the milliseconds of one lockstep step in the policy and in the env (what a slow batched run spends its time on). The
runs for different N must give the same episodes (for a deterministic policy): the result says whether they did,
bit for bit and in outcomes (held object, success, grasp-any, reach; a learned policy's floats may round
differently in a batch or with another thread count).

Writes benchmarks/results/eval_speed.json (eval_speed_cuda.json where a CUDA GPU renders), or --out.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import torch
import tyro

from vla_ladder import files
from vla_ladder.conditions import ConditionGrid
from vla_ladder.contract import EPISODE_STEPS
from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
from vla_ladder.machine import auto_workers, check_workers, cores

RESULTS = Path(__file__).parent / "results"
OUTCOMES = ["seed", "target", "held", "success", "grasp_any", "reach"]


@dataclass
class Args:
    """Evaluation episodes/s against worker processes, state only and filmed."""

    episodes: int = 20
    """state-only episodes per measurement"""
    filmed: int = 4
    """filmed episodes per measurement (0 skips the filmed runs)"""
    workers: tuple[int, ...] = (1, 2)
    """worker counts to measure (each worker process with its own copy of the policy; 0: as many as `eval` starts
    for --workers 0, one per core as memory allows)"""
    num_envs: tuple[int, ...] = (1, 2)
    """batch sizes to measure: one policy acting on N CPU env processes in lockstep (1: nothing extra)"""
    policy: str = "scripted"
    """the policy spec evaluated"""
    regime: str = "full_random"
    """placement regime of the episodes"""
    num_objects: int = 5
    """objects on the table"""
    robot_mesh: str = "lite"
    """lite or full robot visual meshes (what filmed episodes render)"""
    first_seed: int = 0
    """episode j plays seed first_seed + j"""
    out: Path | None = None
    """result JSON (default: benchmarks/results/eval_speed.json, eval_speed_cuda.json with a GPU)"""

    def __post_init__(self):
        # 0 resolved to the count `eval` starts for it, before measuring: the rows report the processes that ran,
        # and the steady rate subtracts one start-up episode per process
        self.workers = tuple(auto_workers(check_workers(n)) for n in self.workers)


def timed(args: Args, episodes: int, workers: int, filmed: bool, num_envs: int = 1,
          ) -> tuple[float, pd.DataFrame, dict]:
    """Wall seconds of one evaluation, its episodes (without the video column), and its summary's timing."""
    grid = ConditionGrid(regimes=(args.regime,), num_objects=(args.num_objects,))
    with tempfile.TemporaryDirectory() as tmp:
        cfg = EvalConfig(policy=args.policy, out=Path(tmp), grid=grid, episodes=episodes, first_seed=args.first_seed,
                         workers=workers, num_envs=num_envs, videos=episodes if filmed else 0,
                         robot_mesh=args.robot_mesh)
        t0 = time.perf_counter()
        summary = run_evaluation(cfg, progress=False)
        wall = time.perf_counter() - t0
        return wall, pd.read_parquet(Path(tmp) / "episodes.parquet").drop(columns="video"), summary["timing"]


def measure(args: Args, workers: int, filmed: bool, num_envs: int = 1) -> tuple[dict, pd.DataFrame]:
    n = args.filmed if filmed else args.episodes
    procs = max(workers, num_envs)
    startup, _, _ = timed(args, procs, workers, filmed, num_envs)  # one episode per process: start-up + 1 episode
    wall, episodes, timing = timed(args, n, workers, filmed, num_envs)
    steady = (n - procs) / (wall - startup) if n > procs and wall > startup else None
    row = {"kind": "filmed" if filmed else "state", "workers": workers, "num_envs": num_envs, "episodes": n,
           "wall_s": round(wall, 2),
           "episodes_per_s": round(n / wall, 3), "env_steps_per_s": round(EPISODE_STEPS * n / wall, 1),
           "startup_and_first_episode_s": round(startup, 2),
           "steady_episodes_per_s": None if steady is None else round(steady, 3),
           "success": float(episodes["success"].mean()), "timing": timing}
    print(f"{row['kind']:6s} workers {workers} num_envs {num_envs}: {n} episodes in {wall:.1f} s = "
          f"{row['episodes_per_s']} episodes/s (start-up + 1 episode {startup:.1f} s; steady "
          f"{row['steady_episodes_per_s']} episodes/s); a step: policy {timing['per_step_ms']['policy']} ms, "
          f"env {timing['per_step_ms']['env']} ms", flush=True)
    return row, episodes


def main(args: Args) -> None:
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    load_before = os.getloadavg()[0]
    timed(args, 1, 1, False)  # warm-up: the first env of this machine (asset caches, the lite robot's meshes)
    rows, same = [], {}
    result = {
        "benchmark": "eval_speed", "policy": args.policy, "sim_backend": "physx_cpu",
        "condition": f"{args.regime}/canonical/{args.num_objects}", "robot_mesh": args.robot_mesh,
        "renderer": "cuda" if gpu else "lavapipe (CPU)", "rows": rows,
        "same_episodes_for_every_worker_count_and_num_envs": same,
        "machine": {"cores": cores(), "gpu": gpu, "load_average_1min": [load_before, None]},
        "provenance": files.provenance(),
    }
    out = args.out or RESULTS / ("eval_speed_cuda.json" if gpu else "eval_speed.json")
    for kind, filmed in (("state", False), ("filmed", True)):
        if filmed and args.filmed < 1:
            continue
        played = []
        for workers, num_envs in [(n, 1) for n in args.workers] + [(1, n) for n in args.num_envs if n > 1]:
            row, episodes = measure(args, workers, filmed, num_envs)
            row["same_episodes_as_first_row"] = bool(not played or episodes.equals(played[0]))
            row["same_outcomes_as_first_row"] = bool(not played or episodes[OUTCOMES].equals(played[0][OUTCOMES]))
            rows.append(row)
            played.append(episodes)
            same[kind] = all(p.equals(played[0]) for p in played[1:])
            result["machine"]["load_average_1min"][1] = os.getloadavg()[0]
            files.write_json(out, result)  # after each row: a time box keeps the rows that finished
    print(f"same episodes for every worker count and num_envs: {same}; load {os.getloadavg()[0]:.1f}; wrote {out}")

if __name__ == "__main__":
    main(tyro.cli(Args))
