"""Reading an evaluation run directory (the `vla-ladder eval --out DIR` contract) back in.

Compare, experiments and the report all start from run directories; this is the one place that checks
one is whole and says exactly what is missing when it is not. A run whose files contradict each other (an
episode twice or not at all, a seed that is not first_seed + episode, a summary.json that counts other episodes
than episodes.parquet holds) is refused: no statistic is ever computed on it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from vla_ladder.conditions import Condition, ConditionGrid
from vla_ladder.contract import METRICS
from vla_ladder.evaluation.metrics import CONDITION_KEYS

REQUIRED_FILES = ("episodes.parquet", "summary.json")
EPISODE_KEY = (*CONDITION_KEYS, "episode")
"""What identifies an episode within a run: its condition and its index j in it (it plays seed first_seed + j)."""
EPISODE_COLUMNS = ("policy", "regime", "split", "num_objects", "episode", "seed", "target", "instruction",
                   "held", *METRICS, "reach_dist", "tcp_x", "tcp_y", "object_set", "layout",
                   "video")
ADDED_COLUMNS = {"tcp_x": float("nan"), "tcp_y": float("nan")}
"""Columns added after run directories existed, with what a run written before them reads as (the TCP's final
x, y in metres, world frame: unknown)."""


@dataclass
class Run:
    """One evaluation run: its episodes, summary and arguments."""

    path: Path
    episodes: pd.DataFrame = field(repr=False)
    summary: dict = field(repr=False)
    config: dict = field(default_factory=dict, repr=False)

    @property
    def label(self) -> str:
        """A short name: the policy spec, else the directory name."""
        specs = self.episodes["policy"].unique() if len(self.episodes) else []
        return str(specs[0]) if len(specs) == 1 else self.path.name

    @property
    def played(self) -> tuple:
        """What the run played, episode by episode (condition, seed, target): runs with the same plays played the
        same scenes, whatever order their workers finished in."""
        e = self.episodes
        return tuple(sorted(zip(e["regime"], e["split"], e["num_objects"], e["seed"], e["target"])))

    def video_path(self, video: str) -> Path | None:
        """Absolute path of an episode's video, None when it has none or the file is gone."""
        if not video:
            return None
        p = self.path / video
        return p if p.is_file() else None


def read_episodes(path: str | Path) -> pd.DataFrame:
    """A run directory's episodes.parquet, with the columns added since it was written (ADDED_COLUMNS) filled in:
    what `load_run` reads and a resumed `eval` goes on from."""
    episodes = pd.read_parquet(path)
    return episodes.assign(**{c: v for c, v in ADDED_COLUMNS.items() if c not in episodes.columns})


def run_config(path: Path) -> dict | None:
    """The evaluation request saved at `path` (a run directory's config.json), or None where there is none: a
    LeRobot checkpoint's config.json, say, whose folder `eval --overwrite` must never replace."""
    try:
        config = json.loads(path.read_text()) if path.is_file() else None
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None
    return config if isinstance(config, dict) and {"policy", "episodes", "first_seed"} <= config.keys() else None


def load_run(path: str | Path) -> Run:
    """Load a run directory; ValueError listing what is missing if it is not one."""
    path = Path(path)
    if not path.is_dir():
        raise ValueError(f"{path} is not a run directory: no such directory")
    missing = [f for f in REQUIRED_FILES if not (path / f).is_file()]
    if missing and len(missing) == len(REQUIRED_FILES) and run_config(path / "config.json") is not None:
        raise ValueError(f"{path} is a run directory that holds no episode yet (its evaluation stopped before the "
                         "first was saved); rerun the command that made it")
    if missing:
        raise ValueError(f"{path} is not a run directory: missing {', '.join(missing)} "
                         f"(a run directory holds {', '.join(REQUIRED_FILES)} and config.json, "
                         f"written by `vla-ladder eval --out DIR`)")
    episodes = read_episodes(path / "episodes.parquet")
    absent = [c for c in EPISODE_COLUMNS if c not in episodes.columns]
    if absent:
        raise ValueError(f"{path}/episodes.parquet lacks columns: {', '.join(absent)}")
    try:
        summary = json.loads((path / "summary.json").read_text())
        config = json.loads((path / "config.json").read_text()) if (path / "config.json").is_file() else {}
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: unreadable JSON: {e}") from None
    run = Run(path, episodes, summary, config)
    check_run(run)
    return run


def load_runs(paths) -> list[Run]:
    """Several run directories, each whole and consistent, and agreeing on the seed of every episode they share."""
    if not paths:
        raise ValueError("give at least one run directory")
    runs = [load_run(p) for p in paths]
    for i, a in enumerate(runs):
        for b in runs[i + 1:]:
            check_same_seeds(a, b)
    return runs


# ------------------------------------------------------------------------------------------ consistency
SHOWN = 3  # problems of one kind named in an error message; the rest are counted


def check_run(run: Run) -> None:
    """ValueError naming every way the run's files contradict each other, and what to do about it. Missing
    episodes and a stale summary.json (a run killed between its two writes) are what the evaluation runner
    repairs when the same command runs again; duplicated episodes, episodes beyond the count, foreign seeds and
    non-boolean outcomes are not."""
    broken = [*_duplicates(run), *_beyond(run), *_bad_values(run), *_wrong_seeds(run)]
    repairable = [*_missing(run), *_summary_disagrees(run)]
    if broken:
        raise ValueError(f"{run.path} is not a consistent run directory: {'; '.join(broken + repairable)}; its "
                         "files were edited or mixed: evaluate again into a new --out")
    if repairable:
        # (a probe's variant or a study's evaluation is resumed by the probe or study that wrote it, not by eval)
        raise ValueError(f"{run.path} is an incomplete run: {'; '.join(repairable)}; rerun the same command that "
                         "wrote it (`vla-ladder eval`, or the `probe` or `study` whose directory holds it): it plays "
                         "only the missing episodes and rewrites summary.json")


