"""Units of work that survive kills: each runs in a child process, logs to a file, and is marked done once whole.

A unit is a named call of one stage's library function on one config (record a dataset, train a model, evaluate
it). `run_units` skips units already marked done and runs the others one after another, each in a child process
that dies with its parent (so a kill -9 of the study leaves no orphan writing), with its stdout/stderr in
DIR/logs/<unit>.log. A unit killed half-way is simply run again: the recorder, the evaluation runner and training
resume their own files (a training run from its last whole checkpoint). `RayExecutor` runs the same units as Ray
tasks, locally or on a cluster (`ray.init(address=...)`), gathering results the same way.
"""

from __future__ import annotations

import importlib
import json
import multiprocessing
import os
import shutil
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from vla_ladder import files
from vla_ladder.conditions import Condition
from vla_ladder.contract import METRICS
from vla_ladder.machine import signal_on_parent_death


@dataclass
class Unit:
    """One call of `function` ("module:name") with `config`, the stage's config dataclass as a dict."""

    id: str
    """unique and file-name safe, e.g. train-smolvla-sj-b64c16"""
    stage: str
    """record, train, select, eval, ... (progress and ETA are per stage)"""
    function: str
    config: dict
    cpus: int = 1
    """cores the unit keeps busy (a hint for parallel executors)"""
    after: list[str] = field(default_factory=list)
    """ids of units that must be done first"""


def marker(root: Path, unit: Unit) -> Path:
    return root / "units" / f"{unit.id}.json"


# How many processes play a unit's episodes: any number gives the same episodes (tested for eval and record), so
# a study resumed with other --workers/--writers/--num-envs (another machine, after a GPU lease ended) keeps its
# done units and their markers, which hold the wall time of the machine that ran them.
PROCESS_COUNTS = ("workers", "writers", "num_envs")


def is_done(root: Path, unit: Unit) -> bool:
    """Done means marked done for this very config, process counts aside: any other change runs it again."""
    path = marker(root, unit)
    return path.is_file() and _what_it_computes(json.loads(path.read_text()).get("config")) == \
        _what_it_computes(files.plain(unit.config))


def _what_it_computes(config: dict | None) -> dict | None:
    return None if config is None else {k: v for k, v in config.items() if k not in PROCESS_COUNTS}


def call(function: str, config: dict) -> Any:
    """Import and call a unit's function with its config."""
    module, _, name = function.partition(":")
    return getattr(importlib.import_module(module), name)(config)


def _child(function: str, config: dict, log: str, result_path: str) -> None:
    signal_on_parent_death(signal.SIGKILL)
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    sys.stdout = os.fdopen(1, "w", buffering=1, closefd=False)
    sys.stderr = os.fdopen(2, "w", buffering=1, closefd=False)
    print(f"==== {time.strftime('%Y-%m-%d %H:%M:%S')} {function}", flush=True)
    result = call(function, config)
    files.write_json(result_path, {"result": result})


def run_in_child(unit: Unit, root: Path) -> Any:
    """Run one unit in a spawned child process; RuntimeError (naming its log) if it fails."""
    log = root / "logs" / f"{unit.id}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    result_path = root / "units" / f".{unit.id}.result.json"
    result_path.unlink(missing_ok=True)
    ctx = multiprocessing.get_context("spawn")
    proc = ctx.Process(target=_child, args=(unit.function, unit.config, str(log), str(result_path)),
                       name=f"unit-{unit.id}")
    proc.start()
    try:
        proc.join()
    except BaseException:
        proc.kill()
        proc.join()
        raise
    if proc.exitcode != 0 or not result_path.is_file():
        tail = log.read_text(errors="replace").splitlines()[-15:] if log.is_file() else []
        raise RuntimeError(f"unit {unit.id} failed (exit code {proc.exitcode}); its log is {log}:\n"
                           + "\n".join(tail))
    result = json.loads(result_path.read_text())["result"]
    result_path.unlink()
    return result


def mark_done(root: Path, unit: Unit, result: Any, wall_s: float) -> None:
    files.write_json(marker(root, unit), {"id": unit.id, "stage": unit.stage, "function": unit.function,
                                         "config": files.plain(unit.config), "result": result,
                                         "wall_s": round(wall_s, 1),
                                         "finished": time.strftime("%Y-%m-%dT%H:%M:%S")})


