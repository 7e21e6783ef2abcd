"""`vla-ladder study`: the micro preset end to end (record -> train -> evaluate -> report), kills and resumes,
and configs refused before any work."""

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict, fields, replace
from pathlib import Path

import pytest

from vla_ladder import files
from vla_ladder.cli import main
from vla_ladder.experiments.study_config import StudyConfig, presets
from vla_ladder.experiments.units import mark_done
from vla_ladder.machine import cores

ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "MS_SKIP_ASSET_DOWNLOAD_PROMPT": "1",
       "WANDB_MODE": "disabled"}


def _micro(**changes) -> dict:
    from importlib import resources
    data = json.loads(resources.files("vla_ladder.configs.study").joinpath("micro.json").read_text())
    for path, value in changes.items():
        *parents, leaf = path.split(".")
        node = data
        for p in parents:
            node = node[int(p)] if p.isdigit() else node[p]
        node[leaf] = value
    return data


def test_presets_load_and_bad_configs_name_the_field(tmp_path, capsys):
    assert {"micro", "cpu-mini", "gpu-session", "gpu-scratch", "paper"} <= set(presets())
    for name in presets():
        StudyConfig.load(name)
    bad = {
        "unknown field 'epochs'": _micro(epochs=3),
        "policies[0]: unknown field 'stepz'": {**_micro(), "policies": [{"name": "x", "type": "act", "stepz": 3}]},
        "policies[0]: type: unknown policy type 'transformer'": _micro(**{"policies.0.type": "transformer"}),
        "unknown regime 'tiny_jitter'": _micro(**{"datasets.0.condition": "tiny_jitter/canonical/2"}),
        "horizons: no horizon in [8] fits a chunk size in [4]": _micro(**{"grid.horizons": [8]}),
        "reference_policies: unknown 'oracle'": _micro(**{"evaluation.reference_policies": ["oracle"]}),
        "the evaluation and probe seeds (0-": _micro(**{"datasets.0.first_seed": 1}),
        # A name is a folder under --out: it cannot climb out of it.
        "name '../../etc': use letters": _micro(**{"datasets.0.name": "../../etc"}),
        "name '': use letters": _micro(**{"policies.0.name": ""}),
        "lerobot_args: --output_dir is the study's to set": _micro(**{"policies.0.lerobot_args": [
            "--output_dir=/tmp/elsewhere"]}),
        "num_workers must be >= 0": _micro(num_workers=-4),
        # 0 fell back to the VLM's size, and a size without a vlm was ignored
        "image_size must be a positive integer, for a policy with a vlm": _micro(**{"policies.0.image_size": 0}),
        # Validation starts below the dataset but runs into it; probes reach into the dataset's seeds.
        "the validation (grid.select_first_seed) seeds (999990-": _micro(**{"grid.select_first_seed": 999_990,
                                                                          "grid.select_episodes": 20}),
        # Seeds past numpy's were refused by the validation's eval, after recording and training.
        "the validation (grid.select_first_seed) seeds (4294967295-4294967296) must lie in 0..2**32-1": _micro(
            **{"grid.select_first_seed": 2**32 - 1, "grid.select_episodes": 2}),
        "overlap the datasets[": _micro(**{"evaluation.probes": ["instruction-swap"],
                                          "evaluation.probe_episodes": 5000, "datasets.0.first_seed": 1000}),
        "policies[x].datasets: unknown dataset 'fr'": {**_micro(), "policies": [
            {"name": "x", "type": "act", "steps": 1, "datasets": ["fr"]}]},
        # data/sj-blind held both the recording of sj-blind and the blind copy of sj, which replaced it: the models
        # of sj-blind trained on sj's demonstrations without their instructions.
        "datasets[sj-blind]: name taken by the instruction-blind copy of sj": {**_micro(), "datasets": [
            *_micro()["datasets"], {**_micro()["datasets"][0], "name": "sj-blind", "first_seed": 2_000_000}],
            "policies": [*_micro()["policies"], {**_micro()["policies"][0], "name": "blind", "blind": True}]},
        # JSON of another type: a string seed ended in a TypeError naming no field, a string for a list was read
        # letter by letter ("unknown regime 'a'"), a boolean counted as a step count.
        'datasets[0].first_seed: expected an integer, got "5"': _micro(**{"datasets.0.first_seed": "5"}),
        'evaluation.regimes: expected a list of strings, got "all"': _micro(**{"evaluation.regimes": "all"}),
        'evaluation.num_objects[1]: expected an integer, got "2"': _micro(**{"evaluation.num_objects": [1, "2"]}),
        "policies[0].steps: expected an integer, got true": _micro(**{"policies.0.steps": True}),
        "policies[0].train_seed: expected an integer or null, got \"7\"": _micro(**{"policies.0.train_seed": "7"}),
        "policies[0]: train_seed must be >= 0 and < 2**32": _micro(**{"policies.0.train_seed": 2**32}),
        # A value twice trained the same model twice under one unit id, or showed a reference twice.
        "batch_sizes: 4 given twice": _micro(**{"grid.batch_sizes": [4, 4]}),
        "reference_policies: nearest given twice": _micro(**{"evaluation.reference_policies": ["nearest"] * 2}),
        # Diffusion executes at most chunk - n_obs_steps + 1 actions of a chunk: every model would be trained and no
        # horizon of the grid could evaluate it.
        "policies[D]: grid.horizons: no horizon in [8] fits a chunk size in [8] (diffusion executes at most chunk - "
        "n_obs_steps + 1 actions of a chunk: 7 of 8)": {**_micro(**{"grid.chunk_sizes": [8], "grid.horizons": [8]}),
                                                       "policies": [{"name": "D", "type": "diffusion", "steps": 1}]},
        # LeRobot refuses a diffusion horizon off its U-Net's down-sampling (micro's chunk of 4): at the train unit.
        "policies[D]: grid.chunk_sizes 4: diffusion's chunk (horizon) must be a multiple of 8": {
            **_micro(), "policies": [{"name": "D", "type": "diffusion", "steps": 1}]},
        # TD-MPC was trained with n_action_steps = the chunk, which LeRobot refuses; VQ-BeT has no n_action_steps to
        # evaluate each horizon with.
        "policies[0]: type: tdmpc's LeRobot config has no chunk_size field to set, so the chunk sizes and execution "
        "horizons cannot be swept (train it alone with `vla-ladder train`); allowed: act, diffusion,": {
            **_micro(), "policies": [{"name": "T", "type": "tdmpc", "steps": 1}]},
        "policies[0]: type: vqbet's LeRobot config has no chunk_size field and no n_action_steps field": {
            **_micro(), "policies": [{"name": "V", "type": "vqbet", "steps": 1}]},
        # Flags `vla-ladder train` sets itself (diffusion's chunk is --policy.horizon): its train units refused them.
        **{f"policies[0]: lerobot_args: {flag} is set by `vla-ladder train`, which trains the study's models and "
           "refuses it": {**_micro(**{"grid.chunk_sizes": [8]}), "policies": [
               {"name": "D", "type": "diffusion", "steps": 1, "lerobot_args": [f"{flag}=8"]}]}
           for flag in ("--policy.horizon", "--save_freq")},
        # train_seed null is train's 1000: the same models trained twice, reported as replicates that agree.
        "policies[SmolVLA-tiny] and policies[again] would train the same models on datasets[sj]: alike but for the "
        "name, with train_seed 1000 (null is `vla-ladder train`'s)": {**_micro(), "policies": [
            _micro()["policies"][0], {**_micro()["policies"][0], "name": "again", "train_seed": 1000}]},
        # Names are joined with '-' in unit ids and directories: both models were models/A-sj-x-b4c4, eval/A-sj-x.
        "policies[A-sj] on datasets[x] and policies[A] on datasets[sj-x] would share the unit ids and directories "
        "named A-sj-x": {**_micro(), "datasets": [{**_micro()["datasets"][0], "name": n} for n in ("x", "sj-x")],
                         "policies": [{"name": "A-sj", "type": "act", "steps": 1, "datasets": ["x"]},
                                      {"name": "A", "type": "act", "steps": 1, "datasets": ["sj-x"]}]},
        "policies[reference-nearest] on datasets[sj]: its evaluation eval/reference-nearest-sj would be read as one "
        "of the reference policy nearest's": {**_micro(**{"evaluation.reference_policies": ["nearest"]}),
                                              "policies": [{"name": "reference-nearest", "type": "act", "steps": 1}]},
    }
    for message, data in bad.items():
        path = tmp_path / "study.json"
        path.write_text(json.dumps(data))
        assert main(["study", str(path), "--out", str(tmp_path / "out")]) == 2, message
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
        assert not (tmp_path / "out").exists()
    assert main(["study", "nano", "--out", str(tmp_path / "out")]) == 2
    assert "allowed: " in capsys.readouterr().err
    for text in (b"{not json", b"\xff\xfe{}"):
        (tmp_path / "broken.json").write_bytes(text)
        assert main(["study", str(tmp_path / "broken.json"), "--out", str(tmp_path / "out")]) == 2
        assert f"{tmp_path / 'broken.json'}: not a JSON study config" in capsys.readouterr().err
    assert main(["study", "micro", "--out", str(tmp_path / "out"), "--num-envs", str(cores() + 1)]) == 2
    assert "--num-envs must be from 1 to the" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    assert main(["study", "micro", "--out", str(tmp_path / "out"), "--report-only"]) == 2
    assert "--report-only: " in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_experts_and_pretrained_checkpoints_are_read_before_the_first_unit(tmp_path, capsys):
    """A missing PPO expert was found by the record unit, a missing or wrong pretrained checkpoint by the first
    train unit, after the recording: each a traceback in a unit's log. Now one line before anything is written;
    a source that a done unit no longer needs is not read (a resumed study whose expert has moved goes on)."""
    from lerobot.policies.act.configuration_act import ACTConfig

    from vla_ladder.experiments.study import Study, StudyCommand

    ACTConfig().save_pretrained(tmp_path / "act")
    out = tmp_path / "out"
    cases = {
        "datasets[sj].expert: ": _micro(**{"datasets.0.expert": f"ppo:{tmp_path / 'moved.pt'}"}),
        f"policies[SmolVLA-tiny].pretrained: cannot load the pretrained config '{tmp_path / 'nowhere'}'": _micro(
            **{"policies.0.pretrained": str(tmp_path / "nowhere")}),
        f"policies[SmolVLA-tiny].pretrained: --pretrained '{tmp_path / 'act'}' is a 'act' checkpoint, not 'smolvla'":
            _micro(**{"policies.0.pretrained": str(tmp_path / "act")}),
    }
    for message, data in cases.items():
        path = tmp_path / "study.json"
        path.write_text(json.dumps(data))
        assert main(["study", str(path), "--out", str(out)]) == 2, message
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert not out.exists()
    # Done units need no source: the record and train units marked done, the study reads neither.
    path = tmp_path / "study.json"
    path.write_text(json.dumps(_micro(**{"datasets.0.expert": f"ppo:{tmp_path / 'moved.pt'}",
                                         "policies.0.pretrained": str(tmp_path / "nowhere")})))
    study = Study(StudyCommand(config=str(path), out=out))
    for unit in study.record_units():
        mark_done(out, unit, {}, 1.0)
    with pytest.raises(ValueError, match=r"^policies\[SmolVLA-tiny\]\.pretrained"):
        study.check_sources()  # the expert is not read; the checkpoint that a train unit will load is
    (train,) = study.train_units()
    mark_done(out, replace(train, config={**train.config, "steps": train.config["steps"] + 1}), {}, 1.0)
    with pytest.raises(ValueError, match=r"^policies\[SmolVLA-tiny\]\.pretrained"):
        study.check_sources()  # done with other steps: the unit trains again and loads the checkpoint
    mark_done(out, train, {}, 1.0)
    study.check_sources()


