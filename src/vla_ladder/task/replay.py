"""Replaying a recorded episode: its seed's scene, its recorded actions, and the states they lead to.

A physx_cpu env that rebuilds its scene every episode (GraspObjectEnv's default on the CPU) plays an episode as a
function of its seed and actions alone, whatever ran before it in the process (tests/test_env.py). An episode
recorded that way (`vla-ladder record` does by default; the provenance column `replayable`) therefore replays
exactly: its recorded states come back to the last bit. `vla-ladder check-dataset` uses this to check that a
dataset's actions are the ones that produced its states (an action stored a frame late, or altered, changes every
state after it), and anyone can re-simulate a recorded episode with it, e.g. to read privileged state (object
poses, contacts) that a dataset does not hold.

Cameras do not act on physics, so the replay env is state-only (~0.2 s an episode on the 2-core machine).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vla_ladder import contract
from vla_ladder.conditions import Condition
from vla_ladder.task.objects import OBJECT_NAMES


@dataclass(frozen=True)
class Replayed:
    """What one replayed episode did."""

    states: np.ndarray
    """(T, STATE_DIM) float32: the state before each action, as a recording stores it"""
    held: str
    """the object held at the final step, or "none\""""
    success: bool
    """the instructed object held at the final step"""


class Replayer:
    """A state-only physx_cpu env of one condition that replays episodes: `replay(seed, actions)`."""

    def __init__(self, condition: Condition, object_set: str = "auto", robot_mesh: str = "lite"):
        import gymnasium as gym

        import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1)

        condition = Condition.of(condition)
        self.env = gym.make(contract.ENV_ID, obs_mode="state_dict", regime=condition.regime, split=condition.split,
                            num_objects=condition.num_objects, object_set=object_set, robot_mesh=robot_mesh,
                            sim_backend="physx_cpu", num_envs=1, reconfiguration_freq=1)

    def replay(self, seed: int, actions: np.ndarray) -> Replayed:
        """Reset to episode `seed` and apply `actions` ((T, ACTION_DIM), one per control step) in order."""
        import torch

        actions = np.asarray(actions, dtype=np.float32)
        if actions.ndim != 2 or actions.shape[1] != contract.ACTION_DIM:
            raise ValueError(f"actions must be (T, {contract.ACTION_DIM}), got {actions.shape}")
        obs, _ = self.env.reset(seed=int(seed))
        states = np.empty((len(actions), contract.STATE_DIM), np.float32)
        info = None
        with torch.no_grad():
            for t, action in enumerate(actions):
                states[t] = obs["extra"]["proprio"][0].cpu().numpy()
                obs, _, _, _, info = self.env.step(torch.from_numpy(action)[None])
        if info is None:
            raise ValueError("no actions to replay")
        held = int(info["held"][0])
        return Replayed(states, OBJECT_NAMES[held] if held >= 0 else "none", bool(info["success"][0]))

    def close(self) -> None:
        self.env.close()
