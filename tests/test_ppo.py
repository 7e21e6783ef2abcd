"""PPO expert: the advantage and loss maths by hand, a real tiny CPU run that checkpoints, resumes and
acts through load_policy, and clean errors for bad input."""

import dataclasses
import json
import math
import os
import re

import pytest
import torch
from safetensors.torch import load_file

from vla_ladder.conditions import Condition, ConditionGrid
from vla_ladder.policies import load_policy
from vla_ladder.policies.ppo import Agent, load_agent, save_agent
from vla_ladder.ppo.config import TRAIN_SEED_MIN, Args
from vla_ladder.ppo.envs import TrainEnvs, slot_conditions, train_seeds
from vla_ladder.ppo.loss import compute_gae, ppo_loss
from vla_ladder.ppo.train import cli_config, noise_seed, summary_writer, train
from vla_ladder.task.layouts import sample_layout

TINY = dict(sim_backend="physx_cpu", num_envs=1, total_timesteps=100, eval_freq=1, eval_episodes=1,
            grid=ConditionGrid(("small_jitter",), num_objects=(5,)), target_kl=0.0, progress=False)


def test_gae_matches_hand_computation():
    # Transition 1 ends an episode: it bootstraps from V(final obs) = 4 and stops the trace.
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    next_values = torch.tensor([[1.0], [4.0], [2.0]])
    dones = torch.tensor([[0.0], [1.0], [0.0]])
    adv, ret = compute_gae(rewards, values, next_values, dones, gamma=0.5, gae_lambda=0.5)
    # deltas: 1 + .5*1 - .5 = 1;  2 + .5*4 - 1 = 3;  3 + .5*2 - 1.5 = 2.5
    # A2 = 2.5;  A1 = 3 (trace cut);  A0 = 1 + .25*3 = 1.75
    assert adv.flatten().tolist() == pytest.approx([1.75, 3.0, 2.5])
    assert ret.flatten().tolist() == pytest.approx([2.25, 4.0, 4.0])


def test_clipped_loss_matches_hand_computation():
    ratios = torch.tensor([1.5, 0.5, 1.1, 1.5])
    old = torch.zeros(4)
    new = ratios.log().requires_grad_()
    adv = torch.tensor([1.0, -1.0, 2.0, -1.0])
    loss, stats = ppo_loss(new, old, adv, newvalue=torch.tensor([1.0, 2.0, 0.0, 0.0]),
                           returns=torch.tensor([0.0, 4.0, 0.0, 0.0]), entropy=torch.tensor([1.0, 3.0, 0.0, 0.0]),
                           clip_coef=0.2, vf_coef=0.5, ent_coef=0.1, norm_adv=False)
    # pessimistic terms max(-A r, -A clip(r)): -1.2 (clipped), 0.8 (clipped), -2.2, 1.5 (unclipped)
    assert float(stats["pg_loss"]) == pytest.approx(-1.1 / 4)
    assert float(stats["v_loss"]) == pytest.approx(0.5 * (1 + 4) / 4)
    assert float(stats["entropy"]) == pytest.approx(1.0)
    assert float(stats["clipfrac"]) == pytest.approx(0.75)
    kl = sum((r - 1) - math.log(r) for r in ratios.tolist()) / 4
    assert float(stats["approx_kl"]) == pytest.approx(kl, rel=1e-5)
    assert loss.item() == pytest.approx(-1.1 / 4 - 0.1 * 1.0 + 0.5 * 0.625)
    loss.backward()
    # Clipped samples pass no gradient; the others pass -A r / n.
    assert new.grad.tolist() == pytest.approx([0.0, 0.0, -2.2 / 4, 1.5 / 4])


def test_mixture_slots_and_seeds():
    conds = [("small_jitter", "canonical", 5), ("full_random", "canonical", 1), ("large_jitter", "canonical", 3)]
    seen = [c for r in range(3) for c in slot_conditions(conds, 2, r)]
    assert all(seen.count(c) == 2 for c in conds)  # 6 episodes over 3 conditions: even
    seeds = train_seeds(1, 0, 1000)
    assert min(seeds) >= TRAIN_SEED_MIN and max(seeds) < 2**32
    assert seeds == train_seeds(1, 0, 1000) and seeds != train_seeds(1, 1, 1000)
    args = Args(out="x", grid=ConditionGrid(("small_jitter", "full_random"), ("canonical", "pairings_ood"), (5,)),
                sim_backend="physx_cpu", num_envs=1)
    assert args.conditions == [Condition("small_jitter", "canonical", 5), Condition("small_jitter", "pairings_ood", 5),
                               Condition("full_random", "canonical", 5)]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("ppo") / "run"
    state = train(Args(out=str(out), **TINY))
    assert state["global_step"] == 100 and state["iteration"] == 2
    return out


