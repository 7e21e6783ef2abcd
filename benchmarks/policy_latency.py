"""Inference latency per action chunk of LeRobot policies as `lerobot:` evaluation runs them.

Times one chunk for a batch of B GraspObject-v1 observations (two 256x256 cameras, 15-d state,
instruction) through the saved-processor path (preprocessor -> predict_action_chunk -> postprocessor),
with random weights (latency does not depend on them):
  - tiny SmolVLA (the test model: 2-layer VLM from vla_ladder.training.tiny) and tiny ACT;
  - with --full: SmolVLA at its real size (SmolVLM2-500M backbone truncated to 16 layers, as
    lerobot/smolvla_base), built offline from a local config.

    .venv/bin/python benchmarks/policy_latency.py [--full] [--device cpu|cuda] [--threads N] [--batch 1] [--repeats 5]
                                                  [--use-amp]

Writes benchmarks/results/policy_latency_<device>.json (cpu or cuda; --out elsewhere). Rows of earlier runs with
other models, batches, thread counts or GPUs stay in the file; a re-measured one is replaced. Each row keeps its own
run's cores, cpu_count and provenance; those at the top of the file are the latest run's.
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
import torch  # noqa: E402
import tyro  # noqa: E402

from vla_ladder import files  # noqa: E402
from vla_ladder.contract import ACTION_DIM, ACTION_KEY, CAMERA_KEYS, IMAGE_SHAPE, STATE_DIM, STATE_KEY  # noqa: E402
from vla_ladder.machine import cores  # noqa: E402
from vla_ladder.training.tiny import build_vlm_dir  # noqa: E402

CHUNK = 16
CHW = (IMAGE_SHAPE[2], IMAGE_SHAPE[0], IMAGE_SHAPE[1])  # how LeRobot declares a camera


def features():
    from lerobot.configs import FeatureType, PolicyFeature

    inputs = {k: PolicyFeature(FeatureType.VISUAL, CHW) for k in CAMERA_KEYS}
    inputs[STATE_KEY] = PolicyFeature(FeatureType.STATE, (STATE_DIM,))
    return inputs, {ACTION_KEY: PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))}


def stats():
    def unit(d: int) -> dict:
        return {"mean": torch.zeros(d), "std": torch.ones(d), "min": -torch.ones(d), "max": torch.ones(d),
                "q01": -torch.ones(d), "q99": torch.ones(d)}
    return {STATE_KEY: unit(STATE_DIM), ACTION_KEY: unit(ACTION_DIM)}


def build(kind: str, device: str, vlm_root: Path):
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors
    from lerobot.configs.policies import PreTrainedConfig

    inputs, outputs = features()
    common = dict(input_features=inputs, output_features=outputs, device=device, chunk_size=CHUNK,
                  n_action_steps=CHUNK)
    if kind == "smolvla-tiny":
        cfg = PreTrainedConfig.get_choice_class("smolvla")(
            vlm_model_name=str(build_vlm_dir(vlm_root / "tiny", "tiny")), load_vlm_weights=False,
            train_expert_only=False, freeze_vision_encoder=False, resize_imgs_with_padding=(64, 64), **common)
    elif kind == "smolvla-full":
        cfg = PreTrainedConfig.get_choice_class("smolvla")(
            vlm_model_name=str(build_vlm_dir(vlm_root / "full", "smolvlm2-500m")), load_vlm_weights=False,
            **common)
    elif kind == "act-tiny":
        cfg = PreTrainedConfig.get_choice_class("act")(
            pretrained_backbone_weights=None, dim_model=32, n_heads=2, dim_feedforward=64, n_encoder_layers=1,
            n_decoder_layers=1, use_vae=False, **common)
    else:
        raise ValueError(kind)
    policy = get_policy_class(cfg.type)(cfg).to(device).eval()
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats())
    return policy, pre, post


def observation(batch: int, device: str) -> dict:
    g = torch.Generator().manual_seed(0)
    obs = {k: torch.rand(batch, *CHW, generator=g).to(device) for k in CAMERA_KEYS}
    obs[STATE_KEY] = torch.randn(batch, STATE_DIM, generator=g).to(device)
    obs["task"] = ["grasp the apple"] * batch
    return obs


def time_chunks(kind: str, device: str, batch: int, repeats: int, vlm_root: Path, use_amp: bool = False) -> dict:
    t0 = time.perf_counter()
    policy, pre, post = build(kind, device, vlm_root)
    build_s = time.perf_counter() - t0
    obs = observation(batch, device)
    times = []
    # use_amp: torch.autocast around the chunk, as lerobot-eval and `lerobot:CKPT?use_amp=true` run it
    precision = torch.autocast(torch.device(device).type) if use_amp else contextlib.nullcontext()
    with torch.no_grad(), precision:
        for i in range(repeats + 1):  # the first call warms up (allocations, kernels)
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            t = time.perf_counter()
            chunk = post(policy.predict_action_chunk(pre(dict(obs))))
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            if i:
                times.append(time.perf_counter() - t)
    assert chunk.shape == (batch, CHUNK, ACTION_DIM), chunk.shape
    params = sum(p.numel() for p in policy.parameters())
    row = {"policy": kind, "device": device, "batch": batch, "use_amp": use_amp, "chunk_size": CHUNK, "params": params,
           "build_s": round(build_s, 2), "repeats": repeats, "chunk_latency_s_median": statistics.median(times),
           "chunk_latency_s_min": min(times), "per_step_s_at_horizon_8": statistics.median(times) / 8}
    print(f"{kind:14s} {device:5s} batch {batch}{' amp' if use_amp else ''}: {params / 1e6:7.2f}M params, "
          f"{row['chunk_latency_s_median'] * 1e3:9.1f} ms/chunk (median of {repeats}), built in {build_s:.1f} s",
          flush=True)
    return row


@dataclass
class Args:
    """Inference latency per action chunk of tiny (and full-size) LeRobot policies."""

    device: str = "cpu"
    """torch device of the policies: cpu, cuda, cuda:1, ..."""
    batch: int = 1
    """observations per chunk (parallel episodes of a batched evaluation)"""
    repeats: int = 5
    """timed chunks per tiny model (after one warm-up chunk)"""
    full: bool = False
    """also the full-size SmolVLA architecture (450M parameters)"""
    full_repeats: int = 3
    """timed chunks of the full-size SmolVLA"""
    threads: int | None = None
    """torch CPU threads (default: torch's choice)"""
    use_amp: bool = False
    """run the chunks under torch.autocast (float16 on CUDA, bfloat16 on the CPU), as `?use_amp=true` does"""
    out: Path | None = None
    """result JSON (default: benchmarks/results/policy_latency_<cpu|cuda>.json)"""

    def __post_init__(self):
        # checked before the models are built: no timed chunk would leave an empty median after the work
        if self.repeats < 1 or self.full_repeats < 1:
            raise ValueError(f"--repeats and --full-repeats must be >= 1, got {self.repeats} and {self.full_repeats}")


def main(args: Args) -> None:
    if args.threads:
        torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ("smolvla-tiny", "act-tiny"):
            rows.append(time_chunks(kind, args.device, args.batch, args.repeats, Path(tmp), args.use_amp))
        if args.full:
            rows.append(time_chunks("smolvla-full", args.device, args.batch, args.full_repeats, Path(tmp),
                                    args.use_amp))
    gpu = torch.cuda.get_device_name(torch.device(args.device)) if args.device.startswith("cuda") else None
    provenance = files.provenance()
    for row in rows:  # the machine and versions in each row: the file keeps rows of earlier runs beside them
        row.update(torch_threads=torch.get_num_threads(), load_average_1min=[load_before, os.getloadavg()[0]],
                   gpu=gpu, cores=cores(), cpu_count=os.cpu_count(), provenance=provenance)
    out = args.out or Path(__file__).parent / "results" / f"policy_latency_{args.device.split(':')[0]}.json"
    # the GPU too: a run on another GPU sits beside the earlier one's rows instead of replacing them
    key = lambda r: (r["policy"], r["device"], r["batch"], r.get("torch_threads"), r.get("use_amp", False),  # noqa: E731
                     r.get("gpu"))
    old = json.loads(out.read_text())["results"] if out.is_file() else []
    fresh = {key(r) for r in rows}
    rows = [r for r in old if key(r) not in fresh] + rows
    # cpu_count, cores and provenance at the top: the latest run's (kept for readers of older files; rows have theirs)
    files.write_json(out, {"benchmark": "policy_latency", "cpu_count": os.cpu_count(), "cores": cores(),
                           "results": rows, "provenance": provenance})
    print(f"wrote {out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
