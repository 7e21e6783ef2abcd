"""Rebuild vla-ladder's provenance of a dataset that LeRobot's editing tools made from recordings.

`lerobot-edit-dataset` (delete_episodes, split, merge, remove_feature, convert_image_to_video) writes a new
LeRobotDataset from LeRobot's own files only: meta/vla_ladder_recording.json, meta/vla_ladder_episodes/ and
README.md are not carried over, episodes are renumbered, and stats.json's quantiles are averaged per episode
again. (An in-place edit, --new_root equal to --root, moves the original to <root>_old first.) The frames
themselves are copied unchanged, so each edited episode is found again in its source recording by a
fingerprint of its state and action arrays, and its provenance row follows it under its new index.
`rebuild` does that, then rewrites the quantiles over all frames and the dataset card.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated

import numpy as np
import pandas as pd
import tyro

from vla_ladder import files
from vla_ladder.contract import ACTION_KEY, STATE_KEY
from vla_ladder.recordings import (FORMAT_VERSION, PROVENANCE_DIR, RECORDING_FILE, played_to, read_provenance,
                                   read_recording_state)

REBUILT_SHARD = "rebuilt.parquet"


def fingerprints(root: str | Path) -> dict[int, str]:
    """{episode_index: hash of the episode's state and action frames, in frame order}."""
    paths = sorted(Path(root, "data").glob("*/*.parquet"))
    if not paths:
        raise ValueError(f"{root}: no data/*/*.parquet files; is it a LeRobotDataset v3?")
    cols = ["episode_index", "frame_index", STATE_KEY, ACTION_KEY]
    table = pd.concat([pd.read_parquet(p, columns=cols) for p in paths], ignore_index=True)
    out = {}
    for ep, frames in table.sort_values(["episode_index", "frame_index"]).groupby("episode_index"):
        h = hashlib.sha256()
        for key in (STATE_KEY, ACTION_KEY):
            h.update(np.stack(frames[key].to_numpy()).astype(np.float32).tobytes())
        out[int(ep)] = h.hexdigest()
    return out


def missing(root: str | Path) -> list[str]:
    """What of vla-ladder's provenance a dataset lacks or has out of step with LeRobot's metadata (empty: whole)."""
    root = Path(root)
    state = read_recording_state(root)
    if state is None:
        return [f"{RECORDING_FILE} is missing"]
    info = json.loads((root / "meta/info.json").read_text())
    prov = read_provenance(root)
    problems = []
    if prov.empty or prov["episode_index"].tolist() != list(range(info["total_episodes"])):
        problems.append(f"{PROVENANCE_DIR} has {len(prov)} rows for {info['total_episodes']} episodes")
    if state["counters"]["saved"] != info["total_episodes"]:
        problems.append(f"{RECORDING_FILE} counts {state['counters']['saved']} episodes, info.json "
                        f"{info['total_episodes']}")
    return problems


def rebuild(root: str | Path, sources: list[str | Path]) -> pd.DataFrame:
    """Give the edited dataset at `root` the provenance of its episodes in the recordings `sources` (for an
    in-place edit, <root>_old). Every episode must be found in exactly one source episode; the recording state
    is written when all sources were recordings of the same thing (a merge of different conditions keeps only
    the per-episode rows, which say each episode's condition). Returns the new provenance, by episode_index."""
    root = Path(root)
    if not sources:
        raise ValueError("rebuild needs the recording(s) the dataset was made from")
    index: dict[str, tuple[int, int]] = {}
    states, provs = [], []
    for k, src in enumerate(sources):
        state = read_recording_state(src)
        if state is None:
            raise ValueError(f"source {src} is not a vla-ladder recording ({RECORDING_FILE} is missing)")
        states.append(state)
        provs.append(read_provenance(src).set_index("episode_index"))
        for ep, fp in fingerprints(src).items():
            index.setdefault(fp, (k, ep))
    rows = []
    for ep, fp in sorted(fingerprints(root).items()):
        if fp not in index:
            raise ValueError(f"{root}: episode {ep} matches no episode of {', '.join(map(str, sources))}")
        k, src_ep = index[fp]
        rows.append({**provs[k].loc[src_ep].to_dict(), "episode_index": ep})
    prov = pd.DataFrame(rows)
    shutil.rmtree(root / PROVENANCE_DIR, ignore_errors=True)
    files.write_parquet(root / PROVENANCE_DIR / REBUILT_SHARD, prov)
    # one recording only if the sources agree on what they record, and under which task contract
    configs = {json.dumps([s["config"], s.get("contract")], sort_keys=True) for s in states}
    # The recording file says the dataset is whole: it comes after the exact quantiles it vouches for (reading every
    # frame takes a while), so that a kill in between leaves a dataset that is refused, not one trained on
    # LeRobot's averaged quantiles.
    (root / RECORDING_FILE).unlink(missing_ok=True)
    from vla_ladder.recording import card, stats

    stats.write_exact_quantiles(root)
    if len(configs) == 1:
        files.write_json(root / RECORDING_FILE, _derived_state(states, len(prov), sources))
        card.write_card(root)
    return prov


def _derived_state(states: list[dict], episodes: int, sources: list) -> dict:
    first = states[0]
    counters = {k: sum(int(s["counters"].get(k, 0)) for s in states) for k in ("attempted", "failed")}
    return {"format": FORMAT_VERSION, "config": first["config"],
            "next_seed": max(int(s["next_seed"]) for s in states),
            "played_to": max(map(played_to, states)),
            "counters": {"saved": episodes, **counters, "commits": 0},
            "object_set": first.get("object_set"),
            "updated": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "provenance": first.get("provenance", {}), "contract": first.get("contract"),
            "derived_from": [str(Path(s).resolve()) for s in sources]}


@dataclass
class RebuildProvenanceConfig:
    """Give a dataset that LeRobot's editing tools made from recordings its vla-ladder provenance back."""

    dataset: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATASET")]
    """the edited LeRobotDataset (lerobot-edit-dataset's output)"""
    sources: Annotated[tuple[Path, ...], tyro.conf.arg(metavar="DIR [DIR ...]")]
    """the recordings it was made from (for an in-place edit: DATASET_old)"""

    def __post_init__(self):
        for p in (self.dataset, *self.sources):
            if not (Path(p) / "meta" / "info.json").is_file():
                raise ValueError(f"{p} is not a LeRobotDataset (no meta/info.json)")


def run(cfg: RebuildProvenanceConfig) -> int:
    prov = rebuild(cfg.dataset, list(cfg.sources))
    print(f"rebuilt the provenance of {len(prov)} episodes in {cfg.dataset}")
    return 0
