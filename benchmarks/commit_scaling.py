"""What one commit of a recording costs as its dataset grows (`record`'s one writer, toward 100k demos).

    .venv/bin/python benchmarks/commit_scaling.py [--demos 2000] [--commit-every 50] [--quantile-demos 10000 100000]

A commit makes a batch of demos part of DATASET_DIR (recording/store.py): the next batch opens a staging copy
(hard links, LeRobot's resume), and the commit finalizes it, recomputes stats.json's quantiles over the frames,
writes the dataset card from the provenance, flushes and swaps. Every part but the batch's own episodes reads the
whole dataset, so a commit's cost grows with it. This records D synthetic demos (both cameras as AV1 video, the
task's episode length; seed-coloured frames, no simulation) in batches of --commit-every and times each batch's
open and commit, and its parts; then, at sizes a real recording takes days to reach, the two parts that read the
whole dataset: the quantiles over its frames (synthetic data files as LeRobot writes them, 1000 episodes a file),
which a commit now computes only once the dataset grew by a tenth (stats.REFRESH_GROWTH), and the card's
provenance, one file per commit, which the recorder now keeps in memory between commits.

Writes benchmarks/results/commit_scaling_cpu.json (or --out).
"""

from __future__ import annotations

import functools
import json
import os
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("SVT_LOG", "1")

import numpy as np  # noqa: E402
import tyro  # noqa: E402
from merge_speed import CONDITION, demo  # noqa: E402

from vla_ladder import files  # noqa: E402
from vla_ladder.contract import ACTION_DIM, ACTION_KEY, EPISODE_STEPS, STATE_DIM, STATE_KEY  # noqa: E402
from vla_ladder.machine import cores  # noqa: E402

RESULTS = Path(__file__).parent / "results"


@dataclass
class Args:
    """Seconds a recording's commit takes against the demos its dataset holds."""

    demos: int = 2000
    """synthetic demos to record, one writer"""
    commit_every: int = 50
    """demos a batch (record's --commit-every default)"""
    quantile_demos: tuple[int, ...] = (10_000, 50_000, 100_000)
    """dataset sizes at which the quantiles alone are timed, on synthetic data files"""
    out: Path | None = None
    """result JSON (default: benchmarks/results/commit_scaling_cpu.json)"""


class Clock:
    """Seconds spent in wrapped functions since the last `take`."""

    def __init__(self):
        self.spent: dict[str, float] = defaultdict(float)

    def wrap(self, owner, name: str, label: str) -> None:
        fn = getattr(owner, name)

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.spent[label] += time.perf_counter() - t0
        setattr(owner, name, timed)

    def take(self) -> dict[str, float]:
        spent, self.spent = dict(self.spent), defaultdict(float)
        return spent


def record(work: Path, demos: int, commit_every: int) -> list[dict]:
    from vla_ladder.recording import card, stats, store
    from vla_ladder.recordings import Recording

    clock = Clock()
    clock.wrap(store, "_link_copy", "open_link_copy")
    clock.wrap(store.DatasetStore, "_dataset", "open")  # (with the link copy and LeRobot's resume)
    clock.wrap(stats, "write_exact_quantiles", "commit_quantiles")
    clock.wrap(stats, "copy_quantiles", "commit_quantiles_kept")
    clock.wrap(card, "write_card", "commit_card")
    clock.wrap(store, "_fsync_tree", "commit_fsync")
    clock.wrap(store.DatasetStore, "commit", "commit")
    ds = store.DatasetStore(work / "grown", Recording("scripted", CONDITION), commit_every=commit_every)
    rows = []
    for seed in ds.reserve_seeds(demos):
        before = ds.saved
        ds.add(demo(seed))  # commits every commit_every demos
        if ds.saved > before:
            spent = clock.take()
            add = spent.pop("open")  # (only the batch's first add opens the staging copy)
            rows.append({"demos_before": before, **{k: round(v, 4) for k, v in spent.items()},
                         "open": round(add, 4)})
            print(f"{before:6d} demos: open {add:.2f} s (link copy {spent.get('open_link_copy', 0):.2f}), commit "
                  f"{spent['commit']:.2f} s (quantiles {spent.get('commit_quantiles', 0):.2f} computed, "
                  f"{spent.get('commit_quantiles_kept', 0):.2f} kept, card "
                  f"{spent['commit_card']:.2f}, fsync {spent['commit_fsync']:.2f})", flush=True)
    ds.close()
    return rows