def test_a_moved_study_is_refused_before_any_unit_runs_again(tmp_path, capsys):
    """Unit configs hold absolute paths: a study directory moved elsewhere would redo every unit."""
    from vla_ladder.experiments.study import Study, StudyCommand

    old, new = tmp_path / "old", tmp_path / "new"
    study = Study(StudyCommand("micro", out=old))
    unit = study.record_units()[0]
    mark_done(old, unit, {"saved": 3}, 1.0)
    files.write_json(old / "study.json", asdict(study.cfg))
    StudyCommand("micro", out=old)  # in place: resumes
    shutil.copytree(old, new)
    assert main(["study", "micro", "--out", str(new)]) == 2
    err = capsys.readouterr().err
    assert f"{new} was moved: its units ran in {old}" in err and "Traceback" not in err


def test_a_finished_study_resumes_with_probes_added_and_refuses_any_other_change(tmp_path):
    """Adding a grounding probe to a study that ran runs that probe only (its other units are done); dropping one,
    or changing anything else, is another study."""
    from vla_ladder.experiments.study import StudyCommand, StudyConfig

    base = StudyConfig.load("cpu-mini")
    files.write_json(tmp_path / "s" / "study.json", asdict(base))

    def config(**evaluation) -> str:
        path = tmp_path / f"c{len(list(tmp_path.glob('c*.json')))}.json"
        data = asdict(base)
        data["evaluation"].update(evaluation)
        path.write_text(json.dumps(data))
        return str(path)

    probes = list(base.evaluation.probes)
    StudyCommand(config(probes=[*probes, "distractor-removal"]), out=tmp_path / "s")  # resumes
    StudyCommand(config(probes=probes[::-1]), out=tmp_path / "s")  # the same probes in another order
    for changed, field in ((dict(probes=probes[1:]), "evaluation.probes"),
                           (dict(probes=[*probes, "paraphrase"], probe_episodes=11), "evaluation.probe_episodes"),
                           (dict(episodes=51), "evaluation.episodes")):
        with pytest.raises(ValueError, match=f"holds another study .*its {field}"):
            StudyCommand(config(**changed), out=tmp_path / "s")
    # A study.json written before a field existed (policies' train_seed, 2026-11-28) reads it as its default, as
    # the committed studies' do: they resume and report again.
    saved = asdict(base)
    for policy in saved["policies"]:
        del policy["train_seed"]
    files.write_json(tmp_path / "s" / "study.json", saved)
    StudyCommand(config(), out=tmp_path / "s")
    replicate = asdict(base)
    replicate["policies"][1]["train_seed"] = 7
    (tmp_path / "r.json").write_text(json.dumps(replicate))
    with pytest.raises(ValueError, match=r"its policies\[1\].train_seed differs"):
        StudyCommand(str(tmp_path / "r.json"), out=tmp_path / "s")


