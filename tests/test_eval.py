"""`vla-ladder eval` and the evaluation runner on the real simulator (CPU)."""

import json

import imageio.v3 as iio
import pandas as pd
import pytest
import torch

from vla_ladder.cli import main
from vla_ladder.conditions import REGIMES, ConditionGrid, parse_regimes
from vla_ladder.contract import EPISODE_STEPS, IMAGE_SHAPE
from vla_ladder.evaluation.rundir import EPISODE_COLUMNS
from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
from vla_ladder.files import write_json
from vla_ladder.policies import Policy


class HoldStill(Policy):
    """A real (if useless) policy: keeps the arm where it is with the gripper open."""

    name = "hold-still"

    def act(self, obs, instructions):
        action = torch.zeros(len(instructions), 7)
        action[:, 6] = 1.0
        return action


@pytest.mark.slow
def test_eval_command_writes_run_directory(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["eval", "--policy", "scripted", "--regimes", "small_jitter", "--num-objects", "3",
               "--episodes", "2", "--first-seed", "5", "--out", str(out), "--videos", "1"])
    assert rc == 0
    assert "small_jitter/canonical/3" in capsys.readouterr().out
    df = pd.read_parquet(out / "episodes.parquet")
    assert list(df.columns) == list(EPISODE_COLUMNS)
    assert len(df) == 2
    assert df["seed"].tolist() == [5, 6] and df["episode"].tolist() == [0, 1]
    assert set(df["policy"]) == {"scripted"} and set(df["num_objects"]) == {3}
    assert df["success"].all() and df["grasp_any"].all() and df["reach"].all()
    assert (df["held"] == df["target"]).all()
    layout = json.loads(df["layout"][0])
    assert layout["seed"] == 5 and layout["target"] == df["target"][0] and len(layout["positions"]) == 3
    assert df["instruction"][0] == f"grasp the {df['target'][0].replace('_', ' ')}".replace("rubiks", "Rubik's")

    # Both cameras side by side, the first frame plus one per control step.
    assert df["video"][1] == ""
    frames = iio.imread(out / df["video"][0], plugin="pyav")
    h, w, _ = IMAGE_SHAPE
    assert frames.shape == (EPISODE_STEPS + 1, h, 2 * w, 3)  # the first frame and one per step, cameras side by side

    summary = json.loads((out / "summary.json").read_text())
    assert summary["policy"]["name"] == "scripted"
    assert summary["first_seed"] == 5 and summary["episodes_per_condition"] == 2
    cond = summary["conditions"]["small_jitter/canonical/3"]
    assert cond["n"] == 2 and cond["success"] == 1.0
    assert summary["provenance"]["object_set"] == df["object_set"][0]
    config = json.loads((out / "config.json").read_text())
    assert config["grid"]["regimes"] == ["small_jitter"] and config["videos"] == 1


@pytest.mark.slow
def test_same_seeds_give_same_layouts_for_every_policy(tmp_path):
    kwargs = dict(grid=ConditionGrid(("medium_jitter", "full_random"), num_objects=(2,)), episodes=2, first_seed=11)
    a = run_evaluation(EvalConfig("scripted", out=tmp_path / "a", **kwargs), progress=False)
    b = run_evaluation(EvalConfig("hold-still", out=tmp_path / "b", **kwargs), HoldStill(), progress=False)
    da, db = (pd.read_parquet(tmp_path / r / "episodes.parquet") for r in "ab")
    for col in ("regime", "seed", "episode", "target", "instruction", "layout"):
        assert da[col].tolist() == db[col].tolist(), col
    assert set(db["policy"]) == {"hold-still"}
    assert da["success"].all() and not db["success"].any() and not db["grasp_any"].any()
    assert list(a["conditions"]) == list(b["conditions"]) == ["medium_jitter/canonical/2", "full_random/canonical/2"]
    assert b["conditions"]["full_random/canonical/2"]["success"] == 0.0


