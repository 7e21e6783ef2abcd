"""Checks that a local directory is a GraspObject-v1 LeRobotDataset v3, before any training starts."""

from __future__ import annotations

import json
from pathlib import Path

from vla_ladder.conditions import Condition
from vla_ladder.contract import CAMERA_KEYS, FEATURE_SHAPES, POLICY_FIELDS, contract_changes
from vla_ladder.recordings import read_recording, read_recording_state


def read_info(root: str | Path) -> dict:
    """meta/info.json of the dataset at `root`; ValueError when it is not a LeRobotDataset v3 directory."""
    root = Path(root)
    if not root.is_dir():
        what = "is a file, not a dataset directory" if root.exists() else "does not exist"
        raise ValueError(f"dataset directory {str(root)!r} {what}")
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
    for key, shape in FEATURE_SHAPES.items():
        if key not in features:
            problems.append(f"{key} missing")
        elif tuple(features[key]["shape"]) != shape:
            problems.append(f"{key} has shape {tuple(features[key]['shape'])}, expected {shape}")
    for key in CAMERA_KEYS:
        if key in features and features[key]["dtype"] not in ("video", "image"):
            problems.append(f"{key} has dtype {features[key]['dtype']!r}, expected video or image")
    if problems:
        expected = ", ".join(f"{k} {s}" for k, s in FEATURE_SHAPES.items())
        raise ValueError(f"dataset {str(root)!r} does not match GraspObject-v1: " + "; ".join(problems)
                         + f". Expected: {expected}")


def dataset_condition(root: str | Path) -> Condition | None:
    """The condition the dataset was recorded in, from the recording metadata the recorder writes (None for a
    dataset vla-ladder did not record)."""
    recording = read_recording(root)
    return None if recording is None else recording.condition


def dataset_contract(root: str | Path) -> dict | None:
    """The task contract (contract.policy_fingerprint's fields) the dataset was recorded under; None where it does
    not say (another tool's dataset, or a recording made before recordings kept it). ValueError when it differs
    from this contract in what a policy sees or does: a policy trained on it would be evaluated on another task."""
    saved = (read_recording_state(root) or {}).get("contract")
    if saved is None:
        return None
    if changed := contract_changes(saved, POLICY_FIELDS):
        raise ValueError(f"dataset {str(root)!r} was recorded under another task contract ({'; '.join(changed)}): "
                         "a policy trained on it would be evaluated on a task it never saw; record it again with "
                         "this version, or train with the version that recorded it")
    return {k: saved[k] for k in POLICY_FIELDS}
