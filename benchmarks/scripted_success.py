"""Success, grasp_any and reach of the scripted expert per regime x object count (CPU, state only).

    .venv/bin/python benchmarks/scripted_success.py [--episodes 100] [--first-seed 0] [--num-objects 1 2 3 4 5]

One `vla-ladder eval --policy scripted` over every cell (regimes x object counts), played by --workers
processes (any number gives the same episodes). Writes benchmarks/results/scripted_success.json (--out
elsewhere); the aim is >= 95% success in every cell.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import tyro

from vla_ladder import files
from vla_ladder.conditions import ConditionGrid
from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
from vla_ladder.machine import auto_workers, cores

RESULT = Path(__file__).parent / "results" / "scripted_success.json"


@dataclass
class Args:
    """Success, grasp_any and reach of the scripted expert per regime x object count."""

    episodes: int = 100
    """seeded episodes per cell"""
    first_seed: int = 0
    """episode j of every cell plays seed first_seed + j"""
    num_objects: tuple[int, ...] = (1, 2, 3, 4, 5)
    """object counts (one cell per regime and count)"""
    regimes: tuple[str, ...] = ("all",)
    """regimes, or all"""
    workers: int = 0
    """evaluation worker processes (0: one per core)"""
    out: Path = RESULT
    """result JSON to write"""


def main(args: Args) -> None:
    load_before = os.getloadavg()[0]
    grid = ConditionGrid(regimes=args.regimes, num_objects=args.num_objects)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_evaluation(EvalConfig(policy="scripted", out=Path(tmp), grid=grid, episodes=args.episodes,
                                            first_seed=args.first_seed, workers=args.workers))
        df = pd.read_parquet(Path(tmp) / "episodes.parquet")
    wall = time.perf_counter() - t0
    cells = []
    for c in summary["conditions"].values():
        cells.append({key: c[key] for key in ("regime", "num_objects", "n", "success", "grasp_any", "reach")})
        print(f"{c['regime']:>14} {c['num_objects']} objects: success {c['success']:.3f}  "
              f"grasp_any {c['grasp_any']:.3f}  reach {c['reach']:.3f}  (n={c['n']})")
    failures = df[~df["success"]][["regime", "num_objects", "seed", "target", "held"]].to_dict("records")
    per_target = df.groupby("target")["success"].agg(["mean", "count"]).reset_index().to_dict("records")
    result = {
        "benchmark": "scripted_success", "episodes_per_cell": args.episodes, "first_seed": args.first_seed,
        "cells": cells, "min_success": min(c["success"] for c in cells),
        "overall_success": float(df["success"].mean()), "per_target": per_target, "failures": failures,
        "wall_s": round(wall, 1), "workers": auto_workers(args.workers),
        "machine": {"cores": cores(), "gpu": None, "load_average_1min": [load_before, os.getloadavg()[0]],
                    "note": "CPU only: state-only episodes never render"},
        "provenance": files.provenance(df["object_set"].iloc[0]),
    }
    files.write_json(args.out, result)
    print(f"min success over cells {result['min_success']:.3f}, overall {result['overall_success']:.3f} "
          f"in {wall:.0f} s; wrote {args.out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