@pytest.mark.parametrize("args, message", [
    (["--regimes", "tiny_jitter"], "allowed: small_jitter"),
    (["--policy", "oracle"], "allowed: scripted"),
    (["--policy", "ppo"], "needs a path"),
    (["--splits", "pairings_xx"], "allowed: canonical"),
    (["--regimes", "full_random", "--splits", "pairings_ood"], "need a jitter regime"),
    (["--num-objects", "6"], "from 1 to 5"),
    (["--episodes", "0"], "positive integer"),
    (["--num-envs", "4096"], "runs one process per env: --num-envs must be at most the"),
    (["--sim-backend", "bullet"], "allowed: physx_cpu, physx_cuda"),
    (["--videos", "-1"], ">= 0"),
])
def test_bad_input_is_rejected_before_any_work(tmp_path, capsys, args, message):
    base = {"--policy": "scripted", "--regimes": "small_jitter", "--episodes": "3", "--first-seed": "0",
            "--out": str(tmp_path / "run")}
    for flag, value in zip(args[::2], args[1::2]):
        base[flag] = value
    rc = main(["eval", *[x for kv in base.items() for x in kv]])
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_regime_lists():
    assert parse_regimes("all") == parse_regimes(["all"]) == tuple(REGIMES)
    assert parse_regimes("large_jitter, small_jitter") == ("large_jitter", "small_jitter")
    assert parse_regimes(["large_jitter", "small_jitter"]) == ("large_jitter", "small_jitter")
    assert EvalConfig(policy="scripted", grid=ConditionGrid(("all",))).grid.regimes == tuple(REGIMES)
    with pytest.raises(ValueError, match="no regime"):
        EvalConfig(policy="scripted", grid=ConditionGrid(()))
    assert parse_regimes(["all", "all"]) == tuple(REGIMES)
    with pytest.raises(ValueError, match="all already names every regime; give it alone or name regimes"):
        parse_regimes(["all", "small_jitter"])
    # A repeated split or count played its episodes twice under one key, a run the tool then refused to read.
    for grid, words in ((dict(num_objects=(1, 1)), "num_objects must be distinct, got 1 1"),
                        (dict(splits=("canonical", "canonical")), "splits must be distinct, got canonical canonical"),
                        (dict(regimes=("small_jitter", "full_random,small_jitter")),
                         "regimes must be distinct, got small_jitter full_random small_jitter")):
        with pytest.raises(ValueError, match=words):
            ConditionGrid(**{"regimes": ("small_jitter",), **grid})


@pytest.mark.slow
def test_any_number_of_workers_plays_the_same_episodes(tmp_path):
    """Episode j of a condition is a function of its seed alone: 1 or 2 worker processes, same rows."""
    grid = ConditionGrid(("small_jitter", "full_random"), num_objects=(3,))
    runs = {}
    for workers in (1, 2):
        cfg = EvalConfig("layout-prior", out=tmp_path / f"w{workers}", grid=grid, episodes=3, workers=workers)
        run_evaluation(cfg, progress=False)
        runs[workers] = pd.read_parquet(cfg.out / "episodes.parquet")
    pd.testing.assert_frame_equal(runs[1], runs[2])
    assert len(runs[1]) == 6 and runs[1]["success"].any() and not runs[1]["success"].all()


@pytest.mark.slow
def test_batched_cpu_envs_play_the_same_episodes(tmp_path):
    """--num-envs 2 on physx_cpu: two env processes in lockstep, one policy acting on both as a batch (the
    first episode filmed, from cameras rendered in the env processes), the same rows as one env at a time."""
    grid = ConditionGrid(("small_jitter", "full_random"), num_objects=(3,))
    runs, timing = {}, {}
    for n in (1, 2):
        cfg = EvalConfig("layout-prior", out=tmp_path / f"n{n}", grid=grid, episodes=3, workers=1, num_envs=n,
                         videos=1)
        timing[n] = run_evaluation(cfg, progress=False)["timing"]
        runs[n] = pd.read_parquet(cfg.out / "episodes.parquet")
    pd.testing.assert_frame_equal(runs[1].drop(columns="video"), runs[2].drop(columns="video"))
    assert runs[1]["success"].any() and not runs[1]["success"].all()
    for video in runs[2]["video"][runs[2]["video"] != ""]:
        frames = iio.imread(tmp_path / "n2" / video)
        assert frames.shape == (EPISODE_STEPS + 1, IMAGE_SHAPE[0], 2 * IMAGE_SHAPE[1], 3) and frames.std() > 10
    with pytest.raises(ValueError, match="choose one"):
        EvalConfig("layout-prior", grid=grid, workers=2, num_envs=2)
    # Where the time went: the 6 episodes are 6 batches of one env, or 3 of two (a batch may mix conditions).
    for n, batches in ((1, 6), (2, 3)):
        t = timing[n]
        assert t["episodes"] == 6 and t["lockstep_steps"] == EPISODE_STEPS * batches
        assert all(t[f"{phase}_s"] > 0 for phase in ("reset", "policy", "env", "film", "encode"))
        assert t["reset_s"] + t["policy_s"] + t["env_s"] + t["film_s"] + t["encode_s"] < t["wall_s"]
        assert t["per_step_ms"]["env"] == pytest.approx(1e3 * t["env_s"] / t["lockstep_steps"], abs=0.01)


