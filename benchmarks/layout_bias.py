"""Does where the objects stand give the target away? For each regime and object count, over many seeds: how often
the instructed object is the one nearest the workspace centre, and the one nearest the gripper's start (what the
`nearest` reference grasps; chance: 1 / objects for both), and how much nearer the centre an object stands when it
is the target than when it is a distractor.

`sample_layout` draws the target first and places the objects one after another, each drawn again until it
collides with none placed before it. In full random the first object lands uniformly, the later ones are pushed
away from it: the target ends nearer the centre than its distractors. The script also places the same objects in an
order drawn at random ("shuffled order", not what `sample_layout` does), which makes the target's place the same
as any object's, to show how big the effect of the order is. No simulator.

    python benchmarks/layout_bias.py        # 10000 seeds a condition, about 10 s on 2 cores

writes benchmarks/results/layout_bias.json.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from vla_ladder import files
from vla_ladder.conditions import Condition
from vla_ladder.stats import wilson
from vla_ladder.task import layouts as L
from vla_ladder.task.objects import OBJECT_NAMES, OBJECTS


TCP_START_XY = np.array([-0.0208, 0.0])  # the gripper at the robot's rest pose (env.unwrapped.agent.tcp.pose.p)


@dataclass
class Args:
    seeds: int = 10000
    """layouts per condition (seeds 0 .. seeds - 1)"""
    regimes: tuple[str, ...] = ("small_jitter", "large_jitter", "full_random")
    objects: tuple[int, ...] = (2, 3, 5)
    out: Path = Path(__file__).parent / "results" / "layout_bias.json"


def shuffled_order_xy(condition: Condition, seed: int) -> tuple[tuple[str, ...], np.ndarray]:
    """The objects `sample_layout` puts on the table for this seed, placed in an order drawn from the seed (target
    first in the returned names, as in a Layout)."""
    lay = L.sample_layout(condition, seed)
    rng = np.random.default_rng([seed, 0xB1A5])
    order = rng.permutation(len(lay.objects))
    names = tuple(lay.objects[i] for i in order)
    radii = tuple(OBJECTS[OBJECT_NAMES.index(n)].footprint_radius for n in names)
    boxes = L._boxes(names, condition.regime, None if lay.regions is None else tuple(lay.regions[i] for i in order))
    xy: list[tuple[float, float]] = []
    for i, box in enumerate(boxes):  # (the shipped objects always fit: no restart needed in full random)
        for _ in range(L.MAX_TRIES):
            xy[i:] = [L._draw(rng, box)]
            if not L._collides(xy, radii, i):
                break
    back = np.argsort(order)
    return lay.objects, np.array(xy)[back]


def measure(condition: Condition, seeds: int, shuffled: bool) -> dict:
    nearest, by_gripper, target_d, distractor_d = 0, 0, {n: [] for n in OBJECT_NAMES}, {n: [] for n in OBJECT_NAMES}
    for seed in range(seeds):
        if shuffled:
            names, xy = shuffled_order_xy(condition, seed)
        else:
            lay = L.sample_layout(condition, seed)
            names, xy = lay.objects, np.asarray(lay.xy)
        d = np.linalg.norm(xy - L.WORKSPACE_CENTER, axis=1)
        nearest += int(np.argmin(d) == 0)
        by_gripper += int(np.argmin(np.linalg.norm(xy - TCP_START_XY, axis=1)) == 0)
        target_d[names[0]].append(d[0])
        for name, dist in zip(names[1:], d[1:]):
            distractor_d[name].append(dist)
    lo, hi = wilson(nearest, seeds)
    gap = {n: round(100 * float(np.mean(distractor_d[n]) - np.mean(target_d[n])), 2) for n in OBJECT_NAMES
           if target_d[n] and distractor_d[n]}
    lo_g, hi_g = wilson(by_gripper, seeds)
    return {"target_nearest_centre": round(nearest / seeds, 4), "ci95": [round(lo, 4), round(hi, 4)],
            "target_nearest_gripper": round(by_gripper / seeds, 4), "gripper_ci95": [round(lo_g, 4), round(hi_g, 4)],
            "chance": round(1 / condition.num_objects, 4),
            "target_nearer_cm": gap}  # per object: its mean distance as a distractor minus as the target


def main(args: Args) -> None:
    rows, t0 = [], time.monotonic()
    for regime in args.regimes:
        for k in args.objects:
            condition = Condition(regime, "canonical", k)
            for shuffled in (False, True) if regime == "full_random" else (False,):
                rows.append({"condition": condition.key, "placement": "shuffled order" if shuffled else "sample_layout",
                             **measure(condition, args.seeds, shuffled)})
                r = rows[-1]
                print(f"{r['condition']:28s} {r['placement']:14s} target nearest the centre "
                      f"{100 * r['target_nearest_centre']:.1f}% [{100 * r['ci95'][0]:.1f}, {100 * r['ci95'][1]:.1f}] "
                      f"(chance {100 * r['chance']:.0f}%), nearest the gripper "
                      f"{100 * r['target_nearest_gripper']:.1f}% "
                      f"| nearer as target (cm): {r['target_nearer_cm']} "
                      f"({time.monotonic() - t0:.0f} s)", flush=True)
    files.write_json(args.out, {"seeds": args.seeds, "rows": rows, "provenance": files.provenance()})
    print(args.out)


if __name__ == "__main__":
    main(tyro.cli(Args))