def _optimizer_steps(run) -> float:
    state = json.loads((run / "state.json").read_text())
    return load_file(run / state["checkpoint"] / "optimizer.safetensors")["state.0.step"].item()


@pytest.mark.slow
def test_tiny_cpu_run_writes_checkpoint_that_acts(run_dir, make_env):
    state = json.loads((run_dir / "state.json").read_text())
    assert state["checkpoint"] == "checkpoints/step_000000000100"
    for name in ("model.safetensors", "optimizer.safetensors", "state.json"):
        assert (run_dir / state["checkpoint"] / name).is_file()
    assert (run_dir / "checkpoints/best/model.safetensors").is_file()
    config = json.loads((run_dir / "config.json").read_text())
    assert config["obs_dim"] == 96 and config["act_dim"] == 7 and config["gamma"] == 0.8
    evals = json.loads((run_dir / "evals.json").read_text())
    assert [e["global_step"] for e in evals] == [50, 100]
    assert set(evals[-1]["all"]) >= {"n", "success", "grasp_any", "reach"}
    # By instructed object too: the targets the evaluation seeds give, their episodes and successes adding up.
    targets, total = evals[-1]["targets"], evals[-1]["all"]
    args = Args(out="x", **TINY)
    assert set(targets) == {sample_layout(c, args.eval_first_seed + j).target
                            for c in args.conditions for j in range(args.eval_episodes)}
    assert sum(t["n"] for t in targets.values()) == total["n"]
    assert sum(round(t["success"] * t["n"]) for t in targets.values()) == round(total["success"] * total["n"])
    assert list((run_dir / "tb").glob("events.out.tfevents.*"))

    policy = load_policy(f"ppo:{run_dir}", device="cpu")
    assert policy.describe()["global_step"] == 100
    env = make_env(obs_mode=policy.obs_mode, sim_backend="physx_cpu", num_objects=5)
    # Per-episode conditions (used for the training mixture) override the env's own.
    obs, _ = env.reset(seed=[TRAIN_SEED_MIN + 3], options={"conditions": [("full_random", "canonical", 2)]})
    assert env.unwrapped.layouts[0].condition.regime == "full_random" and int(env.unwrapped.present.sum()) == 2
    policy.reset([0])
    for _ in range(3):
        action = policy.act(obs, env.unwrapped.instructions)
        assert action.shape == (1, 7) and action.abs().max() <= 1
        obs, *_ = env.step(action)
    again = load_policy(f"ppo:{run_dir}/checkpoints/best", device="cpu")
    assert again.act(obs, env.unwrapped.instructions).shape == (1, 7)
    assert again.describe()["selected_on"] == {"first_seed": args.eval_first_seed, "episodes": args.eval_episodes,
                                               "conditions": [c.key for c in args.conditions]}
    # `vla-ladder eval` of it on the episode it was chosen on keeps the count in summary.json.
    from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
    summary = run_evaluation(EvalConfig(f"ppo:{run_dir}/checkpoints/best", out=run_dir.parent / "eval", episodes=2,
                                        grid=TINY["grid"], workers=1), progress=False)
    assert summary["episodes_seen_in_selection"] == 1
    assert json.loads((run_dir.parent / "eval" / "summary.json").read_text())["episodes_seen_in_selection"] == 1


def test_a_killed_save_neither_costs_the_checkpoint_nor_the_best_score(tmp_path):
    """A save killed midway leaves a step directory past the one state.json points to, and a best model newer than
    state.json's best_success: the next save keeps its own checkpoint whatever --keep-checkpoints, and a resumed run
    knows the best score its best model had."""
    from vla_ladder.ppo.checkpoint import load_run_state, save_checkpoint

    agent = Agent(4, 2, (8,))
    optimizer = torch.optim.AdamW(agent.parameters())
    state = {"global_step": 100, "iteration": 2, "best_success": 0.25}
    save_checkpoint(tmp_path, agent, optimizer, state, keep=1, best=True)
    orphan = tmp_path / "checkpoints/step_000000000150"  # a killed save, of a run then resumed in smaller batches
    orphan.mkdir()
    save_checkpoint(tmp_path, agent, optimizer, {**state, "global_step": 125}, keep=1, best=False)
    kept = sorted(d.name for d in (tmp_path / "checkpoints").iterdir())
    assert kept == ["best", "step_000000000125"]
    assert json.loads((tmp_path / "state.json").read_text())["checkpoint"] == "checkpoints/step_000000000125"
    assert load_policy(f"ppo:{tmp_path}", device="cpu").describe()["global_step"] == 125
    # Killed after checkpoints/best took a better model (0.5), before state.json said so.
    best = tmp_path / "checkpoints/best/state.json"
    best.write_text(json.dumps({**json.loads(best.read_text()), "best_success": 0.5}))
    assert load_run_state(tmp_path)["best_success"] == 0.5
    assert json.loads((tmp_path / "state.json").read_text())["best_success"] == 0.25