def test_a_replicate_trains_with_its_own_seed_and_the_others_as_before(tmp_path):
    """train_seed reaches `train`'s --train-seed (lerobot-train's --seed); a policy without one trains with its default
    under a unit config without the key, so that units marked done before the field existed stay done."""
    from vla_ladder.experiments.study import Study, StudyCommand
    from vla_ladder.training.train import TrainConfig

    replicate = {**_micro()["policies"][0], "name": "SmolVLA-tiny-s2", "train_seed": 2}
    path = tmp_path / "study.json"
    path.write_text(json.dumps({**_micro(), "policies": [_micro()["policies"][0], replicate]}))
    study = Study(StudyCommand(config=str(path), out=tmp_path / "s"))
    first, second = study.train_units()
    assert "train_seed" not in first.config and second.config["train_seed"] == 2
    assert first.id != second.id and first.config["out"] != second.config["out"]
    assert set(second.config) <= {f.name for f in fields(TrainConfig)}  # train_unit: TrainConfig(**config)


def test_replicates_are_grouped_by_recipe_and_their_episodes_paired():
    """Policies alike but for name and train_seed are one group; per dataset and condition the table gives each
    one's successes and, pair by pair, the episodes whose success agrees (seeds pair up; rows are not in order)."""
    from types import SimpleNamespace

    import pandas as pd

    from vla_ladder.experiments.study_results import replicate_cells, replicate_groups
    from vla_ladder.report.study import replicates_markdown

    base = _micro()["policies"][0]
    policies = [base, {**base, "name": "s2", "train_seed": 2}, {**base, "name": "other", "steps": 7},
                {**base, "name": "s3", "train_seed": 3}]
    groups = replicate_groups(policies)
    assert groups == {base["name"]: [base["name"], "s2", "s3"]}

    def run(success: list[int]):
        rows = [dict(regime=r, split="canonical", num_objects=5, seed=seed, success=bool(s))
                for r, outcomes in (("small_jitter", success[:4]), ("full_random", success[4:]))
                for seed, s in enumerate(outcomes)]
        return SimpleNamespace(episodes=pd.DataFrame(rows[::-1])), ("sj", "small_jitter/canonical/5")

    runs = {f"{base['name']} (sj)": run([1, 1, 0, 0, 1, 0, 0, 0]), "s2 (sj)": run([1, 0, 1, 0, 0, 0, 0, 0]),
            "s3 (sj)": run([1, 1, 0, 0, 0, 0, 0, 1]), "other (sj)": run([0] * 8)}
    cells = replicate_cells(groups, runs)
    assert [(c["eval_condition"], c["n"]) for c in cells] == [("full_random/canonical/5", 4),
                                                              ("small_jitter/canonical/5", 4)]
    sj = cells[1]
    assert sj["success_count"] == {base["name"]: 2, "s2": 2, "s3": 2}
    assert list(sj["episodes_alike"].values()) == [2, 4, 2]  # seeds 1 and 2 differ between the first and s2
    assert "| 50 / 50 / 50 | 0 | 2 of 4, 4 of 4, 2 of 4 |" in replicates_markdown(cells)


