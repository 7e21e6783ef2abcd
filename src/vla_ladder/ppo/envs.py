"""The trainer's environments: num_envs GraspObject-v1 episodes in lockstep, and the seeds and conditions
each reset hands them.

Episodes always last `max_episode_steps` and never terminate (success is judged at the final step), so
every parallel env starts and ends its episodes together: the trainer resets all envs at once with
seeds it chooses (>= TRAIN_SEED_MIN, disjoint from evaluation seeds).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from vla_ladder.conditions import Condition
from vla_ladder.contract import CONTROL_MODE, ENV_ID, METRICS
from vla_ladder.ppo.config import TRAIN_SEED_MIN, Args
from vla_ladder.task.vector import cpu_vector_env


class TrainEnvs:
    """num_envs GraspObject-v1 episodes in lockstep, as torch tensors on `device`: one GPU env
    (ManiSkillVectorEnv), one CPU env, or several CPU envs in spawned processes (AsyncVectorEnv)."""

    def __init__(self, args: Args, device: torch.device):
        import vla_ladder.task.env  # noqa: F401

        self.num_envs, self.device = args.num_envs, device
        # Training rollouts promise no bit-exact replay, so the CPU envs keep their scene across resets instead of
        # rebuilding it (a rebuild costs about as much as the 50 steps of an episode); the curve's evaluation
        # episodes are then not replayable either: `vla-ladder eval` of a checkpoint is the exact measure.
        kw = dict(obs_mode="state", control_mode=CONTROL_MODE, reward_mode="normalized_dense",
                  max_episode_steps=args.max_episode_steps, reconfiguration_freq=0)
        self._async = args.sim_backend == "physx_cpu" and args.num_envs > 1
        if self._async:
            self.env = cpu_vector_env(args.num_envs, **kw)
        else:
            from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv
            self.env = ManiSkillVectorEnv(gym.make(ENV_ID, num_envs=args.num_envs, sim_backend=args.sim_backend, **kw),
                                          auto_reset=False, ignore_terminations=True)
        self.obs_dim = int(np.prod(self.env.single_observation_space.shape))
        self.act_dim = int(np.prod(self.env.single_action_space.shape))

    @property
    def object_set(self) -> str:
        return self.env.get_attr("object_set")[0] if self._async else self.env.unwrapped.object_set

    def _t(self, x) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x) if self._async else x).to(self.device)

    def reset(self, seeds: list[int], conditions: list[Condition]) -> torch.Tensor:
        obs, _ = self.env.reset(seed=[int(s) for s in seeds], options={"conditions": conditions})
        return self._t(obs).float()

    def step(self, action: torch.Tensor):
        """obs, reward, truncated and the final-step metrics (success, grasp_any, reach)."""
        a = action.cpu().numpy() if self._async else action.to(self.env.device)
        obs, reward, _, truncated, info = self.env.step(a)
        metrics = {k: self._t(info[k]).bool() for k in METRICS}
        return self._t(obs).float(), self._t(reward).float(), self._t(truncated).bool(), metrics

    def close(self):
        self.env.close()


def slot_conditions(conditions: list, num_envs: int, round_: int) -> list:
    """Env slot i plays conditions[(i + round_ * num_envs) % K]: an even mixture over time even when
    the conditions outnumber the envs."""
    return [conditions[(i + round_ * num_envs) % len(conditions)] for i in range(num_envs)]


def train_seeds(seed: int, round_: int, n: int) -> list[int]:
    """Episode seeds of the round_-th training reset: a pure function, so --resume replays none."""
    return np.random.default_rng([seed, round_]).integers(TRAIN_SEED_MIN, 2**32, n).tolist()
