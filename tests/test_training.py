"""`vla-ladder train` and `vla-ladder grid`: real LeRobot training of tiny policies on a dataset recorded by the
recording pipeline, evaluated in the real simulator (with rendering) by the eval runner. CPU, offline."""

import json
import os
import shlex
import shutil
import subprocess
import sys
import time

import pandas as pd
import pytest

import lerobot_helpers as H
from vla_ladder.cli import main
from vla_ladder.contract import CONTROL_HZ, TRAINED_CONTRACT_FILE, policy_fingerprint
from vla_ladder.experiments.grid import best_row
from vla_ladder.training.train import TrainConfig

EVAL = ["--regimes", "small_jitter", "--num-objects", "2", "--first-seed", "100"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return H.dataset(tmp_path_factory)


def _evaluate(spec: str, out, episodes: int) -> tuple[pd.DataFrame, dict]:
    assert main(["eval", "--policy", spec, "--out", str(out), "--episodes", str(episodes), *EVAL]) == 0
    return pd.read_parquet(out / "episodes.parquet"), json.loads((out / "summary.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["smolvla", "act"])
def test_tiny_policy_trains_saves_reloads_and_evaluates(kind, tmp_path_factory, tmp_path):
    run = H.trained(tmp_path_factory, kind)
    ckpt = run / "checkpoints" / "last" / "pretrained_model"
    for name in ("config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json"):
        assert (ckpt / name).is_file(), name
    record = json.loads((run / "vla_ladder_train.json").read_text())
    assert record["lerobot_train_command"].startswith("lerobot-train ")
    assert "--policy.push_to_hub=false" in record["lerobot_train_command"]
    cfg = json.loads((ckpt / "config.json").read_text())
    assert cfg["type"] == kind and cfg["chunk_size"] == 4
    # the task contract of the data it learned from travels with the checkpoint (eval refuses another)
    assert json.loads((ckpt / TRAINED_CONTRACT_FILE).read_text()) == policy_fingerprint() == \
        record["dataset"]["contract"]
    assert set(cfg["input_features"]) == {"observation.images.hand_camera", "observation.images.fixed_camera",
                                          "observation.state"}

    episodes, summary = _evaluate(f"lerobot:{run}?n_action_steps=2", tmp_path / "eval", episodes=1)
    assert len(episodes) == 1 and episodes["seed"].tolist() == [100]
    assert episodes["instruction"].iloc[0].startswith("grasp the ")
    assert summary["policy"]["type"] == kind and summary["policy"]["n_action_steps"] == 2
    cond = summary["conditions"]["small_jitter/canonical/2"]
    assert cond["n"] == 1 and all(0.0 <= cond[m] <= 1.0 for m in ("success", "grasp_any", "reach"))


@pytest.mark.slow
def test_a_dataset_recorded_under_another_task_contract_is_refused(data, tmp_path):
    """Data recorded at another control rate would teach a policy a task that eval no longer plays: refused before
    training, the field named. A change that only scores episodes differently (the episode length) is not."""
    from vla_ladder.recordings import RECORDING_FILE

    copy = tmp_path / "data"
    shutil.copytree(data, copy)
    state = json.loads((copy / RECORDING_FILE).read_text())
    (copy / RECORDING_FILE).write_text(json.dumps({**state, "contract": {**state["contract"], "episode_steps": 80}}))
    assert TrainConfig(policy_type="act", dataset=copy, out=tmp_path / "run").contract == policy_fingerprint()
    (copy / RECORDING_FILE).write_text(json.dumps({**state, "contract": {**state["contract"], "control_hz": 10}}))
    with pytest.raises(ValueError, match=rf"was recorded under another task contract \(control_hz was 10, now "
                                         rf"{CONTROL_HZ}\): a policy trained on it would be evaluated on a task"):
        TrainConfig(policy_type="act", dataset=copy, out=tmp_path / "run")


@pytest.mark.slow
def test_checkpoints_last_moves_in_one_step(tmp_path):
    """While `vla-ladder train` runs LeRobot's loop, a kill while `checkpoints/last` moves to a new checkpoint leaves
    it at the previous one, never absent (LeRobot's own unlinks it, then links the new one: a run killed between the
    two was taken for one with nothing to keep, and its checkpoints deleted)."""
    import lerobot.scripts.lerobot_train as loop
    from vla_ladder.training.train import stamp_checkpoints

    checkpoints = tmp_path / "checkpoints"
    for name in ("000001", "000002", "000003"):
        (checkpoints / name).mkdir(parents=True)
    own = loop.update_last_checkpoint

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with stamp_checkpoints(None, tmp_path, {}):
        loop.update_last_checkpoint(checkpoints / "000001")
        with pytest.MonkeyPatch.context() as mp, pytest.raises(KeyboardInterrupt):
            mp.setattr(os, "symlink", killed)  # the kill, as the new link is made (Path.symlink_to calls it too)
            loop.update_last_checkpoint(checkpoints / "000002")
        assert os.path.realpath(checkpoints / "last") == str(checkpoints / "000001")
        loop.update_last_checkpoint(checkpoints / "000003")
    assert os.path.realpath(checkpoints / "last") == str(checkpoints / "000003")
    assert os.readlink(checkpoints / "last") == "000003"  # relative, as LeRobot links it: the run can move
    assert sorted(p.name for p in checkpoints.iterdir()) == ["000001", "000002", "000003", "last"]
    assert loop.update_last_checkpoint is own


def test_a_run_with_its_own_optimizer_resumes_with_it(data, tmp_path, monkeypatch, capsys):
    """A resumed run was given the policy's optimizer and scheduler presets whatever the first part used: trained with
    `--use_policy_training_preset=false` and its own (lr 1e-3), it resumed at ACT's 1e-5. It resumes with --out
    spelled otherwise, not with another recording at the same --dataset."""
    shutil.copytree(data, tmp_path / "data")
    data, out = tmp_path / "data", tmp_path / "run"
    own = ["--use_policy_training_preset=false", "--optimizer.type=adamw", "--optimizer.lr=0.001",
           "--scheduler.type=cosine_decay_with_warmup", "--scheduler.num_warmup_steps=0",
           "--scheduler.num_decay_steps=3", "--scheduler.peak_lr=0.001", "--scheduler.decay_lr=0.001"]
    args = [*H.train_args("act", data, out, steps=3), *own]
    args[args.index("--"):args.index("--")] = ["--save-freq", "1"]
    assert main(args) == 0
    checkpoints = out / "checkpoints"
    # As if killed after its second checkpoint
    from vla_ladder.training.train import RUN_FILE
    (out / RUN_FILE).unlink()
    shutil.rmtree(checkpoints / "000003")
    (checkpoints / "last").unlink()
    (checkpoints / "last").symlink_to("000002")
    info = data / "meta" / "info.json"
    original = info.read_text()
    info.write_text(json.dumps({**json.loads(original), "total_episodes": 99}))
    assert main(args) == 2
    assert "holds a training run with other arguments (dataset_size was" in capsys.readouterr().err
    info.write_text(original)
    monkeypatch.chdir(tmp_path)
    assert main([a if a != str(out) else "run" for a in args]) == 0
    groups = json.loads((checkpoints / "000003" / "training_state" / "optimizer_param_groups.json").read_text())
    assert {g["lr"] for g in groups} == {0.001}


@pytest.mark.slow
def test_a_killed_training_resumes_from_its_last_checkpoint(data, tmp_path, capsys):
    """Each checkpoint gets the data's task contract as LeRobot saves it, not when training ends, so a run killed
    after a save leaves a `checkpoints/last` that `lerobot:` can check. The same command then resumes it there
    (LeRobot's resume: the steps before the kill are not trained again), a finished run is left as it is, and
    other arguments on the same directory are refused, naming what differs."""
    from vla_ladder.training.train import REQUEST_FILE, RUN_FILE

    out = tmp_path / "run"
    args = H.train_args("act", data, out, steps=30)
    args[args.index("--"):args.index("--")] = ["--save-freq", "1"]
    proc = subprocess.Popen([sys.executable, "-m", "vla_ladder.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    last = out / "checkpoints" / "last"
    try:
        deadline = time.monotonic() + 300
        while not last.exists():
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline, "no checkpoint in 300 s"
            time.sleep(0.05)
    finally:
        proc.kill()
        proc.wait()
    assert not (out / RUN_FILE).exists()  # killed mid-run: the end-of-run file was never written
    assert json.loads((last / "pretrained_model" / TRAINED_CONTRACT_FILE).read_text()) == policy_fingerprint()
    assert (out / REQUEST_FILE).is_file()
    saved = {p.name: p.stat().st_mtime_ns for p in (out / "checkpoints").glob("0*")}
    killed_at = max(int(n) for n in saved)
    assert killed_at < 30, "the run ended before it was killed: nothing to resume"

    other = H.train_args("act", data, out, steps=31)
    other[other.index("--"):other.index("--")] = ["--save-freq", "1"]
    assert main(other) == 2
    assert "holds a training run with other arguments (steps was 30, now 31)" in capsys.readouterr().err

    # Where it trains is not what it learns: resumed without --device (LeRobot picks), as a study's "auto" may be
    # resolved otherwise on the machine that finishes it.
    assert main(args[:args.index("--device")] + args[args.index("--device") + 2:]) == 0
    steps = sorted(int(p.name) for p in (out / "checkpoints").glob("0*"))
    assert steps == list(range(1, 31))
    for name, mtime in saved.items():  # the checkpoints before the kill were not trained again
        assert (out / "checkpoints" / name).stat().st_mtime_ns == mtime or int(name) == killed_at
    state = json.loads((last / "training_state" / "training_step.json").read_text())
    assert state["step"] == 30 and os.path.realpath(last) == str(out / "checkpoints" / "000030")
    assert all((out / "checkpoints" / f"{s:06d}" / "pretrained_model" / TRAINED_CONTRACT_FILE).is_file()
               for s in steps)
    finished = (out / RUN_FILE).stat().st_mtime_ns
    assert main(args) == 0 and (out / RUN_FILE).stat().st_mtime_ns == finished  # finished: nothing to do

    # Killed during its first save: the request is there, no whole checkpoint. The same command starts afresh.
    for p in [out / RUN_FILE, last, *(out / "checkpoints").glob("0*")]:
        shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
    (out / "checkpoints" / "000001" / "pretrained_model").mkdir(parents=True)
    assert main(args) == 0
    assert sorted(int(p.name) for p in (out / "checkpoints").glob("0*")) == list(range(1, 31))


@pytest.mark.slow
def test_pi05_gets_the_paper_settings_and_a_clear_offline_error(data, tmp_path):
    req = TrainConfig(policy_type="pi05", dataset=data, out=tmp_path / "pi05", pretrained="none")
    assert (req.batch_size, req.chunk_size, req.steps) == (64, 16, 30_000)  # small_jitter data: batch 64
    policy = req.build_config().policy
    assert (policy.dtype, policy.gradient_checkpointing, policy.freeze_vision_encoder,
            policy.train_expert_only, policy.chunk_size, policy.push_to_hub) == \
        ("bfloat16", True, True, True, 16, False)
    assert "--policy.path=lerobot/pi05_base" in TrainConfig(
        policy_type="pi05", dataset=data, out=tmp_path / "p").lerobot_command()
    # Offline, LeRobot's pi05 processor cannot get its PaliGemma tokenizer: the run stops before any work.
    if os.environ.get("HF_HUB_OFFLINE") == "1":
        rc = main(["train", "--policy-type", "pi05", "--dataset", str(data), "--out", str(tmp_path / "pi05"),
                   "--pretrained", "none", "--steps", "1"])
        assert rc == 2 and not (tmp_path / "pi05").exists()
        rc = main(["train", "--policy-type", "pi05", "--dataset", str(data), "--out", str(tmp_path / "pi05")])
        assert rc == 2  # lerobot/pi05_base is not in the local cache


@pytest.mark.slow
def test_a_second_training_run_into_the_same_directory_is_refused(data, tmp_path, capsys):
    """Started again while the first still trains, a run into the same --out removed the first's directory when it
    had not saved a checkpoint yet, or trained beside it; now one line, and the first's files stay."""
    from vla_ladder import files

    out = tmp_path / "run"
    out.mkdir()
    (out / "first.txt").write_text("the first run's")
    with files.writing(out, "training run"):
        assert main(["train", "--policy-type", "act", "--dataset", str(data), "--out", str(out), "--steps", "1",
                     "--pretrained", "none"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith(f"another training run is writing {out} (it holds {files.lock_path(out)}); let it finish "
                        "or stop it, then run this again") and len(err.splitlines()) == 1, err
    assert [p.name for p in out.iterdir()] == ["first.txt"]


def test_bad_input_fails_before_any_work(data, tmp_path, capsys):
    base = ["train", "--dataset", str(data), "--out", str(tmp_path / "run"), "--pretrained", "none"]
    assert main(base + ["--policy-type", "nope"]) == 2
    assert "allowed: act, diffusion" in capsys.readouterr().err
    try:  # a type whose LeRobot extra is missing (diffusion: diffusers) failed after loading the data, 174 lines
        import diffusers  # noqa: F401
    except ImportError:
        assert main(base + ["--policy-type", "diffusion"]) == 2
        err = capsys.readouterr().err.strip()
        assert "--policy-type diffusion needs diffusers, which is not installed here (pip install 'lerobot[diffusion]" \
            in err and len(err.splitlines()) == 1, err
    assert main(["train", "--policy-type", "act", "--dataset", str(tmp_path / "missing"),
                 "--out", str(tmp_path / "run")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "afile").write_text("x")
    assert main(["train", "--policy-type", "act", "--dataset", str(tmp_path / "afile"),
                 "--out", str(tmp_path / "run")]) == 2
    assert "is a file, not a dataset directory" in capsys.readouterr().err
    assert main(base + ["--policy-type", "act", "--device", "tpu"]) == 2
    assert "--device 'tpu': allowed: cpu, cuda, cuda:N, mps" in capsys.readouterr().err
    # Raw flags that would move the run away from --out (it trained there, and --out was left empty) or its data.
    assert main(base + ["--policy-type", "act", "--", f"--output_dir={tmp_path / 'elsewhere'}"]) == 2
    assert "--output_dir after -- is vla-ladder's to set; use --out" in capsys.readouterr().err
    assert main(["grid", "--train.policy-type", "act", "--train.dataset", str(data), "--out", str(tmp_path / "g"),
                 "--", "--dataset.root=/tmp"]) == 2
    assert "--dataset.root after -- is vla-ladder's to set; use --dataset" in capsys.readouterr().err
    assert not (tmp_path / "elsewhere").exists() and not (tmp_path / "g").exists()
    # A type without an action chunk (VQ-BeT) trained the same model under each chunk size's label; and with one
    # size, every evaluation at a horizon was refused (test_a_grid_refuses_the_types_whose_chunk_it_cannot_sweep).
    assert main(["grid", "--train.policy-type", "vqbet", "--train.dataset", str(data), "--out", str(tmp_path / "g"),
                 "--chunk-sizes", "8", "16"]) == 2
    assert "vqbet's LeRobot config has no chunk_size field" in capsys.readouterr().err and not (tmp_path / "g").exists()
    # The grid replaced --train.batch-size, --train.chunk-size and --train.n-action-steps by each model's, unsaid.
    assert main(["grid", "--train.policy-type", "act", "--train.dataset", str(data), "--out", str(tmp_path / "g"),
                 "--train.batch-size", "4", "--train.chunk-size", "10", "--train.n-action-steps", "3"]) == 2
    assert ("the grid sets --train.batch-size, --train.chunk-size, --train.n-action-steps per model; give "
            "--batch-sizes, --chunk-sizes and --horizons instead") in capsys.readouterr().err
    # (flags after -- rebuild the config with the batch and horizon it filled in: those were nobody's)
    assert main(["grid", "--train.policy-type", "act", "--train.dataset", str(data), "--out", str(tmp_path / "g"),
                 "--train.print-command", "--batch-sizes", "8", "--chunk-sizes", "4", "--horizons", "4", "--",
                 "--policy.dim_model=64"]) == 0
    assert "--batch_size=8" in capsys.readouterr().out
    # train took --chunk-size there and changed nothing; and gave TD-MPC n_action_steps 16, which LeRobot refuses.
    assert main(base + ["--policy-type", "vqbet", "--chunk-size", "8"]) == 2
    # (VQ-BeT's chunk is its own action_chunk_size, set after --: the message said it had none)
    assert ("--chunk-size: vqbet's LeRobot config has no chunk_size field for it to set; leave --chunk-size out, and "
            "set its own fields after --") in capsys.readouterr().err
    assert main(base + ["--policy-type", "tdmpc", "--print-command"]) == 0
    assert "n_action_steps" not in capsys.readouterr().out
    # So are those that set what train's own flags set: they won unsaid (a grid's b4_c4 trained with batch 2).
    for flag, own in (("--batch_size=2", "--batch-size"), ("--policy.chunk_size=8", "--chunk-size"),
                      ("--seed=3", "--train-seed"), ("--policy.n_action_steps=2", "--n-action-steps")):
        assert main(["grid", "--train.policy-type", "act", "--train.dataset", str(data), "--out", str(tmp_path / "g"),
                     "--", flag]) == 2
        assert f"{flag.split('=')[0]} after -- is vla-ladder's to set; use {own}" in capsys.readouterr().err
    # An unknown raw flag printed argparse's usage of every LeRobot flag (540 lines); tyro's failure, 5 lines.
    for extra, says in ((["--", "--unknown_flag=3"], "lerobot-train: unrecognized arguments: --unknown_flag=3"),
                        (["--", "--policy.dim_model", "x"], "`dim_model`: Couldn't parse 'x' into an int"),  # (its
                        # value apart, as lerobot-train takes it: it was "expected one argument")
                        (["--", "--policy.dim_model=x"], "`dim_model`: Couldn't parse 'x' into an int"),
                        (["--rename-map", "a"], "--rename-map takes KEY NEW_KEY [KEY NEW_KEY ...], got 'a'")):
        assert main(base + ["--policy-type", "act", *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "run").exists()
    # The grid ignored --train.print-command and trained: now it prints each model's command and writes nothing.
    assert main(["grid", "--train.policy-type", "act", "--train.dataset", str(data), "--train.print-command",
                 "--out", str(tmp_path / "g"), "--batch-sizes", "8", "--chunk-sizes", "4", "8", "--horizons", "4"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [line.split()[0] for line in lines] == ["lerobot-train"] * 2, lines
    assert all("--batch_size=8" in line for line in lines)
    assert "--policy.chunk_size=4" in lines[0] and "--policy.chunk_size=8" in lines[1]
    assert not (tmp_path / "g").exists()

    wrong = tmp_path / "wrong"
    (wrong / "meta").mkdir(parents=True)
    info = json.loads((data / "meta" / "info.json").read_text())
    info["features"]["observation.state"]["shape"] = [9]
    del info["features"]["observation.images.fixed_camera"]
    (wrong / "meta" / "info.json").write_text(json.dumps(info))
    assert main(["train", "--policy-type", "act", "--dataset", str(wrong), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "observation.state has shape (9,), expected (15,)" in err
    assert "observation.images.fixed_camera missing" in err

    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "x").write_text("")
    assert main(base[:-4] + ["--out", str(tmp_path / "busy"), "--policy-type", "act"]) == 2
    assert "exists and holds no training run of vla-ladder" in capsys.readouterr().err
    assert (tmp_path / "busy" / "x").is_file()
    assert main(base + ["--policy-type", "act", "--chunk-size", "4", "--n-action-steps", "8"]) == 2
    assert not (tmp_path / "run").exists()
    # Refused before the model is built: LeRobot refused a negative worker count after it, trained on the CPU when
    # asked for a missing GPU (a warning said so), and an output it cannot create failed at the first checkpoint.
    import torch

    capsys.readouterr()
    unwritable = [*base[:4], "/proc/vla-ladder-run", *base[5:]]
    cases = [(base, ["--num-workers", "-4"], "--num-workers must be >= 0 (0: load data in the training process)"),
             (unwritable, [], "--out '/proc/vla-ladder-run'")]
    if not torch.cuda.is_available():
        cases.append((base, ["--device", "cuda"], "--device cuda needs a CUDA GPU and none is visible"))
    for argv, extra, words in cases:  # one step, in-process loading: a check that let one through costs little
        extra = [*extra, "--steps", "1", *([] if "--num-workers" in extra else ["--num-workers", "0"])]
        assert main([*argv, "--policy-type", "act", *extra]) == 2, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "run").exists()


def test_a_diffusion_grid_trains_and_evaluates_only_the_horizons_it_executes(data, tmp_path, capsys, monkeypatch):
    """Diffusion's chunk starts n_obs_steps - 1 steps back, so it executes at most chunk - n_obs_steps + 1 of its
    actions: the grid trained it with n_action_steps = chunk and evaluated horizon = chunk, which every evaluation
    of the checkpoint refuses, after the training."""
    from vla_ladder.experiments.grid import GridConfig, units
    from vla_ladder.training import train as train_module

    assert [train_module.max_action_steps("diffusion", c) for c in (8, 16)] == [7, 15]  # LeRobot's n_obs_steps: 2
    assert train_module.max_action_steps("diffusion", 16, ["--policy.n_obs_steps", "4"]) == 13
    assert train_module.max_action_steps("act", 16) == 16
    # Planning needs no diffusers (only building the model does): its check is left out where it is not installed.
    monkeypatch.setattr(train_module, "check_policy_packages", lambda policy_type: None)
    cfg = GridConfig(out=tmp_path / "g", train=TrainConfig(policy_type="diffusion", dataset=data),
                     batch_sizes=(4,), chunk_sizes=(8, 16), horizons=(4, 8, 16))
    trains, evals = units(cfg)
    assert [(u.config["chunk_size"], u.config["n_action_steps"]) for u in trains] == [(8, 7), (16, 15)]
    assert [(c, h) for _, c, h, _ in evals] == [(8, 4), (16, 4), (16, 8)]
    # A grid none of whose horizons it executes, and a training asked for more: refused in one line, before work.
    for argv, says in ((["grid", "--train.policy-type", "diffusion", "--train.dataset", str(data), "--out",
                         str(tmp_path / "g"), "--chunk-sizes", "16", "--horizons", "16"],
                        "no horizon in [16] fits a chunk size in [16] (diffusion executes at most chunk - "
                        "n_obs_steps + 1 actions of a chunk: 15 of 16)"),
                       (["train", "--policy-type", "diffusion", "--dataset", str(data), "--out", str(tmp_path / "run"),
                         "--chunk-size", "16", "--n-action-steps", "16"],
                        "--n-action-steps (16) cannot exceed 15 for diffusion")):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and len(err.splitlines()) == 1, err
        # With one observation step it executes the whole chunk: the flags after -- are read by the first check
        # (the command line's config was built, and refused, without them before).
        assert main([*argv, "--train.print-command" if argv[0] == "grid" else "--print-command", "--",
                     "--policy.n_obs_steps=1"]) == 0
        assert "--policy.n_action_steps=16" in capsys.readouterr().out
    assert not (tmp_path / "g").exists() and not (tmp_path / "run").exists()


def test_train_refuses_a_cuda_device_past_the_gpus(data, tmp_path, monkeypatch, capsys):
    """`--device cuda:3` on a machine with one GPU passed every check and failed once LeRobot moved the model there
    (torch's "invalid device ordinal"); it is refused in one line naming the GPUs there are, before any work. No GPU
    is here, so torch is told of one (the refusal needs nothing else of it); cuda:0 gets past the check."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    argv = ["train", "--policy-type", "act", "--dataset", str(data), "--out", str(tmp_path / "run"), "--pretrained",
            "none", "--steps", "1", "--num-workers", "0", "--device"]
    assert main([*argv, "cuda:3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith("--device cuda:3: this machine has 1 GPU (cuda:0)"), err
    assert not (tmp_path / "run").exists()
    assert TrainConfig(policy_type="act", dataset=data, device="cuda:0").device == "cuda:0"


def test_a_grid_refuses_the_types_whose_chunk_it_cannot_sweep(data, tmp_path, capsys):
    """A grid trains each model with the chunk size in the config's chunk field and evaluates each horizon as
    `lerobot:CKPT?n_action_steps=H`. TD-MPC (no chunk; its n_action_steps of 1 is all LeRobot takes without MPC) was
    trained with n_action_steps 16, which LeRobot refused; VQ-BeT's config has no n_action_steps, so every
    evaluation was refused ("unrecognized arguments"): each after its recording or training. `train` trains them."""
    import dataclasses

    from vla_ladder.training.train import config_class, policy_types, sweep_problem, sweepable_types

    def has(t, *names):
        return set(names) <= {f.name for f in dataclasses.fields(config_class(t))}
    assert sweepable_types() == [t for t in policy_types() if has(t, "n_action_steps") and (
        has(t, "chunk_size") or t in ("diffusion", "multi_task_dit") and has(t, "horizon"))]
    assert {"act", "diffusion", "smolvla", "pi05"} <= set(sweepable_types())
    assert sweep_problem("act") is None and sweep_problem("diffusion") is None
    if "lingbot_va" in policy_types():  # its chunk_size and n_action_steps are read-only: "has no chunk_size" was false
        assert isinstance(config_class("lingbot_va").chunk_size, property)
        assert sweep_problem("lingbot_va").startswith("lingbot_va's LeRobot config has no chunk_size field and no "
                                                      "n_action_steps field to set, so ")
    for policy_type, says in (("tdmpc", "tdmpc's LeRobot config has no chunk_size field to set,"),
                              ("vqbet", "vqbet's LeRobot config has no chunk_size field and no n_action_steps field to "
                                        "set,")):
        assert main(["grid", "--train.policy-type", policy_type, "--train.dataset", str(data), "--out",
                     str(tmp_path / "g")]) == 2
        err = capsys.readouterr().err.strip()
        assert f"--train.policy-type {policy_type}: {says}" in err and "allowed: act, diffusion, " in err, err
        assert len(err.splitlines()) == 1 and not (tmp_path / "g").exists(), err
        assert main(["train", "--policy-type", policy_type, "--dataset", str(data), "--out", str(tmp_path / "run"),
                     "--print-command"]) == 0  # alone it trains as before
        assert f"--policy.type={policy_type}" in capsys.readouterr().out


def test_multi_task_dit_sizes_its_horizon_as_its_chunk_like_diffusion(data, tmp_path, monkeypatch):
    """Multi-task DiT's chunk is a `horizon` that starts n_obs_steps - 1 steps back, as diffusion's: the grid left its
    horizon at LeRobot's 32 under the label of each chunk size, and trained and evaluated horizons up to the label."""
    from vla_ladder.experiments.grid import GridConfig, units
    from vla_ladder.training import train as train_module

    for policy_type in ("diffusion", "multi_task_dit"):  # LeRobot's action indices: n_obs_steps - 1 back, then on
        indices = list(train_module.config_class(policy_type)(horizon=16, n_action_steps=1).action_delta_indices)
        assert len(indices) == 16 and sum(i >= 0 for i in indices) == train_module.max_action_steps(policy_type, 16)
    monkeypatch.setattr(train_module, "check_policy_packages", lambda policy_type: None)  # (diffusers)
    cfg = GridConfig(out=tmp_path / "g", train=TrainConfig(policy_type="multi_task_dit", dataset=data),
                     batch_sizes=(4,), chunk_sizes=(8, 16), horizons=(4, 8, 16))
    trains, evals = units(cfg)
    assert [(u.config["chunk_size"], u.config["n_action_steps"]) for u in trains] == [(8, 7), (16, 15)]
    assert [(c, h) for _, c, h, _ in evals] == [(8, 4), (16, 4), (16, 8)]
    policy = TrainConfig(**{**trains[1].config, "dataset": data}).build_config().policy
    assert (policy.horizon, policy.n_action_steps) == (16, 15)


def test_diffusion_chunk_sizes_are_multiples_of_its_unet_down_sampling(data, tmp_path, capsys, monkeypatch):
    """LeRobot's diffusion U-Net halves the chunk at each of its len(down_dims) stages, and its config refuses a
    horizon that is not a multiple of 2 ** len(down_dims): a study or grid with chunk 4 (the micro preset's) failed
    at its train unit, after the recording."""
    from vla_ladder.training import train as train_module

    diffusion = train_module.config_class("diffusion")
    for args, dims in (((), None), (["--policy.down_dims", "[64,128]"], (64, 128))):
        multiple = train_module.chunk_multiple("diffusion", args)
        assert multiple == (8 if dims is None else 4)
        for c in range(1, 33):  # the rule as LeRobot's config checks it
            try:
                diffusion(horizon=c, n_action_steps=1, **({} if dims is None else {"down_dims": dims}))
                assert c % multiple == 0, c
            except ValueError:
                assert c % multiple, c
    assert train_module.chunk_multiple("act") == train_module.chunk_multiple("multi_task_dit") == 1
    monkeypatch.setattr(train_module, "check_policy_packages", lambda policy_type: None)  # (diffusers)
    says = ("diffusion's chunk (horizon) must be a multiple of 8, the factor its U-Net down-samples it by "
            "(2 ** len(down_dims) in LeRobot); allowed: 8, 16, 24, 32, ...")
    for argv, said in ((["train", "--policy-type", "diffusion", "--dataset", str(data), "--out", str(tmp_path / "run"),
                         "--chunk-size", "4"], f"--chunk-size 4: {says}"),
                       (["grid", "--train.policy-type", "diffusion", "--train.dataset", str(data), "--out",
                         str(tmp_path / "g"), "--chunk-sizes", "4", "8", "12", "--horizons", "3"],
                        f"--chunk-sizes 4, 12: {says}")):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert said in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "run").exists() and not (tmp_path / "g").exists()
    # A U-Net of two stages takes a chunk of 4 (3 of its actions executed).
    assert main(["grid", "--train.policy-type", "diffusion", "--train.dataset", str(data), "--out", str(tmp_path / "g"),
                 "--chunk-sizes", "4", "--horizons", "3", "--train.print-command", "--",
                 "--policy.down_dims=[64,128]"]) == 0
    assert "--policy.horizon=4 --policy.n_action_steps=3" in capsys.readouterr().out


def test_flags_after_dashes_are_read_in_either_spelling():
    """lerobot-train takes `--flag value` as `--flag=value`: train's checks read both (own_flag, and the --policy
    values that size a chunk), the last of a flag given twice winning, as it wins in lerobot-train."""
    from vla_ladder.training.train import _policy_flag, own_flag

    args = ["--policy.dim_model", "64", "--policy.n_obs_steps=3", "--policy.n_obs_steps", " 4 ", "--steps", "5"]
    assert _policy_flag(args, "n_obs_steps") == "4" and _policy_flag(args, "dim_model") == "64"
    assert _policy_flag(args, "down_dims") is None
    assert own_flag("act", args) == "--steps" and own_flag("act", args[:5]) is None
    # The chunk field is the type's: diffusion's --policy.horizon is train's, TD-MPC's planning horizon is not.
    assert [own_flag(t, ["--policy.horizon", "8"]) for t in ("diffusion", "multi_task_dit", "tdmpc")] == \
        ["--policy.horizon", "--policy.horizon", None]


def test_a_policy_package_is_looked_for_by_its_import_name(tmp_path, monkeypatch):
    """LeRobot asks for a package whose module is named otherwise by both names (wall_x:
    `require_package("qwen-vl-utils", extra="wallx", import_name="qwen_vl_utils")`); train looked for a module named
    after the distribution, which no import can find, so it refused wall_x with its extra installed. A LeRobot plugin
    policy (registered as @PreTrainedConfig.register_subclass registers one) asks for PyYAML, imported as yaml."""
    from lerobot.configs.policies import PreTrainedConfig

    from vla_ladder.training.train import check_policy_packages

    plugin = tmp_path / "vla_ladder_test_plugin"
    plugin.mkdir()
    (plugin / "__init__.py").write_text("")
    (plugin / "configuration_probe.py").write_text("class ProbeConfig:\n    pass\n")
    (plugin / "modeling_probe.py").write_text(
        "from lerobot.utils.import_utils import require_package\n\n\nclass ProbePolicy:\n    def __init__(self):\n"
        "        require_package('PyYAML', extra='probe', import_name='yaml')\n"
        "        require_package('no-such-dist', extra='probe', import_name='no_such_module')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    from vla_ladder_test_plugin.configuration_probe import ProbeConfig

    monkeypatch.setitem(PreTrainedConfig.get_known_choices(), "probe", ProbeConfig)
    with pytest.raises(ValueError, match=r"^--policy-type probe needs no-such-dist, which is not installed here "
                                         r"\(pip install 'lerobot\[probe\]'\)$"):
        check_policy_packages("probe")


def test_best_is_success_then_grasp_then_reach():
    df = pd.DataFrame([
        {"batch_size": 64, "chunk_size": 8, "n_action_steps": 1, "success": 0.5, "grasp_any": 0.9, "reach": 0.1},
        {"batch_size": 64, "chunk_size": 8, "n_action_steps": 4, "success": 0.6, "grasp_any": 0.7, "reach": 0.2},
        {"batch_size": 128, "chunk_size": 8, "n_action_steps": 4, "success": 0.6, "grasp_any": 0.8, "reach": 0.0},
        {"batch_size": 128, "chunk_size": 16, "n_action_steps": 8, "success": 0.6, "grasp_any": 0.8, "reach": 0.3},
    ])
    best = best_row(df)
    assert (best["batch_size"], best["chunk_size"], best["n_action_steps"]) == (128, 16, 8)


@pytest.mark.slow
def test_grid_2x2_keeps_every_run_and_picks_the_best(data, tmp_path_factory, tmp_path, capsys):
    vlm = H.tiny_vlm(tmp_path_factory)
    out = tmp_path / "grid"
    argv = ["grid", "--train.policy-type", "smolvla", "--train.dataset", str(data), "--out", str(out),
            "--train.pretrained", "none", "--train.steps", "1", "--train.num-workers", "0", "--train.device", "cpu",
            "--batch-sizes", "2", "4", "--chunk-sizes", "4", "--horizons", "2", "4", "--eval.episodes", "1",
            *[f"--eval.{a[2:]}" if a.startswith("--") else a for a in EVAL],
            "--", *H.tiny_policy_flags("smolvla", vlm)]
    assert main(argv) == 0
    grid = json.loads((out / "grid.json").read_text())
    df = pd.read_parquet(out / "grid.parquet")
    assert sorted(zip(df.batch_size, df.chunk_size, df.n_action_steps)) == \
        [(2, 4, 2), (2, 4, 4), (4, 4, 2), (4, 4, 4)]
    for row in df.itertuples():
        summary = json.loads((out / "runs" / f"b{row.batch_size}_c{row.chunk_size}" /
                              f"eval_h{row.n_action_steps}" / "summary.json").read_text())
        assert summary["policy"]["n_action_steps"] == row.n_action_steps
        assert summary["first_seed"] == 100  # every run sees the same seeded episodes
        assert row.success == summary["conditions"]["small_jitter/canonical/2"]["success"]
    expected = best_row(df)
    assert {k: grid["best"][k] for k in ("batch_size", "chunk_size", "n_action_steps")} == \
        {k: expected[k] for k in ("batch_size", "chunk_size", "n_action_steps")}
    assert len(grid["runs"]) == 4
    # The best's rates are the best of 4 on the same episodes: grid.json and the output say how to measure it on
    # the next ones, and that command runs.
    held_out = shlex.split(grid["best_held_out_command"])
    assert held_out[held_out.index("--first-seed") + 1] == "101" and held_out[held_out.index("--policy") + 1] == \
        grid["best"]["policy"]
    assert "the best of 4 runs on the same episodes" in capsys.readouterr().out
    assert main(held_out[1:]) == 0
    assert json.loads((out / "best_held_out" / "summary.json").read_text())["first_seed"] == 101

    # A rerun finds every model and evaluation done and only rewrites the tables.
    stamp = (out / "runs" / "b2_c4" / "eval_h2" / "summary.json").stat().st_mtime_ns
    assert main(argv) == 0
    assert (out / "runs" / "b2_c4" / "eval_h2" / "summary.json").stat().st_mtime_ns == stamp
    # So does one evaluating with other workers (the same episodes), also where grid_settings.json holds the
    # evaluation's whole config, as grids before 2026-11-28 wrote it.
    settings = out / "grid_settings.json"
    saved = json.loads(settings.read_text())
    saved["eval"] = {**saved["eval"], "workers": 0, "num_envs": 1, "overwrite": False, "out": None}
    for key in ("alone", "switch_at"):  # (fields added since: their absence meant the default)
        del saved["eval"][key]
    settings.write_text(json.dumps(saved))
    assert main([*argv[:argv.index("--")], "--eval.workers", "1", *argv[argv.index("--"):]]) == 0
    assert "workers" not in json.loads(settings.read_text())["eval"]
    # Other settings in the same directory are refused, naming the one that differs.
    other = list(argv)
    other[other.index("--train.steps") + 1] = "2"
    assert main(other) == 2
    assert "other settings" in (err := capsys.readouterr().err) and "its train.steps differs" in err


@pytest.mark.slow
def test_the_grid_refuses_to_evaluate_on_the_scenes_it_trains_on(data, tmp_path, capsys):
    """`data` was recorded on seeds 0 and 1: a seed is a scene (its layout, target and instruction, and nearly the
    same scene in every jitter regime), so a grid evaluating on them measured the models on their training demos."""
    base = ["grid", "--train.policy-type", "act", "--train.dataset", str(data), "--out", str(tmp_path / "g"),
            "--batch-sizes", "2", "--chunk-sizes", "4", "--horizons", "4", "--eval.episodes", "1",
            "--eval.num-objects", "2", "--eval.workers", "1", "--train.steps", "1", "--train.num-workers", "0",
            "--train.device", "cpu"]
    tiny = ["--", *H.tiny_policy_flags("act")]
    assert main([*base, "--eval.regimes", "small_jitter", *tiny]) == 2  # --eval.first-seed 0, the default, as record's
    err = capsys.readouterr().err.strip()
    assert "the training data" in err and "seeds 0-1" in err and "--eval.first-seed 2 or above" in err, err
    assert len(err.splitlines()) == 1 and not (tmp_path / "g").exists()
    # In another regime seed 0 is nearly the same scene; from seed 1 on, the grid plays a training scene itself.
    assert main([*base, "--eval.regimes", "medium_jitter", *tiny]) == 2
    assert main([*base, "--eval.regimes", "small_jitter", "--eval.first-seed", "1", *tiny]) == 2
    assert capsys.readouterr().err.count("--eval.first-seed 2 or above") == 2