def test_diffusion_trains_and_is_selected_only_on_the_horizons_it_executes(tmp_path):
    """Diffusion's chunk starts n_obs_steps - 1 steps back, so it executes at most chunk - n_obs_steps + 1 of its
    actions: the study trained it with n_action_steps = chunk and selected among horizons up to the chunk, which
    every evaluation of its checkpoints refused, after the training. (Planning needs no diffusers.)"""
    from vla_ladder.experiments.study import Study, StudyCommand

    path = tmp_path / "study.json"
    data = _micro(**{"grid.chunk_sizes": [8, 16], "grid.horizons": [4, 8, 16], "grid.select_episodes": 3})
    path.write_text(json.dumps({**data, "policies": [*data["policies"], {"name": "D", "type": "diffusion",
                                                                         "steps": 1},
                                                     {"name": "M", "type": "multi_task_dit", "steps": 1}]}))
    study = Study(StudyCommand(str(path), out=tmp_path / "s"))
    # (multi_task_dit's chunk is a horizon from n_obs_steps - 1 back too: it was left at LeRobot's 32, unswept)
    assert {u.id: u.config["n_action_steps"] for u in study.train_units()} == {
        "train-SmolVLA-tiny-sj-b4c8": 8, "train-SmolVLA-tiny-sj-b4c16": 16,
        "train-D-sj-b4c8": 7, "train-D-sj-b4c16": 15, "train-M-sj-b4c8": 7, "train-M-sj-b4c16": 15}
    assert [u.id for u in study.select_units()] == [
        *(f"select-SmolVLA-tiny-sj-{m}" for m in ("b4c8-h4", "b4c8-h8", "b4c16-h4", "b4c16-h8", "b4c16-h16")),
        *(f"select-{p}-sj-{m}" for p in "DM" for m in ("b4c8-h4", "b4c16-h4", "b4c16-h8"))]
    chosen = study.best({})[("D", "sj")]
    assert [(r["chunk_size"], r["horizon"]) for r in chosen["candidates"]] == [(8, 4), (16, 4), (16, 8)]