def quantiles_alone(work: Path, demos: int) -> dict:
    """write_exact_quantiles over the frames of `demos` synthetic episodes (data files of 1000 episodes, as list
    columns like LeRobot's)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from vla_ladder.recording import stats

    root = work / f"quantiles-{demos}"
    (root / "meta").mkdir(parents=True)
    features = {STATE_KEY: STATE_DIM, ACTION_KEY: ACTION_DIM}
    (root / "meta/info.json").write_text(json.dumps(
        {"features": {k: {"dtype": "float32", "shape": [d]} for k, d in features.items()}}))
    (root / stats.STATS_FILE).write_text(json.dumps(
        {k: {q: [0.0] * d for q in ("q01", "q10", "q50", "q90", "q99")} for k, d in features.items()}))
    rng = np.random.default_rng(0)
    for i, first in enumerate(range(0, demos, 1000)):
        n = min(1000, demos - first) * EPISODE_STEPS
        columns = {k: pa.ListArray.from_arrays(pa.array(np.arange(0, n * d + 1, d, dtype=np.int32)),
                                                pa.array(rng.standard_normal(n * d).astype(np.float32)))
                   for k, d in features.items()}
        (root / "data/chunk-000").mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table(columns), root / f"data/chunk-000/file-{i:03d}.parquet")
    t0 = time.perf_counter()
    stats.write_exact_quantiles(root)
    spent = time.perf_counter() - t0
    print(f"quantiles over {demos} demos' frames: {spent:.2f} s", flush=True)
    return {"demos": demos, "frames": demos * EPISODE_STEPS, "quantiles_s": round(spent, 3)}


def card_alone(work: Path, demos: int, commit_every: int) -> dict:
    """The card's provenance at `demos` demos recorded in batches of `commit_every` (a file each): read from the
    files, as every commit did, against kept in memory and extended by a batch, as the recorder does now."""
    import pandas as pd

    from vla_ladder.recording import card
    from vla_ladder.recording.store import _provenance_row
    from vla_ladder.recordings import PROVENANCE_DIR, read_provenance

    root = work / f"provenance-{demos}"
    (root / PROVENANCE_DIR).mkdir(parents=True)
    batch = pd.DataFrame([_provenance_row(i, demo(i)) for i in range(commit_every)])
    for i in range(demos // commit_every):
        batch["episode_index"] = range(i * commit_every, (i + 1) * commit_every)
        batch.to_parquet(root / PROVENANCE_DIR / f"commit-{i + 1:06d}.parquet")
    t0 = time.perf_counter()
    kept = read_provenance(root)[list(card.COLUMNS)]
    read = time.perf_counter() - t0
    t0 = time.perf_counter()
    kept = pd.concat([kept, batch[list(card.COLUMNS)]], ignore_index=True)
    extended = time.perf_counter() - t0
    print(f"the card's provenance at {demos} demos ({demos // commit_every} files): read {read:.2f} s, kept and "
          f"extended {extended:.3f} s", flush=True)
    return {"demos": demos, "files": demos // commit_every, "read_s": round(read, 3), "extend_s": round(extended, 4)}


def main(args: Args) -> None:
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        rows = record(Path(tmp), args.demos, args.commit_every)
        quantiles = [quantiles_alone(Path(tmp), n) for n in args.quantile_demos]
        cards = [card_alone(Path(tmp), n, args.commit_every) for n in args.quantile_demos]
    out = args.out or RESULTS / "commit_scaling_cpu.json"
    files.write_json(out, {"benchmark": "commit_scaling", "vcodec": "libsvtav1", "episode_steps": EPISODE_STEPS,
                           "commit_every": args.commit_every, "commits": rows, "quantiles_alone": quantiles,
                           "card_provenance_alone": cards,
                           "how": "one writer's batches of synthetic demos (DatasetStore.add/commit), each batch's "
                           "open (link copy + LeRobot's resume) and commit (finalize, quantiles over all frames, card, "
                           "fsync, swap) timed; then stats.write_exact_quantiles alone on synthetic data files, and "
                           "the card's provenance read from one file per commit against kept between commits",
                           "machine": {"cores": cores(), "load_average_1min": [load_before, os.getloadavg()[0]]},
                           "provenance": files.provenance("standin")})
    print(f"wrote {out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
