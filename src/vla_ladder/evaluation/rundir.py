"""Reading an evaluation run directory (the `vla-ladder eval --out DIR` contract) back in.

Compare, experiments and the report all start from run directories; this is the one place that checks
one is whole and says exactly what is missing when it is not.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

REQUIRED_FILES = ("episodes.parquet", "summary.json")
EPISODE_COLUMNS = ("policy", "regime", "split", "num_objects", "episode", "seed", "target", "instruction",
                   "held", "success", "grasp_any", "reach", "reach_dist", "object_set", "layout", "video")


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

    def video_path(self, video: str) -> Path | None:
        """Absolute path of an episode's video, None when it has none or the file is gone."""
        if not video:
            return None
        p = self.path / video
        return p if p.is_file() else None


def load_run(path: str | Path) -> Run:
    """Load a run directory; ValueError listing what is missing if it is not one."""
    path = Path(path)
    if not path.is_dir():
        raise ValueError(f"{path} is not a run directory: no such directory")
    missing = [f for f in REQUIRED_FILES if not (path / f).is_file()]
    if missing:
        raise ValueError(f"{path} is not a run directory: missing {', '.join(missing)} "
                         f"(a run directory holds {', '.join(REQUIRED_FILES)} and config.json, "
                         f"written by `vla-ladder eval --out DIR`)")
    episodes = pd.read_parquet(path / "episodes.parquet")
    absent = [c for c in EPISODE_COLUMNS if c not in episodes.columns]
    if absent:
        raise ValueError(f"{path}/episodes.parquet lacks columns: {', '.join(absent)}")
    try:
        summary = json.loads((path / "summary.json").read_text())
        config = json.loads((path / "config.json").read_text()) if (path / "config.json").is_file() else {}
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: unreadable JSON: {e}") from None
    return Run(path, episodes, summary, config)


def load_runs(paths) -> list[Run]:
    if not paths:
        raise ValueError("give at least one run directory")
    return [load_run(p) for p in paths]