def test_a_policy_type_whose_packages_are_missing_is_refused_before_the_recording(tmp_path):
    """A diffusion policy without diffusers (not installed here) was planned, its datasets recorded, and refused by
    LeRobot at its train unit. The study looks for every untrained type's packages with its other sources, in one
    line before any unit runs; on Ray the trainers' machines, not this one, must have them."""
    from vla_ladder.experiments.study import Study, StudyCommand

    pytest.importorskip("lerobot")
    if importlib.util.find_spec("diffusers") is not None:
        pytest.skip("diffusers is installed here")
    path = tmp_path / "study.json"
    data = _micro(**{"grid.chunk_sizes": [8], "grid.horizons": [4]})
    path.write_text(json.dumps({**data, "policies": [*data["policies"], {"name": "D", "type": "diffusion",
                                                                         "steps": 1}]}))
    with pytest.raises(ValueError, match=r"^policies\[D\]: --policy-type diffusion needs diffusers, which is not "
                                         r"installed here \(pip install 'lerobot\[diffusion\]'\)$"):
        Study(StudyCommand(str(path), out=tmp_path / "s")).run()
    assert not (tmp_path / "s").exists()
    Study(StudyCommand(str(path), out=tmp_path / "r", ray=True)).check_sources()  # Ray: the trainers' packages

def test_learning_curves_are_read_from_their_own_model_only(tmp_path):
    """curves/MODEL-STEP: the curve of model A-sj-b4c4 also took the points of A-sj-b4c4-x-sj-b4c4, whose name
    begins with its own and '-'."""
    from vla_ladder.experiments.study import Study, StudyCommand
    from vla_ladder.experiments.study_results import curve_points

    base = _micro(**{"evaluation.curve_episodes": 2})
    policy = base["policies"][0]
    path = tmp_path / "study.json"
    path.write_text(json.dumps({**base, "policies": [{**policy, "name": "A"},
                                                     {**policy, "name": "A-sj-b4c4-x", "train_seed": 7}]}))
    study = Study(StudyCommand(str(path), out=tmp_path / "s"))
    chosen = study.best({})
    for model, step, success in (("A-sj-b4c4", 4, 0.5), ("A-sj-b4c4-x-sj-b4c4", 4, 1.0),
                                 ("A-sj-b4c4-x-sj-b4c4", 8, 0.0)):
        files.write_json(tmp_path / "s" / "curves" / f"{model}-{step}" / "summary.json", {"conditions": {
            "small_jitter/canonical/2": {"n": 2, "success": success, "grasp_any": 1.0, "reach": 1.0, "ci95": {}}}})
    curves = curve_points(study, chosen)
    assert {k: [(p["step"], p["success"]) for p in v] for k, v in curves.items()} == {
        "A on sj": [(4, 0.5)], "A-sj-b4c4-x on sj": [(4, 1.0), (8, 0.0)]}


