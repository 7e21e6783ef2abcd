"""`vla-ladder grid`: the paper's grid search over batch size x chunk size x execution horizon.

One model is trained per (batch size, chunk size) with LeRobot training (`--train.*`: the flags of
`vla-ladder train`); each is evaluated by the evaluation runner (`--eval.*`: the flags of `vla-ladder eval`)
once per execution horizon <= its chunk size (diffusion: <= what it executes of a chunk, the chunk size -
n_obs_steps + 1), always on the same seeded episodes. Both configs are parsed
and checked before the first training starts. Every training and evaluation is a unit (experiments/units.py):
a child process with its log in OUT/logs/, marked done in OUT/units/; with --ray they run as Ray tasks, on a
local Ray or the cluster at --ray-address, each evaluation after its model's training. The best run has the
highest success rate, ties broken by grasp-anything, then reach. A rerun of the same command skips every unit
already done, so an interrupted grid resumes.

    OUT/runs/b{B}_c{C}/train/          LeRobot run (checkpoints/last/pretrained_model)
    OUT/runs/b{B}_c{C}/eval_h{H}/      eval run directory (episodes.parquet, summary.json, ...)
    OUT/grid.parquet, OUT/grid.json    one row per evaluated (B, C, H), and the best
"""

from __future__ import annotations

import json
import logging
import shlex
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import pandas as pd

from vla_ladder import files
from vla_ladder.checks import check_ray_address, check_output_dir
from vla_ladder.contract import METRICS, RANK_BY
from vla_ladder.evaluation.runner import EvalConfig, saved_request
from vla_ladder.experiments.units import Unit, run_units, run_units_on_ray
from vla_ladder.recordings import recorded_seeds
from vla_ladder.training.train import (TrainConfig, check_offline_assets, checkpoint_dir, sweep_problem,
                                         unfit_chunks, unfit_horizons)

log = logging.getLogger(__name__)

PAPER_BATCH_SIZES = (64, 128)
PAPER_CHUNK_SIZES = (8, 16, 32)
PAPER_HORIZONS = (1, 4, 8, 16)


@dataclass
class GridConfig:
    """The paper's grid search: train per (batch size, chunk size), evaluate per execution horizon, keep the best."""

    out: Path
    """grid directory (rerunning the same command resumes in it)"""
    train: TrainConfig
    """what to train: `vla-ladder train` flags as --train.*; the grid sets --train.out, batch, chunk, horizon"""
    eval: EvalConfig = field(default_factory=EvalConfig)
    """how to evaluate: `vla-ladder eval` flags as --eval.*; the grid sets --eval.policy and --eval.out"""
    batch_sizes: tuple[int, ...] = PAPER_BATCH_SIZES
    """batch sizes trained"""
    chunk_sizes: tuple[int, ...] = PAPER_CHUNK_SIZES
    """action chunk sizes trained"""
    horizons: tuple[int, ...] = PAPER_HORIZONS
    """execution horizons (n_action_steps) evaluated per model, those <= its chunk size (diffusion: <= the chunk
    size - n_obs_steps + 1, what it executes of a chunk)"""
    ray: bool = False
    """run the trainings and evaluations as Ray tasks (a local Ray, or the cluster at --ray-address)"""
    ray_address: str | None = None
    """address of a running Ray cluster (implies --ray)"""

    def __post_init__(self):
        self.out = check_output_dir(self.out, "--out")  # a file, the root: now
        for name in ("batch_sizes", "chunk_sizes", "horizons"):
            values = tuple(getattr(self, name))
            if not values or min(values) < 1 or len(set(values)) != len(values):  # a repeat: two units, one directory
                raise ValueError(f"--{name.replace('_', '-')} must be distinct positive integers, got {list(values)}")
            setattr(self, name, values)
        check_ray_address(self.ray_address)
        if unsweepable := sweep_problem(self.train.policy_type):
            raise ValueError(f"--train.policy-type {self.train.policy_type}: {unsweepable}")
        if unfit := unfit_chunks(self.train.policy_type, self.chunk_sizes, self.train.lerobot_args):
            raise ValueError(f"--chunk-sizes {unfit}")
        if unfit := unfit_horizons(self.train.policy_type, self.chunk_sizes, self.horizons, self.train.lerobot_args):
            raise ValueError(unfit)
        if self.eval.policy or self.eval.out or self.train.out:
            raise ValueError("the grid sets --train.out, --eval.policy and --eval.out per run; leave them out")
        if self.train.given:  # they were replaced by each model's, unsaid
            raise ValueError(f"the grid sets {', '.join(f'--train.{f[2:]}' for f in self.train.given)} per model; "
                             "give --batch-sizes, --chunk-sizes and --horizons instead")

    def settings(self) -> dict:
        """What a rerun must repeat to resume this grid (not how much work is left)."""
        return {"batch_sizes": list(self.batch_sizes), "chunk_sizes": list(self.chunk_sizes),
                "horizons": list(self.horizons), "train": asdict(self.train), "eval": self.eval.request()}


