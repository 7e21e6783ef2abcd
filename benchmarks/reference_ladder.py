"""The reference policies along the ladder: the measured signatures the report and the docs quote.

    .venv/bin/python benchmarks/reference_ladder.py [--episodes 20]

Runs `vla-ladder experiment ladder` and `... pairings` for scripted, nearest, layout-prior and random (CPU,
state only) and writes their results.json files, merged, to benchmarks/results/reference_ladder.json and to
the copy the HTML report ships with (src/vla_ladder/report/data/reference_ladder.json).
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

from vla_ladder import files
from vla_ladder.experiments.experiment import ExperimentCommand, run_experiment

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "benchmarks" / "results" / "reference_ladder.json"
SHIPPED = ROOT / "src" / "vla_ladder" / "report" / "data" / "reference_ladder.json"
POLICIES = ("scripted", "nearest", "layout-prior", "random")


@dataclass
class Args:
    episodes: int = 20
    """seeded episodes per condition"""
    first_seed: int = 0
    """episode j plays seed first_seed + j"""
    out: Path | None = None
    """keep the experiment directories here (default: a temporary directory)"""


def main(args: Args) -> None:
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        base = args.out or Path(tmp)
        merged: dict = {}
        for name in ("ladder", "pairings"):
            cmd = ExperimentCommand(name, base / name, policy=POLICIES, episodes=args.episodes,
                                    first_seed=args.first_seed, report=False)
            run_experiment(cmd)
            results = json.loads((base / name / "results.json").read_text())
            for label, conds in results["results"].items():
                merged.setdefault(label, {}).update(conds)
    data = {"benchmark": "reference_ladder", "device": "cpu", "episodes": args.episodes,
            "first_seed": args.first_seed, "wall_s": round(time.perf_counter() - t0, 1),
            "experiment": {"episodes": args.episodes, "first_seed": args.first_seed},
            "provenance": files.provenance(), "results": merged}
    for path in (RESULT, SHIPPED):
        files.write_json(path, data)
    for label, conds in merged.items():
        print(label, {k: (round(c["success"], 2), round(c["grasp_any"], 2), round(c["reach"], 2))
                      for k, c in conds.items()})


if __name__ == "__main__":
    main(tyro.cli(Args))
