"""stats.json quantiles over every frame of a dataset, instead of LeRobot's average of per-episode quantiles.

LeRobot computes q01...q99 per episode and aggregates episodes by averaging them (weighted by frame count:
lerobot.datasets.compute_stats.aggregate_feature_stats). A mean of quantiles is not a quantile: on
GraspObject-v1 recordings the gripper action is -1 (closed) for most of every episode but +1 at its start,
so every episode's q10 sits at one of the two values and their average lands in between; it was off by up to
0.73 from the quantile over all frames. pi0.5 normalises state and action with q01/q99 (its QUANTILES
normalisation), so those numbers decide what the model sees. The recorder therefore rewrites the quantiles of
every numeric feature from all frames in data/ (exact, numpy's linear interpolation);
min/max/mean/std/count are exact in LeRobot's aggregation and left as they are. Camera features keep the
per-episode image statistics LeRobot's writer computes over every frame (recording/image_stats.py), aggregated by
LeRobot (policies use mean/std or nothing for images, never quantiles). On a large dataset a commit keeps the last
quantiles until the dataset has grown by a tenth (REFRESH_GROWTH).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from vla_ladder import files

STATS_FILE = "meta/stats.json"
# The recorder computes the quantiles again at a commit once the dataset holds this much more than when they were
# last computed, and over all frames when it stops: each computation reads every frame (9 s for 100k demos on 2 cores),
# so at every commit a recording toward 100k demos spent hours on them; between two, the quantiles are those of the
# first frames, at least 1 / (1 + REFRESH_GROWTH) of them (the recording state's quantile_frames says how many).
REFRESH_GROWTH = 0.1
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
    import pyarrow as pa
    import pyarrow.parquet as pq

    paths = sorted(Path(root, "data").glob("*/*.parquet"))
    if not paths:
        raise ValueError(f"{root}: no data/*/*.parquet files; is it a LeRobotDataset v3?")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    for path in paths:  # (one file at a time: LeRobot writes vectors as list or, after a merge, fixed-size list)
        table = pq.read_table(path, columns=keys)
        for k in keys:
            col = table[k].combine_chunks()
            if pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type):
                # A vector per frame, all of one length: its values flat, without a numpy object per frame (stacking
                # those took longer than the quantiles themselves).
                parts[k].append(col.flatten().to_numpy(zero_copy_only=False).reshape(len(col), -1))
            else:
                parts[k].append(col.to_numpy(zero_copy_only=False)[:, None])
    return {k: np.concatenate(v).astype(np.float64) for k, v in parts.items()}


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


def copy_quantiles(src: str | Path, dst: str | Path) -> None:
    """Put src's stats.json quantiles in dst's (atomically): a commit that adds a few demos to a large dataset keeps
    the quantiles it had, which LeRobot's finalize replaced by its average (see REFRESH_GROWTH)."""
    theirs = json.loads(Path(src, STATS_FILE).read_text())
    stats = json.loads(Path(dst, STATS_FILE).read_text())
    for k, feature in stats.items():
        for q in quantile_keys(feature):
            if q in theirs.get(k, {}):
                feature[q] = theirs[k][q]
    _write_stats(dst, stats)


def write_exact_quantiles(root: str | Path) -> dict[str, dict[str, list[float]]]:
    """Replace stats.json's quantiles by quantiles over all frames (atomically); returns what was written."""
    root = Path(root)
    stats = json.loads((root / STATS_FILE).read_text())
    exact = exact_quantiles(root)
    for k, qs in exact.items():
        stats[k].update(qs)
    _write_stats(root, stats)
    return exact


def _write_stats(root: str | Path, stats: dict) -> None:
    # LeRobot aggregates over a set of feature names, whose order follows the process's hash seed: sorted, two
    # recordings of the same episodes write the same file.
    files.write_json(Path(root, STATS_FILE), dict(sorted(stats.items())))
