"""`vla-ladder experiment NAME --policy SPEC ... --out DIR`: one of the paper's experiments, end to end.

NAME is a config in vla_ladder/configs (ladder, pairings, data_scaling, object_count) or a path to such a
JSON file. Every policy is evaluated on the experiment's conditions through the evaluation runner (one
run directory each, under DIR/runs/), then DIR gets the paper-layout table (table.md, table.tex), its
figure, results.json and a self-contained report.html.

--policy takes a policy spec (`scripted`, `nearest`, `lerobot:PATH`, ...) or key=value pairs:
`label=SmolVLA,spec=lerobot:PATH`. data_scaling needs each checkpoint's training regime and dataset
size: `label=SmolVLA,regime=medium_jitter,size=0.5k,spec=lerobot:PATH`; a regime's row appears once
both of its configured sizes have a policy.
"""

from __future__ import annotations

import argparse
import json
import re
from dataclasses import asdict, dataclass, field, replace
from importlib import resources
from pathlib import Path

from vla_ladder.evaluation.rundir import Run, load_run
from vla_ladder.io import provenance, write_json, write_text
from vla_ladder.policies import parse_spec
from vla_ladder.report import plots, tables
from vla_ladder.task.layouts import check_args

TABLES = ("ladder", "pairings", "data_scaling", "object_count")
ENTRY_KEYS = ("label", "spec", "regime", "size")


@dataclass(frozen=True)
class Condition:
    regime: str
    split: str = "canonical"
    num_objects: int = 5

    def __post_init__(self):
        check_args(self.regime, self.split, self.num_objects)

    @property
    def key(self) -> str:
        return f"{self.regime}/{self.split}/{self.num_objects}"


@dataclass
class ExperimentConfig:
    """One of the paper's experiments: which conditions, how many episodes, which table."""

    name: str
    table: str
    """Layout of the result table: ladder, pairings, data_scaling or object_count."""
    conditions: list[Condition]
    episodes: int = 100
    """Episodes per condition (the paper uses 100)."""
    seed: int = 0
    """Episode j of every condition uses seed + j, so every policy sees the same layouts."""
    description: str = ""
    sizes: dict[str, list[str]] = field(default_factory=dict)
    """data_scaling only: regime -> [smaller, larger] dataset size labels."""

    def __post_init__(self):
        if self.table not in TABLES:
            raise ValueError(f"unknown table {self.table!r}; allowed: {', '.join(TABLES)}")
        self.conditions = [c if isinstance(c, Condition) else Condition(**c) for c in self.conditions]
        if not self.conditions:
            raise ValueError(f"experiment {self.name!r} has no conditions")
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if self.table == "data_scaling":
            regimes = {c.regime for c in self.conditions}
            bad = [r for r, s in self.sizes.items() if r not in regimes or len(s) != 2]
            if bad or set(self.sizes) != regimes:
                raise ValueError("data_scaling needs sizes: {regime: [smaller, larger]} for exactly the "
                                 f"regimes of its conditions ({', '.join(sorted(regimes))})")

    @classmethod
    def load(cls, name: str) -> "ExperimentConfig":
        path = Path(name)
        if path.suffix == ".json" and path.is_file():
            text = path.read_text()
        else:
            known = available()
            if name not in known:
                raise ValueError(f"unknown experiment {name!r}; allowed: {', '.join(known)} or a path to a JSON config")
            text = resources.files("vla_ladder.configs").joinpath(f"{name}.json").read_text()
        data = json.loads(text)
        unknown = set(data) - {f for f in cls.__dataclass_fields__}
        if unknown:
            raise ValueError(f"unknown keys in experiment config: {', '.join(sorted(unknown))}")
        return cls(**data)


def available() -> list[str]:
    return sorted(p.name[:-5] for p in resources.files("vla_ladder.configs").iterdir() if p.name.endswith(".json"))


