"""Env steps/s of GraspObject-v1: state-only and with both 256x256 cameras.

CPU:  python benchmarks/env_speed.py                      (one env, physx_cpu)
GPU:  python benchmarks/env_speed.py --sim-backend physx_cuda --num-envs 256,1024,4096
Writes benchmarks/results/env_speed_<backend>.json. Aims (issue 2): CPU state >= 300 steps/s;
GPU state >= 300k env-steps/s; GPU two-camera >= 10k env-steps/s.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import gymnasium as gym
import torch

import vla_ladder.task.env  # noqa: F401
from vla_ladder.io import provenance, write_json


def measure(obs_mode: str, num_envs: int, backend: str, steps: int, regime: str) -> dict:
    t0 = time.perf_counter()
    env = gym.make("GraspObject-v1", obs_mode=obs_mode, num_envs=num_envs, sim_backend=backend, regime=regime)
    make_s = time.perf_counter() - t0
    env.reset(seed=0)
    action = torch.zeros((num_envs, 7), device=env.unwrapped.device)
    for _ in range(5):  # warm-up (first render / kernel launches)
        env.step(action)
    sync = torch.cuda.synchronize if backend == "physx_cuda" else (lambda: None)
    n, step_s, reset_s, resets = 0, 0.0, 0.0, 0
    while n < steps:
        t0 = time.perf_counter()
        for _ in range(50):  # a full episode, then a reset, as in data collection
            action.uniform_(-1, 1)
            env.step(action)
            n += 1
        sync()
        t1 = time.perf_counter()
        env.reset(seed=n)  # on the CPU this rebuilds the scene (bit-exact replay), on the GPU it does not
        sync()
        step_s += t1 - t0
        reset_s += time.perf_counter() - t1
        resets += 1
    env.close()
    return dict(obs_mode=obs_mode, num_envs=num_envs, sim_backend=backend, steps=n,
                env_steps_per_s=round(n * num_envs / (step_s + reset_s), 1),
                env_steps_per_s_excluding_resets=round(n * num_envs / step_s, 1),
                seconds_per_reset=round(reset_s / resets, 3), make_seconds=round(make_s, 2))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sim-backend", default="physx_cpu")
    p.add_argument("--num-envs", default="1", help="comma list")
    p.add_argument("--state-steps", type=int, default=1000, help="control steps per state measurement")
    p.add_argument("--rgb-steps", type=int, default=100, help="control steps per two-camera measurement")
    p.add_argument("--regime", default="full_random")
    args = p.parse_args()
    rows = []
    for n in [int(x) for x in args.num_envs.split(",")]:
        for mode, steps in (("state", args.state_steps), ("rgb", args.rgb_steps)):
            row = measure(mode, n, args.sim_backend, steps, args.regime)
            print(json.dumps(row))
            rows.append(row)
    device = torch.cuda.get_device_name() if torch.cuda.is_available() else platform.processor() or "cpu"
    out = Path(__file__).parent / "results" / f"env_speed_{args.sim_backend}.json"
    write_json(out, dict(benchmark="env_speed", device=device, cpu_count=__import__("os").cpu_count(),
                         provenance=provenance(), results=rows))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
