"""Reference policies in the real simulator (through the evaluation runner) show the metric signatures
they exist for; the pairings experiment runs end to end on one of them."""

import json

import pytest
import torch

from vla_ladder.cli import main
from vla_ladder.conditions import ConditionGrid
from vla_ladder.evaluation.rundir import load_run
from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
from vla_ladder.policies import load_policy

EPISODES = 6


def evaluate(spec: str, regimes, split: str = "canonical", episodes: int = EPISODES) -> dict:
    cfg = EvalConfig(spec, grid=ConditionGrid(tuple(regimes), (split,)), episodes=episodes, first_seed=0)
    return run_evaluation(cfg, progress=False)["conditions"]


@pytest.mark.slow
def test_nearest_grasps_but_ignores_the_instruction():
    c = evaluate("nearest", ["full_random"])["full_random/canonical/5"]
    assert c["grasp_any"] >= 0.8
    assert c["success"] <= c["grasp_any"] - 0.4
    assert c["outcomes"]["wrong_object"] >= 2  # what it holds does not depend on what it was told


@pytest.mark.slow
def test_layout_prior_succeeds_under_small_jitter_not_full_random():
    conds = evaluate("layout-prior", ["small_jitter", "full_random"])
    small, full = conds["small_jitter/canonical/5"], conds["full_random/canonical/5"]
    assert small["success"] >= 0.6
    assert small["success"] > full["success"] + 0.4


@pytest.mark.slow
def test_pairings_experiment_layout_prior_fails_out_of_distribution(tmp_path, capsys):
    out = tmp_path / "pairings"
    assert main(["experiment", "pairings", "--policy", "label=prior,spec=layout-prior", "--episodes", "3",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| Pairings (OOD) | 0 [0, 56] |" in printed and str(out / "report.html") in printed
    ood = load_run(out / "runs" / "prior" / "pairings_ood-5obj")
    c = ood.summary["conditions"]["small_jitter/pairings_ood/5"]
    assert c["success"] == 0.0 and c["reach"] == 0.0
    assert "Pairings (OOD) & $0$" in (out / "table.tex").read_text()
    assert (out / "pairings.png").stat().st_size > 5000
    results = json.loads((out / "results.json").read_text())
    assert results["runs"][0]["label"] == "prior" and "small_jitter/pairings_ood/5" in results["results"]["prior"]
    page = (out / "report.html").read_text()
    assert "Compositional generalization" in page and "recorded no videos" in page


@pytest.mark.slow
def test_random_is_the_floor_and_reproducible():
    c = evaluate("random", ["small_jitter"], episodes=3)["small_jitter/canonical/5"]
    assert c["success"] == 0.0
    a, b = load_policy("random"), load_policy("random")
    a.reset([7, 8])
    b.reset([7, 8])
    assert torch.equal(a.act(None), b.act(None)) and a.act(None).shape == (2, 7)


def test_bad_specs_and_experiment_arguments(tmp_path, capsys):
    with pytest.raises(ValueError, match="takes no argument"):
        load_policy("nearest:foo")
    assert main(["experiment", "ladder", "--policy", "teleport", "--out", str(tmp_path)]) == 2
    assert "unknown policy" in capsys.readouterr().err
    assert main(["experiment", "ladder", "--policy", "nearest", "--num-envs", "4096", "--out", str(tmp_path)]) == 2
    assert "--num-envs must be at most the" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing ran, nothing written


@pytest.mark.parametrize("spec", ["nearest", "committed", "layout-prior"])
def test_reference_policies_act_on_the_device_of_the_observations(spec, make_env):
    """Under physx_cuda the observations are CUDA tensors; built on the CPU, these policies subtracted their sites
    from them (a device error at the first step) where the scripted expert moves itself. This machine has one
    device, so a policy built for `cpu:0` stands in for one built elsewhere: it must adopt the observations'."""
    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=5)
    policy = load_policy(spec, device="cpu:0")
    obs, _ = env.reset(seed=0)
    policy.reset([0])
    action = policy.act(obs, env.unwrapped.instructions)
    assert policy.device == obs["extra"]["tcp_pose"].device == action.device
    assert action.shape == (1, 7)
