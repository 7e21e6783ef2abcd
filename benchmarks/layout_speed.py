"""Layout sampling speed: the CPU work of every reset, one layout per env being reset.

A batched physx_cuda reset of N envs samples N layouts in Python before the GPU sees a pose (layouts are pure
NumPy so that a seed gives the same scene on every backend). At 1024-4096 envs and 50-step episodes this can
rival the simulation itself; this script times `sample_layouts` for batches of seeds, per regime and object count.

    .venv/bin/python benchmarks/layout_speed.py [--batches 1024 4096] [--repeats 3]

Writes benchmarks/results/layout_speed.json (--out elsewhere).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

from vla_ladder import files
from vla_ladder.conditions import REGIMES, Condition
from vla_ladder.machine import cores
from vla_ladder.task.layouts import sample_layouts


@dataclass
class Args:
    batches: tuple[int, ...] = (1024, 4096)
    """envs reset at once (seeds sampled per batch)"""
    num_objects: tuple[int, ...] = (1, 5)
    """objects on the table"""
    splits: tuple[str, ...] = ("canonical", "pairings_ood")
    """splits to time (pairings splits are skipped for full_random, which has no regions)"""
    repeats: int = 3
    """batches timed per row; the fastest is kept (the others carry the machine's noise)"""
    out: Path | None = None
    """result JSON (default: benchmarks/results/layout_speed.json)"""


def main(args: Args) -> None:
    out = args.out or Path(__file__).parent / "results" / "layout_speed.json"
    load_before = os.getloadavg()[0]
    rows = []
    for split in args.splits:
        for regime, extent in REGIMES.items():
            if split != "canonical" and extent is None:
                continue
            for k in args.num_objects:
                condition = Condition(regime, split, k)
                for n in args.batches:
                    times = []
                    for r in range(args.repeats):
                        t0 = time.perf_counter()
                        sample_layouts(condition, range(r * n, (r + 1) * n))
                        times.append(time.perf_counter() - t0)
                    best = min(times)
                    rows.append({"condition": condition.key, "num_envs": n, "seconds_per_reset": round(best, 4),
                                 "ms_per_layout": round(best / n * 1e3, 4), "layouts_per_s": round(n / best)})
                    print(f"{condition.key:40s} {n:5d} envs: {best:6.3f} s a reset, "
                          f"{best / n * 1e3:.3f} ms a layout")
    files.write_json(out, {"benchmark": "layout_speed", "results": rows,
                           "machine": {"cores": cores(), "load_average_1min": [load_before, os.getloadavg()[0]]},
                           "provenance": files.provenance()})
    print(f"wrote {out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
