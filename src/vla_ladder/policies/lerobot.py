"""Any LeRobot checkpoint as a GraspObject-v1 `Policy`: `--policy lerobot:CHECKPOINT_DIR[?n_action_steps=H]`.

The checkpoint is loaded with the pre/post-processors LeRobot saved next to it (normalisation statistics,
tokenizer, camera renames), so the policy sees observations exactly as in training: both 256x256 cameras
as contiguous float CHW in [0, 1], the 15-d proprioceptive state and the instruction as `task`. The execution horizon is
the checkpoint's `n_action_steps`, which `?n_action_steps=H` (or the `n_action_steps` argument) overrides.

Flow-matching policies (SmolVLA, pi0, pi0.5) turn noise into an action chunk. LeRobot's `select_action` draws
that noise for the whole batch from torch's global generator, so an episode's actions would depend on which
episodes share its batch (`eval --num-envs`). Here each episode's noise is drawn from its own generator, seeded
by the episode's seed and the chunk's index, and passed to LeRobot's `predict_action_chunk`; the chunk's first
`n_action_steps` actions are queued as `select_action` queues them (and the observation is preprocessed only
when a chunk is predicted). So an episode gets the same noise alone or in any batch, on the CPU or the GPU.
`?noise_seed=K` (K > 0) draws another stream for every episode: the same scenes played again with other noise
measure how much of a policy's result is its own sampling rather than the scene (docs/evaluation.md). Other
policies queue chunks the same way (ACT, without noise), or act through LeRobot's own `select_action` when a chunk
depends on more than the current observation (diffusion, VQ-BeT, ACT with temporal ensembling). As in `lerobot-eval`,
a checkpoint whose config says `use_amp` acts under torch.autocast (float16 on CUDA, bfloat16 on the CPU);
`?use_amp=true|false` overrides it. The same code runs one CPU env or a batch of GPU envs.
"""

from __future__ import annotations

import collections
import contextlib
import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from vla_ladder.checks import TORCH_DEVICE, ascii_digits, check_torch_device
from vla_ladder.contract import (ACTION_DIM, ACTION_KEY, CAMERAS, CAMERA_KEYS, IMAGE_SHAPE, POLICY_FIELDS, STATE_DIM,
                                 STATE_KEY, TRAINED_CONTRACT_FILE, contract_changes)
from vla_ladder.files import own_tempdir
from vla_ladder.policies import Policy, instruction_text, parse_options, positive_int

ENV_IMAGE_SHAPE = (IMAGE_SHAPE[2], IMAGE_SHAPE[0], IMAGE_SHAPE[1])  # CHW, as LeRobot declares visual features
# Policies that resize every camera image to their own resolution (LeRobot's VLAs): a checkpoint trained on another
# image size still gets images it can use. Every camera they declare must still be fed, except the blank
# `empty_camera_i` slots their `empty_cameras` option adds on purpose, and, for a checkpoint fine-tuned from a base
# (which keeps the base's declared inputs), a camera its training data never had; they pad the state to
# max_state_dim, so the base's declared state size does not matter where the training data's was the env's.
RESIZES_IMAGES = {"smolvla", "pi0", "pi05", "pi0_fast"}
# Policies whose predict_action_chunk takes the flow-matching noise, (batch, chunk_size, max_action_dim), and which
# see one observation a step: their chunks are drawn here from per-episode noise (module docstring).
NOISE_PER_EPISODE = {"smolvla", "pi0", "pi05"}
# Policies whose action chunk can depend on the current observation only (and the noise); chunks_from_one_observation
# says whether a checkpoint's does.
ONE_OBSERVATION_CHUNKS = ("smolvla", "pi0", "pi05", "act")
WEIGHTS_FILE = "model.safetensors"
# Policies whose chunk of `horizon` actions starts n_obs_steps - 1 steps back, at the observed past: LeRobot keeps
# actions n_obs_steps - 1 onwards of it, n_action_steps of them but unchecked (a slice past the end is short).
HORIZON_CHUNKS = ("diffusion", "multi_task_dit")


def executable_steps(policy_type: str | None, chunk: int, n_obs_steps: int) -> int:
    """The most actions a policy of this type executes of a chunk of `chunk` (its largest n_action_steps): the
    chunk, but chunk - n_obs_steps + 1 for HORIZON_CHUNKS. More would play fewer a chunk than the run says (15 a
    chunk for n_action_steps 16 on a horizon of 16)."""
    return chunk - n_obs_steps + 1 if policy_type in HORIZON_CHUNKS else chunk


