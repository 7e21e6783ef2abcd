"""What a vla-ladder dataset says about itself, as the recorder writes it and every reader reads it.

Next to LeRobot's own metadata, a recording holds meta/vla_ladder_recording.json (what it is a recording
of: the expert, the condition, the first seed, video or images; counters; versions) and one Parquet shard
of per-episode provenance per commit under meta/vla_ladder_episodes/ (seed, layout, metrics...).
Simulator-free, so training and dataset checks read it without the recorder.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from vla_ladder.conditions import Condition

FORMAT_VERSION = 2
RECORD_FIRST_SEED = 1_000_000
"""Where recordings start by default (`record`, a study's datasets): far from the evaluation seeds (0...) and the
grid's validation seeds (500,000...), so that no scene a model is evaluated on is one of its demonstrations. A seed
is a scene: in the recorded condition its very layout, target and instruction, in the other jitter regimes nearly
the same one."""
RECORDING_FILE = "meta/vla_ladder_recording.json"
PROVENANCE_DIR = "meta/vla_ladder_episodes"
# Video codecs a recording may use, by LeRobot's names: SVT-AV1 is LeRobot's default; H.264 costs the writer a
# quarter less CPU (benchmarks/video_codec.py). Not HEVC: torchcodec, LeRobot's default reader, fails on the HEVC
# files LeRobot's encoder writes (FrameTimestampError: the frame it finds is one step from the one asked for).
VCODECS = ("libsvtav1", "h264")
DEFAULT_VCODEC = "libsvtav1"


@dataclass(frozen=True)
class Recording:
    """What a dataset is a recording of; resuming requires the same values."""

    policy: str
    """expert spec (scripted, ppo:PATH, ...)"""
    condition: Condition
    first_seed: int = 0
    """first episode seed; later ones follow without repeats"""
    video: bool = True
    """cameras stored as MP4 video (LeRobot's default) or as PNG images inside the Parquet files"""
    robot_mesh: str = "lite"
    """how the robot looked in the pictures (see vla_ladder.task.robot)"""
    instructions: str = "canonical"
    """the instruction set worded from: canonical, paraphrase-train or paraphrase-heldout"""
    vcodec: str = DEFAULT_VCODEC
    """the cameras' video codec (one per dataset: LeRobot concatenates episodes into shared MP4 files)"""

    def __post_init__(self):
        if self.vcodec not in VCODECS:
            raise ValueError(f"unknown vcodec {self.vcodec!r}; allowed: {', '.join(VCODECS)}")

    def to_dict(self) -> dict:
        return {"policy": self.policy, "condition": self.condition.key, "first_seed": self.first_seed,
                "video": self.video, "robot_mesh": self.robot_mesh, "instructions": self.instructions,
                "vcodec": self.vcodec}

    @classmethod
    def from_dict(cls, data: dict, format_version: int = FORMAT_VERSION) -> "Recording":
        if format_version == 1:  # before conditions had one key, seeds a name, and the robot a lite mesh
            data = {"policy": data["policy"], "first_seed": data["seed"], "video": data["video"], "robot_mesh": "full",
                    "condition": Condition(data["regime"], data["split"], data["num_objects"]).key}
        return cls(data["policy"], Condition.parse(data["condition"]), int(data["first_seed"]), bool(data["video"]),
                   data.get("robot_mesh", "lite"), data.get("instructions", "canonical"),
                   data.get("vcodec", DEFAULT_VCODEC))

    def differences(self, other: "Recording") -> list[str]:
        mine, theirs = self.to_dict(), other.to_dict()
        return [f"{k}={theirs[k]!r} (this command: {v!r})" for k, v in mine.items() if theirs[k] != v]


def read_recording(root: str | os.PathLike) -> Recording | None:
    """What the dataset at `root` is a recording of, from the recording state the recorder writes (None when
    it is not a vla-ladder recording)."""
    state = read_recording_state(root)
    return None if state is None else _recording(state, Path(root) / RECORDING_FILE)


def read_provenance(root: str | os.PathLike) -> pd.DataFrame:
    """Per-episode provenance of a recorded dataset (seed, layout, expert, metrics...), by episode_index."""
    shards = sorted((Path(root) / PROVENANCE_DIR).glob("*.parquet"))
    if not shards:
        return pd.DataFrame()
    return pd.concat([pd.read_parquet(p) for p in shards], ignore_index=True).sort_values(
        "episode_index", ignore_index=True)


def recorded_seeds(root: str | os.PathLike, episodes=None) -> set[int]:
    """The seeds the dataset's episodes (those in `episodes`, where given) were recorded on: the scenes a model
    trained on it has seen (empty for a dataset without provenance)."""
    prov = read_provenance(root)
    if "seed" not in prov:
        return set()
    if episodes:
        prov = prov[prov["episode_index"].isin(episodes)]
    return set(prov["seed"].astype(int))


def read_recording_state(root: str | os.PathLike) -> dict | None:
    """The recording state at `root` (None when there is none); ValueError naming the file when it is damaged
    (cut short by a full disk, edited by hand): json's own message does not say which file it read."""
    path = Path(root) / RECORDING_FILE
    if not path.exists():
        return None
    try:
        state = json.loads(path.read_text())
    except ValueError as e:  # JSONDecodeError, or bytes that are not UTF-8
        raise _not_a_state(path, str(e)) from None
    # What every reader takes from it (a resume, the card, check-dataset), so that none meets a KeyError.
    if not (isinstance(state, dict) and isinstance(state.get("config"), dict)
            and isinstance(state.get("counters"), dict) and isinstance(state.get("next_seed"), int)):
        raise _not_a_state(path, "expected an object with config, counters and next_seed")
    if state.get("format", FORMAT_VERSION) in (1, FORMAT_VERSION):  # (another format is refused by its readers)
        _recording(state, path)
    return state


def _recording(state: dict, path: Path) -> Recording:
    try:
        return Recording.from_dict(state["config"], state.get("format", FORMAT_VERSION))
    except (KeyError, TypeError, ValueError) as e:  # a field missing, of another type, or a bad value
        raise _not_a_state(path, f"{type(e).__name__}: {e}") from None


def _not_a_state(path: Path, why: str) -> ValueError:
    return ValueError(f"{path}: not a vla-ladder recording state ({why})")


def played_to(state: dict) -> int:
    """Where a recording whose state this is plays on: the seed after the last one written or counted failed
    (recordings before it was kept: the next seed reserved, which skips the seeds a kill left in flight)."""
    return int(state.get("played_to", state["next_seed"]))


# ---------------------------------------------------------------------- stats.json's quantiles
STATS_FILE = "meta/stats.json"
_QUANTILE = re.compile(r"^q(\d{2})$")
_NOT_NUMERIC = ("image", "video", "string", "language")


def quantile_keys(feature_stats: dict) -> list[str]:
    """The quantile entries LeRobot wrote for a feature (q01, q10, q50, q90, q99 in LeRobot 0.6)."""
    return [k for k in feature_stats if _QUANTILE.match(k)]


def numeric_features(info: dict) -> list[str]:
    """Features stored as numbers in data/*.parquet (not cameras, not text)."""
    return [k for k, f in info["features"].items() if f["dtype"] not in _NOT_NUMERIC]


def frames(root: str | Path, keys: list[str]) -> dict[str, np.ndarray]:
    """Every frame's value of each key, as (frames, dim) float64 arrays, read from the dataset's Parquet files."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    paths = sorted(Path(root, "data").glob("*/*.parquet"))
    if not paths:
        raise ValueError(f"{root}: no data/*/*.parquet files; is it a LeRobotDataset v3?")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    for path in paths:  # (one file at a time: LeRobot writes vectors as list or, after a merge, fixed-size list)
        table = pq.read_table(path, columns=keys)
        for k in keys:
            col = table[k].combine_chunks()
            if pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type):
                # A vector per frame, all of one length: its values flat, without a numpy object per frame (stacking
                # those took longer than the quantiles themselves).
                parts[k].append(col.flatten().to_numpy(zero_copy_only=False).reshape(len(col), -1))
            else:
                parts[k].append(col.to_numpy(zero_copy_only=False)[:, None])
    return {k: np.concatenate(v).astype(np.float64) for k, v in parts.items()}


def exact_quantiles(root: str | Path) -> dict[str, dict[str, list[float]]]:
    """{feature: {q01: [...], ...}} over all frames, for every numeric feature stats.json has quantiles of."""
    root = Path(root)
    info = json.loads((root / "meta/info.json").read_text())
    stats = json.loads((root / STATS_FILE).read_text())
    keys = [k for k in numeric_features(info) if k in stats and quantile_keys(stats[k])]
    values = frames(root, keys)
    out = {}
    for k in keys:
        qkeys = quantile_keys(stats[k])
        qs = np.quantile(values[k], [int(_QUANTILE.match(q).group(1)) / 100 for q in qkeys], axis=0)
        for q, v in zip(qkeys, qs):
            if np.shape(stats[k][q]) != v.shape:
                raise ValueError(f"{root}: stats.json {k}/{q} has shape {np.shape(stats[k][q])} but the data "
                                 f"gives {v.shape}")
        out[k] = {q: v.tolist() for q, v in zip(qkeys, qs)}
    return out
