"""The reference policies under the grounding probes: the calibration docs/probes.md quotes.

    .venv/bin/python benchmarks/probes_reference.py [--swap-scenes 20] [--scenes 10] [--absent-scenes 20]
        [--position-scenes 20] [--switch-scenes 20] [--removal-scenes 20] [--switch-steps 5 25] [--probes P ...]
        [--out DIR]

Runs `vla-ladder probe` (CPU, state only, five objects, small jitter and full random) for
- instruction-swap: scripted, nearest, layout-prior, random;
- paraphrase: scripted, layout-prior (nearest and random never read the instruction);
- appearance-swap: scripted, layout-prior (state policies see no colour: a sanity check of the probe's plumbing);
- absent-object: scripted, nearest, layout-prior, random, with three objects, canonical and pairings_id (small
  jitter; full random has no pairing split),
- position-swap: scripted, nearest, layout-prior, random,
- instruction-switch: scripted, committed, nearest, layout-prior, random (at --switch-steps),
- distractor-removal: scripted, nearest, layout-prior, random,
and writes every probe's per-condition results to benchmarks/results/probes_reference.json; with --probes, only
those probes, to probes_reference_<probe>[+<probe>...].json beside it (the full file stays as it was measured).
With --out the probe directories are kept there and a second run resumes them (only probe.json is recomputed).
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

from vla_ladder import files
from vla_ladder.conditions import ConditionGrid
from vla_ladder.experiments.probes import SWITCH_STEPS, ProbeConfig, ProbeGrid, run_probe
from vla_ladder.report.probes import summary_lines

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "benchmarks" / "results" / "probes_reference.json"
PLAN = {"instruction-swap": ("scripted", "nearest", "layout-prior", "random"),
        "paraphrase": ("scripted", "layout-prior"),
        "appearance-swap": ("scripted", "layout-prior"),
        "absent-object": ("scripted", "nearest", "layout-prior", "random"),
        "position-swap": ("scripted", "nearest", "layout-prior", "random"),
        "instruction-switch": ("scripted", "committed", "nearest", "layout-prior", "random"),
        "distractor-removal": ("scripted", "nearest", "layout-prior", "random")}
REGIMES = ("small_jitter", "full_random")
ABSENT_GRID = ProbeGrid(REGIMES, ("canonical", "pairings_id"), (3,))


@dataclass
class Args:
    swap_scenes: int = 20
    """scenes per condition of the instruction-swap probe (each played once per object)"""
    scenes: int = 10
    """scenes per condition of the paraphrase and appearance-swap probes"""
    absent_scenes: int = 20
    """scenes per condition of the absent-object probe (each played once as it is and once per absent object)"""
    position_scenes: int = 20
    """scenes per condition of the position-swap probe (each played as it is and swapped)"""
    switch_scenes: int = 20
    """scenes per condition of the instruction-switch probe (each played as it is and once per switch step)"""
    removal_scenes: int = 20
    """scenes per condition of the distractor-removal probe (each played as it is and alone)"""
    switch_steps: tuple[int, ...] = SWITCH_STEPS
    """the instruction-switch probe's switch steps"""
    probes: tuple[str, ...] = tuple(PLAN)
    """the probes to run (a subset writes its own result file)"""
    first_seed: int = 0
    """scene j plays seed first_seed + j"""
    workers: int = 1
    """worker processes (any number plays the same episodes)"""
    out: Path | None = None
    """keep the probe directories here (default: a temporary directory)"""


def main(args: Args) -> None:
    unknown = [p for p in args.probes if p not in PLAN]
    if unknown:
        raise SystemExit(f"--probes: unknown {', '.join(unknown)}; allowed: {', '.join(PLAN)}")
    t0 = time.perf_counter()
    results: dict = {}
    scenes = {"instruction-swap": args.swap_scenes, "paraphrase": args.scenes, "appearance-swap": args.scenes,
              "absent-object": args.absent_scenes, "position-swap": args.position_scenes,
              "instruction-switch": args.switch_scenes, "distractor-removal": args.removal_scenes}
    with tempfile.TemporaryDirectory() as tmp:
        base = args.out or Path(tmp)
        for probe, policies in ((p, PLAN[p]) for p in args.probes):
            for policy in policies:
                absent = probe == "absent-object"
                cfg = ProbeConfig(probe, policy=policy, out=base / probe / policy,
                                  grid=ABSENT_GRID if absent else ConditionGrid(REGIMES),
                                  episodes=scenes[probe], switch_steps=args.switch_steps,
                                  first_seed=args.first_seed, workers=args.workers, report=False)
                data = run_probe(cfg, progress=False)
                results.setdefault(probe, {})[policy] = data["conditions"]
                print(f"{probe} {policy}:", *summary_lines(data), sep="\n  ")
    everything = tuple(args.probes) == tuple(PLAN)
    result = RESULT if everything else RESULT.with_name(f"probes_reference_{'+'.join(args.probes)}.json")
    files.write_json(result, {
        "benchmark": "probes_reference", "device": "cpu", "regimes": list(REGIMES), "num_objects": 5,
        **({"absent_object": {"num_objects": 3, "splits": list(ABSENT_GRID.splits)}}
           if "absent-object" in args.probes else {}),
        **({"switch_steps": list(args.switch_steps)} if "instruction-switch" in args.probes else {}),
        "scenes": {p: scenes[p] for p in args.probes},
        "first_seed": args.first_seed, "wall_s": round(time.perf_counter() - t0, 1),
        "provenance": json.loads(json.dumps(data["provenance"])), "results": results})
    print(result)


if __name__ == "__main__":
    main(tyro.cli(Args))
