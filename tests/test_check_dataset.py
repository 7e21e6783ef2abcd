"""`vla-ladder check-dataset` on a dataset recorded by `vla-ladder record`, and on copies broken on purpose."""

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vla_ladder.cli import main
from vla_ladder.conditions import Condition
from vla_ladder.contract import EPISODE_STEPS
from vla_ladder.files import write_json
from vla_ladder.recordings import PROVENANCE_DIR, RECORDING_FILE, read_recording_state
from vla_ladder.task.layouts import HELD_OUT_REGIONS, sample_layout
from vla_ladder.task.objects import OBJECT_NAMES
from vla_ladder.training.check_dataset import CheckDatasetConfig, Checker, occupancy, pair_probabilities


def test_pair_probabilities_follow_the_split():
    canonical = pair_probabilities(Condition("small_jitter", num_objects=5))
    assert np.allclose(canonical, np.eye(5))  # object i always in region i
    pid = pair_probabilities(Condition("small_jitter", "pairings_id", 3))
    for i in range(5):
        assert all(pid[i, r] == 0 for r in HELD_OUT_REGIONS[i]) and pid[i].sum() == pytest.approx(3 / 5, abs=0.05)
    lay = sample_layout(Condition("full_random", num_objects=2), 0).to_dict()
    assert [name for name, _ in occupancy(lay)] == list(lay["positions"])


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """Three successful scripted episodes of small_jitter/pairings_id/2, recorded by the real pipeline."""
    root = tmp_path_factory.mktemp("data") / "pid"
    argv = ["record", "--out", str(root), "--episodes", "3", "--regime", "small_jitter", "--split", "pairings_id",
            "--num-objects", "2", "--first-seed", "0"]  # (the seeds whose episodes the replay test's edit was sized on)
    for _ in range(3):  # an overloaded machine can drop the server connection; rerunning resumes
        rc = main(argv)
        if rc != 1:
            break
    assert rc == 0
    return root


def check(root: Path, tmp_path: Path, capsys, *flags) -> tuple[int, dict, list[str]]:
    out = tmp_path / f"{root.name}.json"
    rc = main(["check-dataset", str(root), "--out", str(out), *flags])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("check-dataset: ")]
    return rc, json.loads(out.read_text()), [line.removeprefix("check-dataset: ") for line in lines]


@pytest.mark.slow
def test_a_recorded_dataset_passes(recorded, tmp_path, capsys):
    rc, summary, lines = check(recorded, tmp_path, capsys)
    assert rc == 0 and summary["ok"] and lines == [] and summary["violations"] == []
    assert summary["episodes"] == 3 and summary["frames"] == 3 * EPISODE_STEPS
    checks = summary["checks"]
    assert checks["frames"]["per_episode"] == [EPISODE_STEPS] and checks["layouts"] == {"checked": 3, "mismatched": 0}
    # Each episode's first state is its seed's start (layouts.initial_qpos) to the bit.
    assert checks["start"] == {"checked": 3, "differing": 0, "not_checked_gpu": 0, "max_diff": 0.0}
    assert np.array(checks["coverage"]["counts"]).sum() == 6  # two objects in each of three episodes
    assert checks["coverage"]["episodes"] == 3 and checks["coverage"]["pairs_missing"] == 0
    assert checks["coverage"]["pairs_expected"] == 0  # (no pair is expected 5 times in 3 episodes)
    assert checks["leakage"]["checked"] and checks["leakage"]["episodes_with_held_out_pairs"] == 0
    assert checks["leakage"]["episodes"] == 3
    assert sum(checks["balance"]["counts"].values()) == 3 and checks["balance"]["p_value"] is None
    assert checks["actions"]["frames"] == 3 * EPISODE_STEPS and checks["actions"]["frames_outside"] == 0
    assert checks["actions"]["frames_non_finite_state"] == 0
    assert all(-1 <= v <= 1 for v in checks["actions"]["min"] + checks["actions"]["max"])
    assert checks["quantiles"]["differing"] == 0 and "action" in checks["quantiles"]["features"]
    assert checks["quantiles"]["checked"] >= 10  # q01..q99 of the action and the state at least
    assert checks["stats"]["checked"] == 10 and checks["stats"]["differing"] == 0  # mean...count of both
    # `record` rebuilds every scene, so each episode's seed and actions give back its states to the last bit.
    replay = checks["replay"]
    assert replay["replayed"] == replay["bit_exact"] == 3 and replay["max_state_diff"] == 0.0
    assert all(e["replayable"] and e["held"] == e["held_replayed"] != "none" for e in replay["episodes"])


