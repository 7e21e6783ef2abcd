"""A trained PPO expert as a `Policy`: `load_policy("ppo:PATH")`.

PATH is a run directory of `vla-ladder train-expert` (its latest checkpoint), or one checkpoint
directory inside it, e.g. RUN/checkpoints/best.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import torch

from vla_ladder.experts.ppo import checkpoint_dir, load_agent
from vla_ladder.policies import Policy


class PPOPolicy(Policy):
    """Acts with the mean of the Gaussian policy (deterministic) unless `deterministic=False`."""

    obs_mode = "state"
    name = "ppo"

    def __init__(self, path: str | Path, device: str | torch.device | None = None, deterministic: bool = True):
        self.checkpoint = checkpoint_dir(path)
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self.agent = load_agent(self.checkpoint, device=self.device).eval()
        self.deterministic = deterministic
        state = self.checkpoint / "state.json"
        self.state = json.loads(state.read_text()) if state.is_file() else {}
        self._generator: torch.Generator | None = None

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> None:
        if not self.deterministic and env_ids is None:
            # One generator for the batch: per-episode seeding of a batched sampler would need one each.
            self._generator = torch.Generator(self.device).manual_seed(int(seeds[0]) if len(seeds) else 0)

    def act(self, obs: Any, instructions: Sequence[str]) -> torch.Tensor:
        if isinstance(obs, dict):
            from mani_skill.utils.common import flatten_state_dict
            obs = flatten_state_dict(obs, use_torch=True)
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        if x.ndim != 2 or x.shape[1] != self.agent.obs_dim:
            raise ValueError(f"PPO checkpoint {self.checkpoint} was trained for {self.agent.obs_dim}-d "
                             f"observations; got observations of shape {tuple(x.shape)} (obs_mode='state')")
        with torch.no_grad():
            mean = self.agent.actor_mean(x)
            if self.deterministic:
                action = mean
            else:
                std = self.agent.actor_logstd.exp().expand_as(mean)
                action = mean + std * torch.randn(mean.shape, generator=self._generator, device=self.device)
        return action.clamp(-1.0, 1.0)

    def describe(self) -> dict:
        return {"name": self.name, "checkpoint": str(self.checkpoint), "deterministic": self.deterministic,
                "global_step": self.state.get("global_step")}


def make_policy(arg: str | None, **kwargs) -> PPOPolicy:
    if not arg:
        raise ValueError("policy 'ppo' needs a path: ppo:PATH (a train-expert run or checkpoint directory)")
    return PPOPolicy(arg, **kwargs)
