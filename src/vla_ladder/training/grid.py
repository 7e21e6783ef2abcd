"""`vla-ladder grid`: the paper's grid search over batch size x chunk size x execution horizon.

One model is trained per (batch size, chunk size) with `vla-ladder train`; each is evaluated by the eval
runner (`vla-ladder eval`) once per execution horizon <= its chunk size, always with the same evaluation
arguments and therefore the same seeded episodes. The best run has the highest success rate, ties broken
by grasp-anything, then reach. Runs go one after another; a rerun of the same command skips every model
already trained and every evaluation already written, so an interrupted grid resumes.

    OUT/runs/b{B}_c{C}/train/          LeRobot run (checkpoints/last/pretrained_model)
    OUT/runs/b{B}_c{C}/eval_h{H}/      eval run directory (episodes.parquet, summary.json, ...)
    OUT/grid.parquet, OUT/grid.json    one row per evaluated (B, C, H), and the best
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import shutil
from dataclasses import replace
from pathlib import Path

import pandas as pd

from vla_ladder import io
from vla_ladder.evaluation.metrics import METRICS
from vla_ladder.training import cli as train_cli

log = logging.getLogger(__name__)

PAPER_BATCH_SIZES = (64, 128)
PAPER_CHUNK_SIZES = (8, 16, 32)
PAPER_HORIZONS = (1, 4, 8, 16)
RANK_BY = ("success", "grasp_any", "reach")


def int_list(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"expected comma-separated integers such as 8,16,32, got {text!r}") from None
    if not values or min(values) < 1:
        raise ValueError(f"expected positive integers, got {text!r}")
    return values


def overall(summary: dict) -> dict:
    """Episode-weighted rates over every condition of an eval run's summary.json."""
    conds = list(summary["conditions"].values())
    n = sum(c["n"] for c in conds)
    return {"n": n, **{m: (sum(c[m] * c["n"] for c in conds) / n if n else float("nan")) for m in METRICS}}


def best_row(df: pd.DataFrame) -> dict:
    """The run with the highest success, then grasp_any, then reach (first in grid order on a full tie)."""
    order = df.sort_values(list(RANK_BY), ascending=False, kind="stable")
    return order.iloc[0].to_dict()


def check_eval_args(eval_args: list[str]) -> None:
    """Parse the eval arguments as `vla-ladder eval` will, so a typo fails before any training."""
    from vla_ladder.cli import build_parser

    for flag in ("--policy", "--out"):
        if any(a == flag or a.startswith(flag + "=") for a in eval_args):
            raise ValueError(f"--eval-args must not set {flag}; the grid sets it per run")
    parser, modules = build_parser("eval")
    if "eval" not in modules:
        raise ValueError("the eval runner (vla_ladder.evaluation.cli) is not available in this build")
    try:
        parser.parse_args(["eval", "--policy", "lerobot:CKPT", "--out", "DIR", *eval_args])
    except SystemExit:
        raise ValueError(f"--eval-args {shlex.join(eval_args)!r} are not valid `vla-ladder eval` arguments "
                         "(it needs at least --regime, --episodes and --seed)") from None


def evaluate(spec: str, out: Path, eval_args: list[str]) -> dict:
    """Run the eval runner on one checkpoint + horizon and return its summary."""
    from vla_ladder.cli import main as cli_main
    from vla_ladder.evaluation.rundir import load_run

    rc = cli_main(["eval", "--policy", spec, "--out", str(out), *eval_args])
    if rc != 0:
        raise RuntimeError(f"vla-ladder eval failed ({rc}) for {spec}")
    return load_run(out).summary


def _done_rows(out: Path) -> dict[tuple[int, int, int], dict]:
    """Rows of an earlier, interrupted invocation whose evaluations finished (grid.parquet is rewritten
    after each evaluation, so a row there means a whole run directory)."""
    path = out / "grid.parquet"
    if not path.is_file():
        return {}
    return {(r["batch_size"], r["chunk_size"], r["n_action_steps"]): r
            for r in pd.read_parquet(path).to_dict("records") if (Path(r["eval_dir"]) / "summary.json").is_file()}


