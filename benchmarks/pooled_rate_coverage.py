"""How often a probe's pooled rate interval (grounding.pooled_rate: Wilson of the plays divided by their design
effect over scenes) holds the true rate, on simulated scenes (no simulation of the robot): each of n scenes has its
own rate q ~ Beta with mean p and intra-scene correlation rho (a = p (1 - rho) / rho, b = (1 - p) (1 - rho) / rho),
and plays m times, k ~ Binomial(m, q). rho is how much a scene decides its plays: near 0 every play nearly
independent, near 1 a scene's plays nearly all alike (the Beta needs 0 < rho < 1 and 0 < p < 1, so neither limit is
a setting). grounding.pooled_rate is called on each draw as a probe calls it.

    python benchmarks/pooled_rate_coverage.py          # 4000 draws a setting, about 1 minute on 2 cores

writes benchmarks/results/pooled_rate_coverage.json: per (rho, scenes, plays, rate) the share of draws whose 95%
interval holds p, and the mean width; and the lowest and highest coverage per rho.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from vla_ladder import files
from vla_ladder.evaluation.grounding import pooled_rate


@dataclass
class Args:
    draws: int = 4000
    """simulated probes per setting"""
    correlations: tuple[float, ...] = (0.05, 0.2, 0.5, 0.8)
    """intra-scene correlations rho of the plays, each strictly between 0 and 1"""
    scenes: tuple[int, ...] = (10, 20, 50)
    """scenes per probe"""
    plays: tuple[int, ...] = (2, 3, 5)
    """plays per scene (the instruction swap plays each of its K objects once; the absent object 5 - K)"""
    rates: tuple[float, ...] = (0.1, 0.5, 0.9, 0.95)
    """true pooled rates p, each strictly between 0 and 1"""
    seed: int = 11
    out: Path = Path(__file__).parent / "results" / "pooled_rate_coverage.json"

    def __post_init__(self):
        # checked before any setting runs: the Beta's parameters divide by rho and vanish at rho = 1, p = 0 or 1,
        # which failed only when that setting came, losing the ones before it
        bad = [rho for rho in self.correlations if not 0 < rho < 1]
        if bad:
            raise ValueError(f"--correlations must each be strictly between 0 and 1, got {bad}")
        bad = [p for p in self.rates if not 0 < p < 1]
        if bad:
            raise ValueError(f"--rates must each be strictly between 0 and 1, got {bad}")
        if self.draws < 1 or min(self.scenes, default=0) < 1 or min(self.plays, default=0) < 1:
            raise ValueError(f"--draws must be >= 1 and --scenes, --plays one or more values >= 1, got {self.draws}, "
                             f"{self.scenes} and {self.plays}")


def main(args: Args) -> None:
    rng = np.random.default_rng(args.seed)
    rows, t0 = [], time.monotonic()
    for rho in args.correlations:
        for n in args.scenes:
            for m in args.plays:
                for p in args.rates:
                    q = rng.beta(p * (1 - rho) / rho, (1 - p) * (1 - rho) / rho, (args.draws, n))
                    k = rng.binomial(m, q).astype(float)
                    plays = np.full(n, float(m))
                    intervals = np.array([pooled_rate(k[d], plays)["ci95"] for d in range(args.draws)])
                    rows.append({"rho": rho, "scenes": n, "plays": m, "rate": p,
                                 "coverage": float(np.mean((intervals[:, 0] <= p) & (p <= intervals[:, 1]))),
                                 "mean_width": round(float(np.mean(intervals[:, 1] - intervals[:, 0])), 4)})
        cov = [r["coverage"] for r in rows if r["rho"] == rho]
        print(f"rho {rho}: coverage {min(cov):.3f}-{max(cov):.3f} over {len(cov)} settings "
              f"({time.monotonic() - t0:.0f} s)", flush=True)
    by_rho = {str(rho): {"min": min(r["coverage"] for r in rows if r["rho"] == rho),
                         "max": max(r["coverage"] for r in rows if r["rho"] == rho)} for rho in args.correlations}
    files.write_json(args.out, {"confidence": 0.95, "draws": args.draws, "seed": args.seed, "coverage_by_rho": by_rho,
                                "rows": rows, "provenance": files.provenance()})
    print(args.out)


if __name__ == "__main__":
    main(tyro.cli(Args))