@pytest.mark.slow
def test_a_killed_run_resumes_and_another_request_is_refused(tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["eval", "--policy", "scripted", "--regimes", "small_jitter", "--num-objects", "2", "--episodes", "3",
            "--out", str(out), "--workers", "1"]
    assert main(argv) == 0
    full = pd.read_parquet(out / "episodes.parquet")
    # As if killed after the first episode: the run directory holds one whole row.
    full.iloc[:1].to_parquet(out / "episodes.parquet", index=False)
    capsys.readouterr()
    assert main(argv) == 0
    assert "1 episodes done, 2 to play" in capsys.readouterr().out
    pd.testing.assert_frame_equal(pd.read_parquet(out / "episodes.parquet"), full)
    summary = json.loads((out / "summary.json").read_text())
    # The timing goes on from the first invocation's: 3 episodes played there, 2 here.
    assert summary["complete"] and summary["timing"]["episodes"] == 5
    assert summary["timing"]["lockstep_steps"] == 5 * 50 and "untimed_episodes" not in summary["timing"]
    # A kill between the writes of episodes.parquet and summary.json left the summary behind the rows (the timing
    # of 1 episode, 2 rows): the episode whose time was lost is said, and the timed and untimed add up to the rows.
    (out / "summary.json").write_text(json.dumps({**summary, "timing": {**summary["timing"], "episodes": 1}}))
    full.iloc[:2].to_parquet(out / "episodes.parquet", index=False)
    (out / ".episodes.parquet.k1ll3d.tmp").write_bytes(b"half a file")  # a write kill -9 cut short: cleared
    assert main(argv) == 0
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "episodes.parquet", "summary.json"]
    timing = json.loads((out / "summary.json").read_text())["timing"]
    assert (timing["episodes"], timing["untimed_episodes"]) == (2, 1)
    # Rows this request never plays, or plays once (an edited or mixed file), are refused, not counted.
    for odd in (full.iloc[[0]].assign(episode=3, seed=3), full.iloc[[1]]):
        pd.concat([full, odd]).to_parquet(out / "episodes.parquet", index=False)
        capsys.readouterr()
        assert main(argv) == 2
        assert f"small_jitter/canonical/2 episode {odd['episode'].item()}); its files were edited" in \
            capsys.readouterr().err
    # Episodes of the other object set ("auto" resolved on a machine with YCB's meshes) are not resumed with these.
    full.iloc[:1].assign(object_set="ycb").to_parquet(out / "episodes.parquet", index=False)
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "played with the ycb objects, and object_set='auto' plays the standin objects here" in err
    full.to_parquet(out / "episodes.parquet", index=False)
    # The same request with another worker count, or played as a batch, is the same run; another policy is
    # refused, or replaces it.
    assert main([*argv[:-1], "2"]) == 0
    assert main([*argv, "--num-envs", "2"]) == 0
    assert main([*argv[:2], "random", *argv[3:]]) == 2
    assert "another evaluation request" in capsys.readouterr().err
    assert main([*argv[:2], "random", *argv[3:], "--overwrite"]) == 0
    assert set(pd.read_parquet(out / "episodes.parquet")["policy"]) == {"random"}
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "mine.txt").write_text("keep me")
    assert main([*argv[:-4], "--out", str(tmp_path / "notes")]) == 2
    assert (tmp_path / "notes" / "mine.txt").read_text() == "keep me"


