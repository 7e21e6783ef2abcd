"""`lerobot:CHECKPOINT` policies and the LeRobot env plugin, with real LeRobot checkpoints trained here."""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import lerobot_helpers as H
from vla_ladder.policies.lerobot import LeRobotPolicy, parse_arg, resolve_checkpoint
from vla_ladder.recordings import read_provenance
from vla_ladder.policies import load_policy

pytestmark = pytest.mark.slow  # the real simulator, rendering, recording or training


def _obs(n: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    cam = {"rgb": torch.randint(0, 256, (n, 256, 256, 3), dtype=torch.uint8, generator=g)}
    return {"sensor_data": {"hand_camera": cam, "fixed_camera": {"rgb": cam["rgb"].flip(1)}},
            "extra": {"proprio": torch.randn(n, 15, generator=g)}}


@pytest.fixture(scope="module")
def smolvla_run(tmp_path_factory):
    return H.trained(tmp_path_factory, "smolvla")


def test_loads_with_processors_and_runs_chunks_batched(smolvla_run):
    policy = load_policy(f"lerobot:{smolvla_run}?n_action_steps=2", device="cpu")
    assert policy.obs_mode == "rgb"
    assert policy.describe()["n_action_steps"] == 2 and policy.describe()["chunk_size"] == 4
    calls = []
    inner = policy.policy._get_action_chunk
    policy.policy._get_action_chunk = lambda *a, **k: calls.append(1) or inner(*a, **k)

    policy.reset([0, 1])
    obs = _obs(2)
    actions = [policy.act(obs, ["grasp the apple", "grasp the mug"]) for _ in range(5)]
    assert all(a.shape == (2, 7) and a.dtype == torch.float32 for a in actions)
    assert all(float(a.abs().max()) <= 1.0 for a in actions)
    assert len(calls) == 3  # a new chunk every 2 steps: steps 0, 2, 4

    # Same seeds, same observations -> the same (flow-matching) actions.
    policy.reset([0, 1])
    again = policy.act(obs, ["grasp the apple", "grasp the mug"])
    torch.testing.assert_close(again, actions[0])
    assert policy.predict_chunk(obs, ["grasp the apple"] * 2).shape == (2, 4, 7)


def test_act_queues_its_chunks_as_select_action_does(tmp_path_factory):
    """ACT (without temporal ensembling) acts from chunks queued here, as the flow-matching policies do: the actions
    LeRobot's own select_action gives on the same observations, with each observation preprocessed once a chunk
    (steps 0, 2, 4 at horizon 2) rather than every step."""
    policy = load_policy(f"lerobot:{H.trained(tmp_path_factory, 'act')}?n_action_steps=2", device="cpu")
    observations, tasks = [_obs(2, seed=s) for s in range(5)], ["grasp the apple", "grasp the mug"]
    preprocessor, calls = policy.preprocessor, []
    policy.preprocessor = lambda batch: calls.append(1) or preprocessor(batch)
    policy.reset([0, 1])
    ours = torch.stack([policy.act(obs, tasks) for obs in observations])
    assert len(calls) == 3
    policy.policy.reset()
    with torch.no_grad():
        theirs = torch.stack([policy.postprocessor(policy.policy.select_action(preprocessor(policy.batch(obs, tasks))))
                              for obs in observations]).clamp(-1, 1)
    torch.testing.assert_close(ours, theirs, atol=0, rtol=0)
    assert policy.noise(2) is None  # ACT takes no noise
    # so another noise stream would be recorded and play the same episodes: refused, before and at loading
    from vla_ladder.policies import check_spec
    spec = f"lerobot:{H.trained(tmp_path_factory, 'act')}?noise_seed=1"
    for call in (lambda: check_spec(spec), lambda: load_policy(spec, device="cpu")):
        with pytest.raises(ValueError, match="only pi0, pi05, smolvla draw; this checkpoint is act"):
            call()
    if not torch.backends.mps.is_available():  # (LeRobot played on the CPU, with a warning)
        with pytest.raises(ValueError, match="device=mps needs Apple's Metal"):
            check_spec(f"lerobot:{H.trained(tmp_path_factory, 'act')}?device=mps")


def test_flow_matching_noise_is_drawn_per_episode(smolvla_run):
    """An episode's noise comes from its own seed and chunk index: alone or beside another episode, a SmolVLA
    acts the same (to float rounding), and another seed acts otherwise."""
    policy = load_policy(f"lerobot:{smolvla_run}?n_action_steps=2", device="cpu")
    both, tasks = _obs(2, seed=4), ["grasp the apple", "grasp the mug"]
    first = {"sensor_data": {cam: {"rgb": v["rgb"][:1]} for cam, v in both["sensor_data"].items()},
             "extra": {"proprio": both["extra"]["proprio"][:1]}}

    def actions(obs, seeds):
        policy.reset(seeds)
        return torch.stack([policy.act(obs, tasks[:len(seeds)]) for _ in range(5)])[:, 0]  # 3 chunks

    alone = actions(first, [11])
    torch.testing.assert_close(actions(both, [11, 12]), alone, atol=1e-5, rtol=0)
    torch.testing.assert_close(actions(both, [11, 99]), alone, atol=1e-5, rtol=0)
    assert (actions(first, [12]) - alone).abs().max() > 1e-3
    policy.reset([11])
    chunk0 = policy.noise(1)
    assert chunk0.shape == (1, 4, policy.config.max_action_dim) and policy.noise(2) is None  # 2 envs, 1 seed
    policy.act(first, tasks[:1])
    assert not torch.equal(policy.noise(1), chunk0)  # the next chunk draws other noise

    # ?noise_seed=K plays the same episode with another stream; the same K, the same stream again.
    other = load_policy(f"lerobot:{smolvla_run}?n_action_steps=2&noise_seed=1", device="cpu")
    assert other.describe()["noise_seed"] == 1 and policy.describe()["noise_seed"] == 0
    policy = other  # what actions() plays
    stream_1 = actions(first, [11])
    assert (stream_1 - alone).abs().max() > 1e-3
    torch.testing.assert_close(actions(both, [11, 12]), stream_1, atol=1e-5, rtol=0)
    # Seeds given with env_ids in another order are each env's own (they were taken by position).
    policy.reset([12, 11], env_ids=[1, 0])
    assert policy._seeds == [11, 12]
    with pytest.raises(ValueError, match="reset all envs together"):
        policy.reset([11, 12], env_ids=[0, 0])
    with pytest.raises(ValueError, match="noise_seed=.-1.* expected an integer from 0"):
        load_policy(f"lerobot:{smolvla_run}?noise_seed=-1")


def test_mixed_precision_as_lerobot_eval_runs_it(smolvla_run):
    """`?use_amp=true` (or a checkpoint trained with use_amp) acts under torch.autocast, as lerobot-eval does: the
    same actions up to bfloat16's rounding on the CPU, and not bit for bit the float32 ones."""
    obs, tasks = _obs(2, seed=3), ["grasp the apple", "grasp the mug"]
    full = load_policy(f"lerobot:{smolvla_run}", device="cpu")
    amp = load_policy(f"lerobot:{smolvla_run}?use_amp=true", device="cpu")
    assert full.describe()["use_amp"] is False and amp.describe()["use_amp"] is True
    chunks = []
    for policy in (full, amp):
        policy.reset([0, 1])
        chunks.append(policy.predict_chunk(obs, tasks))
        policy.reset([0, 1])
        assert policy.act(obs, tasks).dtype == torch.float32
    assert not torch.equal(chunks[0], chunks[1]), "autocast did not change a single number: it was not used"
    torch.testing.assert_close(chunks[1], chunks[0], atol=0.03, rtol=0)  # 0.0045 at most measured
    with pytest.raises(ValueError, match="option use_amp='maybe' .*: expected true or false"):
        parse_arg(f"{smolvla_run}?use_amp=maybe")


def test_loading_leaves_nothing_in_the_temp_directory(smolvla_run, tmp_path, monkeypatch):
    """LeRobot's config loader writes a temp file it never removes; two loads here leave the directory empty."""
    import tempfile
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    for _ in range(2):
        load_policy(f"lerobot:{smolvla_run}?n_action_steps=2", device="cpu")
    assert list(tmp_path.iterdir()) == []
    assert tempfile.gettempdir() == str(tmp_path)  # the caller's setting is back


def test_checkpoint_paths_resolve(smolvla_run):
    ckpt = smolvla_run / "checkpoints" / "last" / "pretrained_model"
    assert resolve_checkpoint(smolvla_run) == ckpt
    assert resolve_checkpoint(ckpt.parent) == ckpt
    assert resolve_checkpoint(ckpt) == ckpt
    with pytest.raises(ValueError, match="no LeRobot checkpoint"):
        resolve_checkpoint(smolvla_run / "nope")


def test_bad_specs_fail_before_loading(smolvla_run):
    with pytest.raises(ValueError, match="allowed: n_action_steps, device"):
        parse_arg(f"{smolvla_run}?horizon=3")
    # draccus said only "Couldn't instantiate class SmolVLAConfig using the given arguments"
    with pytest.raises(ValueError, match=r"^n_action_steps must be from 1 to the checkpoint's chunk size \(4\)"):
        load_policy(f"lerobot:{smolvla_run}?n_action_steps=8")
    with pytest.raises(ValueError, match="needs a path"):
        load_policy("lerobot")


def test_every_option_may_be_given_as_a_keyword(smolvla_run):
    """load_policy(spec, **kwargs) takes a spec's options as keywords: instruction= and noise_seed= were dropped
    unsaid (only the config's options were taken), so the episode's own instruction and stream 0 played."""
    policy = load_policy(f"lerobot:{smolvla_run}?n_action_steps=2", device="cpu", noise_seed=3,
                         instruction="grasp the thing")
    assert {k: policy.describe()[k] for k in ("n_action_steps", "device", "noise_seed", "instruction")} == \
        {"n_action_steps": 2, "device": "cpu", "noise_seed": 3, "instruction": "grasp the thing"}


def test_mismatched_checkpoint_features_are_rejected(smolvla_run, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(smolvla_run / "checkpoints" / "last" / "pretrained_model", bad)
    cfg = json.loads((bad / "config.json").read_text())
    feats = cfg["input_features"]
    feats["observation.images.top"] = feats.pop("observation.images.hand_camera")
    feats["observation.images.side"] = feats.pop("observation.images.fixed_camera")
    cfg["output_features"]["action"]["shape"] = [6]
    (bad / "config.json").write_text(json.dumps(cfg))
    (bad / "model.safetensors").unlink()  # the check must come before any weight is read
    with pytest.raises(ValueError) as err:
        LeRobotPolicy(bad)
    msg = str(err.value)
    assert "none of its cameras" in msg and "observation.images.top" in msg
    assert "action has shape (6,)" in msg


def test_lerobot_env_config_refuses_what_the_simulator_or_the_first_episode_would(tmp_path, monkeypatch):
    """A directory as --env.episode_metrics failed with IsADirectoryError after the first episode; an unknown object
    set or backend once the simulator started, after LeRobot had loaded the policy."""
    from vla_ladder.lerobot_env import GraspObjectEnvConfig

    monkeypatch.setenv("VLA_LADDER_OBJECT_SET", "auto")
    for kwargs, says in [
        (dict(episode_metrics=str(tmp_path)), f"--env.episode_metrics {tmp_path} is a directory; give a file name"),
        (dict(episode_metrics=str(tmp_path / "nowhere" / "e.jsonl")), "does not exist"),
        (dict(object_set="foo"), "--env.object_set: unknown object_set 'foo'; allowed: auto, ycb, standin"),
        (dict(sim_backend="gpu"), "--env.sim_backend: unknown sim_backend 'gpu'; allowed: physx_cpu, physx_cuda"),
        (dict(robot_mesh="fancy"), "--env.robot_mesh: unknown robot_mesh 'fancy'; allowed: lite, full"),
        (dict(instructions="klingon"), "--env.instructions: unknown instruction set 'klingon'; allowed: canonical,"),
    ]:
        with pytest.raises(ValueError, match=re.escape(says)):
            GraspObjectEnvConfig(**kwargs)
    GraspObjectEnvConfig(object_set="standin", sim_backend="physx_cpu", episode_metrics=str(tmp_path / "e.jsonl"))
    assert list(tmp_path.iterdir()) == []


def test_lerobot_env_plugin_steps_and_scores_the_final_step(tmp_path):
    """Found the way lerobot-eval finds it (an installed lerobot_env_* distribution); is_success is the final
    step's success, and each finished episode's decomposed metrics land in --env.episode_metrics."""
    from lerobot.envs.factory import make_env, make_env_config
    from lerobot.envs.utils import close_envs, preprocess_observation
    from lerobot.utils.import_utils import register_third_party_plugins

    from vla_ladder.lerobot_env import LeRobotGraspObject

    register_third_party_plugins()  # what lerobot-eval, lerobot-train... call first
    metrics = tmp_path / "episodes.jsonl"
    cfg = make_env_config("grasp_object", condition="small_jitter/canonical/2", episode_metrics=str(metrics))
    assert cfg.type == "grasp_object" and cfg.features_map["pixels/hand_camera"] == "observation.images.hand_camera"
    with pytest.raises(ValueError, match="regime"):
        make_env_config("grasp_object", condition="nowhere/canonical/5")
    with pytest.raises(ValueError, match="episode_length must be 50"):
        make_env_config("grasp_object", episode_length=30)
    with pytest.raises(ValueError, match="does not exist"):
        make_env_config("grasp_object", episode_metrics=str(tmp_path / "nowhere" / "e.jsonl"))
    envs = make_env(cfg, n_envs=1)
    vec = envs["grasp_object"][0]
    try:
        obs, _ = vec.reset(seed=[7])
        batch = preprocess_observation(obs)
        assert batch["observation.images.hand_camera"].shape == (1, 3, 256, 256)
        assert batch["observation.state"].shape == (1, 15)
        assert vec.call("task_description")[0].startswith("grasp the ")
        assert vec.call("_max_episode_steps")[0] == 50
        for t in range(50):
            obs, reward, terminated, truncated, info = vec.step(np.zeros((1, 7), np.float32))
            assert not terminated[0] and truncated[0] == (t == 49)
            if t < 49:
                assert info["is_success"].dtype == bool and info["is_success"].shape == (1,)
                assert {"grasp_any", "reach"} <= set(info)
        final = info["final_info"]  # gymnasium's same-step autoreset, as LeRobot configures it
        assert {"is_success", "grasp_any", "reach"} <= set(final)
    finally:
        close_envs(envs)
    (record,) = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert record["seed"] == 7 and record["condition"] == "small_jitter/canonical/2"
    assert record["instruction"].startswith("grasp the ") and record["held"] == "none"
    assert all(record[k] == bool(final[k][0]) for k in ("success", "grasp_any", "reach"))
    # LeRobot counts an episode as a success if is_success was true at any step: only the final step may say so.
    held_now = {"success": torch.tensor([True]), "grasp_any": torch.tensor([True]), "reach": torch.tensor([True])}
    assert LeRobotGraspObject._info(held_now)["is_success"] is False
    assert LeRobotGraspObject._info(held_now, final=True)["is_success"] is True


def test_the_lerobot_env_plays_the_robot_mesh_and_instructions_asked(tmp_path):
    """lerobot-eval could only play the lite mesh and the canonical wording: a policy recorded with `record
    --robot-mesh full` or a paraphrase set met another robot or other words there than under `vla-ladder eval`."""
    from lerobot.envs.factory import make_env_config

    from vla_ladder.lerobot_env import LeRobotGraspObject
    from vla_ladder.task.layouts import sample_layout
    from vla_ladder.conditions import Condition

    cfg = make_env_config("grasp_object", condition="small_jitter/canonical/2", robot_mesh="full",
                          instructions="paraphrase-heldout")
    assert {k: cfg.gym_kwargs[k] for k in ("robot_mesh", "instructions")} == \
        {"robot_mesh": "full", "instructions": "paraphrase-heldout"}
    env = LeRobotGraspObject(regime="small_jitter", num_objects=2, **{k: cfg.gym_kwargs[k]
                                                                       for k in ("robot_mesh", "instructions")})
    try:
        env.reset(seed=11)
        assert env.env.unwrapped.robot_mesh == "full"
        expected = sample_layout(Condition("small_jitter", "canonical", 2), 11, instructions="paraphrase-heldout")
        assert env.task_description == expected.instruction != sample_layout(expected.condition, 11).instruction
    finally:
        env.close()


def test_the_lerobot_env_clamps_actions_as_vla_ladder_eval_does():
    """ManiSkill clips only the rotation's norm: a rotation component past 1 turned the wrist otherwise under
    lerobot-eval than under `vla-ladder eval`, which clamps every action to [-1, 1]."""
    from vla_ladder.lerobot_env import LeRobotGraspObject

    env = LeRobotGraspObject(regime="small_jitter", num_objects=2)
    try:
        states = []
        for action in ([0.0, 0.0, 0.0, 1.5, 0.5, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0, 0.5, 0.0, 1.0]):
            env.reset(seed=3)
            for _ in range(5):
                obs = env.step(np.array(action, np.float32))[0]
            states.append(obs["agent_pos"])
    finally:
        env.close()
    np.testing.assert_array_equal(states[0], states[1])


def test_lerobot_eval_runs_grasp_object_from_the_installed_plugin(smolvla_run, tmp_path):
    """`lerobot-eval --env.type=grasp_object` as a user types it: no --env.discover_packages_path, offline."""
    from importlib.metadata import distribution

    # LeRobot matches the distribution's name as written, underscores included, and imports it as a module.
    assert distribution("lerobot_env_grasp_object").metadata["Name"] == "lerobot_env_grasp_object"
    out, metrics = tmp_path / "eval", tmp_path / "episodes.jsonl"
    cmd = [str(Path(sys.executable).parent / "lerobot-eval"), "--env.type=grasp_object",
           "--env.condition=small_jitter/canonical/2", f"--env.episode_metrics={metrics}",
           f"--policy.path={smolvla_run / 'checkpoints' / 'last' / 'pretrained_model'}", "--policy.device=cpu",
           "--eval.n_episodes=1", "--eval.batch_size=1", "--seed=11", f"--output_dir={out}"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "MS_SKIP_ASSET_DOWNLOAD_PROMPT": "1"}
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=1200, env=env)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    info = json.loads((out / "eval_info.json").read_text())
    task = info["per_task"][0]
    assert task["task_group"] == "grasp_object" and len(task["metrics"]["successes"]) == 1
    assert info["overall"]["n_episodes"] == 1
    (record,) = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert record["seed"] == 11  # episode i of eval_info.json played seed --seed + i
    assert record["success"] == task["metrics"]["successes"][0]
    assert isinstance(record["grasp_any"], bool) and isinstance(record["reach"], bool)
    assert f"GraspObject-v1 episode seed=11 {record['instruction']!r}" in done.stdout + done.stderr


def test_vla_ladder_eval_plays_what_lerobot_eval_plays(tmp_path_factory, tmp_path, monkeypatch):
    """`vla-ladder eval --policy lerobot:RUN` and LeRobot's own eval loop (lerobot-eval's main, in this process, on
    the installed env plugin) play a tiny ACT's episode alike: the same 50 actions bit for bit, the same outcome to
    the last digit of the final distance. With the same torch thread count (lerobot-eval's default is every core):
    another one rounds otherwise. The adapter fed the cameras as a channels-last view, on which the ResNet's
    convolution rounded otherwise (3e-7 at the first step, 2e-3 by the 50th, 1 mm of final distance)."""
    import pandas as pd
    import vla_ladder.task.env as task_env
    from lerobot.scripts import lerobot_eval
    from vla_ladder.cli import main

    run = H.trained(tmp_path_factory, "act")
    played: list[torch.Tensor] = []
    step = task_env.GraspObjectEnv.step  # (both paths step this env; the action is recorded, then played)
    monkeypatch.setattr(task_env.GraspObjectEnv, "step",
                        lambda self, action: played.append(torch.as_tensor(action).cpu().clone()) or step(self, action))
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)  # the player then acts on one thread

    assert main(["eval", "--policy", f"lerobot:{run}?device=cpu", "--out", str(tmp_path / "ours"), "--episodes", "1",
                 "--first-seed", "2", "--workers", "1", "--regimes", "small_jitter", "--num-objects", "2"]) == 0
    ours, played = played, []
    (row,) = pd.read_parquet(tmp_path / "ours" / "episodes.parquet").to_dict("records")

    metrics, threads = tmp_path / "episodes.jsonl", torch.get_num_threads()
    monkeypatch.setattr(sys, "argv", [
        "lerobot-eval", "--env.type=grasp_object", "--env.condition=small_jitter/canonical/2",
        f"--env.episode_metrics={metrics}", f"--policy.path={run / 'checkpoints' / 'last' / 'pretrained_model'}",
        "--policy.device=cpu", "--eval.n_episodes=1", "--eval.batch_size=1", "--seed=2",
        f"--output_dir={tmp_path / 'theirs'}"])
    flags = torch.backends.cudnn.benchmark, torch.backends.cuda.matmul.allow_tf32  # (eval_main turns both on)
    torch.set_num_threads(1)
    try:
        lerobot_eval.main()
    finally:
        torch.set_num_threads(threads)
        torch.backends.cudnn.benchmark, torch.backends.cuda.matmul.allow_tf32 = flags
    (record,) = [json.loads(line) for line in metrics.read_text().splitlines()]

    assert len(ours) == len(played) == 50
    torch.testing.assert_close(torch.cat(ours), torch.cat(played), atol=0, rtol=0)
    assert record["seed"] == row["seed"] == 2 and record["instruction"] == row["instruction"]
    assert {k: record[k] for k in ("success", "grasp_any", "reach", "held", "reach_dist")} == \
        {k: row[k] for k in ("success", "grasp_any", "reach", "held", "reach_dist")}