def _provenance(root: Path) -> tuple[Path, pd.DataFrame]:
    path = sorted((root / PROVENANCE_DIR).glob("*.parquet"))[0]
    return path, pd.read_parquet(path)


@pytest.mark.slow
def test_quantiles_that_are_not_those_of_every_frame_are_flagged(recorded, tmp_path, capsys):
    """pi0.5 normalises state and action with stats.json's q01/q99: LeRobot's average of per-episode quantiles (an
    edit by LeRobot's tools) or those of a stopped recording's first frames would change what the model sees."""
    edited = tmp_path / "edited"
    shutil.copytree(recorded, edited)
    stats = json.loads((edited / "meta/stats.json").read_text())
    stats["action"]["q01"][0] += 0.1
    write_json(edited / "meta/stats.json", stats)
    rc, summary, lines = check(edited, tmp_path, capsys, "--replay", "0")
    assert rc == 1 and lines == summary["violations"] and len(lines) == 1
    assert lines[0].startswith(f"quantiles: 1 quantiles in stats.json are not those of the {3 * EPISODE_STEPS} "
                               "frames (the furthest, action q01, by 0.1;")
    assert "rebuild-provenance" in lines[0]
    state = read_recording_state(edited)
    state["quantile_frames"] = 2 * EPISODE_STEPS
    write_json(edited / RECORDING_FILE, state)
    rc, summary, lines = check(edited, tmp_path, capsys, "--replay", "0")
    assert rc == 1 and f"they are of its first {2 * EPISODE_STEPS} frames" in lines[0]
    assert "rerun its `record`" in lines[0]
    assert summary["checks"]["quantiles"]["differing"] == 1


@pytest.mark.slow
def test_a_mean_std_min_or_max_that_is_not_that_of_every_frame_is_flagged(recorded, tmp_path, capsys):
    """SmolVLA and ACT normalise state and action with stats.json's mean/std, diffusion with min/max: an edited
    stats.json, or one of other frames, changes what the model sees as much as a wrong quantile does."""
    edited = tmp_path / "edited"
    shutil.copytree(recorded, edited)
    stats = json.loads((edited / "meta/stats.json").read_text())
    stats["action"]["mean"][0] += 0.01
    stats["observation.state"]["std"][3] *= 1.5
    write_json(edited / "meta/stats.json", stats)
    rc, summary, lines = check(edited, tmp_path, capsys, "--replay", "0")
    assert rc == 1 and lines == summary["violations"] and len(lines) == 1
    assert lines[0].startswith("stats: 2 of stats.json's mean/std/min/max/count of observation.state and action are "
                               f"not those of the {3 * EPISODE_STEPS} frames (the furthest, observation.state std, ")
    assert summary["checks"]["stats"]["differing"] == 2 and summary["checks"]["quantiles"]["differing"] == 0