def test_evaluating_the_best_checkpoint_on_the_seeds_it_was_chosen_on_is_said(tmp_path, capsys):
    """checkpoints/best is the best of the run's evaluations on seeds eval_first_seed + j of its training conditions:
    an evaluation that plays any of those episodes says how many before it starts (its rates lean high there) and
    keeps the count in summary.json; other seeds, other conditions and the latest checkpoint say nothing."""
    from vla_ladder.evaluation.runner import EvalConfig, selection_overlap
    from vla_ladder.ppo.checkpoint import save_checkpoint

    agent = Agent(4, 2, (8,))
    optimizer = torch.optim.AdamW(agent.parameters())
    state = {"global_step": 100, "iteration": 2, "best_success": 0.25}
    save_checkpoint(tmp_path, agent, optimizer, state, keep=1, best=True,
                    selected_on={"first_seed": 10, "episodes": 20, "conditions": ["small_jitter/canonical/5"]})
    best = f"ppo:{tmp_path}/checkpoints/best"
    assert load_policy(best, device="cpu").describe()["selected_on"]["first_seed"] == 10

    def overlap(spec, **kw) -> int:
        return selection_overlap(EvalConfig(policy=spec, **kw))

    # Seeds 0-99 of four regimes: only small_jitter's seeds 10-29 were seen.
    assert overlap(best) == 20
    assert "best of its training evaluations, on seeds 10 to 29; 20 of the 400 episodes" in capsys.readouterr().out
    assert overlap(best, first_seed=25, episodes=10) == 5
    assert "--first-seed 30 or above plays held-out episodes" in capsys.readouterr().out
    assert overlap(best, first_seed=30) == 0
    assert overlap(best, grid=ConditionGrid(("small_jitter",), num_objects=(3,))) == 0
    assert overlap(f"ppo:{tmp_path}") == 0 and overlap("scripted") == 0
    assert capsys.readouterr().out == ""


def test_a_resumed_run_draws_noise_no_other_run_draws():
    """A fresh run seeds torch and NumPy with train_seed (the committed curves); a run resumed at iteration i with a
    seed that no run of any train_seed starts from or resumes to, reproducibly."""
    assert [noise_seed(s, 0) for s in range(4)] == [0, 1, 2, 3]
    resumed = {(s, i): noise_seed(s, i) for s in range(20) for i in range(1, 20)}
    assert len(set(resumed.values())) == len(resumed) and not set(resumed.values()) & set(range(20))
    assert all(0 <= v < 2**32 for v in resumed.values()) and noise_seed(3, 7) == resumed[(3, 7)]


