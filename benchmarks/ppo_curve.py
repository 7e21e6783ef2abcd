"""Learning curves of PPO expert runs: evaluation success, grasp-any and reach (95% Wilson intervals) against
env steps, with the training-loop seconds each evaluation came at, read from each run's evals.json.

    .venv/bin/python benchmarks/ppo_curve.py RUN [RUN ...] --name physx_cpu2 [--labels few-envs paper]
                                             [--out FILE]

Writes benchmarks/results/ppo_curve_<name>.json (or --out) and the .png beside it (one panel per run). The JSON
keeps, per run, the settings that differ from `vla-ladder train-expert`'s defaults (the paper's), so the command can
be rebuilt.
"""

from __future__ import annotations

import json
import os
import platform
from dataclasses import MISSING, dataclass, fields
from pathlib import Path

import tyro

from vla_ladder import files
from vla_ladder.contract import METRICS
from vla_ladder.machine import cores
from vla_ladder.ppo.config import Args as PPOArgs

RESULTS = Path(__file__).parent / "results"


@dataclass
class Args:
    """Learning curves of finished (or stopped) PPO runs."""

    runs: tyro.conf.Positional[tuple[Path, ...]]
    """`vla-ladder train-expert --out` directories"""
    name: str
    """results are written to benchmarks/results/ppo_curve_<name>.json and .png"""
    labels: tuple[str, ...] = ()
    """a label per run (default: the run directory's name)"""
    device: str = ""
    """the machine, in words, to stamp into the result (default: this machine's CPU count and GPU, if any)"""
    out: Path | None = None
    """result JSON, the PNG beside it (default: benchmarks/results/ppo_curve_<name>.json)"""

    def __post_init__(self):
        missing = [str(r) for r in self.runs if not (Path(r) / "evals.json").is_file()]
        if missing:
            raise ValueError(f"not PPO runs with evaluations (no evals.json): {', '.join(missing)}")
        if self.labels and len(self.labels) != len(self.runs):
            raise ValueError(f"--labels needs one label per run: {len(self.runs)} runs, {len(self.labels)} labels")
        # the runs are kept by label: a repeated one (a/ppo and b/ppo by default) would keep only the last run
        repeated = sorted({x for x in self.run_labels() if self.run_labels().count(x) > 1})
        if repeated:
            raise ValueError(f"runs need different labels (--labels, one per run), repeated: {', '.join(repeated)}")

    def run_labels(self) -> tuple[str, ...]:
        """--labels, or each run directory's name."""
        return self.labels or tuple(Path(r).name for r in self.runs)


def changed_settings(config: dict) -> dict:
    """The run's settings that differ from the trainer's defaults (`out` aside)."""
    defaults = {f.name: f.default for f in fields(PPOArgs) if f.default is not MISSING}
    changed = {k: config[k] for k, d in defaults.items()
               if k in config and k not in ("out", "progress", "resume")
               and config[k] != json.loads(json.dumps(d, default=str))}  # as config.json stores it
    changed["conditions"] = config["conditions"]
    return changed


def curve(run: Path) -> dict:
    config = json.loads((run / "config.json").read_text())
    evals = json.loads((run / "evals.json").read_text())
    points = [{"step": e["global_step"], "wall_s": e["wall_s"], "n": e["all"]["n"],
               **{m: e["all"][m] for m in METRICS}, "ci95": e["all"]["ci95"]} for e in evals]
    first = next((p for p in points if p["success"] > 0), None)
    best = max(points, key=lambda p: tuple(p[m] for m in METRICS))  # success, then grasp-any, then reach
    last = points[-1]
    return {"run": str(run), "settings": changed_settings(config), "env_steps": last["step"],
            "train_loop_s": last["wall_s"], "env_steps_per_s": round(last["step"] / last["wall_s"], 1),
            "first_success": {k: first[k] for k in ("step", "wall_s", "success")} if first else None,
            "best": {k: best[k] for k in ("step", "wall_s", *METRICS)},
            "last": {k: last[k] for k in ("step", "wall_s", *METRICS)}, "curve": points,
            # success by instructed object at the last evaluation (runs from before it was recorded: None)
            "last_by_target": {name: {"n": r["n"], "success": r["success"]} for name, r in evals[-1]["targets"].items()}
            if "targets" in evals[-1] else None,
            "provenance": config.get("provenance")}


def machine() -> str:
    import torch
    gpu = f", {torch.cuda.get_device_name()}" if torch.cuda.is_available() else ", no GPU"
    return f"{platform.processor() or platform.machine()}, {cores()} of {os.cpu_count()} CPU cores{gpu}"


def main(args: Args) -> None:
    from vla_ladder.report.study import plot_curves

    runs = {label: curve(Path(r)) for label, r in zip(args.run_labels(), args.runs)}
    for label, r in runs.items():
        print(f"{label}: {r['env_steps']} env steps in {r['train_loop_s']:.0f} s ({r['env_steps_per_s']}/s); "
              f"first success {r['first_success']}; best {r['best']}; last by target {r['last_by_target']}")
    out = args.out or RESULTS / f"ppo_curve_{args.name}.json"
    files.write_json(out, {"benchmark": "ppo_curve", "device": args.device or machine(), "runs": runs})
    panels = {f"{label} ({r['settings'].get('num_envs', 1024)} envs)": r["curve"] for label, r in runs.items()}
    png = plot_curves(panels, out.with_suffix(".png"), xlabel="env steps", ylabel="% of evaluation episodes")
    print(f"wrote {out} and {png}")


if __name__ == "__main__":
    main(tyro.cli(Args))