@pytest.mark.slow
def test_a_leaky_dataset_built_on_purpose_is_caught(recorded, tmp_path, capsys):
    leaky = tmp_path / "leaky"
    shutil.copytree(recorded, leaky)
    path, prov = _provenance(leaky)
    # Episode 1 gets the layout its seed has on *held-out* pairings, relabelled as training data: the kind of
    # mix-up (two recordings merged, a wrong --split) that makes an OOD result meaningless.
    seed = int(prov.loc[1, "seed"])
    ood = sample_layout(Condition("small_jitter", "pairings_ood", 2), seed).to_dict()
    ood["split"] = "pairings_id"
    prov.loc[1, ["layout", "target", "instruction"]] = [json.dumps(ood), ood["target"], ood["instruction"]]
    prov.loc[2, "seed"] = prov.loc[0, "seed"]  # a seed recorded twice
    prov.to_parquet(path, index=False)
    data_path = sorted((leaky / "data").glob("*/*.parquet"))[0]
    data = pd.read_parquet(data_path)
    action = data.at[7, "action"].copy()
    action[2] = 1.5  # outside the normalised action box
    data.at[7, "action"] = action
    data = data.drop(index=data.index[(data["episode_index"] == 2) & (data["frame_index"] == EPISODE_STEPS - 1)])
    # Episode 1's actions stored one frame late (the classic off-by-one between an observation and its action):
    # every other check passes them, only a replay sees that they did not produce the recorded states.
    ep1 = data.index[data["episode_index"] == 1]
    data.loc[ep1, "action"] = pd.Series([data.at[ep1[0], "action"], *data.loc[ep1[:-1], "action"]], index=ep1)
    # Episode 0's frames point at a task meta/tasks.parquet lacks: training would read no instruction for them,
    # while meta/episodes' `tasks` still names the right one.
    data.loc[data["episode_index"] == 0, "task_index"] = 99
    data.to_parquet(data_path, index=False)
    state = read_recording_state(leaky)  # and recorded when the episode was 10 steps longer
    state["contract"]["episode_steps"] = EPISODE_STEPS + 10
    saved = state["counters"]["saved"]
    state["counters"]["saved"] = 99  # and counting other episodes than it holds
    write_json(leaky / RECORDING_FILE, state)

    rc, summary, lines = check(leaky, tmp_path, capsys)
    assert rc == 1 and not summary["ok"] and lines == summary["violations"]
    held_out = [f"{n} in region {r}" for n, r in occupancy(ood) if r in HELD_OUT_REGIONS[OBJECT_NAMES.index(n)]]
    assert held_out and f"leakage: episode 1 (seed {seed}) holds held-out pairs: {', '.join(held_out)}" in lines
    assert any(line.startswith("layouts: episode 1 ") and "but the seed gives" in line for line in lines)
    assert any(line.startswith("layouts: episode 0 ") and "its frames' task_index gives [None]" in line
               for line in lines)
    assert any(line.startswith(f"seeds: seed {int(prov.loc[0, 'seed'])} recorded 2 times (episodes 0, 2)")
               for line in lines)
    assert any(line.startswith("actions: episode 0: 1 frames with actions outside [-1, 1]") for line in lines)
    frames = f"frames: episode 2: {EPISODE_STEPS - 1} frames, the contract has {EPISODE_STEPS}"
    assert any(line.startswith(frames) for line in lines)
    assert (f"structure: recorded under another task contract: episode_steps was {EPISODE_STEPS + 10}, now "
            f"{EPISODE_STEPS}") in lines
    assert f"structure: the recording state counts 99 episodes but info.json has {saved}" in lines
    assert summary["checks"]["leakage"]["episodes_with_held_out_pairs"] == 1
    assert summary["checks"]["actions"]["frames_outside"] == 1
    replayed = {e["episode_index"]: e for e in summary["checks"]["replay"]["episodes"]}
    assert 2 not in replayed  # its missing frame is the frames check's to report
    # Frame 1 now holds action 0 again; the state it leads to, frame 2's, is the first to differ.
    assert replayed[1]["max_state_diff"] > 0.25 and replayed[1]["first_frame_differing"] == 2
    assert any(line.startswith("replay: episode 1 ") and line.endswith("must replay bit for bit") for line in lines)


