"""`vla-ladder grid`: the paper's grid search over batch size x chunk size x execution horizon.

One model is trained per (batch size, chunk size) with LeRobot training (`--train.*`: the flags of
`vla-ladder train`); each is evaluated by the evaluation runner (`--eval.*`: the flags of `vla-ladder eval`)
once per execution horizon <= its chunk size, always on the same seeded episodes. Both configs are parsed
and checked before the first training starts. The best run has the highest success rate, ties broken
by grasp-anything, then reach. Runs go one after another; a rerun of the same command skips every model
already trained and every evaluation already written, so an interrupted grid resumes.

    OUT/runs/b{B}_c{C}/train/          LeRobot run (checkpoints/last/pretrained_model)
    OUT/runs/b{B}_c{C}/eval_h{H}/      eval run directory (episodes.parquet, summary.json, ...)
    OUT/grid.parquet, OUT/grid.json    one row per evaluated (B, C, H), and the best
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import pandas as pd

from vla_ladder import files
from vla_ladder.contract import METRICS
from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
from vla_ladder.training.train import TrainConfig, check_offline_assets, checkpoint_dir, train

log = logging.getLogger(__name__)

PAPER_BATCH_SIZES = (64, 128)
PAPER_CHUNK_SIZES = (8, 16, 32)
PAPER_HORIZONS = (1, 4, 8, 16)
RANK_BY = ("success", "grasp_any", "reach")


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
    """execution horizons (n_action_steps) evaluated per model, those <= its chunk size"""

    def __post_init__(self):
        self.out = Path(self.out)
        for name in ("batch_sizes", "chunk_sizes", "horizons"):
            values = tuple(getattr(self, name))
            if not values or min(values) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be positive integers, got {list(values)}")
            setattr(self, name, values)
        if not any(h <= c for h in self.horizons for c in self.chunk_sizes):
            raise ValueError(f"no horizon in {list(self.horizons)} fits a chunk size in {list(self.chunk_sizes)}")
        if self.eval.policy or self.eval.out or self.train.out:
            raise ValueError("the grid sets --train.out, --eval.policy and --eval.out per run; leave them out")

    def settings(self) -> dict:
        """What a rerun must repeat to resume this grid (not how much work is left)."""
        return {"batch_sizes": list(self.batch_sizes), "chunk_sizes": list(self.chunk_sizes),
                "horizons": list(self.horizons), "train": asdict(self.train), "eval": asdict(self.eval)}


def overall(summary: dict) -> dict:
    """Episode-weighted rates over every condition of an eval run's summary.json."""
    conds = list(summary["conditions"].values())
    n = sum(c["n"] for c in conds)
    return {"n": n, **{m: (sum(c[m] * c["n"] for c in conds) / n if n else float("nan")) for m in METRICS}}


def best_row(df: pd.DataFrame) -> dict:
    """The run with the highest success, then grasp_any, then reach (first in grid order on a full tie)."""
    order = df.sort_values(list(RANK_BY), ascending=False, kind="stable")
    return order.iloc[0].to_dict()


def evaluate(base: EvalConfig, spec: str, out: Path) -> dict:
    """Run the evaluation runner on one checkpoint + horizon and return its summary."""
    return run_evaluation(replace(base, policy=spec, out=out))


def _done_rows(out: Path) -> dict[tuple[int, int, int], dict]:
    """Rows of an earlier, interrupted invocation whose evaluations finished (grid.parquet is rewritten
    after each evaluation, so a row there means a whole run directory)."""
    path = out / "grid.parquet"
    if not path.is_file():
        return {}
    return {(r["batch_size"], r["chunk_size"], r["n_action_steps"]): r
            for r in pd.read_parquet(path).to_dict("records") if (Path(r["eval_dir"]) / "summary.json").is_file()}


def run_grid(cfg: GridConfig) -> pd.DataFrame:
    out = cfg.out
    done = _done_rows(out)
    rows = []
    for bs in cfg.batch_sizes:
        for cs in cfg.chunk_sizes:
            model_dir = out / "runs" / f"b{bs}_c{cs}"
            train_dir = model_dir / "train"
            ckpt = checkpoint_dir(train_dir)
            if not (ckpt / "config.json").is_file() or not (train_dir / "vla_ladder_train.json").is_file():
                if train_dir.exists():
                    log.warning("removing the unfinished training run %s", train_dir)
                    shutil.rmtree(train_dir)
                log.info("grid: training batch %d, chunk %d", bs, cs)
                train(replace(cfg.train, out=train_dir, batch_size=bs, chunk_size=cs, n_action_steps=cs))
            for h in cfg.horizons:
                if h > cs:
                    continue
                if (bs, cs, h) in done:
                    rows.append(done[(bs, cs, h)])
                    continue
                spec = f"lerobot:{ckpt}?n_action_steps={h}"
                log.info("grid: evaluating b%d_c%d with horizon %d", bs, cs, h)
                summary = evaluate(cfg.eval, spec, model_dir / f"eval_h{h}")
                rows.append({"batch_size": bs, "chunk_size": cs, "n_action_steps": h, "policy": spec,
                             "train_dir": str(train_dir), "eval_dir": str(model_dir / f"eval_h{h}"),
                             **overall(summary)})
                files.write_parquet(out / "grid.parquet", pd.DataFrame(rows))
    return pd.DataFrame(rows)


def run(cfg: GridConfig) -> int:
    out = cfg.out
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {str(out)!r} is a file; give a directory")
    # LeRobot's side of the training config (policy flags, tokenizer) is checked once, before the first training.
    probe = replace(cfg.train, out=out / "runs" / ".check")
    check_offline_assets(probe.build_config().policy)
    grid = cfg.settings()
    path = out / "grid_settings.json"
    if path.is_file() and json.loads(path.read_text()) != json.loads(json.dumps(grid, default=files._default)):
        raise ValueError(f"{out} holds a grid run with other settings ({path}); use a new --out")
    files.write_json(path, grid)
    log.info("grid over %s", grid)
    df = run_grid(cfg)
    best = best_row(df)
    files.write_parquet(out / "grid.parquet", df)
    files.write_json(out / "grid.json", {"grid": grid, "rank_by": list(RANK_BY), "best": best,
                                         "runs": df.to_dict("records"), "provenance": files.provenance()})
    print(df.to_string(index=False))
    print(f"best: batch {best['batch_size']}, chunk {best['chunk_size']}, horizon {best['n_action_steps']} "
          f"(success {best['success']:.3f}, grasp_any {best['grasp_any']:.3f}, reach {best['reach']:.3f})")
    return 0
