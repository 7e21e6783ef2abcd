"""What appending one episode to a dataset's video file costs against the episodes already in it.

    .venv/bin/python benchmarks/video_append.py [--episodes-in-file 50 200 1000 3000]

LeRobot v3 keeps many episodes in one MP4 a camera: within a writer session, DatasetWriter._save_episode_video
appends each new episode with concatenate_video_files([file, episode], file), which remuxes every packet
already in the file. A recorder commit resumes the dataset and so starts new files (docs/recording.md): the
episodes a file collects are at most one commit batch (`record --commit-every`, 50 by default). This times that
append on one camera's AV1 episode video (50 frames, LeRobot's RGB encoder settings) for files of each size, and
writes benchmarks/results/video_append_cpu.json (or --out).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its configuration for every video otherwise

import numpy as np  # noqa: E402
import tyro  # noqa: E402

from vla_ladder import files  # noqa: E402
from vla_ladder.contract import EPISODE_STEPS, IMAGE_SHAPE  # noqa: E402
from vla_ladder.machine import cores  # noqa: E402

RESULTS = Path(__file__).parent / "results"


@dataclass
class Args:
    """Seconds to append one episode's video to a file holding N episodes."""

    episodes_in_file: tuple[int, ...] = (50, 200, 1000, 3000)
    """file sizes, in episodes, to append to"""
    repeats: int = 3
    """appends timed at each size (the fastest is reported)"""
    out: Path | None = None
    """where to write the JSON (default: benchmarks/results/video_append_cpu.json)"""


def episode_frames(seed: int = 0) -> list[np.ndarray]:
    """A camera's episode: a smooth gradient that brightens step by step, with a little noise (an AV1 episode of
    about the size a recorded camera gives)."""
    rng = np.random.default_rng(seed)
    h, w, _ = IMAGE_SHAPE
    y, x = np.linspace(0, 1, h)[:, None], np.linspace(0, 1, w)[None]
    base = np.stack(np.broadcast_arrays(x * y, (1 - x) * y, x * (1 - y)), axis=-1) * 200 + 20
    return [np.clip(base + rng.normal(0, 6, base.shape) + t, 0, 255).astype(np.uint8) for t in range(EPISODE_STEPS)]


def main(args: Args) -> None:
    import torch
    from lerobot.configs.video import RGBEncoderConfig
    from lerobot.datasets.video_utils import concatenate_video_files
    from record_speed import encode_mp4

    load_before = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        episode = tmp / "episode.mp4"
        encode_mp4(episode, episode_frames(), RGBEncoderConfig())
        for n in args.episodes_in_file:
            full = tmp / f"file{n}.mp4"
            concatenate_video_files([episode] * n, full)
            times = []
            for _ in range(args.repeats):
                work = tmp / "work.mp4"
                shutil.copy(full, work)
                t = time.perf_counter()
                concatenate_video_files([work, episode], work)
                times.append(time.perf_counter() - t)
            rows.append({"episodes_in_file": n, "file_mb": full.stat().st_size / 1e6, "append_s": min(times),
                         "append_ms_per_episode_in_file": 1e3 * min(times) / n})
            print(f"{n} episodes ({rows[-1]['file_mb']:.1f} MB): append {min(times):.3f} s", flush=True)
        result = {"benchmark": "video_append", "episode_kb": episode.stat().st_size / 1e3, "rows": rows,
                  "how": "LeRobot's concatenate_video_files([file, episode], file), as its writer appends each "
                         "episode within a session; fastest of `repeats` on a fresh copy of the file",
                  # the GPU is not used (remuxing runs on the CPU) but says which machine this was
                  "machine": {"cores": cores(),
                              "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
                              "load_average_1min": [load_before, os.getloadavg()[0]]},
                  "date": datetime.now().isoformat(timespec="seconds"),
                  "provenance": files.provenance()}
    out = args.out or RESULTS / "video_append_cpu.json"
    files.write_json(out, result)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
