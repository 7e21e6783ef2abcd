"""`vla-ladder placements`: sample layouts of the ladder without the simulator."""

from __future__ import annotations

import argparse

from vla_ladder.task.layouts import REGIMES, SPLITS, check_args, parse_regimes, sample_layouts
from vla_ladder.task.objects import NUM_OBJECTS


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--regime", required=True, help=f"one of {', '.join(REGIMES)}, a comma list, or all")
    p.add_argument("--split", default="canonical", help=f"one of {', '.join(SPLITS)}")
    p.add_argument("--num-objects", type=int, default=NUM_OBJECTS, help="objects per scene, 1-5 (target included)")
    p.add_argument("--target", default=None, help="instructed object (default: uniform)")
    p.add_argument("--n", type=int, required=True, help="layouts per regime")
    p.add_argument("--seed", type=int, required=True, help="first episode seed; episode j uses seed + j")
    p.add_argument("--json", default=None, help="write the layouts here (JSON)")
    p.add_argument("--plot", default=None, help="write the placement figure here (PNG/PDF/SVG)")


def run(args: argparse.Namespace) -> int:
    from vla_ladder.io import write_json

    regimes = parse_regimes(args.regime)
    for r in regimes:
        check_args(r, args.split, args.num_objects, args.target)
    if args.n < 1:
        raise ValueError(f"--n must be at least 1, got {args.n}")
    seeds = range(args.seed, args.seed + args.n)
    layouts = {r: sample_layouts(r, args.split, args.num_objects, seeds, args.target) for r in regimes}
    if args.json:
        write_json(args.json, {"split": args.split, "num_objects": args.num_objects, "units": "metres",
                               "episodes": [lay.to_dict() for r in regimes for lay in layouts[r]]})
        print(f"wrote {args.n * len(regimes)} layouts to {args.json}")
    if args.plot:
        from vla_ladder.report.placements import plot_layouts
        plot_layouts(layouts, args.plot)
        print(f"wrote placement figure to {args.plot}")
    if not args.json and not args.plot:
        for r in regimes:
            for lay in layouts[r]:
                pos = ", ".join(f"{n} ({x:+.3f}, {y:+.3f})" for n, (x, y) in zip(lay.objects, lay.xy))
                print(f"{r} seed {lay.seed}: {lay.instruction!r}: {pos}")
    return 0