@dataclass(frozen=True)
class PolicyEntry:
    """One policy of an experiment: its spec, a label for tables, and (data_scaling) regime and size."""

    spec: str
    label: str
    regime: str | None = None
    size: str | None = None

    @classmethod
    def parse(cls, text: str) -> "PolicyEntry":
        if not any(text.startswith(f"{k}=") for k in ENTRY_KEYS):
            parse_spec(text)
            return cls(text, text)
        fields = {}
        for part in text.split(","):
            key, eq, value = part.partition("=")
            if not eq or key not in ENTRY_KEYS or not value:
                raise ValueError(f"bad --policy {text!r}: expected SPEC or comma-separated key=value pairs with "
                                 f"keys {', '.join(ENTRY_KEYS)}")
            fields[key] = value
        if "spec" not in fields:
            raise ValueError(f"bad --policy {text!r}: needs spec=SPEC")
        parse_spec(fields["spec"])
        if "regime" in fields:
            check_args(fields["regime"])
        return cls(fields["spec"], fields.get("label", fields["spec"]), fields.get("regime"), fields.get("size"))

    @property
    def slug(self) -> str:
        parts = [self.label] + ([self.regime, self.size] if self.regime else [])
        return re.sub(r"[^A-Za-z0-9._-]+", "_", "-".join(p for p in parts if p)).strip("_") or "policy"


def plan(cfg: ExperimentConfig, entries: list[PolicyEntry]) -> list[tuple[PolicyEntry, list[Condition]]]:
    """Which conditions each policy is evaluated on; ValueError on entries that do not fit the experiment."""
    if not entries:
        raise ValueError("give at least one --policy")
    if len({e.slug for e in entries}) != len(entries):
        raise ValueError("two --policy entries share a label (and regime/size): give each a distinct label=")
    if cfg.table != "data_scaling":
        extra = [e for e in entries if e.regime or e.size]
        if extra:
            raise ValueError(f"regime=/size= are for data_scaling only, got them in experiment {cfg.name!r}")
        return [(e, list(cfg.conditions)) for e in entries]
    out = []
    for e in entries:
        if e.regime not in cfg.sizes or e.size not in cfg.sizes[e.regime]:
            allowed = "; ".join(f"regime={r},size={'|'.join(s)}" for r, s in cfg.sizes.items())
            raise ValueError(f"data_scaling --policy {e.spec!r} needs regime= and size= from: {allowed}")
        out.append((e, [c for c in cfg.conditions if c.regime == e.regime]))
    return out


def evaluate(entry: PolicyEntry, conditions: list[Condition], episodes: int, seed: int, out: Path,
             videos: int, num_envs: int, sim_backend: str) -> list[Run]:
    """Evaluate one policy on the conditions with the evaluation runner, one run directory per
    (split, object count) under `out` (a run covers several regimes); finished run dirs are reused."""
    from vla_ladder.evaluation.runner import run_evaluation
    groups: dict[tuple[str, int], list[str]] = {}
    for c in conditions:
        groups.setdefault((c.split, c.num_objects), []).append(c.regime)
    runs = []
    for (split, k), regimes in groups.items():
        run_dir = out / f"{split}-{k}obj"
        want = {Condition(r, split, k).key for r in regimes}
        if (run_dir / "summary.json").is_file():
            old = load_run(run_dir)
            if old.summary.get("seed") == seed and old.summary.get("episodes_per_condition") == episodes \
                    and set(old.summary.get("conditions", {})) == want and old.label == entry.spec:
                print(f"[experiment] reusing {run_dir}")
                runs.append(old)
                continue
        print(f"[experiment] {entry.label}: {', '.join(regimes)} / {split} / {k} objects, {episodes} episodes "
              f"-> {run_dir}")
        run_evaluation(entry.spec, regimes, split=split, num_objects=k, episodes=episodes, seed=seed, out=run_dir,
                       num_envs=num_envs, sim_backend=sim_backend, videos=videos)
        runs.append(load_run(run_dir))
    return runs


