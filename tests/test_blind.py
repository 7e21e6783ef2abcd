"""The instruction-blind control: a recorded dataset copied with one fixed instruction, and a LeRobot policy
played with it."""

import json

import pytest

import lerobot_helpers as H
from vla_ladder.contract import BLIND_INSTRUCTION, IMAGE_SHAPE
from vla_ladder.training.blind import blind_copy

pytestmark = pytest.mark.slow  # records a dataset


def test_blind_copy_hides_the_instruction_and_shares_the_videos(tmp_path_factory, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    src = H.dataset(tmp_path_factory)
    before = {p: p.read_bytes() for p in (src / "meta").rglob("*.parquet")}
    dst = blind_copy(src, tmp_path / "blind")
    original, blind = LeRobotDataset("x/a", root=src), LeRobotDataset("x/b", root=dst)
    assert len(blind) == len(original) and blind.meta.total_episodes == original.meta.total_episodes
    assert len({original[i]["task"] for i in range(0, len(original), 25)}) >= 1
    assert {blind[i]["task"] for i in range(0, len(blind), 25)} == {BLIND_INSTRUCTION}
    assert (blind[7]["observation.state"] == original[7]["observation.state"]).all()
    video = next((src / "videos").rglob("*.mp4"))
    assert (dst / video.relative_to(src)).stat().st_ino == video.stat().st_ino  # a hard link, not a copy
    assert {p: p.read_bytes() for p in (src / "meta").rglob("*.parquet")} == before  # the source is untouched
    assert json.loads((dst / "meta" / "info.json").read_text())["total_tasks"] == 1
    assert blind_copy(src, tmp_path / "blind") == dst  # made once, then reused


def test_a_lerobot_policy_can_be_played_with_a_fixed_instruction(tmp_path_factory):
    import torch

    from vla_ladder.policies import load_policy

    run = H.trained(tmp_path_factory, "smolvla")
    seen = []
    policy = load_policy(f"lerobot:{run}?instruction={BLIND_INSTRUCTION}&device=cpu")
    policy.preprocessor_orig, policy.preprocessor = policy.preprocessor, lambda b: seen.append(b["task"]) or \
        policy.preprocessor_orig(b)
    obs = {"sensor_data": {c: {"rgb": torch.zeros(2, *IMAGE_SHAPE, dtype=torch.uint8)}
                           for c in ("hand_camera", "fixed_camera")}, "extra": {"proprio": torch.zeros(2, 15)}}
    policy.reset([0, 1])
    assert policy.act(obs, ["grasp the mug", "grasp the apple"]).shape == (2, 7)
    assert seen == [[BLIND_INSTRUCTION, BLIND_INSTRUCTION]]
    assert policy.describe()["instruction"] == BLIND_INSTRUCTION