def chunks_from_one_observation(policy_type: str | None, temporal_ensemble_coeff: float | None = None) -> bool:
    """Whether a policy's action chunk depends on the current observation only (and its noise): then `act` queues
    the first n_action_steps of each chunk itself, as LeRobot's select_action does, and preprocesses an observation
    once a chunk instead of every step; and a policy server answers each request alone (serving.py). Not ACT with
    temporal ensembling (it blends overlapping chunks every step), nor diffusion or VQ-BeT (they keep a history)."""
    return policy_type in ONE_OBSERVATION_CHUNKS and temporal_ensemble_coeff is None


def _bool(value: str) -> bool:
    if value.lower() not in ("true", "false"):
        raise ValueError(f"expected true or false, got {value!r}")
    return value.lower() == "true"


def _noise_seed(value: str) -> int:
    if not ascii_digits(value) or int(value) >= 2**63:
        raise ValueError(f"expected an integer from 0 to 2**63 - 1, got {value!r}")
    return int(value)


def _device(value: str) -> str:
    if not TORCH_DEVICE.fullmatch(value):
        raise ValueError(f"expected cpu, cuda, cuda:N or mps, got {value!r}")
    return value


QUERY_KEYS = {"n_action_steps": positive_int, "device": _device, "instruction": instruction_text, "use_amp": _bool,
              "noise_seed": _noise_seed}
CONFIG_OPTIONS = ("n_action_steps", "device", "use_amp")
"""The options that override the checkpoint's own config (checked_config); the others are the policy's."""


def resolve_checkpoint(path: str | Path) -> Path:
    """A training run dir, a checkpoint dir or a pretrained_model dir -> the dir holding config.json."""
    path = Path(path)
    for cand in (path, path / "pretrained_model", path / "checkpoints" / "last" / "pretrained_model"):
        if (cand / "config.json").is_file():
            return cand
    raise ValueError(f"no LeRobot checkpoint at {str(path)!r}: expected config.json in it, in "
                     "pretrained_model/ or in checkpoints/last/pretrained_model/ (a `vla-ladder train` run dir)")


def read_saved_config(path: Path) -> dict:
    """The config.json of checkpoint directory `path` (from resolve_checkpoint), or ValueError naming the file."""
    try:
        saved = json.loads((path / "config.json").read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path / 'config.json'}: not a JSON config ({e})") from None
    if not isinstance(saved, dict):
        raise ValueError(f"{path / 'config.json'}: not a JSON config (a {type(saved).__name__}, not an object)")
    return saved


def check_checkpoint(path: str | Path) -> Path:
    """resolve_checkpoint, and the weights are there too (a checkpoint copied without them fails here, in one
    line, rather than inside LeRobot's loader)."""
    found = resolve_checkpoint(path)
    if not (found / WEIGHTS_FILE).is_file():
        raise ValueError(f"the LeRobot checkpoint {str(found)!r} has config.json but no {WEIGHTS_FILE}: copy the "
                         "checkpoint directory whole, or point at another checkpoints/<step>/pretrained_model")
    return found


def checkpoint_name(path: str | Path) -> tuple[tuple[str, ...], str | None]:
    """What names the model of checkpoint spec `path`, from the path as written (never resolved: that would name the
    machine's folders): (the parts of its training run's folder, its step). RUN/checkpoints/STEP[/pretrained_model]
    and RUN (which plays RUN/checkpoints/last) -> (RUN's parts, STEP, "2" for LeRobot's 000002); any other folder ->
    (its parts, None). "last" is read as the step it stands for where the checkpoint is on this machine."""
    model = Path(path).parent if Path(path).name == "pretrained_model" else Path(path)
    if model.parent.name == "checkpoints":
        run, step_dir = model.parent.parent, model
    else:
        run, step_dir = model, model / "checkpoints" / "last" if (model / "checkpoints" / "last").is_dir() else None
    step = step_dir.name if step_dir else None
    if step == "last":
        try:  # (what LeRobot wrote beside the weights; "last" is a link to the step's folder, or a copy of it)
            step = str(json.loads((step_dir / "training_state" / "training_step.json").read_text())["step"])
        except (OSError, ValueError, KeyError, TypeError):
            pass
    step = str(int(step)) if step and ascii_digits(step) else step
    return run.parts[1 if run.anchor else 0:], step