def settings_as_now(saved: dict) -> dict:
    """grid_settings.json as this version writes it: the evaluation's request, which leaves out how it runs (workers,
    batching: the same episodes) and holds the fields added since at the value their absence meant."""
    return {**saved, "eval": saved_request(saved.get("eval", {}))}


def overall(summary: dict) -> dict:
    """Episode-weighted rates over every condition of an eval run's summary.json."""
    conds = list(summary["conditions"].values())
    n = sum(c["n"] for c in conds)
    return {"n": n, **{m: (sum(c[m] * c["n"] for c in conds) / n if n else float("nan")) for m in METRICS}}


def best_row(df: pd.DataFrame) -> dict:
    """The run with the highest success, then grasp_any, then reach (first in grid order on a full tie)."""
    order = df.sort_values(list(RANK_BY), ascending=False, kind="stable")
    return order.iloc[0].to_dict()


def held_out_command(cfg: GridConfig, best: dict) -> str:
    """`vla-ladder eval` of the best run on the episodes after the grid's: the best of several runs on the same
    episodes won partly by their luck, so its rates there lean high."""
    e, g = cfg.eval, cfg.eval.grid
    settings = []  # the grid's other --eval.* settings, those not at their defaults
    for f in fields(EvalConfig):
        value = getattr(e, f.name)
        if f.name in ("policy", "out", "grid", "episodes", "first_seed", "overwrite") or value == f.default:
            continue
        flag = f"--{f.name.replace('_', '-')}"
        settings += [flag if value else f"--no-{flag[2:]}"] if isinstance(value, bool) else [flag, str(value)]
    return shlex.join(["vla-ladder", "eval", "--policy", best["policy"], "--regimes", *g.regimes, "--splits",
                       *g.splits, "--num-objects", *map(str, g.num_objects), "--episodes", str(e.episodes),
                       "--first-seed", str(e.first_seed + e.episodes), *settings,
                       "--out", str(cfg.out / "best_held_out")])


def model_train(cfg: GridConfig, bs: int, cs: int) -> TrainConfig:
    """The training of the grid's (batch size, chunk size) model, into OUT/runs/b{B}_c{C}/train, saved with the
    longest horizon it executes (the chunk; diffusion's less n_obs_steps - 1)."""
    return replace(cfg.train, out=cfg.out / "runs" / f"b{bs}_c{cs}" / "train", batch_size=bs, chunk_size=cs,
                   n_action_steps=cfg.train.max_action_steps(cs))


def units(cfg: GridConfig) -> tuple[list[Unit], list[tuple[int, int, int, Unit]]]:
    """The training units, and (batch, chunk, horizon, unit) for every evaluation."""
    trains, evals = [], []
    for bs in cfg.batch_sizes:
        for cs in cfg.chunk_sizes:
            train = model_train(cfg, bs, cs)
            model_dir = train.out.parent
            trains.append(Unit(f"train-b{bs}_c{cs}", "train", "vla_ladder.experiments.units:train_unit",
                               files.plain(asdict(train)), cpus=2))
            for h in cfg.horizons:
                if h <= cfg.train.max_action_steps(cs):
                    spec = f"lerobot:{checkpoint_dir(model_dir / 'train')}?n_action_steps={h}"
                    ev = replace(cfg.eval, policy=spec, out=model_dir / f"eval_h{h}")
                    evals.append((bs, cs, h, Unit(f"eval-b{bs}_c{cs}_h{h}", "eval",
                                                  "vla_ladder.experiments.units:eval_unit", files.plain(asdict(ev)),
                                                  cpus=2, after=[f"train-b{bs}_c{cs}"])))
    return trains, evals


