"""What merging the shards of `record --writers K` costs against their number.

    .venv/bin/python benchmarks/merge_speed.py [--shards 10 50 100] [--demos-per-shard 1]

Parallel writers keep each block of seeds in a shard of its own (recording/ledger.py; at most
ledger.MAX_BLOCK seeds a block), and `DatasetStore.settle` joins them in seed order with LeRobot's
aggregate_datasets at the end of a run. This builds S shards of synthetic demos (both cameras as AV1 video, the
task's episode length; seed-coloured frames, no simulation) as consecutive blocks and times one settle of all of
them into an empty dataset: seconds in all, per shard and per demo.

Writes benchmarks/results/merge_speed_cpu.json (or --out).
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("SVT_LOG", "1")

import numpy as np  # noqa: E402
import tyro  # noqa: E402

from vla_ladder import files  # noqa: E402
from vla_ladder.conditions import Condition  # noqa: E402
from vla_ladder.contract import EPISODE_STEPS  # noqa: E402
from vla_ladder.machine import cores  # noqa: E402

RESULTS = Path(__file__).parent / "results"
CONDITION = Condition("small_jitter", "canonical", 2)


@dataclass
class Args:
    """Seconds to merge S shards of parallel writers into a dataset."""

    shards: tuple[int, ...] = (10, 50, 100)
    """shard counts to merge, each into a dataset of its own"""
    demos_per_shard: int = 1
    """demos in each shard"""
    out: Path | None = None
    """result JSON (default: benchmarks/results/merge_speed_cpu.json)"""


def demo(seed: int):
    """A well-formed successful episode of the task's length without simulation: seed-coloured frames."""
    from vla_ladder.recording.client import Episode
    from vla_ladder.task.layouts import sample_layout

    layout = sample_layout(CONDITION, seed)
    shade = np.random.default_rng(seed).integers(0, 255, size=3)
    ramp = np.linspace(0, 255, 256, dtype=np.float32)
    image = ((ramp[:, None, None] + shade) % 256).astype(np.uint8) * np.ones((1, 256, 1), np.uint8)
    header = {"seed": seed, "instruction": layout.instruction, "layout": layout.to_dict(), "target": layout.target,
              "condition": CONDITION.key, "object_set": "standin", "robot_mesh": "lite", "instructions": "canonical",
              "expert": {"spec": "scripted", "name": "scripted"}, "num_frames": EPISODE_STEPS, "has_frames": True,
              "metrics": {"success": True, "grasp_any": True, "reach": True, "lifted": True, "held": layout.target,
                          "reach_dist": 0.0}}
    frames = np.repeat(image[None], EPISODE_STEPS, axis=0)
    state, action = np.full((EPISODE_STEPS, 15), seed, np.float32), np.zeros((EPISODE_STEPS, 7), np.float32)
    return Episode(seed, header, {"hand_camera": frames, "fixed_camera": frames}, state, action, "synthetic")


def merge(work: Path, n_shards: int, per_shard: int) -> dict:
    from vla_ladder.recording.store import DatasetStore
    from vla_ladder.recordings import Recording

    recording = Recording("scripted", CONDITION)
    main = DatasetStore(work / f"merged-{n_shards}", recording)
    t0 = time.perf_counter()
    for i in range(n_shards):
        start = i * per_shard
        shard = DatasetStore(main.shard(start), recording, seeds_from=start)
        for seed in shard.reserve_seeds(per_shard):
            shard.add(demo(seed))
        shard.close()
    built = time.perf_counter() - t0
    t0 = time.perf_counter()
    main.settle(n_shards * per_shard)
    merged = time.perf_counter() - t0
    assert main.saved == n_shards * per_shard
    main.close()
    demos = n_shards * per_shard
    print(f"{n_shards} shards of {per_shard} demos: merged in {merged:.1f} s ({merged / n_shards:.3f} s a shard, "
          f"{merged / demos:.3f} s a demo); building them took {built:.0f} s", flush=True)
    return {"shards": n_shards, "demos": demos, "merge_s": merged, "merge_s_per_shard": merged / n_shards,
            "merge_s_per_demo": merged / demos, "build_s": built}


def main(args: Args) -> None:
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        rows = [merge(Path(tmp), s, args.demos_per_shard) for s in args.shards]
    out = args.out or RESULTS / "merge_speed_cpu.json"
    files.write_json(out, {"benchmark": "merge_speed", "vcodec": "libsvtav1", "episode_steps": EPISODE_STEPS,
                           "rows": rows, "how": "DatasetStore.settle of S consecutive block shards into an empty "
                           "dataset (LeRobot's aggregate_datasets, stats, card, fsync, swap)",
                           "machine": {"cores": cores(), "load_average_1min": [load_before, os.getloadavg()[0]]},
                           "provenance": files.provenance("standin")})
    print(f"wrote {out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
