"""Shared, once-per-session artefacts for the training and LeRobot-policy tests.

Recording a dataset and training a tiny model take tens of seconds on CPU, so every test module asks these
helpers, which build each artefact once per pytest process and hand back its path.
"""

from __future__ import annotations

import json
from pathlib import Path

_CACHE: dict[str, Path] = {}


def _record_with_pipeline(root: Path, episodes: int, seed: int) -> Path:
    from vla_ladder.cli import main

    argv = ["record", "--out", str(root), "--episodes", str(episodes), "--first-seed", str(seed),
            "--regime", "small_jitter", "--num-objects", "2"]
    # On an overloaded machine a server can drop the connection (exit code 1); the recorder's documented
    # remedy is to rerun the same command, which resumes.
    for _ in range(3):
        rc = main(argv)
        if rc != 1:
            break
    assert rc == 0, f"vla-ladder record failed ({rc})"
    assert json.loads((root / "meta" / "info.json").read_text())["total_episodes"] == episodes
    return root


def dataset(tmp_path_factory, episodes: int = 2, seed: int = 0) -> Path:
    """A small LeRobotDataset v3 recorded by `vla-ladder record` (scripted expert, two 256x256 cameras,
    15-d state, 7-d action)."""
    key = f"dataset-{episodes}-{seed}"
    if key not in _CACHE:
        root = tmp_path_factory.mktemp("data") / "tiny"
        _CACHE[key] = _record_with_pipeline(root, episodes, seed)
    return _CACHE[key]


def tiny_vlm(tmp_path_factory) -> Path:
    if "vlm" not in _CACHE:
        from vla_ladder.training.tiny import build_vlm_dir
        _CACHE["vlm"] = build_vlm_dir(tmp_path_factory.mktemp("vlm") / "tiny-smolvlm")
    return _CACHE["vlm"]


def tiny_policy_flags(kind: str, vlm: Path | None = None) -> list[str]:
    """lerobot-train flags (after `--`) that shrink a policy: SmolVLA to 0.2M parameters on the local tiny
    VLM, ACT to a one-layer transformer (its ResNet-18 backbone stays, randomly initialised)."""
    if kind == "smolvla":
        from vla_ladder.training.tiny import scratch_smolvla_args
        return [*scratch_smolvla_args(vlm, 64), "--policy.num_steps=2"]
    if kind == "act":
        return ["--policy.dim_model=32", "--policy.n_heads=2", "--policy.dim_feedforward=64",
                "--policy.n_encoder_layers=1", "--policy.n_decoder_layers=1", "--policy.use_vae=false"]
    raise ValueError(kind)


def train_args(kind: str, data: Path, out: Path, vlm: Path | None = None, steps: int = 2,
               batch_size: int = 4, chunk_size: int = 4) -> list[str]:
    return ["train", "--policy-type", kind, "--dataset", str(data), "--out", str(out), "--pretrained", "none",
            "--steps", str(steps), "--batch-size", str(batch_size), "--chunk-size", str(chunk_size),
            "--num-workers", "0", "--log-freq", "1", "--device", "cpu", "--", *tiny_policy_flags(kind, vlm)]


def trained(tmp_path_factory, kind: str) -> Path:
    """A `vla-ladder train` run directory of a tiny `kind` policy trained 2 steps on `dataset()`."""
    key = f"trained-{kind}"
    if key not in _CACHE:
        from vla_ladder.cli import main

        data = dataset(tmp_path_factory)
        vlm = tiny_vlm(tmp_path_factory) if kind == "smolvla" else None
        out = tmp_path_factory.mktemp("runs") / kind
        assert main(train_args(kind, data, out, vlm)) == 0
        _CACHE[key] = out
    return _CACHE[key]
