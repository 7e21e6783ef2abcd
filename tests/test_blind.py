"""The instruction-blind control: a recorded dataset copied with one fixed instruction, and a LeRobot policy
played with it."""

import json
import shutil

import pandas as pd
import pytest

import lerobot_helpers as H
from vla_ladder.cli import main
from vla_ladder.contract import BLIND_INSTRUCTION, EPISODE_STEPS, IMAGE_SHAPE
from vla_ladder.recordings import read_provenance
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
    # Its card says what it is (it was the source's, hard-linked, listing the instructions its frames do not hold),
    # and the source's card is untouched.
    card, source_card = (dst / "README.md").read_text(), (src / "README.md").read_text()
    assert card.startswith("# Instruction-blind copy") and card.endswith(source_card)
    assert not source_card.startswith("# Instruction-blind copy")
    assert blind_copy(src, tmp_path / "blind") == dst  # made once, then reused


def test_check_dataset_passes_a_blind_copy_and_finds_an_instruction_left_in_it(tmp_path_factory, tmp_path, capsys):
    """A blind copy is checked as a recording whose tasks are all BLIND_INSTRUCTION (its task index's statistics
    included), holding its source's frames and videos; an instruction shown anywhere LeRobot reads a task, or a
    video that is not the source's, is a `blind` line."""
    src = H.dataset(tmp_path_factory)
    dst = blind_copy(src, tmp_path / "blind")

    def check(root):
        out = tmp_path / f"{root.name}.json"
        rc = main(["check-dataset", str(root), "--replay", "0", "--out", str(out)])
        lines = [line.removeprefix("check-dataset: ") for line in capsys.readouterr().err.splitlines()
                 if line.startswith("check-dataset: ")]
        return rc, json.loads(out.read_text()), lines

    rc, summary, lines = check(dst)
    assert rc == 0 and lines == [], lines
    blind = summary["checks"]["blind"]
    assert blind["blind_copy"] and blind["tasks"] == [BLIND_INSTRUCTION] and blind["episodes_showing_a_task"] == 0
    assert blind["frames_compared"] == 2 * EPISODE_STEPS and blind["videos_compared"] == 2
    assert blind["videos_differing"] == 0 and blind["features_differing"] == []

    broken = tmp_path / "broken"
    shutil.copytree(dst, broken)  # (the videos copied, not linked: the same bytes still pass)
    instruction = read_provenance(src)["instruction"][0]
    pd.DataFrame({"task_index": [0, 1]}, index=pd.Index([BLIND_INSTRUCTION, instruction], name="task")).to_parquet(
        broken / "meta/tasks.parquet")
    data_path = next((broken / "data").rglob("*.parquet"))
    data = pd.read_parquet(data_path)
    data.loc[data["episode_index"] == 0, "task_index"] = 1  # episode 0 still tells its instruction
    data.to_parquet(data_path, index=False)
    video = next((broken / "videos").rglob("*.mp4"))
    video.write_bytes(video.read_bytes()[:-1] + b"\0")  # no longer the source's pictures
    rc, summary, lines = check(broken)
    assert rc == 1 and summary["checks"]["blind"]["episodes_showing_a_task"] == 1
    seed = int(read_provenance(src)["seed"][0])
    assert (f"blind: episode 0 (seed {seed}): its frames' task_index gives [{instruction!r}], not the blind copy's "
            f"{BLIND_INSTRUCTION!r} (what training reads)") in lines
    assert (f"blind: meta/tasks.parquet holds {[BLIND_INSTRUCTION, instruction]}; a blind copy's holds only "
            f"{BLIND_INSTRUCTION!r}") in lines
    assert f"blind: 1 video file(s) differ from or are missing in its source's ({video.relative_to(broken)}): the " \
           "blind twin must see the same pictures" in lines


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