def run_grid(cfg: GridConfig) -> pd.DataFrame:
    trains, evals = units(cfg)
    every = trains + [u for *_, u in evals]
    if cfg.ray or cfg.ray_address:
        results = run_units_on_ray(every, cfg.out, cfg.ray_address)
    else:
        results = run_units(every, cfg.out)
    rows = []
    for bs, cs, h, unit in evals:
        summary = json.loads((Path(unit.config["out"]) / "summary.json").read_text())
        rows.append({"batch_size": bs, "chunk_size": cs, "n_action_steps": h, "policy": unit.config["policy"],
                     "train_dir": str(cfg.out / "runs" / f"b{bs}_c{cs}" / "train"), "eval_dir": unit.config["out"],
                     **overall(summary)})
    del results
    return pd.DataFrame(rows)


def check_unseen_seeds(cfg: GridConfig) -> None:
    """ValueError when the grid's episodes, or the held-out ones after them (held_out_command), play a seed its
    training data were recorded on. A seed is a scene: in the data's condition the very layout, target and
    instruction of a demonstration, and in the other jitter regimes nearly the same one (the same draws, scaled),
    so a model scored there is scored on what it was trained on; a study keeps the two apart the same way
    (study_config._check_seeds). Eval starts at seed 0, record at RECORD_FIRST_SEED (at 0 before 2026-11-28)."""
    e = cfg.eval
    played = range(e.first_seed, e.first_seed + 2 * e.episodes)
    seeds = recorded_seeds(cfg.train.dataset)
    if not any(s in played for s in seeds):
        return
    lo, hi = min(seeds), max(seeds)
    below = f", or one that ends below {lo}" if lo >= 2 * e.episodes else ""
    raise ValueError(f"--eval.first-seed {e.first_seed}: the grid plays seeds {played.start}-"
                     f"{played.start + e.episodes - 1} and its best's held-out evaluation the next {e.episodes}, "
                     f"and the training data {str(cfg.train.dataset)!r} were recorded on seeds {lo}-{hi}: the same "
                     f"scenes (a seed's layout and target, nearly alike in every jitter regime); give "
                     f"--eval.first-seed {hi + 1} or above{below}")


def run(cfg: GridConfig) -> int:
    out = cfg.out  # (a file there was refused with the config: check_output_dir)
    if cfg.train.print_command:  # a dry run: each model's lerobot-train command, nothing written
        for bs in cfg.batch_sizes:
            for cs in cfg.chunk_sizes:
                print(shlex.join(model_train(cfg, bs, cs).lerobot_command()))
        return 0
    check_unseen_seeds(cfg)
    # LeRobot's side of the training config (policy flags, tokenizer) is checked once, before the first training.
    probe = replace(cfg.train, out=out / "runs" / ".check")
    check_offline_assets(probe.build_config().policy)
    grid = cfg.settings()
    path = out / "grid_settings.json"
    if path.is_file() and (differs := files.first_difference(settings_as_now(json.loads(path.read_text())),
                                                               files.plain(grid))):
        raise ValueError(f"{out} holds a grid run with other settings ({path}: its {differs} differs); use a new "
                         "--out")
    files.write_json(path, grid)
    log.info("grid over %s", grid)
    df = run_grid(cfg)
    best = best_row(df)
    files.write_parquet(out / "grid.parquet", df)
    held_out = held_out_command(cfg, best)
    files.write_json(out / "grid.json", {"grid": grid, "rank_by": list(RANK_BY), "best": best,
                                         "best_held_out_command": held_out, "runs": df.to_dict("records"),
                                         "provenance": files.provenance()})
    print(df.to_string(index=False))
    print(f"best: batch {best['batch_size']}, chunk {best['chunk_size']}, horizon {best['n_action_steps']} "
          f"(success {best['success']:.3f}, grasp_any {best['grasp_any']:.3f}, reach {best['reach']:.3f}): the best "
          f"of {len(df)} runs on the same episodes, so these rates lean high; on held-out episodes:\n  {held_out}")
    return 0