def build_outputs(cfg: ExperimentConfig, runs: list[tuple[PolicyEntry, Run]], out: Path) -> dict:
    """Table (Markdown + LaTeX), figure and results.json of finished runs."""
    results: dict[str, dict] = {}
    for e, r in runs:
        results.setdefault(e.label, {}).update(r.summary["conditions"])
    figure = out / f"{cfg.table}.png"
    if cfg.table == "data_scaling":
        stages = []
        by: dict[tuple, dict] = {}
        for e, r in runs:
            by.setdefault((e.label, e.regime, e.size), {}).update(r.summary["conditions"])
        for label in dict.fromkeys(e.label for e, _ in runs):
            for regime, (small, large) in cfg.sizes.items():
                if (label, regime, small) in by and (label, regime, large) in by:
                    stages.append({"model": label, "regime": regime, "sizes": (small, large),
                                   "before": by[label, regime, small], "after": by[label, regime, large]})
        table = tables.data_scaling_table(stages)
        if stages:
            plots.plot_data_scaling(stages, figure)
    else:
        table = {"ladder": tables.ladder_table, "pairings": tables.pairings_table,
                 "object_count": tables.object_count_table}[cfg.table](results)
        {"ladder": plots.plot_ladder, "pairings": plots.plot_pairings,
         "object_count": plots.plot_object_count}[cfg.table](results, figure)
    write_text(out / "table.md", table.to_markdown())
    write_text(out / "table.tex", table.to_latex())
    summary = {"experiment": asdict(cfg),
               "provenance": provenance(),
               "runs": [{**asdict(e), "run_dir": str(r.path.relative_to(out))} for e, r in runs],
               "results": results}
    write_json(out / "results.json", summary)
    return summary


def run_experiment(cfg: ExperimentConfig, entries: list[PolicyEntry], out: str | Path, videos: int = 0,
                   num_envs: int = 1, sim_backend: str = "physx_cpu", report: bool = True) -> Path:
    """Evaluate every entry, then write table.md, table.tex, the figure, results.json and report.html."""
    from vla_ladder.evaluation.runner import EvalConfig
    out = Path(out)
    todo = plan(cfg, entries)
    for e, conds in todo:  # every argument is checked before a simulator starts
        for c in conds:
            EvalConfig(policy=e.spec, regimes=(c.regime,), split=c.split, num_objects=c.num_objects,
                       episodes=cfg.episodes, seed=cfg.seed, num_envs=num_envs, sim_backend=sim_backend, videos=videos)
    runs = [(e, r) for e, conds in todo
            for r in evaluate(e, conds, cfg.episodes, cfg.seed, out / "runs" / e.slug, videos, num_envs,
                                 sim_backend)]
    build_outputs(cfg, runs, out)
    if report:
        from vla_ladder.report.html import build_report
        build_report([r for _, r in runs], out / "report.html", title=f"vla-ladder experiment: {cfg.name}",
                     labels=[e.label for e, _ in runs])
    print((out / "table.md").read_text())
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help=f"experiment: {', '.join(available())}, or a JSON config path")
    p.add_argument("--policy", action="append", default=[], required=True,
                   help="SPEC or label=NAME,spec=SPEC[,regime=R,size=S] (repeatable)")
    p.add_argument("--episodes", type=int, default=None, help="episodes per condition (default: the config's)")
    p.add_argument("--seed", type=int, default=None, help="first episode seed (default: the config's)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--videos", type=int, default=0, help="record videos of the first N episodes per condition")
    p.add_argument("--num-envs", type=int, default=1, help="episodes simulated at once (needs physx_cuda)")
    p.add_argument("--sim-backend", default="physx_cpu", help="physx_cpu or physx_cuda")
    p.add_argument("--no-report", action="store_true", help="skip report.html")


def run(args: argparse.Namespace) -> int:
    cfg = ExperimentConfig.load(args.name)
    cfg = replace(cfg, episodes=cfg.episodes if args.episodes is None else args.episodes,
                  seed=cfg.seed if args.seed is None else args.seed)
    out = run_experiment(cfg, [PolicyEntry.parse(t) for t in args.policy], args.out, args.videos, args.num_envs,
                         args.sim_backend, not args.no_report)
    print(out.resolve() / ("results.json" if args.no_report else "report.html"))
    return 0
