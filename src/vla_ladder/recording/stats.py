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
from pathlib import Path

from vla_ladder import files
# (what reads a dataset's quantiles is the ground floor's: check-dataset reads them too)
from vla_ladder.recordings import STATS_FILE, exact_quantiles, quantile_keys

# The recorder computes the quantiles again at a commit once the dataset holds this much more than when they were
# last computed, and over all frames when it stops: each computation reads every frame (9 s for 100k demos on 2 cores),
# so at every commit a recording toward 100k demos spent hours on them; between two, the quantiles are those of the
# first frames, at least 1 / (1 + REFRESH_GROWTH) of them (the recording state's quantile_frames says how many).
REFRESH_GROWTH = 0.1


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