def run_grid(base: train_cli.TrainRequest, out: Path, batch_sizes, chunk_sizes, horizons,
             eval_args: list[str]) -> pd.DataFrame:
    done = _done_rows(out)
    rows = []
    for bs in batch_sizes:
        for cs in chunk_sizes:
            model_dir = out / "runs" / f"b{bs}_c{cs}"
            train_dir = model_dir / "train"
            ckpt = train_cli.checkpoint_dir(train_dir)
            if not (ckpt / "config.json").is_file() or not (train_dir / "vla_ladder_train.json").is_file():
                if train_dir.exists():
                    log.warning("removing the unfinished training run %s", train_dir)
                    shutil.rmtree(train_dir)
                log.info("grid: training batch %d, chunk %d", bs, cs)
                req = replace(base, out=train_dir, batch_size=bs, chunk_size=cs, n_action_steps=cs)
                train_cli.train(req)
            for h in horizons:
                if h > cs:
                    continue
                if (bs, cs, h) in done:
                    rows.append(done[(bs, cs, h)])
                    continue
                spec = f"lerobot:{ckpt}?n_action_steps={h}"
                log.info("grid: evaluating b%d_c%d with horizon %d", bs, cs, h)
                summary = evaluate(spec, model_dir / f"eval_h{h}", eval_args)
                rows.append({"batch_size": bs, "chunk_size": cs, "n_action_steps": h, "policy": spec,
                             "train_dir": str(train_dir), "eval_dir": str(model_dir / f"eval_h{h}"),
                             **overall(summary)})
                io.write_parquet(out / "grid.parquet", pd.DataFrame(rows))
    return pd.DataFrame(rows)


def add_arguments(p: argparse.ArgumentParser) -> None:
    train_cli.add_arguments(p)
    for action in p._actions:  # the grid sets these per run
        if action.dest in ("batch_size", "chunk_size", "n_action_steps", "print_command"):
            action.help = argparse.SUPPRESS
        elif action.dest == "out":
            action.help = "grid directory (rerunning the same command resumes in it)"
    p.add_argument("--batch-sizes", type=int_list, default=PAPER_BATCH_SIZES, help="default: 64,128")
    p.add_argument("--chunk-sizes", type=int_list, default=PAPER_CHUNK_SIZES, help="default: 8,16,32")
    p.add_argument("--horizons", type=int_list, default=PAPER_HORIZONS,
                   help="execution horizons (n_action_steps) evaluated per model; default: 1,4,8,16")
    p.add_argument("--eval-args", default="",
                   help="arguments for every `vla-ladder eval`, e.g. \"--regime full_random --episodes 100\"")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    eval_args = shlex.split(args.eval_args)
    check_eval_args(eval_args)
    # Validates policy type, dataset and training flags once, before the first (long) training.
    args.out = out / "runs" / ".check"
    base = train_cli.request_from_args(args)
    train_cli.check_offline_assets(base.build_config().policy)
    grid = {"batch_sizes": list(args.batch_sizes), "chunk_sizes": list(args.chunk_sizes),
            "horizons": list(args.horizons), "eval_args": eval_args, "policy_type": base.policy_type,
            "dataset": str(base.dataset), "steps": base.steps, "extra": base.extra}
    settings = out / "grid_settings.json"
    if settings.is_file() and json.loads(settings.read_text()) != grid:
        raise ValueError(f"{out} holds a grid run with other settings ({settings}); use a new --out")
    io.write_json(settings, grid)
    log.info("grid over %s", grid)
    df = run_grid(base, out, args.batch_sizes, args.chunk_sizes, args.horizons, eval_args)
    if df.empty:
        raise ValueError(f"no horizon in {list(args.horizons)} fits a chunk size in {list(args.chunk_sizes)}")
    best = best_row(df)
    io.write_parquet(out / "grid.parquet", df)
    io.write_json(out / "grid.json", {"grid": grid, "rank_by": list(RANK_BY), "best": best,
                                      "runs": df.to_dict("records"), "provenance": io.provenance()})
    print(df.to_string(index=False))
    print(f"best: batch {best['batch_size']}, chunk {best['chunk_size']}, horizon {best['n_action_steps']} "
          f"(success {best['success']:.3f}, grasp_any {best['grasp_any']:.3f}, reach {best['reach']:.3f})")
    return 0
