"""Training speed of LeRobot policies on a recorded GraspObject-v1 dataset, through `vla-ladder train`.

Each model trains for --steps steps with LeRobot's own loop (random initialisation, offline); the steady rate is
read from the wall-clock times at which LeRobot logs its step lines, so start-up (dataset, model build, first
CUDA kernels) is reported apart. LeRobot's own per-step `updt_s` (forward + backward + optimiser) and
`data_s` (waiting for the data loader, which decodes the videos) say which of the two bounds the rate.
  - smolvla-500m: SmolVLA at its real size (SmolVLM2-500M backbone truncated to 16 layers, as
    lerobot/smolvla_base) with SmolVLA's defaults (frozen vision encoder, action expert trained);
  - smolvla-scratch: the study's from-scratch SmolVLA (`small` VLM, every weight trained);
  - act: ACT with its default ResNet-18 backbone (no pretrained weights offline).

    .venv/bin/python benchmarks/train_speed.py --dataset DIR [--models act smolvla-500m] [--device cuda]
        [--batch-size 64] [--steps 100] [--keep DIR]

Writes benchmarks/results/train_speed_<cpu|cuda>.json; rows of other models, batch sizes or devices stay. Each row
keeps its own run's cores, cpu_count and provenance; those at the top of the file are the latest run's.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

from vla_ladder import files
from vla_ladder.machine import cores

MODELS = ("smolvla-500m", "smolvla-scratch", "act")
# LeRobot logs every --log-freq steps, the step rounded (format_big_number: 1500 prints as "2K"), so the step is the
# line's count times --log-freq, not the number printed.
STEP_LINE = re.compile(r"step:\S+ .*updt_s:([\d.]+) data_s:([\d.]+)")


def model_args(model: str, vlm_root: Path) -> tuple[str, list[str]]:
    """(policy type, lerobot flags) of a benchmark model."""
    from vla_ladder.training.tiny import SIZES, build_vlm_dir, scratch_smolvla_args

    if model == "act":
        return "act", []
    if model == "smolvla-500m":
        vlm = build_vlm_dir(vlm_root / "smolvlm2-500m", "smolvlm2-500m")
        return "smolvla", [f"--policy.vlm_model_name={vlm}", "--policy.load_vlm_weights=false"]
    if model == "smolvla-scratch":  # as the gpu-scratch study trains it (experiments/study.py)
        return "smolvla", scratch_smolvla_args(build_vlm_dir(vlm_root / "small", "small"), SIZES["small"].image_size)
    raise ValueError(f"unknown model {model!r}; allowed: {', '.join(MODELS)}")


def measure(model: str, args: Args, root: Path) -> dict:
    base = args.keep or root  # a kept checkpoint loads its VLM config and tokenizer from vlm/
    policy_type, extra = model_args(model, base / "vlm")
    out = base / model
    cmd = [sys.executable, "-m", "vla_ladder.cli", "train", "--policy-type", policy_type, "--pretrained", "none",
           "--dataset", str(args.dataset), "--out", str(out), "--steps", str(args.steps),
           "--batch-size", str(args.batch_size), "--log-freq", str(args.log_freq), "--save-freq", str(args.steps),
           "--num-workers", str(args.num_workers), "--device", args.device, "--", *extra]
    print(f"== {model}: {' '.join(cmd)}", flush=True)
    start = time.monotonic()
    logged = []  # (seconds since start, step, updt_s, data_s)
    tail = []
    decoder = "torchcodec"  # LeRobot's default where it loads; the two messages below say otherwise
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
        for line in proc.stdout:
            tail = (tail + [line])[-30:]
            if "restarting with PyAV's own FFmpeg" in line:  # training/decoding.restart_with_torchcodec
                decoder = "torchcodec on PyAV's FFmpeg"
            elif "falling back to 'pyav'" in line:  # LeRobot, when torchcodec does not import
                decoder = "pyav"
            m = STEP_LINE.search(line)
            if m:
                step = (len(logged) + 1) * args.log_freq
                logged.append((time.monotonic() - start, step, float(m[1]), float(m[2])))
                print(f"   {logged[-1][0]:7.1f} s  {line.strip()}", flush=True)
    wall = time.monotonic() - start
    if proc.returncode != 0 or len(logged) < 2:
        sys.stdout.write("".join(tail))
        raise RuntimeError(f"{model}: training failed (exit {proc.returncode}, {len(logged)} step lines logged)")
    (t0, s0, *_), (t1, s1, *_) = logged[0], logged[-1]
    steady = (s1 - s0) / (t1 - t0)
    later = logged[1:]
    row = {"model": model, "policy_type": policy_type, "device": args.device, "batch_size": args.batch_size,
           "steps": args.steps, "steps_per_s": round(steady, 3), "samples_per_s": round(steady * args.batch_size, 1),
           "startup_s": round(t0 - s0 / steady, 1), "wall_s": round(wall, 1),
           "update_s_mean": round(sum(r[2] for r in later) / len(later), 4),
           "data_wait_s_mean": round(sum(r[3] for r in later) / len(later), 4),
           "num_workers": args.num_workers, "video_decoder": decoder, "lerobot_args": extra}
    row["bound_by"] = "data loading" if row["data_wait_s_mean"] > row["update_s_mean"] else "the model's update"
    print(f"{model:16s} batch {args.batch_size}: {steady:6.2f} steps/s ({row['samples_per_s']} samples/s), "
          f"update {row['update_s_mean']:.3f} s, data wait {row['data_wait_s_mean']:.3f} s, "
          f"start-up {row['startup_s']} s, decoding with {decoder}", flush=True)
    return row


@dataclass
class Args:
    """Training steps/s of LeRobot policies through `vla-ladder train`."""

    dataset: Path
    """a recorded GraspObject-v1 LeRobotDataset (`vla-ladder record`)"""
    models: tuple[str, ...] = MODELS
    """which models: smolvla-500m, smolvla-scratch, act"""
    device: str = "cuda"
    """torch device: cuda or cpu"""
    batch_size: int = 64
    """training batch size (the paper's, outside full random)"""
    steps: int = 100
    """training steps per model (the rate is taken between the first and the last logged step)"""
    log_freq: int = 20
    """LeRobot logs every N steps; these lines time the steady rate"""
    num_workers: int = 8
    """LeRobot data-loader processes (they decode the videos)"""
    keep: Path | None = None
    """keep the training runs (their checkpoints) under this directory instead of a temporary one"""
    out: Path | None = None
    """result JSON (default: benchmarks/results/train_speed_<cpu|cuda>.json)"""

    def __post_init__(self):
        unknown = [m for m in self.models if m not in MODELS]
        if unknown:
            raise ValueError(f"unknown model {unknown[0]!r}; allowed: {', '.join(MODELS)}")
        if self.steps < 2 * self.log_freq:
            raise ValueError(f"--steps ({self.steps}) must be at least twice --log-freq ({self.log_freq})")
        if not (self.dataset / "meta" / "info.json").is_file():
            raise ValueError(f"--dataset {str(self.dataset)!r} is not a LeRobotDataset (no meta/info.json)")


def main(args: Args) -> None:
    import torch

    load_before = os.getloadavg()[0]
    # the GPU --device names (cuda:1 is not GPU 0; plain cuda is the current one)
    gpu = torch.cuda.get_device_name(torch.device(args.device)) if args.device.startswith("cuda") else None
    provenance = files.provenance()
    info = json.loads((args.dataset / "meta" / "info.json").read_text())
    out = args.out or Path(__file__).parent / "results" / f"train_speed_{args.device.split(':')[0]}.json"
    # A row per model, device, batch, loader workers and GPU: a re-run with other workers sits beside the baseline
    # it is compared with (docs/gpu.md) instead of replacing it.
    key = lambda r: (r["model"], r["device"], r["batch_size"], r.get("num_workers"), r.get("gpu"))  # noqa: E731
    with tempfile.TemporaryDirectory() as tmp:
        for model in args.models:  # the file written after each model: a time box keeps the models that finished
            row = measure(model, args, Path(tmp))
            # the machine and versions in each row: the file keeps rows of earlier runs beside them
            row.update(gpu=gpu, dataset_episodes=info.get("total_episodes"), load_average_1min=load_before,
                       cores=cores(), cpu_count=os.cpu_count(), provenance=provenance)
            old = json.loads(out.read_text())["results"] if out.is_file() else []
            # cpu_count, cores and provenance at the top: the latest run's (kept for older readers; rows have theirs)
            files.write_json(out, {"benchmark": "train_speed", "cpu_count": os.cpu_count(), "cores": cores(),
                                   "results": [r for r in old if key(r) != key(row)] + [row],
                                   "provenance": provenance})
            print(f"wrote {out}")

if __name__ == "__main__":
    main(tyro.cli(Args))
