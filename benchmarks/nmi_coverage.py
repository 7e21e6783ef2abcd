"""How often the instruction swap's NMI interval holds the true NMI, on simulated plays (no simulation of the robot):
in each scene K of the five objects, each instructed once; the instruction is followed with probability g, else a
present object or nothing is held, uniformly at random (or, with --empty-shares, nothing with that probability and
else a present object: a policy that mostly misses). The true NMI of that model is I(X; Y | S) / H(X | S), the same
for every object set S. grounding.instruction_swap is run on each draw as a probe runs it.

    python benchmarks/nmi_coverage.py            # 200 draws a setting, about 8 minutes on 2 cores

writes benchmarks/results/nmi_coverage.json: per (objects, scenes, g, empty share) the true NMI, the mean reported
(bias-corrected) value, the mean plug-in value, the share of draws whose 95% interval holds the truth, and the share
whose permutation p is below 0.05 (where the truth is 0: the test's size).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import tyro

from vla_ladder import files
from vla_ladder.evaluation.grounding import NMI_METHOD, instruction_swap
from vla_ladder.task.objects import OBJECT_NAMES


@dataclass
class Args:
    draws: int = 200
    """simulated probes per setting"""
    objects: tuple[int, ...] = (5, 3, 2)
    """objects on the table"""
    scenes: tuple[int, ...] = (20, 50, 100)
    """scenes per probe (the probe's --episodes)"""
    followed: tuple[float, ...] = (0.0, 0.5, 0.9)
    """probability that the policy holds the instructed object"""
    empty_shares: tuple[float, ...] = (0.8,)
    """further settings with five objects: a play that does not follow holds nothing with this probability"""
    seed: int = 7
    out: Path = Path(__file__).parent / "results" / "nmi_coverage.json"


def true_nmi(k: int, g: float, empty: float) -> float:
    joint = np.full((k, k + 1), (1 - g) * (1 - empty) / k / k)
    joint[:, k] = (1 - g) * empty / k
    joint[np.arange(k), np.arange(k)] += g / k
    independent = joint.sum(1, keepdims=True) * joint.sum(0, keepdims=True)
    nmi = float((joint * np.log(joint / independent)).sum() / np.log(k)) if g < 1 else 1.0
    return min(max(round(nmi, 12), 0.0), 1.0) + 0.0  # (an independent table's float sum lands a hair off 0; no -0.0)


def plays(rng: np.random.Generator, scenes: int, k: int, g: float, empty: float) -> pd.DataFrame:
    rows = []
    for e in range(scenes):
        present = list(rng.choice(OBJECT_NAMES, k, replace=False))
        for rank, target in enumerate(present):
            if rng.random() < g:
                held = target
            elif empty == 1 / (k + 1):  # uniform over the objects and nothing, as the first table draws it
                held = (present + ["none"])[rng.integers(k + 1)]
            else:
                held = "none" if rng.random() < empty else present[rng.integers(k)]
            rows.append(dict(regime="small_jitter", split="canonical", num_objects=k, episode=e, seed=e, target=target,
                             instruct=rank, held=held, success=held == target, grasp_any=held != "none", reach=True))
    return pd.DataFrame(rows)


def main(args: Args) -> None:
    rng = np.random.default_rng(args.seed)
    settings = [(k, n, g, 1 / (k + 1)) for k in args.objects for n in args.scenes for g in args.followed]
    settings += [(5, n, g, e) for e in args.empty_shares for n in args.scenes for g in args.followed]
    rows = []
    for k, n, g, empty in settings:
        truth, hits, rejected, values, plug_in, t0 = true_nmi(k, g, empty), 0, 0, [], [], time.monotonic()
        for _ in range(args.draws):
            nmi = next(iter(instruction_swap(plays(rng, n, k, g, empty), resamples=200).values()))["nmi"]
            hits += nmi["ci95"][0] <= truth <= nmi["ci95"][1]
            rejected += nmi["permutation_p"] < 0.05
            values.append(nmi["value"])
            plug_in.append(nmi["plug_in"])
        rows.append({"objects": k, "scenes": n, "followed": g, "empty_share": round(empty, 4),
                     "true_nmi": round(truth, 4), "mean_value": round(float(np.mean(values)), 4),
                     "mean_plug_in": round(float(np.mean(plug_in)), 4), "coverage": hits / args.draws,
                     "permutation_p_below_0.05": rejected / args.draws})
        print(rows[-1], f"({time.monotonic() - t0:.0f} s)", flush=True)
    files.write_json(args.out, {"method": NMI_METHOD, "confidence": 0.95, "draws": args.draws, "seed": args.seed,
                                "rows": rows, "provenance": files.provenance()})
    print(args.out)


if __name__ == "__main__":
    main(tyro.cli(Args))
