"""stats.json quantiles over every frame of a dataset, instead of LeRobot's average of per-episode quantiles.

LeRobot computes q01...q99 per episode and aggregates episodes by averaging them (weighted by frame count:
lerobot.datasets.compute_stats.aggregate_feature_stats). A mean of quantiles is not a quantile: on
GraspObject-v1 recordings the gripper action is -1 (closed) for most of every episode but +1 at its start,
so every episode's q10 sits at one of the two values and their average lands in between; it was off by up to
0.73 from the quantile over all frames. pi0.5 normalises state and action with q01/q99 (its QUANTILES
normalisation), so those numbers decide what the model sees. The recorder therefore rewrites the quantiles of
every numeric feature at each commit from all frames in data/ (exact, numpy's linear interpolation);
min/max/mean/std/count are exact in LeRobot's aggregation and left as they are. Camera features keep the
per-episode image statistics LeRobot's writer computes over every frame (recording/image_stats.py), aggregated by
LeRobot (policies use mean/std or nothing for images, never quantiles).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd

from vla_ladder import files

STATS_FILE = "meta/stats.json"
_QUANTILE = re.compile(r"^q(\d{2})$")
_NOT_NUMERIC = ("image", "video", "string", "language")


def quantile_keys(feature_stats: dict) -> list[str]:
    """The quantile entries LeRobot wrote for a feature (q01, q10, q50, q90, q99 in LeRobot 0.6)."""
    return [k for k in feature_stats if _QUANTILE.match(k)]


def numeric_features(info: dict) -> list[str]:
    """Features stored as numbers in data/*.parquet (not cameras, not text)."""
    return [k for k, f in info["features"].items() if f["dtype"] not in _NOT_NUMERIC]


def frames(root: str | Path, keys: list[str]) -> dict[str, np.ndarray]:
    """Every frame's value of each key, as (frames, dim) float64 arrays, read from the dataset's Parquet files."""
    paths = sorted(Path(root, "data").glob("*/*.parquet"))
    if not paths:
        raise ValueError(f"{root}: no data/*/*.parquet files; is it a LeRobotDataset v3?")
    table = pd.concat([pd.read_parquet(p, columns=keys) for p in paths], ignore_index=True)
    out = {}
    for k in keys:
        col = table[k].to_numpy()
        out[k] = (np.stack(col) if col.dtype == object else col[:, None]).astype(np.float64)
    return out


def exact_quantiles(root: str | Path) -> dict[str, dict[str, list[float]]]:
    """{feature: {q01: [...], ...}} over all frames, for every numeric feature stats.json has quantiles of."""
    root = Path(root)
    info = json.loads((root / "meta/info.json").read_text())
    stats = json.loads((root / STATS_FILE).read_text())
    keys = [k for k in numeric_features(info) if k in stats and quantile_keys(stats[k])]
    values = frames(root, keys)
    out = {}
    for k in keys:
        qkeys = quantile_keys(stats[k])
        qs = np.quantile(values[k], [int(_QUANTILE.match(q).group(1)) / 100 for q in qkeys], axis=0)
        for q, v in zip(qkeys, qs):
            if np.shape(stats[k][q]) != v.shape:
                raise ValueError(f"{root}: stats.json {k}/{q} has shape {np.shape(stats[k][q])} but the data "
                                 f"gives {v.shape}")
        out[k] = {q: v.tolist() for q, v in zip(qkeys, qs)}
    return out


def write_exact_quantiles(root: str | Path) -> dict[str, dict[str, list[float]]]:
    """Replace stats.json's quantiles by quantiles over all frames (atomically); returns what was written."""
    root = Path(root)
    stats = json.loads((root / STATS_FILE).read_text())
    exact = exact_quantiles(root)
    for k, qs in exact.items():
        stats[k].update(qs)
    # LeRobot aggregates over a set of feature names, whose order follows the process's hash seed: sorted, two
    # recordings of the same episodes write the same file.
    files.write_json(root / STATS_FILE, dict(sorted(stats.items())))
    return exact
