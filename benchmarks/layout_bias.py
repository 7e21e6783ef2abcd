"""Does where the objects stand give the target away? For each regime and object count, over many seeds: how often
the instructed object is the one nearest the workspace centre, and the one nearest the gripper's start (what the
`nearest` reference grasps; chance: 1 / objects for both), how much nearer the centre an object stands when it
is the target than when it is a distractor, and how much further from its nearest neighbour.

Each object is drawn again until it clears those placed before it, so the first one lands uniformly and the later
ones are pushed away from it. The jitter regimes still place the target first (each object keeps to its region, and
in large jitter 19% of five-object layouts redraw an object): the neighbour distance measures what that leaves. Until
2026-11-28 (contract.LAYOUTS 1) `sample_layout` placed the target first, and in
full random it stood nearer the centre than its distractors; it now places full random's objects in an order drawn
from the seed. The script measures `sample_layout` and, for full random, the same objects placed target first
("target first (layouts 1)": that sampler's order, positions from a stream of its own) for the record. No simulator.

    python benchmarks/layout_bias.py        # 10000 seeds a condition, about 20 s on 2 cores

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
from vla_ladder.contract import LAYOUTS
from vla_ladder.stats import wilson
from vla_ladder.task import layouts as L
from vla_ladder.task.objects import OBJECT_NAMES, OBJECTS


TCP_START_XY = np.array([-0.0208, 0.0])  # the gripper at the robot's rest pose (env.unwrapped.agent.tcp.pose.p)


@dataclass
class Args:
    seeds: int = 10000
    """layouts per condition (seeds 0 .. seeds - 1)"""
    regimes: tuple[str, ...] = ("small_jitter", "medium_jitter", "large_jitter", "full_random")
    objects: tuple[int, ...] = (2, 3, 5)
    out: Path = Path(__file__).parent / "results" / "layout_bias.json"


def target_first_xy(condition: Condition, seed: int) -> tuple[tuple[str, ...], np.ndarray]:
    """The objects `sample_layout` puts on the table for this seed, placed target first as layouts 1 did."""
    lay = L.sample_layout(condition, seed)
    rng = np.random.default_rng([seed, 0xB1A5])
    radii = tuple(OBJECTS[OBJECT_NAMES.index(n)].footprint_radius for n in lay.objects)
    xy: list[tuple[float, float]] = []
    for i, box in enumerate(L._boxes(lay.objects, condition.regime, lay.regions)):
        for _ in range(L.MAX_TRIES):  # (the shipped objects always fit: no restart needed in full random)
            xy[i:] = [L._draw(rng, box)]
            if not L._collides(xy, radii, i):
                break
    return lay.objects, np.array(xy)


class _Redraws:
    """Counts the layouts in which `sample_layout` drew some object again (its draw collided with one placed before),
    by watching the sampler's collision test while a layout is sampled."""

    def __init__(self):
        self.hit = False

    def __enter__(self):
        self.real = L._collides

        def collides(*args):
            hit = self.real(*args)
            self.hit |= hit
            return hit
        L._collides = collides
        return self

    def __exit__(self, *exc):
        L._collides = self.real