def test_one_policy_acts_on_cpu_envs_in_lockstep(smolvla_run, tmp_path):
    """`eval --num-envs 2` on physx_cpu: the camera observations of two env processes reach one LeRobot policy
    as one batch; the episodes (seeds, layouts, instructions) are those of one env at a time, and with the
    flow-matching noise drawn per episode so are the outcomes (the actions agree to float rounding, which a
    batch changes, so the final distances only closely)."""
    import pandas as pd

    from vla_ladder.conditions import ConditionGrid
    from vla_ladder.evaluation.runner import EvalConfig, run_evaluation

    runs = {}
    for n in (1, 2):
        cfg = EvalConfig(f"lerobot:{smolvla_run}?device=cpu", out=tmp_path / f"n{n}", workers=1, num_envs=n,
                         grid=ConditionGrid(("small_jitter",), num_objects=(2,)), episodes=3)
        summary = run_evaluation(cfg, progress=False)
        runs[n] = pd.read_parquet(cfg.out / "episodes.parquet")
    # The tiny model was trained on a recording from seed 0 (its train_config.json names it): the episodes played
    # on its demonstrations' seeds are counted, and said (a seed is a scene).
    trained_on = set(read_provenance(H.dataset(None))["seed"])
    assert summary.get("episodes_on_training_seeds", 0) == len(trained_on & {0, 1, 2}) > 0
    same = ["episode", "seed", "target", "instruction", "layout", "held", "success", "grasp_any", "reach"]
    pd.testing.assert_frame_equal(runs[1][same], runs[2][same])
    assert len(runs[2]) == 3 and runs[2]["reach_dist"].between(0, 2).all()
    np.testing.assert_allclose(runs[2]["reach_dist"], runs[1]["reach_dist"], atol=0.005)
