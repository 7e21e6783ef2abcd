"""GraspObject-v1 on the CPU backend in N processes, stepped in lockstep and seen as one batched env.

physx_cpu simulates one env per process. For a policy that acts on a batch (a LeRobot policy on a GPU, the PPO
trainer's network) N such envs run in N spawned processes behind gymnasium's AsyncVectorEnv, and `CPUEnvs`
gives them the face of a batched ManiSkill env: torch observations with a leading env dimension, every env's
layout and instruction, batched info. Episodes always last max_episode_steps and never terminate (success is
judged at the final step), so the N envs reset together and end together, each with its own seed and
condition; each is the same episode as that seed on a single env (one process, one scene, the same calls).
"""

from __future__ import annotations

import functools
import os
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
import torch

from vla_ladder.contract import CAMERA_NAMES, ENV_ID
from vla_ladder.machine import exit_with_parent, limit_threads


class SlotEnv(gym.Wrapper):
    """One CPU env of an AsyncVectorEnv: AsyncVectorEnv sends every sub-env the same reset options,
    so each picks its own row of every option given per env (a list: "conditions", "alone", ...)."""

    def __init__(self, env: gym.Env, index: int):
        super().__init__(env)
        self.index = index

    def reset(self, *, seed=None, options=None):
        from vla_ladder.task.env import PER_ENV_OPTIONS

        options = dict(options or {})
        for name in PER_ENV_OPTIONS:
            if isinstance(options.get(name), (list, tuple)):
                options[name] = [options[name][self.index]]
        return self.env.reset(seed=seed, options=options)


def make_cpu_env(index: int, **make_kwargs) -> gym.Env:
    """Build sub-env `index` in a spawned process (module-level, so it pickles), with one renderer thread and
    one torch thread; it ends with the process that started it."""
    exit_with_parent()
    limit_threads(1)
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1 in this process)

    return SlotEnv(CPUGymWrapper(gym.make(ENV_ID, **make_kwargs), ignore_terminations=True), index)


def cpu_vector_env(num_envs: int, **make_kwargs) -> gym.vector.AsyncVectorEnv:
    """num_envs single CPU envs in spawned processes; numpy in and out, no automatic resets."""
    # AsyncVectorEnv also builds env 0 once in this process, to read its spaces: what make_cpu_env sets for a
    # worker process (one torch thread, one lavapipe thread) must not stay set here, where the policy or the PPO
    # trainer runs (it did: their --torch-threads became 1).
    threads, lavapipe = torch.get_num_threads(), os.environ.get("LP_NUM_THREADS")
    try:
        return gym.vector.AsyncVectorEnv([functools.partial(make_cpu_env, i, sim_backend="physx_cpu", **make_kwargs)
                                          for i in range(num_envs)], context="spawn",
                                         autoreset_mode=gym.vector.AutoresetMode.DISABLED)
    finally:
        torch.set_num_threads(threads)
        if lavapipe is None:
            os.environ.pop("LP_NUM_THREADS", None)


def _torch(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _torch(v) for k, v in x.items()}
    return torch.from_numpy(np.asarray(x))


class CPUEnvs:
    """num_envs CPU envs in lockstep behind the interface of one batched GraspObject-v1 env."""

    spec = None  # episodes last EPISODE_STEPS, as every GraspObject-v1 registration says

    def __init__(self, num_envs: int, **make_kwargs):
        self.num_envs = num_envs
        self.vec = cpu_vector_env(num_envs, **make_kwargs)

    @property
    def unwrapped(self) -> "CPUEnvs":
        return self

    def reset(self, seed: Sequence[int], options: dict | None = None):
        obs, info = self.vec.reset(seed=[int(s) for s in seed], options=options)
        return _torch(obs), info

    def step(self, action: torch.Tensor):
        obs, reward, terminated, truncated, info = self.vec.step(torch.as_tensor(action).cpu().numpy())
        return _torch(obs), _torch(reward), _torch(terminated), _torch(truncated), info

    def _each(self, name: str) -> list:
        return [value[0] for value in self.vec.get_attr(name)]  # each env holds a batch of one

    @property
    def instructions(self) -> list[str]:
        return self._each("instructions")

    @property
    def layouts(self) -> list:
        return self._each("layouts")

    @property
    def object_set(self) -> str:
        return self.vec.get_attr("object_set")[0]

    def get_sensor_images(self) -> dict[str, dict[str, torch.Tensor]]:
        """Both cameras of every env, rendered now (as ManiSkill's get_sensor_images, batched)."""
        images = self.vec.call("get_sensor_images")
        return {cam: {"rgb": torch.cat([im[cam]["rgb"] for im in images])} for cam in CAMERA_NAMES}

    def close(self) -> None:
        self.vec.close()
