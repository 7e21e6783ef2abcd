"""Success, grasp_any and reach of the scripted expert per regime x object count (CPU, state only).

    .venv/bin/python benchmarks/scripted_success.py [--episodes 100] [--seed 0]

Writes benchmarks/results/scripted_success.json; the aim is >= 95% success in every cell.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import pandas as pd

from vla_ladder import io
from vla_ladder.evaluation.runner import run_evaluation
from vla_ladder.task.layouts import REGIMES

RESULT = Path(__file__).parent / "results" / "scripted_success.json"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=100, help="seeded episodes per cell")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--num-objects", default="1,2,3,4,5", help="comma-separated object counts")
    p.add_argument("--regimes", default="all", help="comma-separated regimes or all")
    p.add_argument("--out", type=Path, default=RESULT, help="result JSON")
    args = p.parse_args()
    regimes = list(REGIMES) if args.regimes == "all" else args.regimes.split(",")
    cells, frames = [], []
    t0 = time.perf_counter()
    for k in (int(x) for x in args.num_objects.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            summary = run_evaluation("scripted", regimes, num_objects=k, episodes=args.episodes, seed=args.seed,
                                     out=tmp)
            frames.append(pd.read_parquet(Path(tmp) / "episodes.parquet"))
            for c in summary["conditions"].values():
                cells.append({key: c[key] for key in ("regime", "num_objects", "n", "success", "grasp_any", "reach")})
                print(f"{c['regime']:>14} {k} objects: success {c['success']:.3f}  grasp_any {c['grasp_any']:.3f}"
                      f"  reach {c['reach']:.3f}  (n={c['n']})", flush=True)
            print(f"  {k} objects took {time.perf_counter() - t:.0f} s", flush=True)
    df = pd.concat(frames, ignore_index=True)
    failures = df[~df["success"]][["regime", "num_objects", "seed", "target", "held"]].to_dict("records")
    per_object = df.groupby("target")["success"].agg(["mean", "count"]).reset_index().to_dict("records")
    result = {
        "episodes_per_cell": args.episodes, "seed": args.seed, "cells": cells,
        "min_success": min(c["success"] for c in cells), "overall_success": float(df["success"].mean()),
        "per_target": per_object, "failures": failures,
        "wall_s": round(time.perf_counter() - t0, 1), "provenance": io.provenance(df["object_set"].iloc[0]),
    }
    io.write_json(args.out, result)
    print(f"min success over cells {result['min_success']:.3f}, overall {result['overall_success']:.3f}; "
          f"wrote {args.out}")


if __name__ == "__main__":
    main()