def test_a_policy_trains_and_is_evaluated_only_on_its_datasets(tmp_path):
    """cpu-mini's blind control is trained on sj only: no unit of it on pid or fr, every other model planned."""
    from vla_ladder.experiments.study import Study, StudyCommand

    study = Study(StudyCommand("cpu-mini", out=tmp_path / "s"))
    models = [(p.name, d.name) for p, d, _ in study.models()]
    assert models == [("SmolVLA-scratch", "sj"), ("SmolVLA-scratch", "pid"), ("SmolVLA-scratch", "fr"),
                      ("SmolVLA-scratch-blind", "sj")]
    trains = {u.id: u for u in study.train_units()}
    assert sorted(trains) == sorted(f"train-{p}-{d}-b16c16" for p, d in models)
    assert trains["train-SmolVLA-scratch-blind-sj-b16c16"].config["dataset"] == str(tmp_path / "s/data/sj-blind")
    # device auto stays auto in the plan (each training unit resolves it where it runs): the units a GPU machine
    # marked done are the same units on the CPU machine that finishes the study (it planned them with "cuda").
    study.cfg.device = "auto"
    assert {u.config["device"] for u in study.train_units()} == {"auto"}
    assert study.select_units() == []  # one horizon, chosen while tuning: nothing to select
    chosen = study.best({})
    assert {k: v["horizon"] for k, v in chosen.items()} == {m: 4 for m in models}
    assert all(v["success"] is None and v["candidates"][0]["reach"] is None for v in chosen.values())  # unmeasured
    evals = {u.id: u.config for u in study.eval_units(chosen)}
    assert evals["eval-SmolVLA-scratch-blind-sj"]["policy"].endswith("?n_action_steps=4&instruction=grasp the object")
    assert evals["eval-SmolVLA-scratch-pid"]["grid"]["splits"] == ["pairings_id", "pairings_ood"]
    # Blind models are not probed: they cannot follow an instruction.
    probes = ("instruction-swap", "position-swap", "absent-object", "instruction-switch")
    assert [u.id for u in study.probe_units(chosen)] == [f"probe-SmolVLA-scratch-{d}-{probe}"
                                                         for d in ("sj", "pid", "fr") for probe in probes]
    assert {(u.config["workers"], u.config.get("num_envs", 1)) for u in study.probe_units(chosen)} == {(0, 1)}
    # --num-envs N: every evaluation and probe plays with one copy of the policy on N envs.
    batched = Study(StudyCommand("cpu-mini", out=tmp_path / "b", workers=2, num_envs=2))
    units = [*batched.eval_units(chosen), *batched.probe_units(chosen)]
    assert units and {(u.config["workers"], u.config["num_envs"]) for u in units} == {(1, 2)}
    batched.cfg.evaluation.probes = ["appearance-swap"]  # paints each scene: one env per copy of the policy
    assert {u.config["workers"] for u in batched.probe_units(chosen)} == {2}
    assert all("num_envs" not in u.config for u in batched.probe_units(chosen))


def test_the_gpu_studies_put_every_instruction_reading_model_through_every_probe(tmp_path):
    from vla_ladder.experiments.probes import PROBES
    from vla_ladder.experiments.study import Study, StudyCommand

    for preset in ("gpu-scratch", "paper"):
        study = Study(StudyCommand(preset, out=tmp_path / preset))
        readers = [(p.name, d.name) for p, d, _ in study.models() if not p.blind]
        units = study.probe_units(study.best({}))
        assert [u.id for u in units] == [f"probe-{p}-{d}-{name}" for p, d in readers for name in PROBES], preset
        assert {u.config["episodes"] for u in units} == {50}


