"""When the scripted expert (and layout-prior, which drives the same controller) commits: the action at which it
starts its descent and the one at which it starts closing its gripper, per episode (CPU, state only, stand-in
objects, five objects). The instruction-switch probe's default steps (experiments/probes.py SWITCH_STEPS) are
chosen around these: one before every close, one after nearly every close and lift.

    .venv/bin/python benchmarks/grasp_timing.py [--episodes 20] [--first-seed 0] [--out FILE]

Writes benchmarks/results/grasp_timing.json, or --out. Action t is the policy's (t+1)-th action, applied in control
step t+1; an instruction switch at step K (env option switch_at) comes after actions 0..K-1, so the expert has closed on
the first target before a switch at K exactly when its close action is < K.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import tyro

from vla_ladder import files
from vla_ladder.conditions import Condition
from vla_ladder.contract import ENV_ID, EPISODE_STEPS
from vla_ladder.machine import cores
from vla_ladder.policies import load_policy
from vla_ladder.policies.scripted import CLOSE, DESCEND

RESULT = Path(__file__).parent / "results" / "grasp_timing.json"
REGIMES = ("small_jitter", "full_random")


@dataclass
class Args:
    episodes: int = 20
    """seeded episodes per regime (episode j plays seed first_seed + j)"""
    first_seed: int = 0
    policies: tuple[str, ...] = ("scripted", "layout-prior")
    """policies driven by the scripted controller (its phase machine is read after every action)"""
    out: Path = RESULT
    """result JSON"""

    def __post_init__(self):
        # checked before the env is made: no episode leaves nothing to summarise, after the work
        if self.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {self.episodes}")


def phase_steps(policy, env, seed: int, condition: Condition) -> tuple[int | None, int | None, bool]:
    """(first action in the descent, first action closing the gripper, success at the final step)."""
    obs, _ = env.reset(seed=seed, options={"conditions": [condition]})
    policy.reset([seed])
    expert = getattr(policy, "expert", policy)
    instructions = env.unwrapped.instructions
    descend = close = None
    for t in range(EPISODE_STEPS):
        action = policy.act(obs, instructions)
        phase = int(expert.phase[0])
        descend = t if descend is None and phase >= DESCEND else descend
        close = t if close is None and phase >= CLOSE else close
        obs, _, _, _, info = env.step(action)
    return descend, close, bool(info["success"][0])


def summary(values: list[int | None]) -> dict:
    done = np.array([v for v in values if v is not None])
    return {"per_episode": values, "min": int(done.min()), "median": float(np.median(done)), "max": int(done.max()),
            "never": sum(v is None for v in values)}


def main(args: Args) -> None:
    import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1)

    t0, load_before = time.perf_counter(), os.getloadavg()[0]
    env = gym.make(ENV_ID, obs_mode="state_dict", object_set="standin", num_objects=5)
    results: dict = {}
    try:
        for spec in args.policies:
            policy = load_policy(spec)
            for regime in REGIMES:
                rows = [phase_steps(policy, env, args.first_seed + j, Condition(regime))
                        for j in range(args.episodes)]
                descend, close, success = zip(*rows)
                results.setdefault(spec, {})[regime] = {"descend": summary(list(descend)),
                                                        "close": summary(list(close)), "success": sum(success)}
                print(spec, regime, "descend", list(descend), "close", list(close), "success", sum(success))
    finally:
        env.close()
    files.write_json(args.out, {"benchmark": "grasp_timing", "device": "cpu", "object_set": "standin",
                              "num_objects": 5, "episodes": args.episodes, "first_seed": args.first_seed,
                              "wall_s": round(time.perf_counter() - t0, 1), "results": results,
                              "machine": {"cores": cores(), "load_average_1min": [load_before, os.getloadavg()[0]]},
                              "provenance": files.provenance("standin")})
    print(args.out)


if __name__ == "__main__":
    main(tyro.cli(Args))
