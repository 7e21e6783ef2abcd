"""`vla-ladder eval`: run seeded episodes of a policy per condition and write a run directory."""

from __future__ import annotations

import argparse

from vla_ladder.evaluation.runner import SIM_BACKENDS
from vla_ladder.task.layouts import parse_regimes
from vla_ladder.task.layouts import REGIMES, SPLITS


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--policy", required=True,
                   help="policy spec: scripted, ppo:PATH, lerobot:DIR, nearest, layout-prior, random")
    p.add_argument("--regime", required=True,
                   help=f"comma-separated regimes or 'all' ({', '.join(REGIMES)})")
    p.add_argument("--split", default="canonical", help=f"object-region pairing split ({', '.join(SPLITS)})")
    p.add_argument("--num-objects", type=int, default=5, help="objects on the table, 1-5 (default 5)")
    p.add_argument("--episodes", type=int, required=True, help="episodes per condition")
    p.add_argument("--seed", type=int, required=True, help="episode j of every condition uses seed SEED+j")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--num-envs", type=int, default=1, help="episodes simulated at once (physx_cuda)")
    p.add_argument("--sim-backend", default="physx_cpu", help=f"one of {', '.join(SIM_BACKENDS)}")
    p.add_argument("--videos", type=int, default=0, help="MP4s of both cameras for the first K episodes")
    p.add_argument("--object-set", default="auto", help="auto, ycb or standin")


def run(args: argparse.Namespace) -> int:
    from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
    from vla_ladder.policies import parse_spec

    # Every argument is checked before the policy loads or a simulator starts.
    parse_spec(args.policy)
    EvalConfig(policy=args.policy, regimes=parse_regimes(args.regime), split=args.split,
               num_objects=args.num_objects, episodes=args.episodes, seed=args.seed, num_envs=args.num_envs,
               sim_backend=args.sim_backend, videos=args.videos, object_set=args.object_set)
    summary = run_evaluation(args.policy, parse_regimes(args.regime), split=args.split,
                             num_objects=args.num_objects, episodes=args.episodes, seed=args.seed, out=args.out,
                             num_envs=args.num_envs, sim_backend=args.sim_backend, videos=args.videos,
                             object_set=args.object_set)
    for key, c in summary["conditions"].items():
        print(f"{key}: n={c['n']} success={c['success']:.3f} grasp_any={c['grasp_any']:.3f} "
              f"reach={c['reach']:.3f}")
    print(f"wrote {args.out}/episodes.parquet, summary.json, config.json")
    return 0

