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

import json
import re
from dataclasses import MISSING, asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Annotated, ClassVar

import tyro

from vla_ladder.checks import check_count, check_output_dir
from vla_ladder.conditions import Condition, ConditionGrid
from vla_ladder.evaluation.rundir import Run, load_run
from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
from vla_ladder.files import provenance, write_json, write_text
from vla_ladder.policies import check_spec, parse_spec
from vla_ladder.report import plots, tables

TABLES = ("ladder", "pairings", "data_scaling", "object_count")
ENTRY_KEYS = ("label", "spec", "regime", "size")


@dataclass
class ExperimentConfig:
    """One of the paper's experiments: which conditions, how many episodes, which table."""

    name: str
    table: str
    """Layout of the result table: ladder, pairings, data_scaling or object_count."""
    conditions: list[Condition]
    episodes: int = 100
    """Episodes per condition (the paper uses 100)."""
    first_seed: int = 0
    """Episode j of every condition uses seed first_seed + j, so every policy sees the same layouts."""
    description: str = ""
    sizes: dict[str, list[str]] = field(default_factory=dict)
    """data_scaling only: regime -> [smaller, larger] dataset size labels."""

    def __post_init__(self):
        if self.table not in TABLES:
            raise ValueError(f"unknown table {self.table!r}; allowed: {', '.join(TABLES)}")
        if not isinstance(self.conditions, list):
            raise ValueError(f"conditions: expected a list of conditions (regime/split/num_objects), got "
                             f"{type(self.conditions).__name__}")
        self.conditions = [Condition.of(c) for c in self.conditions]
        if not self.conditions:
            raise ValueError(f"experiment {self.name!r} has no conditions")
        check_count(self.episodes, "episodes")
        check_count(self.first_seed, "first_seed", least=0)
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
            text = path.read_bytes()
        else:
            known = available()
            if name not in known:
                raise ValueError(f"unknown experiment {name!r}; allowed: {', '.join(known)} or a path to a JSON config")
            text = resources.files("vla_ladder.configs").joinpath(f"{name}.json").read_text()
        try:
            data = json.loads(text)
        except ValueError as e:  # JSONDecodeError, or bytes that are not UTF-8
            raise ValueError(f"{name}: not a JSON experiment config ({e})") from None
        fields = list(cls.__dataclass_fields__)
        required = [f for f in fields if cls.__dataclass_fields__[f].default is MISSING
                    and cls.__dataclass_fields__[f].default_factory is MISSING]
        if not isinstance(data, dict) or set(data) - set(fields) or set(required) - set(data):
            raise ValueError(f"{name}: expected an object with {', '.join(required)} and optionally "
                             f"{', '.join(f for f in fields if f not in required)}; got "
                             f"{sorted(data) if isinstance(data, dict) else type(data).__name__}")
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
        # A spec may hold commas of its own (a plugin's `constant:A0,...,A6`): split only before the next key.
        for part in re.split(rf",(?=(?:{'|'.join(ENTRY_KEYS)})=)", text):
            key, eq, value = part.partition("=")
            if not eq or key not in ENTRY_KEYS or not value or ("," in value and key != "spec"):
                raise ValueError(f"bad --policy {text!r}: expected SPEC or comma-separated key=value pairs with "
                                 f"keys {', '.join(ENTRY_KEYS)}")
            if key in fields:
                raise ValueError(f"bad --policy {text!r}: {key} given twice")
            fields[key] = value
        if "spec" not in fields:
            raise ValueError(f"bad --policy {text!r}: needs spec=SPEC")
        parse_spec(fields["spec"])
        if "regime" in fields:
            Condition(fields["regime"])
        return cls(fields["spec"], fields.get("label", fields["spec"]), fields.get("regime"), fields.get("size"))

    @property
    def slug(self) -> str:
        parts = [self.label] + ([self.regime, self.size] if self.regime else [])
        return re.sub(r"[^A-Za-z0-9._-]+", "_", "-".join(p for p in parts if p)).strip("_") or "policy"


def plan(cfg: ExperimentConfig, entries: list[PolicyEntry]) -> list[tuple[PolicyEntry, list[Condition]]]:
    """Which conditions each policy is evaluated on; ValueError on entries that do not fit the experiment."""
    if not entries:
        raise ValueError("give at least one --policy")
    seen: dict[str, PolicyEntry] = {}
    for e in entries:
        if (first := seen.setdefault(e.slug, e)) is not e:  # a label is a run directory's name, cleaned
            raise ValueError(f"two --policy entries share a label (and regime/size): {first.label!r} and {e.label!r} "
                             f"both name runs/{e.slug}; give each a distinct label= (letters, digits, '.', '_' and "
                             "'-' are kept, anything else becomes '_')")
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