def test_selection_plays_validation_seeds_and_picks_by_success_then_grasp_then_reach(tmp_path):
    """A 2x2 grid with horizons {2, 4}: every (model, horizon) is played on the validation seeds of the training
    condition, and the choice ranks success, then grasp-any, then reach (first in grid order on a full tie)."""
    from vla_ladder.experiments.study import Study, StudyCommand

    path = tmp_path / "study.json"
    path.write_text(json.dumps(_micro(**{"grid.batch_sizes": [4, 8], "grid.chunk_sizes": [2, 4],
                                         "grid.horizons": [2, 4], "grid.select_episodes": 3})))
    study = Study(StudyCommand(str(path), out=tmp_path / "s"))
    units = {u.id: u for u in study.select_units()}
    # Horizon 4 does not fit chunk 2: three (chunk, horizon) pairs per batch size.
    assert sorted(units) == sorted(f"select-SmolVLA-tiny-sj-b{b}c{c}-h{h}" for b in (4, 8) for c in (2, 4)
                                   for h in (2, 4) if h <= c)
    for u in units.values():
        assert (u.config["first_seed"], u.config["episodes"]) == (500_000, 3)
        assert u.config["grid"] == {"regimes": ["small_jitter"], "splits": ["canonical"], "num_objects": [2]}

    def played(success, grasp, reach):
        return {"conditions": {"small_jitter/canonical/2": {"success": success, "grasp_any": grasp, "reach": reach}}}
    results = {"select-SmolVLA-tiny-sj-b4c2-h2": played(1 / 3, 1.0, 1.0),
               "select-SmolVLA-tiny-sj-b4c4-h4": played(2 / 3, 2 / 3, 2 / 3),
               "select-SmolVLA-tiny-sj-b8c4-h2": played(2 / 3, 1.0, 1 / 3),
               "select-SmolVLA-tiny-sj-b8c4-h4": played(2 / 3, 1.0, 2 / 3)}
    chosen = study.best(results)[("SmolVLA-tiny", "sj")]
    assert (chosen["model"], chosen["horizon"]) == ("SmolVLA-tiny-sj-b8c4", 4)
    assert len(chosen["candidates"]) == len(units)
    # A full tie keeps grid order: the first model and horizon.
    tie = study.best({k: played(0.5, 0.5, 0.5) for k in units})[("SmolVLA-tiny", "sj")]
    assert (tie["model"], tie["horizon"]) == ("SmolVLA-tiny-sj-b4c2", 2)
    evals = {u.id: u.config for u in study.eval_units(study.best(results))}
    assert evals["eval-SmolVLA-tiny-sj"]["policy"].endswith("SmolVLA-tiny-sj-b8c4/checkpoints/last/pretrained_model"
                                                            "?n_action_steps=4")


def _done_markers(root: Path) -> dict[str, float]:
    return {p.stem: p.stat().st_mtime_ns for p in (root / "units").glob("*.json")}


def _wait(predicate, timeout: float, proc) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert proc.poll() is None, f"the study exited early ({proc.returncode})"
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.5)


def _kill(proc) -> None:
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def test_a_study_summary_with_undefined_rates_is_strict_json_and_its_tables_read_as_before(tmp_path):
    """A rate over no episodes was NaN in summary.json's cells and curves, which strict JSON parsers refuse: it is
    null there now, and --report-only's tables and curves, which read that file back, show it as they showed NaN."""
    from test_files import strict_json

    from vla_ladder.report import study as present

    nan = float("nan")
    rates = {"success": nan, "grasp_any": 0.5, "reach": nan}
    ci = {"success": [nan, nan], "grasp_any": [0.2, 0.8], "reach": [nan, nan]}
    cells = [{"policy": p, "train_dataset": d, "train_condition": t, "eval_condition": e, "n": 0, **rates, "ci95": ci,
              "run": "eval/x"}
             for p, d, t, e in (("SmolVLA", "sj", "small_jitter/canonical/5", "small_jitter/canonical/5"),
                                ("SmolVLA", "sj", "small_jitter/canonical/5", "small_jitter/pairings_ood/5"),
                                ("nearest", None, None, "small_jitter/canonical/5"))]
    curves = {"SmolVLA on sj": [{"step": 10, "n": 0, **rates, "ci95": ci}, {"step": 20, "n": 2, **rates, "ci95": ci}]}
    files.write_json(tmp_path / "summary.json", {"cells": cells, "curves": curves})
    saved = strict_json((tmp_path / "summary.json").read_text())
    assert saved["cells"][0]["success"] is None and saved["curves"]["SmolVLA on sj"][0]["ci95"]["reach"] == [None, None]
    paper = {"ladder": {"SmolVLA": {"small_jitter/canonical/5": {"n": 100, "success": 0.5, "grasp_any": 0.6,
                                                                 "reach": 0.7}}}}
    for table in (present.matrix_markdown, present.matrix_latex, present.matrix_html, present.pairings_html,
                  lambda c: present.paper_comparison_markdown(c, paper)):
        assert table(saved["cells"]) == table(cells)
    assert "– / 50 / –" in present.matrix_markdown(saved["cells"])
    assert present.plot_curves(saved["curves"], tmp_path / "curves.png").is_file()