def _retask(root: Path, instructions: dict[int, str]) -> None:
    """Give episodes other instructions in every file LeRobot reads them from (tasks.parquet, each frame's
    task_index, meta/episodes' tasks), and stats.json the quantiles of the new task indices."""
    from vla_ladder.recording.stats import write_exact_quantiles

    episodes_path = sorted((root / "meta/episodes").glob("*/*.parquet"))[0]
    episodes = pd.read_parquet(episodes_path)
    tasks = [instructions.get(int(e), list(t)[0]) for e, t in zip(episodes["episode_index"], episodes["tasks"])]
    table = list(dict.fromkeys(tasks))
    pd.DataFrame({"task_index": range(len(table))}, index=pd.Index(table, name="task")).to_parquet(
        root / "meta/tasks.parquet")
    episodes["tasks"] = [[t] for t in tasks]
    episodes.to_parquet(episodes_path, index=False)
    data_path = sorted((root / "data").glob("*/*.parquet"))[0]
    data = pd.read_parquet(data_path)
    data["task_index"] = [table.index(tasks[int(e)]) for e in data["episode_index"]]
    data.to_parquet(data_path, index=False)
    write_exact_quantiles(root)


@pytest.mark.slow
def test_a_probe_counterfactual_recorded_as_training_data_is_caught(recorded, tmp_path, capsys):
    """A recording holds each seed's own episode. Another object on the table instructed (the expert grasped one
    object, the label names another), a colour swap or a held-out paraphrase are what probes play: written
    consistently into every file (quantiles included), only the seed's layout tells them apart."""
    copy = tmp_path / "counterfactual"
    shutil.copytree(recorded, copy)
    path, prov = _provenance(copy)
    condition = Condition("small_jitter", "pairings_id", 2)
    seeds = [int(s) for s in prov["seed"]]
    own = sample_layout(condition, seeds[0])
    changed = [own.instructed(own.objects[1]).to_dict(),  # the distractor named, the scene unchanged
               sample_layout(condition, seeds[1], instructions="paraphrase-heldout").to_dict(),
               sample_layout(condition, seeds[2], appearance="swap").to_dict()]  # (orange and apple swap colours)
    for ep, layout in enumerate(changed):
        prov.loc[ep, ["layout", "target", "instruction"]] = [json.dumps(layout), layout["target"],
                                                             layout["instruction"]]
    prov.to_parquet(path, index=False)
    _retask(copy, {0: changed[0]["instruction"], 1: changed[1]["instruction"]})
    rc, summary, lines = check(copy, tmp_path, capsys, "--replay", "0")
    assert rc == 1 and len(lines) == 3 and all(line.startswith("layouts: ") for line in lines)
    assert (f"target {changed[0]['target']!r} but the seed gives {own.target!r}" in lines[0]
            and f"instruction {changed[0]['instruction']!r} but the seed gives {own.instruction!r}" in lines[0])
    assert "instructions 'paraphrase-heldout' but the seed gives None" in lines[1]
    assert "colour_swap ['orange', 'apple'] but the seed gives None" in lines[2]
    assert summary["checks"]["layouts"] == {"checked": 3, "mismatched": 3}


@pytest.mark.slow
def test_provenance_shifted_against_the_frames_is_caught_without_a_replay(recorded, tmp_path, capsys):
    """Episodes 1 and 2 carry each other's provenance (the bookkeeping slip of a merge), their tasks following it
    as they would where the two had the same instruction: every layout is its seed's, so only the frames tell;
    each episode's first state is compared with its seed's start, for every episode, without a simulator."""
    copy = tmp_path / "shifted"
    shutil.copytree(recorded, copy)
    path, prov = _provenance(copy)
    columns = [c for c in prov.columns if c not in ("episode_index", "num_frames")]
    prov.loc[[1, 2], columns] = prov.loc[[2, 1], columns].to_numpy()
    prov.to_parquet(path, index=False)
    _retask(copy, {1: prov.loc[1, "instruction"], 2: prov.loc[2, "instruction"]})
    rc, summary, lines = check(copy, tmp_path, capsys, "--replay", "0")
    s1, s2 = int(prov.loc[1, "seed"]), int(prov.loc[2, "seed"])
    assert rc == 1 and len(lines) == 2 and summary["checks"]["start"]["differing"] == 2
    assert lines[0].startswith(f"start: episode 1 (seed {s1}): its first state's arm joints differ from the seed's "
                               "start by up to ")
    assert lines[0].endswith(f"its frames were not played from its seed (they start as seed {s2} does)")
    assert lines[1].startswith(f"start: episode 2 (seed {s2}): ") and lines[1].endswith(f"as seed {s1} does)")