def eval_configs(entry: PolicyEntry, conditions: list[Condition], base: EvalConfig, out: Path) -> list[EvalConfig]:
    """One evaluation run per (split, object count) of the conditions (a run covers several regimes)."""
    groups: dict[tuple[str, int], list[str]] = {}
    for c in conditions:
        groups.setdefault((c.split, c.num_objects), []).append(c.regime)
    return [EvalConfig(policy=entry.spec, out=out / f"{split}-{k}obj",
                       grid=ConditionGrid(tuple(regimes), (split,), (k,)), episodes=base.episodes,
                       first_seed=base.first_seed, workers=base.workers, num_envs=base.num_envs,
                       sim_backend=base.sim_backend,
                       videos=base.videos, object_set=base.object_set)
            for (split, k), regimes in groups.items()]


def evaluate(entry: PolicyEntry, cfg: EvalConfig) -> Run:
    """Evaluate one policy with the evaluation runner (which resumes a run directory of the same request)."""
    print(f"[experiment] {entry.label}: {', '.join(c.key for c in cfg.conditions)}, {cfg.episodes} episodes "
          f"-> {cfg.out}")
    run_evaluation(cfg)
    return load_run(cfg.out)


def build_outputs(cfg: ExperimentConfig, runs: list[tuple[PolicyEntry, Run]], out: Path) -> dict:
    """Table (Markdown + LaTeX), figure and results.json of finished runs."""
    results: dict[str, dict] = {}
    for e, r in runs:
        # Data scaling evaluates one model per dataset size on the same conditions: keep each size apart.
        results.setdefault(e.label if e.size is None else f"{e.label}@{e.size}", {}).update(r.summary["conditions"])
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


@dataclass
class ExperimentCommand:
    """Run one of the paper's experiments end to end: evaluate every policy, then the table, figure and report."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    """experiment: ladder, pairings, data_scaling, object_count, or a path to a JSON config"""
    out: Path
    """output directory: runs/, table.md, table.tex, the figure, results.json, report.html"""
    policy: Annotated[tuple[str, ...], tyro.conf.arg(metavar="SPEC [SPEC ...]", help_behavior_hint="(required)")] = ()
    """the policies, one value each: a spec (as `vla-ladder eval --policy`) or label=NAME,spec=SPEC[,regime=R,size=S]"""
    episodes: Annotated[int | None, tyro.conf.arg(metavar="INT", help_behavior_hint=(
        "(default: the experiment's; 100 in the paper's four)"))] = None
    """episodes per condition"""
    first_seed: Annotated[int | None, tyro.conf.arg(metavar="INT", help_behavior_hint=(
        "(default: the experiment's; 0 in the paper's four)"))] = None
    """episode j of every condition plays seed first_seed + j, so every policy meets the same layouts"""
    videos: int = 0
    """write MP4s of both cameras for the first K episodes of each condition (the report's rollouts)"""
    workers: int = 0
    """worker processes playing episodes on the CPU backend, each with its own copy of the policy (0: one per
    core, capped by memory); any number gives the same episodes"""
    num_envs: int = 1
    """episodes one copy of the policy acts on at once (batched inference; see `vla-ladder eval --num-envs`)"""
    sim_backend: str = "physx_cpu"
    """physx_cpu or physx_cuda (needs a CUDA GPU)"""
    report: bool = True
    """write report.html"""

    REQUIRED_ON_COMMAND_LINE: ClassVar[tuple[str, ...]] = ("policy",)

    def __post_init__(self):
        self.out = check_output_dir(self.out, "--out")  # a file, the root: now
        self.config = ExperimentConfig.load(self.name)
        if self.episodes is not None:
            self.config.episodes = self.episodes
        if self.first_seed is not None:
            self.config.first_seed = self.first_seed
        self.config.__post_init__()
        self.entries = [PolicyEntry.parse(t) for t in self.policy]
        for spec in dict.fromkeys(e.spec for e in self.entries):  # every policy, before the first one plays
            check_spec(spec)
        todo = plan(self.config, self.entries)
        # Every evaluation is configured (and so checked) before a simulator starts.
        self.evals = [(e, ec) for e, conds in todo
                      for ec in eval_configs(e, conds, self.base_eval(), self.out / "runs" / e.slug)]

    def base_eval(self) -> EvalConfig:
        return EvalConfig(episodes=self.config.episodes, first_seed=self.config.first_seed, workers=self.workers,
                          num_envs=self.num_envs,
                          sim_backend=self.sim_backend, videos=self.videos)


def run_experiment(cmd: ExperimentCommand) -> Path:
    """Evaluate every entry, then write table.md, table.tex, the figure, results.json and report.html."""
    cfg, out = cmd.config, cmd.out
    runs = [(e, evaluate(e, ec)) for e, ec in cmd.evals]
    build_outputs(cfg, runs, out)
    if cmd.report:
        from vla_ladder.report.html import build_report
        build_report([r for _, r in runs], out / "report.html", title=f"vla-ladder experiment: {cfg.name}",
                     labels=[e.label for e, _ in runs])
    print((out / "table.md").read_text())
    return out


def run(cmd: ExperimentCommand) -> int:
    out = run_experiment(cmd)
    print(out.resolve() / ("report.html" if cmd.report else "results.json"))
    return 0
