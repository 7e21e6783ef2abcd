"""Checks that a local directory is a GraspObject-v1 LeRobotDataset v3, before any training starts."""

from __future__ import annotations

import json
from pathlib import Path

# What the recording pipeline writes and what a policy for GraspObject-v1 must consume (paper, appendix
# "Dataset format"): two 256x256 RGB cameras, the 15-d proprioceptive state, the 7-d ee-delta action.
CAMERA_KEYS = ("observation.images.hand_camera", "observation.images.fixed_camera")
IMAGE_SHAPE = (256, 256, 3)
STATE_KEY, STATE_DIM = "observation.state", 15
ACTION_KEY, ACTION_DIM = "action", 7
EXPECTED = {**{k: IMAGE_SHAPE for k in CAMERA_KEYS}, STATE_KEY: (STATE_DIM,), ACTION_KEY: (ACTION_DIM,)}


def read_info(root: str | Path) -> dict:
    """meta/info.json of the dataset at `root`; ValueError when it is not a LeRobotDataset v3 directory."""
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"dataset directory {str(root)!r} does not exist")
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        raise ValueError(f"{str(root)!r} is not a LeRobotDataset: {info_path} is missing")
    info = json.loads(info_path.read_text())
    version = str(info.get("codebase_version", ""))
    if not version.startswith("v3"):
        raise ValueError(f"{str(root)!r} is a LeRobotDataset {version or '(unknown version)'}; need v3.x "
                         "(convert with lerobot's convert_dataset_v21_to_v30)")
    return info


def check_features(info: dict, root: str | Path = "") -> None:
    """ValueError listing every feature that is missing or has the wrong shape."""
    features = info.get("features", {})
    problems = []
    for key, shape in EXPECTED.items():
        if key not in features:
            problems.append(f"{key} missing")
        elif tuple(features[key]["shape"]) != shape:
            problems.append(f"{key} has shape {tuple(features[key]['shape'])}, expected {shape}")
    for key in CAMERA_KEYS:
        if key in features and features[key]["dtype"] not in ("video", "image"):
            problems.append(f"{key} has dtype {features[key]['dtype']!r}, expected video or image")
    if problems:
        expected = ", ".join(f"{k} {s}" for k, s in EXPECTED.items())
        raise ValueError(f"dataset {str(root)!r} does not match GraspObject-v1: " + "; ".join(problems)
                         + f". Expected: {expected}")


def dataset_regime(root: str | Path) -> str | None:
    """The placement regime the dataset was recorded in, when its provenance says so (else None).

    The recorder stamps a provenance JSON next to LeRobot's metadata; every regime in it must agree."""
    root = Path(root)
    regimes: set[str] = set()
    for path in sorted((root / "meta").glob("*.json")) + sorted(root.glob("*.json")):
        if path.name in ("info.json", "stats.json"):
            continue
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        regimes |= _find_regimes(data)
    return regimes.pop() if len(regimes) == 1 else None


def _find_regimes(data, depth: int = 0) -> set[str]:
    if depth > 4:
        return set()
    if isinstance(data, dict):
        found = {data["regime"]} if isinstance(data.get("regime"), str) else set()
        for v in data.values():
            found |= _find_regimes(v, depth + 1)
        return found
    if isinstance(data, list):
        return set().union(*(_find_regimes(v, depth + 1) for v in data[:1000])) if data else set()
    return set()