def measure(condition: Condition, seeds: int, target_first: bool) -> dict:
    nearest, by_gripper, target_d, distractor_d = 0, 0, {n: [] for n in OBJECT_NAMES}, {n: [] for n in OBJECT_NAMES}
    redrawn = 0
    target_nn, distractor_nn, nn_diff = {n: [] for n in OBJECT_NAMES}, {n: [] for n in OBJECT_NAMES}, []
    for seed in range(seeds):
        if target_first:
            names, xy = target_first_xy(condition, seed)
        else:
            with _Redraws() as redraws:
                lay = L.sample_layout(condition, seed)
            redrawn += redraws.hit
            names, xy = lay.objects, np.asarray(lay.xy)
        d = np.linalg.norm(xy - L.WORKSPACE_CENTER, axis=1)
        nearest += int(np.argmin(d) == 0)
        by_gripper += int(np.argmin(np.linalg.norm(xy - TCP_START_XY, axis=1)) == 0)
        target_d[names[0]].append(d[0])
        for name, dist in zip(names[1:], d[1:]):
            distractor_d[name].append(dist)
        if len(names) > 1:  # each object's distance to its nearest neighbour
            pair = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
            np.fill_diagonal(pair, np.inf)
            nn = pair.min(axis=1)
            target_nn[names[0]].append(nn[0])
            for name, dist in zip(names[1:], nn[1:]):
                distractor_nn[name].append(dist)
            nn_diff.append(nn[0] - nn[1:].mean())
    lo, hi = wilson(nearest, seeds)
    gap = {n: round(100 * float(np.mean(distractor_d[n]) - np.mean(target_d[n])), 2) for n in OBJECT_NAMES
           if target_d[n] and distractor_d[n]}
    lo_g, hi_g = wilson(by_gripper, seeds)
    # Placed first, the target is never pushed away from the others; a distractor drawn again stands further from
    # them. Per object, its mean nearest-neighbour distance as the target minus as a distractor; and per layout,
    # the target's minus its distractors' mean, whose expectation is 0 without a cue (the target is any of the
    # objects on the table with equal chance, and in the canonical split an object's region does not depend on
    # which is the target): its mean over the layouts, with a 95% normal interval (the layouts are independent).
    nn_gap = {n: float(np.mean(target_nn[n]) - np.mean(distractor_nn[n])) for n in OBJECT_NAMES
              if target_nn[n] and distractor_nn[n]}
    pooled = float(np.mean(nn_diff)) if nn_diff else 0.0
    pooled_se = float(np.std(nn_diff, ddof=1) / np.sqrt(len(nn_diff))) if len(nn_diff) > 1 else 0.0
    return {"target_nearest_centre": round(nearest / seeds, 4), "ci95": [round(lo, 4), round(hi, 4)],
            "target_nearest_gripper": round(by_gripper / seeds, 4), "gripper_ci95": [round(lo_g, 4), round(hi_g, 4)],
            "chance": round(1 / condition.num_objects, 4),
            # (the layouts in which some object was drawn again; None for the target-first reconstruction)
            "layouts_redrawn": None if target_first else round(redrawn / seeds, 4),
            "target_nearer_cm": gap,  # per object: its mean distance as a distractor minus as the target
            "target_further_from_neighbours_cm": {n: round(100 * v, 2) for n, v in nn_gap.items()},
            "target_further_from_neighbours_cm_mean": round(100 * pooled, 3),
            "target_further_from_neighbours_cm_ci95": [round(100 * (pooled - 1.96 * pooled_se), 3),
                                                       round(100 * (pooled + 1.96 * pooled_se), 3)]}


def main(args: Args) -> None:
    rows, t0 = [], time.monotonic()
    for regime in args.regimes:
        for k in args.objects:
            condition = Condition(regime, "canonical", k)
            for first in (False, True) if regime == "full_random" else (False,):
                rows.append({"condition": condition.key,
                             "placement": "target first (layouts 1)" if first else "sample_layout",
                             **measure(condition, args.seeds, first)})
                r = rows[-1]
                print(f"{r['condition']:28s} {r['placement']:24s} target nearest the centre "
                      f"{100 * r['target_nearest_centre']:.1f}% [{100 * r['ci95'][0]:.1f}, {100 * r['ci95'][1]:.1f}] "
                      f"(chance {100 * r['chance']:.0f}%), nearest the gripper "
                      f"{100 * r['target_nearest_gripper']:.1f}% "
                      f"| nearer as target (cm): {r['target_nearer_cm']} | further from its neighbours as target "
                      f"{r['target_further_from_neighbours_cm_mean']:+.2f} cm "
                      f"{r['target_further_from_neighbours_cm_ci95']} "
                      f"({time.monotonic() - t0:.0f} s)", flush=True)
    files.write_json(args.out, {"seeds": args.seeds, "layouts": LAYOUTS, "rows": rows,
                                "provenance": files.provenance()})
    print(args.out)


if __name__ == "__main__":
    main(tyro.cli(Args))