def check_same_seeds(a: Run, b: Run) -> None:
    """ValueError when two runs played an episode (same condition, same index) with different seeds: their
    layouts differ, so their outcomes cannot be compared."""
    merged = a.episodes[[*EPISODE_KEY, "seed"]].merge(b.episodes[[*EPISODE_KEY, "seed"]], on=list(EPISODE_KEY),
                                                      suffixes=("_a", "_b"))
    bad = merged[merged["seed_a"] != merged["seed_b"]]
    if len(bad):
        ex = "; ".join(f"{_episode(r)}: seed {r.seed_a} vs {r.seed_b}" for _, r in bad.head(SHOWN).iterrows())
        raise ValueError(f"{a.path} and {b.path} used different seeds on {len(bad)} of {len(merged)} shared "
                         f"episodes ({ex}); evaluate both with the same --first-seed so they play the same layouts")


def _episode(row) -> str:
    return f"{Condition(row['regime'], row['split'], int(row['num_objects'])).key} episode {row['episode']}"


def _some(items: list[str]) -> str:
    return ", ".join(items[:SHOWN]) + (f" and {len(items) - SHOWN} more" if len(items) > SHOWN else "")


def _duplicates(run: Run) -> list[str]:
    ep = run.episodes
    counts = ep.groupby(list(EPISODE_KEY), sort=False).size()
    twice = counts[counts > 1]
    if not len(twice):
        return []
    named = [f"{_episode(dict(zip(EPISODE_KEY, k)))} ({n} rows)" for k, n in twice.items()]
    return [f"episodes.parquet holds {len(twice)} episodes more than once: {_some(named)}"]


def _bad_values(run: Run) -> list[str]:
    out = []
    for m in METRICS:
        values = run.episodes[m]
        if values.isna().any() or not values.isin([0, 1]).all():
            out.append(f"column {m!r} holds values other than true/false")
    return out


def _first_seed(run: Run) -> int | None:
    value = run.summary.get("first_seed", run.config.get("first_seed"))
    return None if value is None else int(value)


def _wrong_seeds(run: Run) -> list[str]:
    first = _first_seed(run)
    if first is None:
        return []
    ep = run.episodes
    bad = ep[ep["seed"] != first + ep["episode"]]
    if not len(bad):
        return []
    named = [f"{_episode(r)} has seed {r['seed']}" for _, r in bad.iterrows()]
    return [f"{len(bad)} episodes do not play seed first_seed + episode = {first} + episode: {_some(named)}"]


def _expected_conditions(run: Run) -> list[str] | None:
    """The condition keys the run's config.json asked for (None when it does not say)."""
    grid = run.config.get("grid")
    try:
        return [c.key for c in ConditionGrid(**grid).conditions] if isinstance(grid, dict) else None
    except (TypeError, ValueError):
        return None


def _missing(run: Run) -> list[str]:
    ep = run.episodes
    per = run.summary.get("episodes_per_condition")
    have = {Condition(*k).key: set(g["episode"]) for k, g in ep.groupby(list(CONDITION_KEYS), sort=False)}
    out = []
    absent = [c for c in _expected_conditions(run) or [] if c not in have]
    if absent:
        out.append(f"no episodes of {_some(absent)}")
    if per is not None:
        for key, got in have.items():
            lacking = sorted(set(range(int(per))) - got)
            if lacking:
                out.append(f"{key} lacks episodes {_some([str(j) for j in lacking])} of 0..{int(per) - 1}")
    if not out and run.summary.get("complete") is False:
        out.append("summary.json says complete: false")
    return out


def _beyond(run: Run) -> list[str]:
    """Episodes the run's request never plays (an index past episodes_per_condition): a rerun would count them."""
    per = run.summary.get("episodes_per_condition")
    if per is None:
        return []
    out = []
    for k, g in run.episodes.groupby(list(CONDITION_KEYS), sort=False):
        if beyond := sorted(j for j in set(g["episode"]) if not 0 <= j < int(per)):
            out.append(f"{Condition(*k).key} has episodes {_some([str(j) for j in beyond])} beyond "
                       f"episodes_per_condition {int(per)}")
    return out


def _summary_disagrees(run: Run) -> list[str]:
    ep = run.episodes
    summary = run.summary.get("conditions")
    if not isinstance(summary, dict):
        return ["summary.json has no per-condition figures ('conditions')"]
    groups = {Condition(*k).key: g for k, g in ep.groupby(list(CONDITION_KEYS), sort=False)}
    out = []
    if set(summary) != set(groups):
        only_s, only_e = sorted(set(summary) - set(groups)), sorted(set(groups) - set(summary))
        out.append(f"summary.json and episodes.parquet cover different conditions (only in summary.json: "
                   f"{_some(only_s) or 'none'}; only in episodes.parquet: {_some(only_e) or 'none'})")
    for key in sorted(set(summary) & set(groups)):
        s, g = summary[key], groups[key]
        n = len(g)
        if s.get("n") != n:
            out.append(f"summary.json counts {s.get('n')} episodes of {key}, episodes.parquet holds {n}")
            continue
        for m in METRICS:
            k = int(g[m].astype(bool).sum())
            rate = s.get(m)
            if not isinstance(rate, (int, float)) or round(rate * n) != k:
                out.append(f"summary.json gives {key} {m} = {rate}, episodes.parquet {k}/{n}")
    return out