def check_env_compatible(cfg, rename_map: dict[str, str], trained: dict[str, tuple] | None = None) -> None:
    """ValueError naming every input the policy declares that GraspObject-v1 does not provide, and every size that
    differs, for every policy type. `rename_map` (env key -> policy key) is the one saved with the checkpoint:
    renames are explicit, never guessed. `trained` (trained_inputs: policy key -> shape) is what the checkpoint's
    training data held: LeRobot fine-tunes a VLA under its base's declared inputs (smolvla_base: a 6-d state and
    three cameras), so for those the data, not the declaration, says what it learned from."""
    from lerobot.configs import FeatureType
    from lerobot.utils.constants import OBS_IMAGES

    fed_cameras = {rename_map.get(k, k) for k in CAMERA_KEYS}
    fed_state = rename_map.get(STATE_KEY, STATE_KEY)
    blank_slots = {f"{OBS_IMAGES}.empty_camera_{i}" for i in range(getattr(cfg, "empty_cameras", 0) or 0)}
    resizes = cfg.type in RESIZES_IMAGES
    cameras = [k for k, ft in cfg.input_features.items() if ft.type is FeatureType.VISUAL and k not in blank_slots]
    problems: list[str] = []
    if cameras and not fed_cameras & set(cameras):
        problems.append(f"none of its cameras {cameras} is one the env provides")
    for key, ft in cfg.input_features.items():
        shape = tuple(ft.shape)
        if ft.type is FeatureType.VISUAL:
            if key in blank_slots:
                continue
            if key not in fed_cameras:
                if not (resizes and trained is not None and key not in trained):  # else: never fed in training
                    problems.append(f"camera {key} is not one the env has")
            elif not resizes and shape != ENV_IMAGE_SHAPE:
                problems.append(f"camera {key} has shape {shape}, the env renders {ENV_IMAGE_SHAPE}")
        elif ft.type is FeatureType.STATE and key == fed_state:
            padded = resizes and trained is not None and trained.get(key) == (STATE_DIM,) and \
                STATE_DIM <= getattr(cfg, "max_state_dim", 0)
            if shape != (STATE_DIM,) and not padded:
                problems.append(f"state {key} has shape {shape}, the env provides ({STATE_DIM},)")
        else:
            problems.append(f"input {key} ({ft.type.value}, shape {shape}) is not provided")
    action = cfg.output_features.get(ACTION_KEY)
    if action is None or tuple(action.shape) != (ACTION_DIM,):
        problems.append(f"action has shape {None if action is None else tuple(action.shape)}, the env takes "
                        f"({ACTION_DIM},)")
    if problems:
        renames = f" (with the saved rename map {rename_map})" if rename_map else ""
        hint = ("; a checkpoint with other camera names is fine-tuned with `vla-ladder train --rename-map`, which "
                "saves the map with it" if any("camera" in p for p in problems) else "")
        raise ValueError(f"LeRobot checkpoint ({cfg.type}) does not match GraspObject-v1{renames}: "
                         + "; ".join(problems) + f". The env provides {', '.join(CAMERA_KEYS)} {ENV_IMAGE_SHAPE}, "
                         f"{STATE_KEY} ({STATE_DIM},) and takes action ({ACTION_DIM},){hint}")


