"""An example vla-ladder policy plugin, to copy: the same action at every step, whatever it sees and is told.

Installed (`pip install -e examples/policy_plugin`, or `VIRTUAL_ENV=.venv uv pip install -e ...` in
the venv of scripts/setup.sh), it is `--policy constant[:A0,A1,...,A6]` for the vla-ladder
commands that play a policy (eval, probe, diagnose, experiment; record and serve take a plugin as their expert), in
every worker process. The seven numbers are a pd_ee_delta_pose action in [-1, 1] (`vla_ladder.contract.ACTION_NAMES`:
xyz, rotation, gripper); the default holds the arm still with the gripper open. Your policy replaces `act`.
"""

from __future__ import annotations

from typing import Any, Sequence

import torch

from vla_ladder.contract import ACTION_DIM
from vla_ladder.policies import Policy

DEFAULT = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


class ConstantPolicy(Policy):
    obs_mode = "rgb"  # what a VLA sees: obs["sensor_data"][camera]["rgb"] and the 15-d obs["extra"]["proprio"]
    name = "constant"

    def __init__(self, action: Sequence[float]):
        self.action = torch.tensor(action, dtype=torch.float32)

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> None:
        """New episodes begin in envs `env_ids` (all when None), seeded by `seeds`: nothing to forget here."""

    def act(self, obs: Any, instructions: Sequence[str]) -> torch.Tensor:
        n = obs["extra"]["proprio"].shape[0]  # one row per env; instructions[i] is env i's
        return self.action.expand(n, ACTION_DIM).clone()

    def describe(self) -> dict:
        return {"name": self.name, "action": self.action.tolist()}  # kept in every result file


def parse(arg: str | None) -> tuple[float, ...]:
    if arg is None:
        return DEFAULT
    try:
        action = tuple(float(v) for v in arg.split(","))
    except ValueError:
        action = ()
    if len(action) != ACTION_DIM or not all(-1 <= a <= 1 for a in action):
        raise ValueError(f"constant:A0,...,A6 takes {ACTION_DIM} comma-separated numbers in [-1, 1], got {arg!r}")
    return action


def make_policy(arg: str | None, **kwargs) -> ConstantPolicy:
    """The factory the entry point names: `arg` is what follows `constant:` in the spec (None without it)."""
    return ConstantPolicy(parse(arg))


# Optional: vla-ladder calls the factory's `check(arg)` before any work, so that a bad spec is one line (exit 2)
# rather than an error in the first worker. Make it cheap: no weights are read here.
make_policy.check = parse
# Optional too, for a policy with weights: the file they are in, hashed into every run directory so that resuming
# one with retrained weights at the same path is refused. This one has none.
make_policy.weights_file = lambda arg: None
