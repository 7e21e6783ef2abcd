"""Evaluation throughput of `run_evaluation` on CPU: episodes/s state-only and with filmed episodes.

    .venv/bin/python benchmarks/eval_speed.py [--episodes 20] [--filmed 2]

Writes benchmarks/results/eval_speed.json. The machine's load average is recorded with the figures
because the CPU may be shared.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from vla_ladder import io
from vla_ladder.evaluation.runner import run_evaluation

RESULT = Path(__file__).parent / "results" / "eval_speed.json"


def timed(**kwargs) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        run_evaluation("scripted", out=tmp, progress=False, **kwargs)
        return time.perf_counter() - t


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--filmed", type=int, default=2, help="episodes with MP4 videos of both cameras")
    args = p.parse_args()
    timed(regimes=["small_jitter"], episodes=1)  # warm-up: imports and the first env in the process
    state_s = timed(regimes=["full_random"], episodes=args.episodes)
    video_s = timed(regimes=["full_random"], episodes=args.filmed, videos=args.filmed)
    result = {
        "backend": "physx_cpu", "num_envs": 1, "policy": "scripted", "num_objects": 5,
        "state_only": {"episodes": args.episodes, "wall_s": round(state_s, 2),
                       "episodes_per_s": round(args.episodes / state_s, 3),
                       "env_steps_per_s": round(50 * args.episodes / state_s, 1)},
        "filmed": {"episodes": args.filmed, "wall_s": round(video_s, 2),
                   "s_per_episode": round(video_s / args.filmed, 2)},
        "load_average_1min": os.getloadavg()[0], "cpu_count": os.cpu_count(),
        "provenance": io.provenance(),
    }
    io.write_json(RESULT, result)
    print(f"state only: {result['state_only']['episodes_per_s']} episodes/s "
          f"({result['state_only']['env_steps_per_s']} env steps/s); filmed: "
          f"{result['filmed']['s_per_episode']} s/episode (load {result['load_average_1min']:.1f}); wrote {RESULT}")


if __name__ == "__main__":
    main()