def checked_config(path: str | Path, n_action_steps: int | None = None, device: str | None = None,
                   use_amp: bool | None = None):
    """The checkpoint's LeRobot config with these overrides, once every check that needs no weights loaded has
    passed: the overrides fit the config, the device is there, the env provides every input it declares at the
    size it declares, the weights file is there. `check_spec` runs it before any long work; the
    policy runs it again when it loads."""
    import lerobot.policies  # noqa: F401  (registers every policy type's config, which from_pretrained looks up)
    from lerobot.configs.policies import PreTrainedConfig

    path = resolve_checkpoint(path)
    saved = read_saved_config(path)
    chunk = saved.get("chunk_size")
    if n_action_steps is not None and isinstance(chunk, int) and not 1 <= n_action_steps <= chunk:
        # draccus would say only "Couldn't instantiate class ...Config using the given arguments"
        raise ValueError(f"n_action_steps must be from 1 to the checkpoint's chunk size ({chunk}), got "
                         f"{n_action_steps}")
    horizon, n_obs, steps = (saved.get(k) for k in ("horizon", "n_obs_steps", "n_action_steps"))
    steps = steps if n_action_steps is None else n_action_steps
    kind = saved.get("type")
    if kind in HORIZON_CHUNKS and all(isinstance(v, int) for v in (horizon, n_obs, steps)) and \
            not 1 <= steps <= (most := executable_steps(kind, horizon, n_obs)):
        raise ValueError(f"n_action_steps must be from 1 to {most} for this {kind} checkpoint (horizon {horizon} - "
                         f"n_obs_steps {n_obs} + 1), got {steps}")
    overrides = [] if n_action_steps is None else [f"--n_action_steps={int(n_action_steps)}"]
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    check_torch_device(device, f"device={device}", "use ?device=cpu, or leave device out (cuda when there is one, "
                       "else cpu)")
    overrides.append(f"--device={device}")
    if use_amp is not None:
        overrides.append(f"--use_amp={str(bool(use_amp)).lower()}")
    try:
        with own_tempdir():  # LeRobot leaves a copy of the config in the temp directory otherwise
            cfg = PreTrainedConfig.from_pretrained(path, cli_overrides=overrides)
    except Exception as e:  # draccus wraps the config's own checks (e.g. n_action_steps > chunk_size)
        raise ValueError(f"cannot use the checkpoint {str(path)!r} with {overrides}: {e}") from e
    rename_map = _saved_rename_map(path)
    check_env_compatible(cfg, rename_map, trained_inputs(path, rename_map))
    check_trained_contract(path)
    check_checkpoint(path)  # last: a mismatch is named even where the weights are missing
    return cfg


def check_noise_seed(policy_type: str, noise_seed: int) -> None:
    """Another noise stream (noise_seed > 0) exists only for the types that draw their noise per episode: for the
    others it would be recorded and play the same episodes."""
    if noise_seed and policy_type not in NOISE_PER_EPISODE:
        raise ValueError(f"noise_seed picks a stream of per-episode flow-matching noise, which only "
                         f"{', '.join(sorted(NOISE_PER_EPISODE))} draw; this checkpoint is {policy_type}")


def check_trained_contract(path: Path) -> None:
    """ValueError when the checkpoint was trained on data recorded under another task contract (its
    TRAINED_CONTRACT_FILE, which `vla-ladder train` writes, differs from this one in contract.POLICY_FIELDS): the
    shapes may all fit and the rate, the cameras' view or the meaning of a state entry still differ. A checkpoint
    without the file (trained elsewhere, or before checkpoints kept it) is not checked."""
    if changed := contract_changes(trained_contract(path), POLICY_FIELDS):
        raise ValueError(f"the LeRobot checkpoint {str(path)!r} was trained under another task contract "
                         f"({'; '.join(changed)}): its numbers here would be those of a task it never saw; evaluate "
                         "it with the vla-ladder version it was trained with, or train it again")


def trained_contract(path: Path) -> dict | None:
    """The task contract a checkpoint was trained under (its TRAINED_CONTRACT_FILE), None where it does not say."""
    saved = path / TRAINED_CONTRACT_FILE
    return json.loads(saved.read_text()) if saved.is_file() else None


def training_seeds(path: Path) -> set[int]:
    """The seeds of the demonstrations checkpoint `path` was trained on: those of its train_config.json's dataset
    (the episodes it trained on, where it names them) when that is a vla-ladder recording on this machine; empty
    where the checkpoint or the dataset does not say."""
    from vla_ladder.recordings import RECORDING_FILE, recorded_seeds

    try:
        data = json.loads((path / "train_config.json").read_text())["dataset"]
        root = data.get("root")
        if not root or not Path(root, RECORDING_FILE).is_file():
            return set()
        return recorded_seeds(root, data.get("episodes"))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):  # (a file of another shape says nothing)
        return set()


