"""Env steps/s of GraspObject-v1: state only, and with both 256x256 cameras for each robot mesh (lite, full).

CPU:  .venv/bin/python benchmarks/env_speed.py                  (one env, physx_cpu, lavapipe rendering)
GPU:  python benchmarks/env_speed.py                             (physx_cpu physics, cameras rendered on the GPU)
      python benchmarks/env_speed.py --sim-backend physx_cuda --num-envs 256 1024 4096   (needs SAPIEN's PhysX GPU
      library, see docs/gpu.md)

Each measurement steps random actions in whole 50-step episodes with a reset between them, as data collection
does, and reports stepping and resets apart (on physx_cpu a reset rebuilds the scene so that a seed replays bit
for bit). Writes benchmarks/results/env_speed_<backend>.json (..._cuda.json where a CUDA GPU renders) and
render_speed.json (render_speed_cuda.json): the two-camera rows side by side for robot_mesh lite and full, and
how much the lite robot changes the pictures (mean absolute difference per camera after the same actions).
Aims (issue 2): CPU state >= 300 steps/s; GPU state >= 300k env-steps/s; GPU two-camera >= 10k env-steps/s.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
import tyro

import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1)
from vla_ladder import files
from vla_ladder.contract import ACTION_DIM, CAMERA_NAMES, ENV_ID, EPISODE_STEPS
from vla_ladder.machine import cores

RESULTS = Path(__file__).parent / "results"


@dataclass
class Args:
    """Env steps/s of GraspObject-v1, state only and with both cameras per robot mesh."""

    sim_backend: str = "physx_cpu"
    """physx_cpu (one env) or physx_cuda (batched envs)"""
    num_envs: tuple[int, ...] = (1,)
    """env counts to measure (more than one needs physx_cuda)"""
    state_steps: int = 1000
    """control steps per state-only measurement"""
    rgb_steps: int = 100
    """control steps per two-camera measurement"""
    robot_meshes: tuple[str, ...] = ("lite", "full")
    """robot visual meshes measured with cameras (state-only steps never render)"""
    regime: str = "full_random"
    """placement regime"""
    render_backend: str = "auto"
    """renderer of the camera runs: auto (the GPU when there is one), gpu or cpu"""
    out: Path | None = None
    """env speed JSON (default: benchmarks/results/env_speed_<backend>[_cuda].json)"""
    render_out: Path | None = None
    """render speed JSON (default: benchmarks/results/render_speed[_cuda].json)"""

    def __post_init__(self):
        # checked before measuring: ManiSkill refuses batched envs on the CPU only when one is made, after the
        # earlier counts were measured, and nothing is written then
        if not self.num_envs or min(self.num_envs) < 1:
            raise ValueError(f"--num-envs: one or more counts >= 1, got {self.num_envs}")
        if self.sim_backend in ("physx_cpu", "cpu") and max(self.num_envs) > 1:
            raise ValueError(f"--num-envs above 1 needs --sim-backend physx_cuda (physx_cpu runs one env), "
                             f"got {' '.join(map(str, self.num_envs))}")
        if self.state_steps < 1 or self.rgb_steps < 1:
            raise ValueError(f"--state-steps and --rgb-steps must be >= 1, got {self.state_steps} and {self.rgb_steps}")


def make(args: Args, obs_mode: str, num_envs: int, robot_mesh: str):
    return gym.make(ENV_ID, obs_mode=obs_mode, num_envs=num_envs, sim_backend=args.sim_backend, regime=args.regime,
                    robot_mesh=robot_mesh, render_backend=args.render_backend if obs_mode == "rgb" else "auto")


def measure(args: Args, obs_mode: str, num_envs: int, steps: int, robot_mesh: str) -> dict:
    t0 = time.perf_counter()
    env = make(args, obs_mode, num_envs, robot_mesh)
    make_s = time.perf_counter() - t0
    env.reset(seed=0)
    action = torch.zeros((num_envs, ACTION_DIM), device=env.unwrapped.device)
    for _ in range(5):  # warm-up (first render, kernel launches)
        env.step(action)
    sync = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)
    n, step_s, reset_s, resets = 0, 0.0, 0.0, 0
    while n < steps:
        t0 = time.perf_counter()
        for _ in range(EPISODE_STEPS):  # a full episode, then a reset, as in data collection
            action.uniform_(-1, 1)
            env.step(action)
            n += 1
        sync()
        t1 = time.perf_counter()
        env.reset(seed=n)  # on physx_cpu this rebuilds the scene (bit-exact replay); on physx_cuda it does not
        sync()
        step_s += t1 - t0
        reset_s += time.perf_counter() - t1
        resets += 1
    env.close()
    row = dict(obs_mode=obs_mode, robot_mesh=robot_mesh if obs_mode == "rgb" else None, num_envs=num_envs,
               sim_backend=args.sim_backend, steps=n, env_steps_per_s=round(n * num_envs / (step_s + reset_s), 1),
               env_steps_per_s_excluding_resets=round(n * num_envs / step_s, 1),
               seconds_per_step=round(step_s / n, 4), seconds_per_reset=round(reset_s / resets, 3),
               make_seconds=round(make_s, 2))
    print(f"{obs_mode:5s} {row['robot_mesh'] or '':4s} x{num_envs}: {row['env_steps_per_s']} env-steps/s "
          f"({row['env_steps_per_s_excluding_resets']} stepping, {row['seconds_per_reset']} s a reset)", flush=True)
    return row


def picture_difference(args: Args, steps: int = 5) -> dict:
    """Mean |full - lite| grey levels per camera after the same seed and actions, and the largest joint-position
    difference (0: the lite robot changes pictures only)."""
    obs = {}
    for mesh in ("full", "lite"):
        env = make(args, "rgb", 1, mesh)
        o, _ = env.reset(seed=3)
        for _ in range(steps):
            o, *_ = env.step(torch.tensor([[0.3, 0.2, -0.3, 0, 0, 0, 1.0]], device=env.unwrapped.device))
        # Copied off the env before it closes: a GPU renderer's pictures live in the renderer's CUDA memory,
        # which closing frees (reading them afterwards was an illegal memory access on an H100).
        obs[mesh] = {"rgb": {cam: o["sensor_data"][cam]["rgb"].float().cpu() for cam in CAMERA_NAMES},
                     "qpos": o["agent"]["qpos"].cpu().numpy()}
        env.close()
    diff = {cam: float((obs["full"]["rgb"][cam] - obs["lite"]["rgb"][cam]).abs().mean()) for cam in CAMERA_NAMES}
    qpos = float(np.abs(obs["full"]["qpos"] - obs["lite"]["qpos"]).max())
    return {"seed": 3, "steps": steps, "mean_abs_difference_grey_levels": diff, "max_qpos_difference": qpos}


def main(args: Args) -> None:
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    renderer = args.render_backend if args.render_backend != "auto" else ("gpu" if gpu else "cpu")
    machine = {"cores": cores(), "gpu": gpu, "load_average_1min": [os.getloadavg()[0]]}
    rows = []
    for n in args.num_envs:
        rows.append(measure(args, "state", n, args.state_steps, "lite"))
        rows += [measure(args, "rgb", n, args.rgb_steps, mesh) for mesh in args.robot_meshes]
    machine["load_average_1min"].append(os.getloadavg()[0])
    gpu_render = "_cuda" if renderer == "gpu" and args.sim_backend == "physx_cpu" else ""  # physx_cuda says it
    out = args.out or RESULTS / f"env_speed_{args.sim_backend}{gpu_render}.json"
    common = {"machine": machine, "renderer": "GPU (CUDA)" if renderer == "gpu" else "lavapipe (CPU Vulkan)",
              "provenance": files.provenance()}
    files.write_json(out, {"benchmark": "env_speed", **common, "results": rows})
    print(f"wrote {out}")
    rgb = [r for r in rows if r["obs_mode"] == "rgb"]
    if not rgb:
        return
    by_mesh = {(r["num_envs"], r["robot_mesh"]): r for r in rgb}
    speedup = {str(n): round(by_mesh[n, "full"]["seconds_per_step"] / by_mesh[n, "lite"]["seconds_per_step"], 2)
               for n in args.num_envs if (n, "full") in by_mesh and (n, "lite") in by_mesh}
    render = {"benchmark": "render_speed", "cameras": list(CAMERA_NAMES), "image": "256x256 RGB", **common,
              "results": rgb, "lite_speedup_per_step": speedup,
              "pictures": picture_difference(args) if {"lite", "full"} <= set(args.robot_meshes) else None}
    # physx_cpu keeps the names the docs quote; another backend's rows go to their own file, not over those.
    backend = "" if args.sim_backend == "physx_cpu" else f"_{args.sim_backend}"
    render_out = args.render_out or RESULTS / f"render_speed{backend}{'_cuda' if renderer == 'gpu' else ''}.json"
    files.write_json(render_out, render)
    print(f"two-camera step, full / lite robot mesh: {speedup}x; pictures differ by "
          f"{render['pictures'] and render['pictures']['mean_abs_difference_grey_levels']} grey levels; "
          f"wrote {render_out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
