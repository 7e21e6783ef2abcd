"""A recording as LeRobot's tools meet it: its card, stats.json quantiles over all frames, what
lerobot-edit-dataset does to vla-ladder's provenance (and its rebuild), and lerobot-dataset-viz.

The dataset is written by the real DatasetStore and LeRobot's writer, with synthetic episodes (no rendering,
see test_recording_store.py) whose gripper opens for a seed-dependent number of frames and then stays closed,
like the expert's: the case where LeRobot's averaged per-episode quantiles go wrong.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from test_recording_store import synthetic_episode
from vla_ladder.conditions import Condition
from vla_ladder.contract import fingerprint
from vla_ladder.files import write_json
from vla_ladder.recording import provenance
from vla_ladder.recording.store import DatasetStore
from vla_ladder.recordings import (PROVENANCE_DIR, RECORDING_FILE, Recording, read_provenance, read_recording,
                                   read_recording_state)

pytestmark = pytest.mark.slow  # LeRobot datasets, video encoding, subprocess CLIs

FRAMES, EPISODES, REPO = 20, 4, "vla-ladder/native"
CONFIG = Recording("scripted", Condition("small_jitter", num_objects=2))
BIN = Path(sys.executable).parent


def episode(seed: int):
    """Joint positions drifting from a seed-dependent start; the gripper open (+1) for 2 + 3 * seed frames."""
    ep = synthetic_episode(seed, FRAMES)
    rng = np.random.default_rng(seed)
    ep.state[:] = (rng.normal(0, 0.5, 15) + np.cumsum(rng.normal(0, 0.05, (FRAMES, 15)), axis=0)).astype(np.float32)
    ep.action[:] = rng.uniform(-1, 1, (FRAMES, 7)).astype(np.float32)
    ep.action[:, 6] = np.where(np.arange(FRAMES) < 2 + 3 * seed, 1.0, -1.0)
    return ep


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, str]:
    """A 4-episode recording committed in two batches of two; also returns the card after the first commit."""
    root = tmp_path_factory.mktemp("native") / "ds"
    store = DatasetStore(root, CONFIG, commit_every=2, repo_id=REPO)
    first_card = None
    try:
        for seed in store.reserve_seeds(EPISODES):
            store.count(True)
            store.add(episode(seed))
            if store.saved == 2 and first_card is None:
                first_card = (root / "README.md").read_text()
    finally:
        store.close()
    return root, first_card


def _frames(root: Path) -> dict[str, np.ndarray]:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    data = LeRobotDataset(REPO, root=root).hf_dataset.with_format("numpy")
    return {k: np.asarray(data[k], dtype=np.float64) for k in ("observation.state", "action")}


def _stats(root: Path) -> dict:
    return json.loads((root / "meta/stats.json").read_text())


def _lerobot_average(root: Path, key: str, q: str) -> np.ndarray:
    """What LeRobot writes for a quantile: per-episode quantiles averaged by frame count (its own code)."""
    from lerobot.datasets.compute_stats import aggregate_stats, get_feature_stats

    values = _frames(root)[key]
    values = values.reshape(-1, FRAMES, values.shape[-1])
    return aggregate_stats([{key: get_feature_stats(v, axis=0, keepdims=False)} for v in values])[key][q]


def test_stats_quantiles_are_over_all_frames(recorded):
    root, _ = recorded
    frames, stats = _frames(root), _stats(root)
    assert len(frames["action"]) == EPISODES * FRAMES
    for key, values in frames.items():
        for q in ("q01", "q10", "q50", "q90", "q99"):
            np.testing.assert_allclose(stats[key][q], np.quantile(values, int(q[1:]) / 100, axis=0), atol=1e-6,
                                       err_msg=f"{key} {q}")
        np.testing.assert_allclose(stats[key]["max"], values.max(axis=0), atol=1e-6)  # LeRobot's, left as is
    # LeRobot's averaging is off here, which is what the recorder corrects: the gripper's q10 and q90.
    gripper_error = [abs(_lerobot_average(root, "action", q)[6] - stats["action"][q][6]) for q in ("q10", "q90")]
    assert max(gripper_error) > 0.3, gripper_error
    # Features in a fixed order (LeRobot's follows the hash seed), so recording the same episodes gives the same file.
    assert list(stats) == sorted(stats)


def test_card_says_what_was_recorded(recorded):
    root, first_card = recorded
    card = (root / "README.md").read_text()
    assert card.startswith("---\n") and "- robotics" in card and "data_files: data/*/*.parquet" in card
    for fact in ("`small_jitter/canonical/2`", "`scripted`", "`standin`", "robot mesh `lite`",
                 "seeds 0 to 3 were played", "**Episodes**: 4 (80 frames)", "vla-ladder 0.1.0", "lerobot 0.6.1",
                 "mani-skill 3.0.1"):
        assert fact in card, fact
    # What third-party card checks look for (lerobot-quality-gates): robot, sensors, tasks, limitations, synthetic.
    for word in ("Robot", "Sensors", "Tasks", "Limitations", "Synthetic"):
        assert word in card, word
    assert "**Episodes**: 2 (40 frames)" in first_card  # rewritten at every commit


def test_delete_episodes_drops_provenance_and_rebuild_restores_it(recorded, tmp_path):
    """lerobot-edit-dataset delete_episodes in place: LeRobot keeps its own files only, moves the original to
    <root>_old; provenance.rebuild finds each episode there again by its frames."""
    import shutil

    src, _ = recorded
    root = tmp_path / "ds"
    shutil.copytree(src, root)
    before = read_provenance(root)
    done = subprocess.run([str(BIN / "lerobot-edit-dataset"), f"--repo_id={REPO}", f"--root={root}",
                           f"--new_root={root}", "--operation.type=delete_episodes",
                           "--operation.episode_indices=[1]"],
                          capture_output=True, text=True, timeout=900, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    old = tmp_path / "ds_old"
    assert json.loads((root / "meta/info.json").read_text())["total_episodes"] == EPISODES - 1
    # What LeRobot's tool leaves: no provenance, no card, averaged quantiles; the original is intact beside it.
    assert not (root / RECORDING_FILE).exists() and not (root / PROVENANCE_DIR).exists()
    assert not (root / "README.md").exists() and read_recording(root) is None
    assert provenance.missing(root) == [f"{RECORDING_FILE} is missing"]
    assert (old / RECORDING_FILE).exists() and provenance.missing(old) == []
    exact = np.quantile(_frames(root)["action"], 0.9, axis=0)
    assert np.abs(np.asarray(_stats(root)["action"]["q90"]) - exact).max() > 0.3

    # Killed while it computes the exact quantiles (it reads every frame): the recording file, which says the dataset
    # is whole, is not written yet, so the dataset is still refused rather than trained on the averaged quantiles.
    from vla_ladder.recording import stats

    def killed(*args):
        raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as mp, pytest.raises(KeyboardInterrupt):
        mp.setattr(stats, "write_exact_quantiles", killed)
        provenance.rebuild(root, [old])
    assert provenance.missing(root) == [f"{RECORDING_FILE} is missing"] and read_recording(root) is None
    rebuilt = provenance.rebuild(root, [old])
    kept = before[before["episode_index"] != 1].reset_index(drop=True)
    assert rebuilt["episode_index"].tolist() == [0, 1, 2]
    assert rebuilt["seed"].tolist() == kept["seed"].tolist() == [0, 2, 3]
    assert rebuilt["instruction"].tolist() == kept["instruction"].tolist()
    assert provenance.missing(root) == [] and read_recording(root) == CONFIG
    np.testing.assert_allclose(_stats(root)["action"]["q90"], exact, atol=1e-6)
    assert "**Episodes**: 3 (60 frames)" in (root / "README.md").read_text()
    assert read_recording_state(root)["contract"] == read_recording_state(old)["contract"] == fingerprint()
    # A dataset that is not made of the source's episodes is refused, naming the episode.
    with pytest.raises(ValueError, match="episode 1 matches no episode"):
        provenance.rebuild(old, [root])
    # Sources recorded under two task contracts are no one recording: the provenance comes back, the state not.
    other = tmp_path / "other_contract"
    shutil.copytree(old, other)
    state = read_recording_state(other)
    write_json(other / RECORDING_FILE, {**state, "contract": {**state["contract"], "control_hz": 10}})
    provenance.rebuild(root, [old, other])
    assert len(read_provenance(root)) == 3 and read_recording(root) is None


def test_lerobot_dataset_viz_saves_an_rrd(recorded, tmp_path):
    """LeRobot's viz extra is installed: lerobot-dataset-viz reads a recording and writes a Rerun file."""
    root, _ = recorded
    done = subprocess.run([str(BIN / "lerobot-dataset-viz"), f"--repo-id={REPO}", f"--root={root}",
                           "--episode-index=1", "--save=1", f"--output-dir={tmp_path}", "--num-workers=0"],
                          capture_output=True, text=True, timeout=600, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    (rrd,) = tmp_path.glob("*.rrd")
    assert rrd.stat().st_size > 10_000