class Progress:
    """One line per unit: which stage and unit run, how many are left, and an ETA from the units done so far."""

    def __init__(self, units: Sequence[Unit], root: Path):
        self.total = {s: sum(u.stage == s for u in units) for s in dict.fromkeys(u.stage for u in units)}
        self.done = {s: 0 for s in self.total}
        self.seconds: dict[str, list[float]] = {s: [] for s in self.total}
        for u in units:
            if is_done(root, u):
                self.done[u.stage] += 1
        self.started = time.monotonic()

    def start(self, unit: Unit) -> None:
        print(f"[study] {unit.stage} {self.done[unit.stage] + 1}/{self.total[unit.stage]}: {unit.id} "
              f"(ETA {self.eta()})", flush=True)

    def finish(self, unit: Unit, wall: float) -> None:
        self.done[unit.stage] += 1
        self.seconds[unit.stage].append(wall)
        print(f"[study] done {unit.id} in {wall:.0f} s", flush=True)

    def eta(self) -> str:
        known = [x for v in self.seconds.values() for x in v]
        if not known:
            return "after the first unit"
        mean = sum(known) / len(known)
        left = sum((self.total[s] - self.done[s]) * (sum(v) / len(v) if (v := self.seconds[s]) else mean)
                   for s in self.total)
        return time.strftime("%H:%M:%S", time.localtime(time.time() + left))


def run_units(units: Sequence[Unit], root: Path, executor: "Callable | None" = None) -> dict[str, Any]:
    """Run every unit not yet done, in order; return every unit's result (done ones from their markers)."""
    progress = Progress(units, root)
    results: dict[str, Any] = {}
    for unit in units:
        if is_done(root, unit):
            results[unit.id] = json.loads(marker(root, unit).read_text())["result"]
            continue
        progress.start(unit)
        t0 = time.monotonic()
        results[unit.id] = (executor or run_in_child)(unit, root)
        wall = time.monotonic() - t0
        mark_done(root, unit, results[unit.id], wall)
        progress.finish(unit, wall)
    return results


def run_units_on_ray(units: Sequence[Unit], root: Path, address: str | None = None) -> dict[str, Any]:
    """The same units as Ray tasks (one task a unit, `cpus` cores each), dependencies respected; units already
    done are skipped, and each task marks its unit done, so an interrupted run resumes like a local one."""
    import ray

    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)

    @ray.remote
    def task(unit: Unit, root: str, *deps) -> Any:
        t0 = time.monotonic()
        result = run_in_child(unit, Path(root))
        mark_done(Path(root), unit, result, time.monotonic() - t0)
        return result

    refs: dict[str, Any] = {}
    results: dict[str, Any] = {}
    for unit in units:
        if is_done(root, unit):
            results[unit.id] = json.loads(marker(root, unit).read_text())["result"]
            continue
        deps = [refs[d] for d in unit.after if d in refs]
        refs[unit.id] = task.options(num_cpus=unit.cpus, name=unit.id).remote(unit, str(root), *deps)
        print(f"[study] submitted {unit.stage} unit {unit.id} to Ray", flush=True)
    for uid, ref in refs.items():
        results[uid] = ray.get(ref)
        print(f"[study] done {uid}", flush=True)
    return results


# ---------------------------------------------------------------------- the stages as units (run in children)
def record_unit(config: dict) -> dict:
    from vla_ladder.recording.record import RecordConfig, run
    cfg = RecordConfig(out=config["out"], episodes=config["episodes"], condition=Condition.parse(config["condition"]),
                       policy=config["policy"], first_seed=config["first_seed"], workers=config["workers"],
                       writers=config["writers"])
    if run(cfg) != 0:
        raise RuntimeError(f"recording {cfg.out} stopped before {cfg.episodes} episodes")
    from vla_ladder.recordings import read_recording_state
    return read_recording_state(cfg.out)["counters"]


def train_unit(config: dict) -> dict:
    from vla_ladder.training.train import REQUEST_FILE, RUN_FILE, TrainConfig, train
    out = Path(config["out"])
    if out.is_dir() and not (out / REQUEST_FILE).is_file():  # killed before runs kept their request: start over
        shutil.rmtree(out)
    import torch
    if config.get("device") == "auto":  # resolved here, on the machine that trains: the unit's config stays the same
        config = {**config, "device": "cuda" if torch.cuda.is_available() else "cpu"}
    elif str(config.get("device")).startswith("cuda") and not torch.cuda.is_available():
        # A study planned for a GPU, finished on a CPU machine (docs/study.md): said, not refused (`train` refuses).
        print(f"[study] {out.name}: no GPU here, so this training runs (or resumes) on the CPU", flush=True)
        config = {**config, "device": "cpu"}
    ckpt = train(TrainConfig(**config))  # a run killed after its request was kept resumes from its last checkpoint
    info = json.loads((out / RUN_FILE).read_text())
    return {"checkpoint": str(ckpt), "wall_s": info["wall_s"]}


def probe_unit(config: dict) -> dict:
    from vla_ladder.experiments.probes import ProbeConfig, run_probe
    data = run_probe(ProbeConfig(**config), progress=False)
    return {"probe": data["probe"], "conditions": data["conditions"]}


def eval_unit(config: dict) -> dict:
    from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
    summary = run_evaluation(EvalConfig(**config))
    return {"conditions": {k: {m: c[m] for m in ("n", *METRICS)} for k, c in summary["conditions"].items()}}