@pytest.mark.slow
def test_micro_study_survives_kills_mid_record_and_mid_train_and_reports_learned_rows(tmp_path):
    out = tmp_path / "study"
    cmd = [sys.executable, "-m", "vla_ladder.cli", "study", "micro", "--out", str(out), "--workers", "1"]

    def start():
        return subprocess.Popen(cmd, env=ENV, start_new_session=True, stdout=subprocess.DEVNULL)

    # Killed while recording: after the recorder's first commit, before the record unit is done.
    proc = start()
    _wait(lambda: (out / "data" / "sj" / "meta" / "vla_ladder_recording.json").is_file(), 900, proc)
    _kill(proc)
    assert "record-sj" not in _done_markers(out)
    # Killed while training: the record unit is done, the training unit has started.
    proc = start()
    _wait(lambda: (out / "logs" / "train-SmolVLA-tiny-sj-b4c4.log").is_file(), 900, proc)
    time.sleep(3)
    _kill(proc)
    done = _done_markers(out)
    assert "record-sj" in done and "train-SmolVLA-tiny-sj-b4c4" not in done
    subprocess.run(cmd, env=ENV, check=True, stdout=subprocess.DEVNULL, timeout=1800)

    after = _done_markers(out)
    assert after["record-sj"] == done["record-sj"], "a finished unit ran again"
    assert set(after) == {"record-sj", "train-SmolVLA-tiny-sj-b4c4", "eval-SmolVLA-tiny-sj"}
    recorded = json.loads((out / "units" / "record-sj.json").read_text())["result"]
    assert recorded["saved"] == 3
    from vla_ladder.recordings import read_provenance
    seeds = read_provenance(out / "data" / "sj")["seed"]
    assert len(seeds) == 3 and seeds.is_unique

    summary = json.loads((out / "summary.json").read_text())
    learned = [c for c in summary["cells"] if c["policy"] == "SmolVLA-tiny"]
    assert {c["eval_condition"] for c in learned} == {"small_jitter/canonical/2", "full_random/canonical/2"}
    for c in learned:
        assert c["n"] == 2 and c["train_condition"] == "small_jitter/canonical/2"
        for m in ("success", "grasp_any", "reach"):
            assert 0 <= c[m] <= 1 and len(c["ci95"][m]) == 2 and c[f"{m}_count"] == round(c[m] * 2)
    matrix = (out / "tables" / "matrix.md").read_text()
    assert "| SmolVLA-tiny | sj (small_jitter/canonical/2) |" in matrix
    page = (out / "report.html").read_text()
    assert "Study: train regime x eval regime" in page and "SmolVLA-tiny" in page and "Grasp-any" in page
    # Its ladder's episodes against the named object's distance from its place in small jitter (no references here)
    curve = summary["displacement"]["sj"]
    assert curve["trained_in"] == "small_jitter/canonical/2" and list(curve["runs"]) == ["SmolVLA-tiny (sj)"]
    assert sum(b["n"] for b in curve["runs"]["SmolVLA-tiny (sj)"]["bins"]) == 4
    assert "Study: where the models trained on sj stop finding the object" in page
    assert (out / "logs" / "eval-SmolVLA-tiny-sj.log").stat().st_size > 0
    # A different study in the same directory is refused.
    other = tmp_path / "other.json"
    other.write_text(json.dumps(_micro(**{"evaluation.episodes": 3})))
    r = subprocess.run([*cmd[:4], str(other), "--out", str(out)], env=ENV, capture_output=True, text=True)
    assert r.returncode == 2 and "holds another study" in r.stderr
    # Reworded, the same study resumes: every unit is done, nothing runs again.
    reworded = tmp_path / "reworded.json"
    reworded.write_text(json.dumps(_micro(description="the micro study, described anew")))
    subprocess.run([*cmd[:4], str(reworded), "--out", str(out)], env=ENV, check=True, stdout=subprocess.DEVNULL,
                   timeout=600)
    assert _done_markers(out) == after

    # Copied without its datasets, models and units (as benchmarks/results/ keeps a study), --report-only writes
    # the summary and report again from the evaluations alone: the displacement curves come back, nothing runs.
    copy = tmp_path / "copied"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("data", "models", "units", "logs", "blind"))
    (copy / "report.html").unlink()
    assert not summary["replicates"]["cells"]  # one policy, one seed: a replicates table an earlier report left goes
    (copy / "tables" / "replicates.md").write_text("| stale |")
    trimmed = {k: v for k, v in summary.items() if k != "displacement"}
    files.write_json(copy / "summary.json", trimmed)
    subprocess.run([*cmd[:4], str(copy / "study.json"), "--out", str(copy), "--report-only"], env=ENV, check=True,
                   stdout=subprocess.DEVNULL, timeout=600)
    again = json.loads((copy / "summary.json").read_text())
    assert again["displacement"] == summary["displacement"] and again["cells"] == summary["cells"]
    assert "Study: where the models trained on sj stop finding the object" in (copy / "report.html").read_text()
    assert not (copy / "units").exists() and not (copy / "models").exists()
    assert not (copy / "tables" / "replicates.md").exists()