def test_a_resumed_run_keeps_the_tensorboard_points_of_its_checkpoint(tmp_path):
    """A run checkpointed at step 100 (its losses and evaluation logged at 100 first) and killed after logging 150
    resumes at 100: the killed run's 150 goes, the checkpoint's 100 stays (purge_step=100 dropped it too)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    writer = summary_writer(tmp_path, 0)
    for step in (50, 100, 150):
        writer.add_scalar("eval/success", step / 200, step)
    writer.close()
    writer = summary_writer(tmp_path, 100)
    writer.add_scalar("eval/success", 0.125, 150)
    writer.close()
    events = EventAccumulator(str(tmp_path / "tb"))
    events.Reload()
    assert [(e.step, e.value) for e in events.Scalars("eval/success")] == [(50, 0.25), (100, 0.5), (150, 0.125)]


@pytest.mark.slow
def test_resume_continues_step_count_and_optimizer(run_dir):
    assert _optimizer_steps(run_dir) == 16  # 2 iterations x 4 epochs x 2 minibatches
    state = train(cli_config(["--out", str(run_dir), "--resume", "--total-timesteps", "150"]))
    assert state["global_step"] == 150 and state["iteration"] == 3
    # A fresh optimizer would have counted 8 steps; the restored one goes on from 16.
    assert _optimizer_steps(run_dir) == 24
    assert json.loads((run_dir / "config.json").read_text())["total_timesteps"] == 150
    # Another batch size on resume: the run still ends at --total-timesteps (it counted the saved iterations
    # against the new batch, and went on to 275 here).
    # And an evaluation written by a run killed before its checkpoint is made again, not kept twice.
    evals = json.loads((run_dir / "evals.json").read_text())
    (run_dir / "evals.json").write_text(json.dumps([*evals, {**evals[-1], "global_step": 175}]))
    state = train(cli_config(["--out", str(run_dir), "--resume", "--num-steps", "25", "--total-timesteps", "200"]))
    assert state["global_step"] == 200 and state["iteration"] == 5
    assert [e["global_step"] for e in json.loads((run_dir / "evals.json").read_text())] == [50, 100, 150, 175, 200]


def test_a_run_saved_for_the_gpu_resumes_on_a_cpu_machine_with_the_flags_that_fit(tmp_path):
    """--resume takes the flags not given from the run's config.json; the result is validated, not the saved config
    alone: a run of 1024 physx_cuda envs is refused on a CPU machine until --sim-backend physx_cpu --num-envs N."""
    from dataclasses import asdict

    from vla_ladder.files import write_json

    out = tmp_path / "run"
    saved = {**asdict(Args(out=out, **{**TINY, "eval_freq": 7})), "sim_backend": "physx_cuda", "num_envs": 1024,
             "total_timesteps": 30_000_000}
    write_json(out / "config.json", saved)
    args = cli_config(["--out", str(out), "--resume", "--sim-backend", "physx_cpu", "--num-envs", "1"])
    assert (args.sim_backend, args.num_envs, args.eval_freq, args.total_timesteps) == ("physx_cpu", 1, 7, 30_000_000)
    assert args.grid == TINY["grid"] and args.resume
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="needs a CUDA GPU"):
            cli_config(["--out", str(out), "--resume"])


def test_a_directory_of_other_files_is_refused_and_a_killed_run_starts_again(tmp_path):
    """train-expert wrote its run among a directory's other files; a run killed before its first checkpoint (its
    config.json and tb/ only) still starts again there."""
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"--out '.*' is not empty and holds no PPO run \(notes.txt\); use a new"):
        Args(out=tmp_path, **TINY)
    killed = tmp_path / "killed"
    (killed / "tb").mkdir(parents=True)
    (killed / "config.json").write_text("{}")
    assert Args(out=killed, **TINY).out == killed


@pytest.mark.slow
def test_bad_input_errors(tmp_path, run_dir):
    with pytest.raises(ValueError, match="no PPO checkpoint"):
        load_policy(f"ppo:{tmp_path / 'missing'}")
    with pytest.raises(ValueError, match="ppo:PATH"):
        load_policy("ppo")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "model.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(ValueError, match="unreadable PPO checkpoint"):
        load_policy(f"ppo:{broken}")

    other = tmp_path / "other"
    save_agent(other / "model.safetensors", Agent(80, 7, (16,)))
    with pytest.raises(ValueError, match="80-d observations.*96-d observations"):
        load_agent(other, obs_dim=96, act_dim=7)
    policy = load_policy(f"ppo:{other}", device="cpu")
    with pytest.raises(ValueError, match=r"80-d observations; got observations of shape \(1, 96\)"):
        policy.act(torch.zeros(1, 96), ["grasp the apple"])

    with pytest.raises(ValueError, match="already holds a run"):
        train(Args(out=str(run_dir), **TINY))
    with pytest.raises(ValueError, match="allowed: small_jitter"):
        Args(out="x", grid=ConditionGrid(("nowhere",)))
    with pytest.raises(ValueError, match="--sim-backend: unknown sim_backend .gpu.; allowed: physx_cpu, physx_cuda"):
        Args(out="x", sim_backend="gpu")
    with pytest.raises(ValueError, match="at least one batch"):
        Args(out="x", num_envs=4, total_timesteps=10)
    for flag, value, words in (("gamma", 1.5, "--gamma must be in [0, 1], got 1.5"),
                               ("max_grad_norm", 0.0, "--max-grad-norm must be positive, got 0.0"),
                               ("target_kl", -0.1, "--target-kl must be >= 0, got -0.1"),
                               ("learning_rate", math.inf, "--learning-rate must be a finite number, got inf"),
                               ("init_logstd", math.nan, "--init-logstd must be a finite number, got nan")):
        with pytest.raises(ValueError, match=re.escape(words)):
            Args(out="x", **{**TINY, flag: value})
    # A network of other sizes cannot go on from the run's weights: refused before any env starts.
    with pytest.raises(ValueError, match=re.escape("network has hidden sizes [256, 256, 256], not [16]")):
        train(cli_config(["--out", str(run_dir), "--resume", "--hidden-sizes", "16"]))


def test_a_checkpoint_trained_under_another_task_contract_is_refused(tmp_path):
    """Checkpoints keep the contract's policy fields (rates, cameras, state, action): an expert trained at another
    control rate is refused before any episode, the field named; one written before checkpoints kept it loads."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    from vla_ladder.contract import CONTROL_HZ, policy_fingerprint
    from vla_ladder.policies import check_spec

    f = tmp_path / "model.safetensors"
    save_agent(f, Agent(80, 7, (16,)))
    with safe_open(str(f), framework="pt") as sf:
        meta = sf.metadata()
    assert json.loads(meta["contract"]) == policy_fingerprint()
    save_file(load_file(str(f)), str(f), {**meta, "contract": json.dumps({**policy_fingerprint(),
                                                                          "control_hz": CONTROL_HZ // 2})})
    changed = f"another task contract \\(control_hz was {CONTROL_HZ // 2}, now {CONTROL_HZ}\\)"
    with pytest.raises(ValueError, match=changed):
        check_spec(f"ppo:{tmp_path}")
    del meta["contract"]
    save_file(load_file(str(f)), str(f), meta)
    assert load_agent(tmp_path).obs_dim == 80 and check_spec(f"ppo:{tmp_path}") == ("ppo", str(tmp_path))


def test_cli_exposes_every_field(capsys):
    from vla_ladder.cli import main

    args = cli_config(["--out", "d", "--sim-backend", "physx_cpu", "--num-envs", "1", "--regimes", "small_jitter",
                       "full_random", "--num-objects", "5", "--no-norm-adv", "--ent-coef", "0.05"])
    assert (args.num_envs, args.grid.regimes, args.grid.num_objects, args.norm_adv, args.ent_coef) == \
        (1, ("small_jitter", "full_random"), (5,), False, 0.05)
    assert args.learning_rate == 1e-4 and args.total_timesteps == 30_000_000  # the paper's defaults
    with pytest.raises(SystemExit) as e:
        main(["train-expert", "--help"])
    assert e.value.code == 0
    help_text = capsys.readouterr().out
    names = [f.name for f in dataclasses.fields(Args) if f.name != "grid"]
    names += [f.name for f in dataclasses.fields(ConditionGrid)]
    for name in names:
        assert "--" + name.replace("_", "-") in help_text, name
    assert main(["train-expert", "--out", "d", "--no-such-option", "1"]) == 2
    assert capsys.readouterr().err.strip() == ("vla-ladder train-expert: error: unknown flag --no-such-option; "
                                               "`vla-ladder train-expert --help` lists the flags")
    assert main(["train-expert", "--out", "d", "--gamma", "0.9", "--splits", "sideways"]) == 2


@pytest.mark.slow
def test_several_cpu_envs_run_in_spawned_processes(monkeypatch):
    args = Args(out="x", sim_backend="physx_cpu", num_envs=2, num_steps=50, total_timesteps=100)
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    torch.set_num_threads(2)  # what the trainer sets from --torch-threads before it builds its envs
    envs = TrainEnvs(args, torch.device("cpu"))
    try:
        # One torch thread and one lavapipe thread are for the env processes: the env gymnasium builds here to read
        # its spaces left them set in the trainer's process (its --torch-threads became 1).
        assert torch.get_num_threads() == 2 and "LP_NUM_THREADS" not in os.environ
        conds = [("small_jitter", "canonical", 5), ("full_random", "canonical", 1)]
        obs = envs.reset([TRAIN_SEED_MIN, TRAIN_SEED_MIN + 1], conds)
        assert obs.shape == (2, 96) and envs.object_set == "standin"
        layouts = [lay[0] for lay in envs.env.get_attr("layouts")]
        assert ([(lay.condition.regime, len(lay.objects)) for lay in layouts]
                == [("small_jitter", 5), ("full_random", 1)])
        obs, reward, truncated, metrics = envs.step(torch.zeros(2, 7))
        assert obs.shape == (2, 96) and reward.shape == (2,) and not truncated.any()
        assert set(metrics) == {"success", "grasp_any", "reach"} and metrics["success"].shape == (2,)
    finally:
        envs.close()