def trained_inputs(path: Path, rename_map: dict[str, str]) -> dict[str, tuple] | None:
    """The observations the checkpoint's training data held, under the policy's names, with their statistics'
    shapes (the state's is its size), read from the normalizer its preprocessor saved; None without one."""
    from safetensors import safe_open

    found = sorted(Path(path).glob("policy_preprocessor_step_*_normalizer_processor.safetensors"))
    if not found:
        return None
    with safe_open(str(found[0]), framework="pt") as f:
        keys = {k.rsplit(".", 1)[0]: tuple(f.get_slice(k).get_shape()) for k in f.keys() if k.endswith(".mean")}
    return {rename_map.get(k, k): shape for k, shape in keys.items() if k.startswith("observation.")}


def _saved_rename_map(path: Path) -> dict[str, str]:
    pre = path / "policy_preprocessor.json"
    if not pre.is_file():
        return {}
    for step in json.loads(pre.read_text()).get("steps", []):
        if step.get("registry_name") == "rename_observations_processor":
            return dict(step.get("config", {}).get("rename_map", {}))
    return {}


class LeRobotPolicy(Policy):
    """A LeRobot PreTrainedPolicy with its saved processors, batched over envs."""

    obs_mode = "rgb"

    def __init__(self, path: str | Path, n_action_steps: int | None = None, device: str | None = None,
                 instruction: str | None = None, use_amp: bool | None = None, noise_seed: int = 0):
        """`instruction` replaces every episode's instruction (an instruction-blind policy is trained and played
        with one fixed text, contract.BLIND_INSTRUCTION). `noise_seed` picks the stream of flow-matching noise (0:
        the one every run before the option used)."""
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        self.path = resolve_checkpoint(path)
        cfg = checked_config(self.path, n_action_steps, device, use_amp)
        self.policy = get_policy_class(cfg.type).from_pretrained(self.path, config=cfg).eval()
        self.config = self.policy.config
        self.device = torch.device(self.config.device)
        self.preprocessor, self.postprocessor = make_pre_post_processors(
            self.config, pretrained_path=self.path,
            preprocessor_overrides={"device_processor": {"device": str(self.device)}})
        self.name = f"lerobot-{cfg.type}"
        self.instruction = instruction
        if noise_seed < 0:
            raise ValueError(f"noise_seed must be >= 0, got {noise_seed}")
        check_noise_seed(cfg.type, noise_seed)
        self.noise_seed = int(noise_seed)
        self._num_envs = 0
        self._seeds: list[int] = []
        self._chunks = 0  # chunks predicted since the last reset
        self._queue: collections.deque[torch.Tensor] = collections.deque()

    @property
    def n_action_steps(self) -> int | None:
        return getattr(self.config, "n_action_steps", None)

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> None:
        # LeRobot keeps one action queue for the whole batch, so envs restart together (episodes have a
        # fixed length of 50 steps, so they always do).
        if env_ids is not None and self._num_envs and len(set(env_ids)) < self._num_envs:
            raise ValueError("LeRobot policies keep one action queue per batch: reset all envs together")
        self.policy.reset()
        # Seeds are the envs' in env order (row i's noise is episode i's): given in another order, put them back.
        order = list(range(len(seeds))) if env_ids is None else [int(i) for i in env_ids]
        if sorted(order) != list(range(len(seeds))):
            raise ValueError(f"reset all envs together: env_ids {order} are not each of the {len(seeds)} envs once")
        self._seeds, self._chunks = [int(s) for _, s in sorted(zip(order, seeds))], 0
        self._queue.clear()
        if len(seeds):
            torch.manual_seed(int(seeds[0]))  # any other randomness (a diffusion policy's noise): per batch

    def noise(self, num_envs: int) -> torch.Tensor | None:
        """The flow-matching noise of the next chunk, (num_envs, chunk_size, max_action_dim): row i from a
        generator seeded by episode i's seed and the chunk's index (None, LeRobot's own draw, without seeds; None
        for a policy that takes no noise)."""
        if len(self._seeds) != num_envs or self.config.type not in NOISE_PER_EPISODE:
            return None
        return torch.stack([self.episode_noise(seed, self._chunks) for seed in self._seeds]).to(self.device)

    def episode_noise(self, seed: int, chunk: int) -> torch.Tensor:
        """The noise of chunk `chunk` of the episode of seed `seed`, (chunk_size, max_action_dim), on the CPU: what
        `act` draws for it in any batch, and what a policy server draws for one request (policies/serving.py)."""
        shape = (self.config.chunk_size, self.config.max_action_dim)
        extra = (self.noise_seed,) if self.noise_seed else ()  # stream 0 keeps the entropy it always had
        state = np.random.SeedSequence((int(seed), int(chunk), *extra)).generate_state(1, np.uint64)[0]
        return torch.randn(shape, generator=torch.Generator().manual_seed(int(state)))

    def batch(self, obs: Any, instructions: Sequence[str]) -> dict[str, Any]:
        """Env observation -> LeRobot's raw observation dict (before the saved preprocessor)."""
        out: dict[str, Any] = {}
        for cam in CAMERAS:
            rgb = obs["sensor_data"][cam.name]["rgb"]
            # Contiguous NCHW, as lerobot-eval's preprocess_observation makes it: the permuted view converted
            # as it stands is channels-last, on which a CPU convolution rounds otherwise (ACT: 3e-7 on a chunk).
            image = torch.as_tensor(rgb).permute(0, 3, 1, 2)
            out[cam.key] = image.to(self.device, torch.float32, memory_format=torch.contiguous_format) / 255.0
        out[STATE_KEY] = torch.as_tensor(obs["extra"]["proprio"]).to(self.device, torch.float32)
        out["task"] = [self.instruction or str(t) for t in instructions]
        return out

    def _precision(self):
        """torch.autocast where the config says use_amp (what lerobot-eval does), else nothing."""
        return torch.autocast(self.device.type) if self.config.use_amp else contextlib.nullcontext()

    @torch.no_grad()
    def act(self, obs: Any, instructions: Sequence[str]) -> torch.Tensor:
        proprio = torch.as_tensor(obs["extra"]["proprio"])
        self._num_envs = proprio.shape[0]
        if not chunks_from_one_observation(self.config.type, getattr(self.config, "temporal_ensemble_coeff", None)):
            with self._precision():
                batch = self.preprocessor(self.batch(obs, instructions))
                action = self.postprocessor(self.policy.select_action(batch))
        else:
            if not self._queue:
                chunk = self.predict_chunk(obs, instructions, noise=self.noise(proprio.shape[0]))
                self._chunks += 1
                self._queue.extend(chunk[:, :self.n_action_steps].transpose(0, 1))
            action = self._queue.popleft()
        return action.to(proprio.device, torch.float32).reshape(proprio.shape[0], ACTION_DIM).clamp(-1, 1)

    def predict_chunk(self, obs: Any, instructions: Sequence[str], noise: torch.Tensor | None = None) -> torch.Tensor:
        """One full action chunk (N, chunk, 7), unnormalised, from `noise` for a flow-matching policy (None: LeRobot
        draws it); what `act` queues and the latency benchmark times."""
        with torch.no_grad(), self._precision():
            batch = self.preprocessor(self.batch(obs, instructions))
            kwargs = {} if noise is None else {"noise": noise}
            return self.postprocessor(self.policy.predict_action_chunk(batch, **kwargs))

    def describe(self) -> dict:
        return {"name": self.name, "type": self.config.type, "checkpoint": str(self.path),
                "chunk_size": getattr(self.config, "chunk_size", getattr(self.config, "horizon", None)),
                "n_action_steps": self.n_action_steps, "device": str(self.device), "instruction": self.instruction,
                "use_amp": bool(self.config.use_amp), "noise_seed": self.noise_seed}


def parse_arg(arg: str) -> tuple[str, dict]:
    """"PATH?n_action_steps=8&device=cpu" -> (PATH, {"n_action_steps": 8, "device": "cpu"})."""
    return parse_options("lerobot", arg, QUERY_KEYS)


def make_policy(arg: str | None, **kwargs) -> LeRobotPolicy:
    """Factory for `load_policy("lerobot:PATH[?n_action_steps=H&device=D&instruction=TEXT&use_amp=B&noise_seed=K]")`."""
    if not arg:
        raise ValueError("policy 'lerobot' needs a checkpoint: lerobot:CHECKPOINT_DIR[?n_action_steps=H]")
    path, options = parse_arg(arg)
    # Every option the spec may give may be given as a keyword too (load_policy(spec, noise_seed=1)); only
    # CONFIG_OPTIONS were taken, so instruction= and noise_seed= were dropped unsaid and the default played.
    options.update({k: v for k, v in kwargs.items() if k in QUERY_KEYS and v is not None})
    return LeRobotPolicy(path, **options)