@pytest.mark.slow
def test_replay_tolerates_the_drift_of_a_reused_scene_but_not_altered_actions(recorded, tmp_path):
    """An episode that does not promise a bit-exact replay (recorded with --no-rebuild-scenes, or before
    recordings said) may drift by millimetres, not by what an altered action does."""
    copy = tmp_path / "reused"
    shutil.copytree(recorded, copy)
    path, prov = _provenance(copy)
    prov["replayable"] = False
    prov.to_parquet(path, index=False)
    checker = Checker(CheckDatasetConfig(copy, replay=2))
    checker.replay()
    assert checker.violations == [] and [e["episode_index"] for e in checker.summary["replay"]["episodes"]] == [0, 2]
    data_path = sorted((copy / "data").glob("*/*.parquet"))[0]
    data = pd.read_parquet(data_path)
    row = data.index[(data["episode_index"] == 2) & (data["frame_index"] == 10)][0]
    data.at[row, "action"] = -data.at[row, "action"]  # one action reversed: the arm moves the other way
    data.to_parquet(data_path, index=False)
    checker = Checker(CheckDatasetConfig(copy, replay=2))
    checker.replay()
    assert len(checker.violations) == 1 and checker.violations[0].startswith("replay: episode 2 ")
    assert "more than a reused scene drifts" in checker.violations[0]
    # Episodes simulated by GPU PhysX are not replayed on the CPU: they would drift by design.
    prov["sim_backend"] = "physx_cuda"
    prov.to_parquet(path, index=False)
    checker = Checker(CheckDatasetConfig(copy, replay=2))
    checker.replay()
    assert checker.violations == [] and checker.summary["replay"]["not_replayed_gpu"] == 2


@pytest.mark.slow
def test_balance_and_coverage_flag_what_a_condition_should_produce(recorded, tmp_path):
    checker = Checker(CheckDatasetConfig(recorded, min_expected=0.1))
    checker.coverage()
    # Three episodes cannot show every pair pairings_id/2 produces; with a low enough bar the gaps are reported.
    assert checker.violations and all(v.startswith("coverage: ") and "never in region" in v
                                      for v in checker.violations)
    assert checker.summary["coverage"]["pairs_missing"] == len(checker.violations)
    checker = Checker(CheckDatasetConfig(recorded))
    checker.prov = pd.DataFrame({"target": ["apple"] * 20 + ["mug"] * 5})
    checker.balance()
    assert len(checker.violations) == 1 and checker.violations[0].startswith(
        "balance: instructions per object {'apple': 20, 'orange': 0, 'rubiks_cube': 0, 'mug': 5")


def test_bad_input_is_one_line(tmp_path, capsys):
    assert main(["check-dataset", str(tmp_path / "nope")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "ds" / "meta").mkdir(parents=True)
    (tmp_path / "ds" / "meta" / "info.json").write_text(json.dumps({"codebase_version": "v3.0", "features": {}}))
    assert main(["check-dataset", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err
    assert "is not a vla-ladder recording" in err and len(err.strip().splitlines()) == 1
    assert main(["check-dataset", str(tmp_path / "ds"), "--balance-alpha", "2"]) == 2
    assert "--balance-alpha must be in (0, 1)" in capsys.readouterr().err
    assert main(["check-dataset", str(tmp_path / "ds"), "--replay", "-1"]) == 2
    assert "--replay must be >= 0" in capsys.readouterr().err
