"""A LeRobot checkpoint whose declared inputs GraspObject-v1 cannot feed is refused before any episode, every
mismatch named, whatever the policy type (the VLAs used to pass with a missing camera).

The checkpoints are LeRobot's own config classes saved as LeRobot saves them (config.json, and for renames the
policy_preprocessor.json that `lerobot-train --rename_map` writes) without weights: the check must come before
any weight is read, so a checkpoint that passes it stops at the missing weights file instead."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vla_ladder.contract import ACTION_KEY, CAMERA_KEYS, IMAGE_SHAPE, STATE_KEY

pytestmark = pytest.mark.slow  # imports LeRobot's policy stack (~30 s on a busy 2-core machine)

TYPES = ["act", "smolvla", "pi0", "pi05", "pi0_fast", "diffusion"]
HAND, FIXED = CAMERA_KEYS


def _checkpoint(root: Path, kind: str, cameras: dict[str, tuple], state: tuple | None = (15,),
                action: tuple = (7,), rename: dict[str, str] | None = None, **options) -> Path:
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_policy_config

    inputs = {k: PolicyFeature(FeatureType.VISUAL, shape) for k, shape in cameras.items()}
    if state is not None:
        inputs[STATE_KEY] = PolicyFeature(FeatureType.STATE, state)
    cfg = make_policy_config(kind, input_features=inputs, device="cpu", **options,
                             output_features={ACTION_KEY: PolicyFeature(FeatureType.ACTION, action)})
    root.mkdir(parents=True)
    cfg._save_pretrained(root)
    if rename is not None:  # the step LeRobot's processor saves when trained with --rename_map
        (root / "policy_preprocessor.json").write_text(json.dumps({"name": "policy_preprocessor", "steps": [
            {"registry_name": "rename_observations_processor", "config": {"rename_map": rename}}]}))
    return root


def _refusal(path: Path) -> str:
    from vla_ladder.policies.lerobot import LeRobotPolicy

    with pytest.raises(ValueError) as e:
        LeRobotPolicy(path, device="cpu")
    return str(e.value)


CHW = (3, *IMAGE_SHAPE[:2])  # the env's cameras as LeRobot declares images
ENV_CAMERAS = {HAND: CHW, FIXED: CHW}


@pytest.mark.parametrize("kind", TYPES)
def test_every_mismatch_is_named_for_every_policy_type(kind, tmp_path):
    top = HAND.replace("hand_camera", "top")
    bad = _checkpoint(tmp_path / "bad", kind, {HAND: CHW, top: CHW}, state=(6,), action=(6,))
    msg = _refusal(bad)
    assert f"LeRobot checkpoint ({kind}) does not match GraspObject-v1" in msg
    assert f"camera {top} is not one the env has" in msg
    assert f"state {STATE_KEY} has shape (6,), the env provides (15,)" in msg
    assert "action has shape (6,), the env takes (7,)" in msg
    assert "--rename-map" in msg and "\n" not in msg

    # The same checkpoint with GraspObject-v1's features passes the check and stops at the absent weights.
    good = _checkpoint(tmp_path / "good", kind, ENV_CAMERAS)
    assert "has config.json but no model.safetensors" in _refusal(good)


@pytest.mark.parametrize("kind", ["act", "smolvla"])
def test_image_sizes_matter_only_to_policies_that_do_not_resize(kind, tmp_path):
    small = _checkpoint(tmp_path / "small", kind, {HAND: (3, 96, 96), FIXED: (3, 96, 96)})
    msg = _refusal(small)
    if kind == "act":
        assert f"camera {HAND} has shape (3, 96, 96), the env renders {CHW}" in msg
    else:  # SmolVLA resizes every image to its own resolution
        assert "no model.safetensors" in msg


def test_renames_are_the_saved_ones_and_blank_camera_slots_are_allowed(tmp_path):
    top, side = HAND.replace("hand_camera", "top"), HAND.replace("hand_camera", "side")
    renamed = _checkpoint(tmp_path / "renamed", "smolvla", {top: CHW, side: CHW},
                          rename={HAND: top, FIXED: side})
    assert "no model.safetensors" in _refusal(renamed)
    half = _checkpoint(tmp_path / "half", "smolvla", {top: CHW, side: CHW}, rename={HAND: top})
    msg = _refusal(half)
    assert f"with the saved rename map {{'{HAND}': '{top}'}}" in msg and f"camera {side} is not one" in msg
    assert "none of its cameras" not in msg
    none = _checkpoint(tmp_path / "none", "pi05", {top: (3, 224, 224)})
    assert "none of its cameras" in _refusal(none)
    blank = _checkpoint(tmp_path / "blank", "smolvla", ENV_CAMERAS, empty_cameras=1)
    assert "no model.safetensors" in _refusal(blank)


def test_a_vla_fine_tuned_from_its_base_is_judged_by_its_training_data(tmp_path):
    """LeRobot fine-tunes a VLA under its base's declared inputs (smolvla_base: a 6-d state, cameras camera1-3), and
    trains it on what the data holds: the 15-d state, padded to max_state_dim, and the two cameras renamed. Its
    normalizer's statistics say so, and the checkpoint is used (it was refused: state (6,), camera3 not fed); a
    camera its data did have, or a state of another size there, is still refused."""
    import torch
    from safetensors.torch import save_file

    slots = {HAND.replace("hand_camera", f"camera{i}"): CHW for i in (1, 2, 3)}
    rename = {FIXED: HAND.replace("hand_camera", "camera1"), HAND: HAND.replace("hand_camera", "camera2")}

    def fine_tuned(name: str, data: dict[str, tuple]) -> Path:
        ckpt = _checkpoint(tmp_path / name, "smolvla", slots, state=(6,), rename=rename)
        save_file({f"{k}.mean": torch.zeros(shape) for k, shape in {**data, ACTION_KEY: (7,)}.items()},
                  ckpt / "policy_preprocessor_step_5_normalizer_processor.safetensors")
        return ckpt

    env_data = {STATE_KEY: (15,), HAND: (3, 1, 1), FIXED: (3, 1, 1)}
    assert "no model.safetensors" in _refusal(fine_tuned("ours", env_data))
    third = HAND.replace("hand_camera", "camera3")
    msg = _refusal(fine_tuned("three", {**env_data, third: (3, 1, 1)}))
    assert f"camera {third} is not one the env has" in msg and "has shape (6,)" not in msg
    assert f"state {STATE_KEY} has shape (6,)" in _refusal(fine_tuned("six", {**env_data, STATE_KEY: (6,)}))


def test_other_inputs_and_a_missing_state_or_action(tmp_path):
    from lerobot.configs.types import FeatureType

    env_state = STATE_KEY.replace("state", "environment_state")
    ckpt = _checkpoint(tmp_path / "env_state", "act", ENV_CAMERAS)
    cfg = json.loads((ckpt / "config.json").read_text())
    cfg["input_features"][env_state] = {"type": FeatureType.ENV.value, "shape": [10]}
    cfg["output_features"] = {}
    (ckpt / "config.json").write_text(json.dumps(cfg))
    msg = _refusal(ckpt)
    assert f"input {env_state} (ENV, shape (10,)) is not provided" in msg and "action has shape None" in msg
    stateless = _checkpoint(tmp_path / "stateless", "act", ENV_CAMERAS, state=None)
    assert "no model.safetensors" in _refusal(stateless)  # a policy that ignores the state is fine


def test_a_cuda_device_without_a_gpu_is_refused(tmp_path):
    import torch

    from vla_ladder.policies.lerobot import LeRobotPolicy

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    good = _checkpoint(tmp_path / "good", "act", ENV_CAMERAS)
    with pytest.raises(ValueError, match=r"device=cuda needs a CUDA GPU and none is visible; use \?device=cpu"):
        LeRobotPolicy(good, device="cuda")


def test_a_cuda_device_past_the_gpus_is_refused_by_eval_and_serve_policy(tmp_path, monkeypatch, capsys):
    """`?device=cuda:3` on a machine with one GPU passed the checks and failed once the model was moved there, after
    the checkpoint loaded; eval and serve-policy refuse it in one line naming the GPUs there are, before any work.
    No GPU is here, so torch is told of some (the refusal needs nothing else of it)."""
    import torch
    from safetensors.torch import save_file

    from vla_ladder.checks import check_torch_device
    from vla_ladder.cli import main
    from vla_ladder.policies.lerobot import LeRobotPolicy

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    good = _checkpoint(tmp_path / "good", "act", ENV_CAMERAS)
    save_file({}, good / "model.safetensors")  # (the commands check the weights file is there before the device)
    spec = f"lerobot:{good}?device=cuda:3"
    for argv in (["eval", "--policy", spec, "--out", str(tmp_path / "run"), "--episodes", "1"],
                 ["serve-policy", "--policy", spec, "--port", "0"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].endswith("device=cuda:3: this machine has 1 GPU (cuda:0)"), err
    assert not (tmp_path / "run").exists()
    assert check_torch_device("cuda:0", "device=cuda:0", "") == "cuda:0"  # the GPU there is, taken
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 4)
    with pytest.raises(ValueError, match=r"^device=cuda:4: this machine has 4 GPUs \(cuda:0 to cuda:3\)$"):
        LeRobotPolicy(good, device="cuda:4")


def test_eval_refuses_a_mismatched_checkpoint_before_its_run_directory(tmp_path):
    """`vla-ladder eval` in a fresh process (nothing of LeRobot imported yet): a checkpoint whose cameras the env
    cannot feed, weights and all, is refused in one line by check_spec, and the run directory is never written."""
    import subprocess
    import sys

    small = _checkpoint(tmp_path / "small", "act", {HAND: (3, 96, 96), FIXED: (3, 96, 96)})
    (small / "model.safetensors").write_bytes(b"")  # present: the mismatch, not a missing file, must stop it
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "vla_ladder.cli", "eval", "--policy", f"lerobot:{small}",
                           "--episodes", "1", "--out", str(out)], capture_output=True, text=True, timeout=600)
    err = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(err) == 1, done.stderr[-3000:]
    assert f"camera {HAND} has shape (3, 96, 96), the env renders {CHW}" in err[0]
    assert not out.exists()


def test_a_checkpoint_trained_under_another_task_contract_is_refused(tmp_path):
    """Every shape fits, and the camera looked through another lens when its data was recorded: the file `train`
    writes beside the checkpoint names the difference, before any weight is read. The same contract passes to the
    next check (the missing weights), and so does a checkpoint without the file (trained elsewhere)."""
    from vla_ladder.contract import TRAINED_CONTRACT_FILE, policy_fingerprint

    ckpt = _checkpoint(tmp_path / "ckpt", "act", ENV_CAMERAS)
    assert "no model.safetensors" in _refusal(ckpt)
    trained = policy_fingerprint()
    trained["cameras"][1]["fov_deg"] = 60.0
    (ckpt / TRAINED_CONTRACT_FILE).write_text(json.dumps(trained))
    msg = _refusal(ckpt)
    assert "was trained under another task contract (cameras[1].fov_deg was 60.0, now 45.0):" in msg
    assert "no model.safetensors" not in msg
    (ckpt / TRAINED_CONTRACT_FILE).write_text(json.dumps(policy_fingerprint()))
    assert "no model.safetensors" in _refusal(ckpt)


@pytest.mark.parametrize("kind", ["diffusion", "multi_task_dit"])
def test_a_horizon_chunk_plays_no_more_actions_a_chunk_than_it_holds(kind, tmp_path):
    """Diffusion's and multi_task_dit's chunk of `horizon` actions starts n_obs_steps - 1 steps back: they queue
    horizon - n_obs_steps + 1 of them, so n_action_steps=16 on a horizon of 16 played 15 a chunk while the run said
    16 (multi_task_dit's was not checked)."""
    from vla_ladder.policies.lerobot import checked_config

    path = _checkpoint(tmp_path / "c", kind, ENV_CAMERAS, horizon=16, n_obs_steps=2, n_action_steps=8)
    for h in (16, 40):
        with pytest.raises(ValueError, match=rf"^n_action_steps must be from 1 to 15 for this {kind} checkpoint "
                                             r"\(horizon 16 - n_obs_steps 2 \+ 1\), got " + str(h)):
            checked_config(path, h, device="cpu")
    with pytest.raises(ValueError, match="no model.safetensors"):  # 15 passes, and stops at the absent weights
        checked_config(path, 15, device="cpu")
    saved = _checkpoint(tmp_path / "saved", kind, ENV_CAMERAS, horizon=16, n_obs_steps=2, n_action_steps=16)
    with pytest.raises(ValueError, match=r"from 1 to 15 .* got 16"):  # its own n_action_steps too
        checked_config(saved, device="cpu")
