"""The PPO expert as a policy: its network, its checkpoint format, and acting (`load_policy("ppo:PATH")`).

PATH is a run directory of `vla-ladder train-expert` (its latest checkpoint), or one checkpoint
directory inside it, e.g. RUN/checkpoints/best. The network sees the flat "state" observation (joint
state, TCP pose, every object's pose, which objects are present, a one-hot of the instructed object,
grasp flags and the instructed grasp point), so one policy serves every instruction. Training lives in
vla_ladder.ppo, which writes checkpoints with `save_agent`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn as nn
from safetensors import SafetensorError
from safetensors.torch import load_file, safe_open, save_file
from torch.distributions.normal import Normal

from vla_ladder import files
from vla_ladder.contract import POLICY_FIELDS, contract_changes, policy_fingerprint
from vla_ladder.policies import Policy

FORMAT = "vla-ladder-ppo/1"


def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


def mlp(sizes: list[int], out_std: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-2], sizes[1:-1]):
        layers += [layer_init(nn.Linear(a, b)), nn.Tanh()]
    return nn.Sequential(*layers, layer_init(nn.Linear(sizes[-2], sizes[-1]), std=out_std))


class Agent(nn.Module):
    """Tanh MLP critic and Gaussian actor with a state-independent standard deviation."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_sizes=(256, 256, 256), init_logstd: float = -0.5):
        super().__init__()
        self.obs_dim, self.act_dim, self.hidden_sizes = int(obs_dim), int(act_dim), tuple(hidden_sizes)
        self.critic = mlp([obs_dim, *hidden_sizes, 1], out_std=1.0)
        self.actor_mean = mlp([obs_dim, *hidden_sizes, act_dim], out_std=0.01 * np.sqrt(2))
        self.actor_logstd = nn.Parameter(torch.full((1, act_dim), float(init_logstd)))

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).squeeze(-1)

    def get_action(self, x: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        mean = self.actor_mean(x)
        return mean if deterministic else Normal(mean, self.actor_logstd.exp().expand_as(mean)).sample()

    def get_action_and_value(self, x: torch.Tensor, action: torch.Tensor | None = None):
        mean = self.actor_mean(x)
        probs = Normal(mean, self.actor_logstd.exp().expand_as(mean))
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(1), probs.entropy().sum(1), self.get_value(x)


# ------------------------------------------------------------------------------------- checkpoints
def save_agent(path: Path, agent: Agent) -> None:
    meta = {"format": FORMAT, "obs_dim": str(agent.obs_dim), "act_dim": str(agent.act_dim),
            "hidden_sizes": ",".join(map(str, agent.hidden_sizes)),
            "contract": json.dumps(policy_fingerprint())}  # the task it learned: load_agent refuses another
    with files.atomic_path(path) as tmp:
        save_file({k: v.detach().cpu().contiguous() for k, v in agent.state_dict().items()}, str(tmp), meta)


def checkpoint_dir(path: str | Path) -> Path:
    """The checkpoint a path names: a checkpoint directory, or a run directory's latest checkpoint."""
    p = Path(path)
    if (p / "model.safetensors").is_file():
        return p
    if (p / "state.json").is_file():
        try:
            return p / json.loads((p / "state.json").read_text())["checkpoint"]
        except (ValueError, KeyError) as e:
            raise ValueError(f"unreadable PPO run state {p / 'state.json'}: {e}") from e
    raise ValueError(f"no PPO checkpoint at {str(path)!r}: expected a run directory with state.json "
                     "or a checkpoint directory with model.safetensors")


def checkpoint_state(checkpoint: Path) -> dict:
    """A checkpoint directory's state.json ({} where it has none)."""
    state = checkpoint / "state.json"
    return json.loads(state.read_text()) if state.is_file() else {}


def selection_episodes(state: dict) -> dict[str, range]:
    """The episodes a checkpoint was chosen on, from its state.json, as {condition key: seeds}: checkpoints/best is
    the best of the run's evaluations, each on seeds first_seed + j (j < episodes) of every training condition, so its
    success on those episodes leans high."""
    sel = state.get("selected_on")
    if not sel:
        return {}
    return {key: range(sel["first_seed"], sel["first_seed"] + sel["episodes"]) for key in sel["conditions"]}


def load_agent(path: str | Path, obs_dim: int | None = None, act_dim: int | None = None,
               device: str | torch.device = "cpu") -> Agent:
    """Load model.safetensors of a checkpoint (or run) directory; ValueError when it is unreadable, was trained
    under another task contract (contract.POLICY_FIELDS), or for other observation/action sizes than the ones
    given."""
    f = checkpoint_dir(path) / "model.safetensors"
    try:
        with safe_open(str(f), framework="pt") as sf:
            meta = sf.metadata() or {}
        if meta.get("format") != FORMAT:
            raise ValueError(f"format {meta.get('format')!r}, expected {FORMAT!r}")
        agent = Agent(int(meta["obs_dim"]), int(meta["act_dim"]), [int(h) for h in meta["hidden_sizes"].split(",")])
        agent.load_state_dict(load_file(str(f)))
        trained_under = json.loads(meta["contract"]) if "contract" in meta else None  # None: written before it was
    except (SafetensorError, OSError, KeyError, ValueError, RuntimeError) as e:
        raise ValueError(f"unreadable PPO checkpoint {f}: {e}") from e
    if changed := contract_changes(trained_under, POLICY_FIELDS):
        raise ValueError(f"PPO checkpoint {f} was trained under another task contract ({'; '.join(changed)}): "
                         "its numbers here would be those of a task it never saw; train it again")
    if (obs_dim is not None and obs_dim != agent.obs_dim) or (act_dim is not None and act_dim != agent.act_dim):
        raise ValueError(f"PPO checkpoint {f} was trained for {agent.obs_dim}-d observations and "
                         f"{agent.act_dim}-d actions; this environment has {obs_dim}-d observations and "
                         f"{act_dim}-d actions")
    return agent.to(device)


# ------------------------------------------------------------------------------------------ policy
class PPOPolicy(Policy):
    """Acts with the mean of the Gaussian policy (deterministic) unless `deterministic=False`."""

    obs_mode = "state"
    name = "ppo"

    def __init__(self, path: str | Path, device: str | torch.device | None = None, deterministic: bool = True):
        self.checkpoint = checkpoint_dir(path)
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self.agent = load_agent(self.checkpoint, device=self.device).eval()
        self.deterministic = deterministic
        self.state = checkpoint_state(self.checkpoint)
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
                "global_step": self.state.get("global_step"),
                **({"selected_on": self.state["selected_on"]} if "selected_on" in self.state else {})}


def make_policy(arg: str | None, **kwargs) -> PPOPolicy:
    if not arg:
        raise ValueError("policy 'ppo' needs a path: ppo:PATH (a train-expert run or checkpoint directory)")
    return PPOPolicy(arg, **kwargs)
