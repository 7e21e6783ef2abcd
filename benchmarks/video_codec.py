"""The cameras' video codec: what each of `record --vcodec` costs the writer, the disk and the trainer's loader.

    .venv/bin/python benchmarks/video_codec.py [--episodes 6] [--samples 200] [--vcodec libsvtav1 h264]

The same scripted episodes (both 256x256 cameras, rendered as `record`'s servers render them) are written with
each codec through DatasetStore (LeRobot's streaming encoder with its default settings for that codec: the
real writer), then read back through LeRobotDataset as `vla-ladder train` reads them:
  writer  - CPU seconds per episode of DatasetStore.add and its commit (the cameras' per-frame statistics included,
            counted as the recorder counts them, recording/image_stats.py: they cost the same for every codec; the
            committed video_codec.json predates that and measured LeRobot's own statistics class), and the codec
            alone on the same frames;
  size    - bytes of video per episode;
  fidelity- PSNR (dB) of every decoded frame against the rendered one;
  decode  - ms per training sample (both cameras of one random frame, one thread, as one DataLoader worker)
            with PyAV and, where it loads, torchcodec (`--dataset.video_backend`);
  long file - ms per random frame of one 20000-frame MP4 (what a 400-demo dataset holds per camera): PyAV opens
            the file for every sample, torchcodec keeps it open.
Training on a GPU waits on decoding when the loader workers cannot keep up (docs/gpu.md: PyAV, AV1, 10 workers,
~0.1 s a step at batch 64); the decode column says how many loader workers a batch size needs per codec.

Writes benchmarks/results/video_codec.json, or --out.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro
# benchmarks/ is on sys.path when run as a script; importing record_speed also sets the offline and SVT-AV1 logging
# environment every benchmark that records sets.
from record_speed import Args as RecordArgs
from record_speed import encode_and_write, encode_mp4, encoder_alone, simulate

from vla_ladder import files
from vla_ladder.conditions import Condition
from vla_ladder.contract import CAMERAS
from vla_ladder.machine import cores
from vla_ladder.recordings import VCODECS

RESULTS = Path(__file__).parent / "results"


@dataclass
class Args:
    """Writer cost, size, fidelity and training-side decode speed of each video codec."""

    episodes: int = 6
    """scripted episodes written with each codec"""
    samples: int = 200
    """random training samples decoded per codec and backend"""
    vcodec: tuple[str, ...] = VCODECS
    """codecs to measure (`record --vcodec` values)"""
    long_frames: int = 20000
    """frames of the long file whose decoding is timed too: a 400-demo dataset keeps each camera's 20000 frames in
    one MP4 (0 skips it)"""
    regime: str = "small_jitter"
    """placement regime of the episodes"""
    num_objects: int = 5
    """objects on the table"""
    out: Path = RESULTS / "video_codec.json"
    """result file"""

    def __post_init__(self):
        bad = [c for c in self.vcodec if c not in VCODECS]
        if bad:
            raise SystemExit(f"--vcodec {' '.join(bad)}: allowed: {', '.join(VCODECS)}")
        if self.episodes < 1 or self.samples < 1:
            raise SystemExit(f"--episodes and --samples must be >= 1, got {self.episodes} and {self.samples}")


def write(episodes: list, work: Path, vcodec: str, args: Args) -> tuple[Path, dict]:
    """The episodes through DatasetStore (add each, one commit: record_speed's writer stage) into work/video: the
    dataset's root, and CPU s and video bytes per episode."""
    stage = encode_and_write(RecordArgs(regime=args.regime, num_objects=args.num_objects, vcodec=vcodec), episodes,
                             work, video=True)
    root, n = work / "video", len(episodes)
    return root, {"writer_s_per_episode": stage["encode_s_per_episode"] + stage["write_s_per_episode"],
                  "writer_cpu_s_per_episode": stage["writer_cpu_s_per_episode"],
                  "video_bytes_per_episode": sum(f.stat().st_size for f in (root / "videos").rglob("*.mp4")) / n}


def fidelity(episodes: list, root: Path) -> dict:
    """PSNR (dB) of every decoded frame against the frame rendered, per camera: mean and worst frame."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(root.name, root=root, video_backend="pyav")
    out = {}
    for cam in CAMERAS:
        psnr, i = [], 0
        for e in episodes:  # the store writes episodes in the order they were added
            for frame in e.images[cam.name]:
                decoded = (ds[i][cam.key].numpy().transpose(1, 2, 0) * 255).round()
                mse = np.mean((decoded - frame.astype(np.float64)) ** 2)
                psnr.append(10 * np.log10(255**2 / max(mse, 1e-10)))
                i += 1
        out[cam.name] = {"mean_db": float(np.mean(psnr)), "worst_db": float(np.min(psnr))}
        if out[cam.name]["mean_db"] < 20:
            raise RuntimeError(f"{cam.name}: decoded frames do not match the rendered ones (PSNR "
                               f"{out[cam.name]['mean_db']:.1f} dB): the episodes are not in the order written")
    return out


def decode(root: Path, backend: str, samples: int) -> float | None:
    """ms per training sample (both cameras of one random frame) in one thread; None if the backend fails."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    try:
        ds = LeRobotDataset(root.name, root=root, video_backend=backend)
        ds[0]
    except Exception as e:  # torchcodec without FFmpeg's libraries, for one
        print(f"  {backend}: unavailable ({type(e).__name__}: {str(e).splitlines()[0][:120]})")
        return None
    order = np.random.default_rng(0).integers(0, len(ds), samples)
    t0 = time.perf_counter()
    for i in order:
        ds[int(i)]
    return (time.perf_counter() - t0) / samples * 1000


def long_file(episodes: list, root: Path, vcodec: str, frames: int, samples: int) -> dict:
    """ms to decode one random frame of a `frames`-frame MP4 (the episodes' fixed-camera frames over and over,
    LeRobot's settings for `vcodec`) with PyAV and torchcodec, through LeRobot's decode_video_frames."""
    from lerobot.configs.video import RGBEncoderConfig
    from lerobot.datasets.video_utils import decode_video_frames

    from vla_ladder.contract import CONTROL_HZ

    pictures = np.concatenate([e.images["fixed_camera"] for e in episodes])
    path = root / f"long-{vcodec}.mp4"
    encode_mp4(str(path), (pictures[i % len(pictures)] for i in range(frames)), RGBEncoderConfig(vcodec=vcodec))
    times = np.random.default_rng(1).integers(0, frames, samples) / CONTROL_HZ
    row = {"frames": frames}
    for backend in ("pyav", "torchcodec"):
        decode_video_frames(path, [0.0], 1e-4, backend)  # torchcodec opens the file once and keeps it
        t0 = time.perf_counter()
        for t in times:
            decode_video_frames(path, [float(t)], 1e-4, backend)
        row[f"{backend}_ms_per_frame"] = (time.perf_counter() - t0) / samples * 1000
    return row


def main(args: Args) -> None:
    torch.set_num_threads(1)  # as one DataLoader worker
    condition = Condition(args.regime, "canonical", args.num_objects)
    print(f"simulating {args.episodes} episodes of {condition.key} ...", flush=True)
    _, episodes = simulate(RecordArgs(regime=args.regime, num_objects=args.num_objects,
                                      stage_episodes=args.episodes), rebuild=False)
    episodes = [e for e in episodes if e.success and e.has_frames]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for vcodec in args.vcodec:  # warm-up: LeRobot's first dataset and each codec's first encoder cost seconds
            write(episodes[:1], Path(tmp) / f"warm-up-{vcodec}", vcodec, args)
        for vcodec in args.vcodec:
            root, written = write(episodes, Path(tmp) / vcodec, vcodec, args)
            row = {"vcodec": vcodec, **written}
            alone = encoder_alone(episodes, 0, vcodec)
            row["codec_alone_cpu_s_per_episode"] = alone["cpu_s_per_episode"]
            row["codec_options"] = alone["options"]
            row["psnr"] = fidelity(episodes, root)
            row["decode_ms_per_sample"] = {b: decode(root, b, args.samples) for b in ("pyav", "torchcodec")}
            if args.long_frames:
                row["long_file"] = long_file(episodes, Path(tmp), vcodec, args.long_frames, args.samples)
            rows.append(row)
            print(f"{vcodec}: writer {row['writer_cpu_s_per_episode']:.2f} CPU s/episode (codec alone "
                  f"{row['codec_alone_cpu_s_per_episode']:.2f}), "
                  f"{row['video_bytes_per_episode'] / 1024:.0f} KiB/episode, "
                  "PSNR " + ", ".join(f"{c} {v['mean_db']:.1f} dB" for c, v in row["psnr"].items()) + ", decode "
                  + ", ".join(f"{b} {'-' if v is None else f'{v:.1f}'} ms" for b, v in
                              row["decode_ms_per_sample"].items()) + " a sample", flush=True)
            if args.long_frames:
                lf = row["long_file"]
                print(f"  {lf['frames']}-frame file: PyAV {lf['pyav_ms_per_frame']:.2f} ms, torchcodec "
                      f"{lf['torchcodec_ms_per_frame']:.2f} ms a frame", flush=True)
    files.write_json(args.out, {
        "benchmark": "video_codec", "condition": condition.key, "episodes": len(episodes),
        "samples": args.samples, "rows": rows,
        "note": "writer: CPU s per episode of DatasetStore (LeRobot's streaming encoder, the recorder's counted "
                "image statistics and the commit); codec_alone: the codec on the same frames by itself; decode: ms "
                "per training sample (both cameras of one random frame) through LeRobotDataset in one thread; "
                "long_file: ms per random frame of one long MP4 through LeRobot's decode_video_frames",
        "machine": {"cores": cores(), "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
                    "load_average_1min": os.getloadavg()[0]},
        "provenance": files.provenance()})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