def test_a_player_acts_with_one_torch_thread_unless_told_and_gives_the_process_its_own_back(monkeypatch):
    """Each --workers copy of a policy has one torch thread; so has the copy that plays in-process (two threads
    under passive OpenMP waits doubled a SmolVLA step on 2 cores). OMP_NUM_THREADS wins; close() restores."""
    import torch

    from vla_ladder.evaluation.player import EnvSettings, Player
    from vla_ladder.policies import load_policy

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        player = Player(load_policy("scripted"), EnvSettings())
        assert torch.get_num_threads() == 1
        player.close()
        assert torch.get_num_threads() == 2
        monkeypatch.setenv("OMP_NUM_THREADS", "2")
        player = Player(load_policy("scripted"), EnvSettings())
        assert torch.get_num_threads() == 2
        player.close()
    finally:
        torch.set_num_threads(before)


@pytest.mark.slow
@pytest.mark.parametrize("procs", [["--workers", "2"], ["--num-envs", "2"]])
def test_an_evaluation_killed_with_minus_9_leaves_no_process_behind(procs, tmp_path):
    """Worker processes (a process pool's, a vector env's) end with the evaluation that started them: they idled on
    with ~0.8 GB each after kill -9 of their parent."""
    import signal
    import subprocess
    import sys
    import time

    import psutil

    out, children = tmp_path / "run", []
    proc = subprocess.Popen([sys.executable, "-m", "vla_ladder.cli", "eval", "--policy", "scripted", "--episodes",
                             "400", "--regimes", "full_random", "--out", str(out), *procs],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 600
        while not (out / "episodes.parquet").exists():  # the first flush: the workers are playing
            assert proc.poll() is None and time.monotonic() < deadline, "the evaluation never flushed"
            time.sleep(0.5)
        children = psutil.Process(proc.pid).children(recursive=True)
        assert len(children) >= 2
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        gone, alive = psutil.wait_procs(children, timeout=60)
        assert not alive, [p.cmdline()[:3] for p in alive]
    finally:
        proc.kill()
        for p in children:  # (reparented once their parent died: not this process's children any more)
            if p.is_running():
                p.kill()


def test_a_run_directory_played_under_another_task_contract_is_not_resumed(tmp_path):
    """config.json keeps contract.fingerprint(): a run resumed after the task's episode length, cameras, state or
    action changed would mix episodes of two tasks. Run directories from before it resume."""
    from vla_ladder.contract import CONTROL_HZ, fingerprint
    from vla_ladder.evaluation.runner import open_run_dir

    cfg = EvalConfig("scripted", out=tmp_path / "run", episodes=2)
    assert open_run_dir(cfg) == []
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["contract"] == fingerprint()
    write_json(tmp_path / "run" / "config.json", {**config, "contract": {**config["contract"], "control_hz": 10}})
    with pytest.raises(ValueError, match=rf"holds episodes of another task contract \(control_hz was 10, now "
                                         rf"{CONTROL_HZ}\); evaluate into a new --out, or pass --overwrite"):
        open_run_dir(cfg)
    # Nor one played with the placement sampler before full random stopped placing the target first.
    write_json(tmp_path / "run" / "config.json",
               {**config, "contract": {k: v for k, v in config["contract"].items() if k != "layouts"}})
    with pytest.raises(ValueError, match=r"another task contract \(layouts was 1, now 2\)"):
        open_run_dir(cfg)
    (tmp_path / "run" / "episodes.parquet").write_bytes(b"")  # what --overwrite must clear
    assert open_run_dir(EvalConfig("scripted", out=tmp_path / "run", episodes=2, overwrite=True)) == []
    assert not (tmp_path / "run" / "episodes.parquet").exists()
    write_json(tmp_path / "run" / "config.json", {k: v for k, v in config.items() if k != "contract"})
    assert open_run_dir(cfg) == []  # from before the contract was kept: resumes, and keeps it from now on
    assert json.loads((tmp_path / "run" / "config.json").read_text())["contract"] == fingerprint()


def test_a_resumed_run_reads_old_episodes_with_the_columns_added_since(tmp_path, monkeypatch):
    """A run directory from before a column existed resumes with the value rundir.ADDED_COLUMNS gives it, as
    load_run reads it (it resumed with empty cells before). Here a made-up value, so that the fill is visible."""
    from vla_ladder.evaluation import rundir
    from vla_ladder.evaluation.runner import open_run_dir

    cfg = EvalConfig("scripted", out=tmp_path / "run", grid=ConditionGrid(("small_jitter",)), episodes=2)
    assert open_run_dir(cfg) == []
    old = pd.DataFrame([{"regime": "small_jitter", "split": "canonical", "num_objects": 5, "episode": 0,
                         "success": True}])  # written before tcp_x and tcp_y were kept
    old.to_parquet(tmp_path / "run" / "episodes.parquet")
    monkeypatch.setitem(rundir.ADDED_COLUMNS, "tcp_x", 0.25)
    (row,) = open_run_dir(cfg)
    assert row["tcp_x"] == 0.25 and row["success"] and pd.isna(row["tcp_y"])


def test_a_run_directory_refuses_a_checkpoint_retrained_at_the_same_path(tmp_path):
    """The request names the checkpoint by its path: a run resumed after the model there was retrained would mix two
    models' episodes. config.json keeps the weights' sha256 and the resume compares it."""
    from vla_ladder.evaluation.runner import open_run_dir
    from vla_ladder.policies import weights_identity
    from vla_ladder.policies.ppo import Agent, save_agent

    ckpt = tmp_path / "ckpt"
    save_agent(ckpt / "model.safetensors", Agent(10, 7, (8,)))
    cfg = EvalConfig(f"ppo:{ckpt}", out=tmp_path / "run", episodes=2)
    first = weights_identity(cfg.policy)
    assert open_run_dir(cfg, first) == [] and open_run_dir(cfg, weights_identity(cfg.policy)) == []  # resumes
    assert json.loads((tmp_path / "run" / "config.json").read_text())["policy_weights"] == first

    torch.manual_seed(1)
    save_agent(ckpt / "model.safetensors", Agent(10, 7, (8,)))  # retrained in place
    retrained = weights_identity(cfg.policy)
    assert retrained["sha256"] != first["sha256"]
    with pytest.raises(ValueError, match="holds episodes of other weights at ppo:.*retrained.*new --out"):
        open_run_dir(cfg, retrained)
    (tmp_path / "run" / "episodes.parquet").write_bytes(b"")  # what --overwrite must clear
    again = EvalConfig(f"ppo:{ckpt}", out=tmp_path / "run", episodes=2, overwrite=True)
    assert open_run_dir(again, retrained) == [] and not (tmp_path / "run" / "episodes.parquet").exists()
    assert weights_identity("scripted") is None


def test_the_player_clamps_every_policys_actions_to_the_action_space():
    """A plugin's action past 1 reached ManiSkill, which clips only the rotation's norm: the wrist turned otherwise
    than under lerobot-eval (whose env clamps) or for the same action clamped by the policy itself."""
    import torch

    from vla_ladder.conditions import Condition
    from vla_ladder.evaluation.player import EnvSettings, Job, Player
    from vla_ladder.policies import Policy

    class Constant(Policy):
        def __init__(self, action):
            self.action, self.qpos = torch.tensor([action]), []

        def act(self, obs, instructions):
            self.qpos.append(obs["agent"]["qpos"].clone())
            return self.action.numpy()  # (a plugin may hand back numpy)

    seen = []
    for action in ([0.0, 0.0, 0.0, 1.5, 0.5, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0, 0.5, 0.0, 1.0]):
        policy = Constant(action)
        player = Player(policy, EnvSettings())
        try:
            player.play([Job(Condition("small_jitter", num_objects=2), 0, 3)])
        finally:
            player.close()
        seen.append(torch.stack(policy.qpos))
    assert torch.equal(seen[0], seen[1])
