"""`vla-ladder train`: train or fine-tune a LeRobot policy on a recorded GraspObject-v1 dataset with LeRobot's own
training loop (lerobot.scripts.lerobot_train), the paper's defaults and fully offline.

The command composes `lerobot-train` flags, parses them with LeRobot's own config parser into a
TrainPipelineConfig and runs LeRobot's `train` in this process, so every LeRobot flag is accepted after
`--` and the equivalent `lerobot-train` command is saved with the run. Multi-GPU: LeRobot always trains
through an `accelerate` Accelerator, so `accelerate launch -m vla_ladder.cli train ...` spreads it over GPUs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import logging
import os
import re
import shlex
import time
from urllib.error import URLError
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, ClassVar

import tyro

from vla_ladder import files
from vla_ladder.checks import TORCH_DEVICE, check_output_dir, check_seed, check_torch_device
from vla_ladder.contract import CAMERA_KEYS, TRAINED_CONTRACT_FILE
from vla_ladder.policies.lerobot import HORIZON_CHUNKS, executable_steps
from vla_ladder.training.dataset import check_features, dataset_condition, dataset_contract, read_info

log = logging.getLogger(__name__)

# lerobot-train flags that `train` sets itself from its own (raw flags after -- may not): where the run writes
# (and so what a rerun resumes and what eval finds) and what it trains on.
OWN_FLAGS = {"--output_dir": "--out", "--dataset.root": "--dataset",
             "--dataset.repo_id": "--dataset", "--resume": "the same command again (it resumes)",
             "--config_path": "train's own flags",
             # what the run is, as its request, its log and a grid's labels say: given after --, they won unsaid
             "--batch_size": "--batch-size", "--steps": "--steps", "--seed": "--train-seed",
             "--save_freq": "--save-freq", "--log_freq": "--log-freq", "--num_workers": "--num-workers",
             "--wandb.enable": "--wandb", "--policy.device": "--device", "--policy.n_action_steps": "--n-action-steps",
             "--policy.chunk_size": "--chunk-size"}
# Paper, appendix "VLA implementation details": checkpoints and per-policy settings.
DEFAULT_PRETRAINED = {"smolvla": "lerobot/smolvla_base", "pi05": "lerobot/pi05_base"}
POLICY_PRESETS: dict[str, dict[str, str]] = {
    "pi05": {"dtype": "bfloat16", "gradient_checkpointing": "true", "freeze_vision_encoder": "true",
             "train_expert_only": "true"},
}
# Batch size by placement regime: 128 in full random, 64 in the jitter regimes and the pairings.
BATCH_FOR_REGIME = {"full_random": 128}
DEFAULT_BATCH = 64
# The config field that holds the action chunk length, where it is not called chunk_size: the types whose chunk of
# `horizon` actions starts n_obs_steps - 1 steps back, at the observed past (max_action_steps).
CHUNK_FIELD = dict.fromkeys(HORIZON_CHUNKS, "horizon")
DEFAULT_CHUNK = 16
DEFAULT_TRAIN_SEED = 1000
"""lerobot-train's --seed where none is given (a study's policies with train_seed null train with it)"""
# Tokenizers the policies' saved processors load by name; offline they must be local or in the HF cache.
PALIGEMMA_TOKENIZER = "google/paligemma-3b-pt-224"
TOKENIZER_OF = {"pi0": lambda cfg: PALIGEMMA_TOKENIZER, "pi05": lambda cfg: PALIGEMMA_TOKENIZER,
                "pi0_fast": lambda cfg: PALIGEMMA_TOKENIZER, "smolvla": lambda cfg: cfg.vlm_model_name}
# Dataset camera -> pretrained camera slot when a checkpoint names its cameras differently
# (lerobot/smolvla_base and pi05_base: observation.images.camera1/2/3; the paper feeds camera1 and camera2).
CAMERA_ORDER = (CAMERA_KEYS[1], CAMERA_KEYS[0])  # fixed camera first, then the wrist camera
PAPER_RENAME = dict(zip(CAMERA_ORDER, ("observation.images.camera1", "observation.images.camera2")))


def policy_types() -> list[str]:
    """Every policy type registered in LeRobot (including installed plugins)."""
    import lerobot.policies  # noqa: F401  (registers the built-in configs)
    from lerobot.configs.policies import PreTrainedConfig

    return sorted(PreTrainedConfig.get_known_choices())


def joined_flags(args) -> tuple[str, ...]:
    """lerobot-train flags as --flag=value: `--policy.dim_model 64`, which lerobot-train takes too, split the value
    from its flag when train sorted the flags into the policy's and the pipeline's."""
    out: list[str] = []
    for a in args:
        if out and not a.startswith("--") and out[-1].startswith("--") and "=" not in out[-1]:
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return tuple(out)


def flag_values(args) -> list[tuple[str, str]]:
    """(flag, value) of each of joined_flags(args), in order: `--policy.n_obs_steps 3` and `--policy.n_obs_steps=3`
    are both ("--policy.n_obs_steps", "3"); a flag without a value has "" (lerobot-train refuses it itself)."""
    return [(flag, value) for flag, _, value in (a.partition("=") for a in joined_flags(args))]


def check_policy_packages(policy_type: str) -> None:
    """ValueError in one line when a policy type needs a package that is not installed: LeRobot's policies ask for
    their extra's packages (`require_package("diffusers", extra="diffusion")`) only when the model is built, after the
    dataset has loaded, in a 170-line traceback. Each is looked for as LeRobot looks for it, by its import name where
    that is another (wall_x's `require_package("qwen-vl-utils", ..., import_name="qwen_vl_utils")`)."""
    import inspect
    import re
    import sys

    from lerobot.policies.factory import get_policy_class
    from lerobot.utils.import_utils import is_package_available

    try:
        module = sys.modules[get_policy_class(policy_type).__module__]
    except ImportError as e:
        raise ValueError(f"--policy-type {policy_type} cannot load here: {e}") from None
    asks = re.findall(r"require_package\(\s*[\"']([\w.-]+)[\"'],\s*extra=[\"']([\w-]+)[\"']"
                      r"(?:,\s*import_name=[\"']([\w.]+)[\"'])?", inspect.getsource(module))
    for package, extra, import_name in asks:
        if not is_package_available(package, import_name or None):
            raise ValueError(f"--policy-type {policy_type} needs {package}, which is not installed here "
                             f"(pip install 'lerobot[{extra}]')")


def config_class(policy_type: str):
    """LeRobot's config class of a registered policy type."""
    import lerobot.policies  # noqa: F401  (registers the built-in configs)
    from lerobot.configs.policies import PreTrainedConfig

    return PreTrainedConfig.get_choice_class(policy_type)


def config_fields(policy_type: str) -> set[str]:
    """The field names of LeRobot's config class of a registered policy type."""
    return {f.name for f in dataclasses.fields(config_class(policy_type))}


def chunk_name(policy_type: str) -> str:
    """The name of the policy config's chunk field (chunk_size, or CHUNK_FIELD's), whether or not its config has it."""
    return CHUNK_FIELD.get(policy_type, "chunk_size")


def config_default(policy_type: str, name: str):
    """The default of field `name` of LeRobot's config for `policy_type`, read from the dataclass: making one runs
    its __post_init__, which picks a device and logs about it."""
    field = next(f for f in dataclasses.fields(config_class(policy_type)) if f.name == name)
    return field.default_factory() if field.default is dataclasses.MISSING else field.default


def chunk_field(policy_type: str) -> str | None:
    """The policy config's field that --chunk-size sets (chunk_size, or CHUNK_FIELD's), None where it has none
    (vqbet, tdmpc, ...: --chunk-size changes nothing there)."""
    name = chunk_name(policy_type)
    return name if name in config_fields(policy_type) else None


def sweepable_types() -> list[str]:
    """The policy types a grid or study can train per chunk size and evaluate per execution horizon: their config
    has the chunk field that --chunk-size sets and n_action_steps, which `lerobot:CKPT?n_action_steps=H` sets."""
    return [t for t in policy_types() if chunk_field(t) is not None
            and "n_action_steps" in config_fields(t)]


def sweep_problem(policy_type: str) -> str | None:
    """Why a grid or study cannot sweep this type's chunk size and execution horizon (one line naming the types it
    can), or None. Refused before any work: TD-MPC (a planning horizon, no chunk) was trained with n_action_steps 16,
    which LeRobot refuses, and VQ-BeT's config has no n_action_steps, so every evaluation at a horizon was refused."""
    if policy_type in sweepable_types():
        return None
    fields = config_fields(policy_type)
    missing = [f for f in (chunk_name(policy_type), "n_action_steps") if f not in fields]
    # "field": a chunk of its own under another name (vqbet's action_chunk_size, fastwam's action_horizon) or a
    # read-only one (lingbot_va's chunk_size and n_action_steps are properties) is not one the grid can set
    return (f"{policy_type}'s LeRobot config has no {' field and no '.join(missing)} field to set, so the chunk sizes "
            f"and execution horizons cannot be swept (train it alone with `vla-ladder train`); allowed: "
            f"{', '.join(sweepable_types())}")


def _policy_flag(lerobot_args, name: str) -> str | None:
    """The value of the last --policy.NAME in `lerobot_args` (None where it is not given)."""
    given = [value.strip() for flag, value in flag_values(lerobot_args) if flag == f"--policy.{name}"]
    return given[-1] if given else None


def max_action_steps(policy_type: str, chunk_size: int, lerobot_args=()) -> int:
    """The most actions a policy of this type executes of a chunk of `chunk_size` (the largest n_action_steps it
    takes): the chunk, but for the types whose chunk is a `horizon` (diffusion, multi_task_dit) the chunk less
    n_obs_steps - 1, as their chunk starts that many steps back, at the observed past. The grid and the study train
    and evaluate no horizon above it, where one failed after training. n_obs_steps: LeRobot's default, or
    --policy.n_obs_steps in `lerobot_args`. The rule is the one every evaluation of a checkpoint checks
    (policies.lerobot.executable_steps)."""
    if policy_type not in CHUNK_FIELD:
        return chunk_size
    n_obs = config_default(policy_type, "n_obs_steps")
    if (value := _policy_flag(lerobot_args, "n_obs_steps")) is not None and re.fullmatch(r"[0-9]+", value):
        n_obs = int(value)
    return executable_steps(policy_type, chunk_size, n_obs)


def chunk_multiple(policy_type: str, lerobot_args=()) -> int:
    """What every chunk size of this type must be a multiple of: 1, but for a U-Net over the chunk (diffusion's,
    whose config has `down_dims`) the factor it down-samples the chunk by, 2 ** len(down_dims), which LeRobot's
    config checks (DiffusionConfig.__post_init__; 8 by default). down_dims: LeRobot's default, or
    --policy.down_dims in `lerobot_args`."""
    if policy_type not in CHUNK_FIELD or "down_dims" not in config_fields(policy_type):
        return 1
    value = _policy_flag(lerobot_args, "down_dims")
    stages = len(config_default(policy_type, "down_dims")) if value is None else len(re.findall(r"[0-9]+", value))
    return 2 ** stages


def unfit_chunks(policy_type: str, chunk_sizes, lerobot_args=()) -> str | None:
    """Why some chunk sizes cannot be trained (a one-line reason after the sizes, naming those allowed), or None: a
    diffusion chunk off its U-Net's down-sampling was refused by LeRobot when the run was built, a study's after its
    recording."""
    m = chunk_multiple(policy_type, lerobot_args)
    bad = [c for c in chunk_sizes if c % m]
    if not bad:
        return None
    return (f"{', '.join(map(str, bad))}: {policy_type}'s chunk ({chunk_field(policy_type)}) must be a multiple of "
            f"{m}, the factor its U-Net down-samples it by (2 ** len(down_dims) in LeRobot); allowed: "
            f"{', '.join(str(m * k) for k in range(1, 5))}, ...")


def own_flag(policy_type: str, lerobot_args) -> str | None:
    """The first flag of `lerobot_args` that `train` sets itself (OWN_FLAGS, and the chunk field of this type:
    --policy.chunk_size, diffusion's --policy.horizon), None where there is none: given after --, they would move the
    run away from what vla-ladder keeps and resumes, so train refuses them, and a study config before any work."""
    chunk_flag = f"--policy.{chunk_name(policy_type)}"
    return next((flag for flag, _ in flag_values(lerobot_args) if flag in OWN_FLAGS or flag == chunk_flag), None)


def unfit_horizons(policy_type: str, chunk_sizes, horizons, lerobot_args=()) -> str | None:
    """Why no horizon fits any chunk size (a one-line reason), or None when one does: a grid or study refuses it
    before training models that none of its horizons could evaluate."""
    fits = {c: max_action_steps(policy_type, c, lerobot_args) for c in chunk_sizes}
    if any(h <= m for h in horizons for m in fits.values()):
        return None
    said = f"no horizon in {list(horizons)} fits a chunk size in {list(chunk_sizes)}"
    if policy_type in CHUNK_FIELD:
        said += (f" ({policy_type} executes at most chunk - n_obs_steps + 1 actions of a chunk: "
                 f"{', '.join(f'{m} of {c}' for c, m in fits.items())})")
    return said


NO_PRETRAINED = ("", "none", "None")
"""--pretrained values that mean from scratch"""


@dataclass
class TrainConfig:
    """Train a LeRobot policy on a recorded GraspObject-v1 dataset with LeRobot's own training loop.

    Further lerobot-train flags go after `--` (they win), e.g. `-- --policy.optimizer_lr=5e-5`."""

    policy_type: str
    """LeRobot policy type: smolvla, pi05, act, diffusion, ... (every type LeRobot registers)"""
    dataset: Path
    """local LeRobotDataset v3 directory"""
    out: Annotated[Path | None, tyro.conf.arg(metavar="DIR", help_behavior_hint="")] = None
    """run directory, new or empty, or holding this run to resume (required on the command line; the grid sets one
    per model)"""
    pretrained: Annotated[str | None, tyro.conf.arg(metavar="STR", help_behavior_hint=(
        "(default: lerobot/smolvla_base for smolvla, lerobot/pi05_base for pi05, else none)"))] = "default"
    """local checkpoint dir or hub id to fine-tune; none trains from scratch"""
    batch_size: Annotated[int | None, tyro.conf.arg(metavar="INT", help_behavior_hint=(
        "(default: the paper's for the dataset's recorded regime: 128 full_random, else 64)"))] = None
    """training batch size (per GPU under accelerate launch); a dataset that is not a vla-ladder recording needs
    it"""
    chunk_size: int = DEFAULT_CHUNK
    """action chunk length (policy types with an action chunk: act, smolvla, pi05, diffusion's horizon, ...)"""
    n_action_steps: Annotated[int | None, tyro.conf.arg(metavar="INT", help_behavior_hint=(
        "(default: the chunk size, or LeRobot's default for policies with observation history such as diffusion)"))] \
        = None
    """execution horizon stored with the checkpoint, at most the chunk size (diffusion: chunk size - n_obs_steps + 1);
    evaluation can override it"""
    steps: int = 30_000
    """training steps"""
    save_freq: int = 20_000
    """checkpoint every N steps (and at the end)"""
    log_freq: int = 200
    """log every N steps"""
    num_workers: int = 4
    """data-loader worker processes (0: load data in the training process)"""
    train_seed: int = DEFAULT_TRAIN_SEED
    """seed of the training run (initialisation, data order, augmentation)"""
    device: Annotated[str | None, tyro.conf.arg(metavar="STR", help_behavior_hint="(default: LeRobot picks)")] = None
    """cpu, cuda, cuda:N or mps"""
    wandb: bool = False
    """log to Weights & Biases"""
    rename_map: Annotated[dict[str, str] | None, tyro.conf.arg(
        metavar="KEY NEW_KEY [KEY NEW_KEY ...]", help_behavior_hint=(
            "(default: fine-tuning, the fixed and hand cameras -> the checkpoint's first and second image slots; "
            "from scratch, none)"))] = None
    """dataset key -> checkpoint key, e.g. observation.images.hand_camera observation.images.camera2"""
    print_command: bool = False
    """print the equivalent lerobot-train command and exit"""
    lerobot_args: Annotated[tuple[str, ...], tyro.conf.arg(help_behavior_hint="(default: none)")] = ()
    """raw lerobot-train flags appended last (they win); on the command line, everything after --"""

    REQUIRED_ON_COMMAND_LINE: ClassVar[tuple[str, ...]] = ("out",)

    def __post_init__(self):
        allowed = policy_types()
        if self.policy_type not in allowed:
            raise ValueError(f"unknown policy type {self.policy_type!r}; allowed: {', '.join(allowed)}")
        self.dataset = Path(self.dataset)
        self.out = None if self.out is None else Path(self.out)
        self.lerobot_args = joined_flags(self.lerobot_args)
        if flag := own_flag(self.policy_type, self.lerobot_args):
            raise ValueError(f"{flag} after -- is vla-ladder's to set; use {OWN_FLAGS.get(flag, '--chunk-size')}")
        check_policy_packages(self.policy_type)
        self.info = read_info(self.dataset)
        check_features(self.info, self.dataset)
        if self.pretrained == "default":
            self.pretrained = DEFAULT_PRETRAINED.get(self.policy_type)
        if self.pretrained in NO_PRETRAINED:
            self.pretrained = None
        self.condition = dataset_condition(self.dataset)
        self.contract = dataset_contract(self.dataset)
        auto_batch = None if self.condition is None else BATCH_FOR_REGIME.get(self.condition.regime, DEFAULT_BATCH)
        chunked = self.chunk_field() is not None
        if not chunked and self.chunk_size != DEFAULT_CHUNK:  # it changed nothing, and the run was labelled with it
            raise ValueError(f"--chunk-size: {self.policy_type}'s LeRobot config has no {chunk_name(self.policy_type)} "
                             "field for it to set; leave --chunk-size out, and set its own fields after --")
        # Without a chunk field, n_action_steps stays LeRobot's where the type has one (tdmpc's 1: it refuses more).
        auto_steps = None
        if chunked and self.policy_type not in CHUNK_FIELD:
            auto_steps = self.chunk_size
        elif chunked:  # LeRobot's default, where the chunk of `horizon` steps holds it (diffusion runs actions
            # n_obs_steps - 1 .. of its horizon: its default 32 of 64 queued 15 with a horizon of 16)
            auto_steps = min(config_default(self.policy_type, "n_action_steps"), self.max_action_steps())
        # The flags that set what a grid sets per model (it refuses them): a value other than the one filled in. (A
        # config rebuilt with dataclasses.replace holds the filled-in values, which nobody gave.)
        self.given = tuple(flag for flag, given in (
            ("--batch-size", self.batch_size is not None and self.batch_size != auto_batch),
            ("--chunk-size", self.chunk_size != DEFAULT_CHUNK),
            ("--n-action-steps", self.n_action_steps is not None and self.n_action_steps != auto_steps)) if given)
        if self.batch_size is None:
            if auto_batch is None:
                raise ValueError(f"{str(self.dataset)!r} is not a vla-ladder recording, so its regime is unknown; "
                                 "pass --batch-size (the paper: 128 for full_random, else 64)")
            self.batch_size = auto_batch
        if self.n_action_steps is None:
            self.n_action_steps = auto_steps
        for name in ("batch_size", "chunk_size", "n_action_steps", "steps"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if chunked and (unfit := unfit_chunks(self.policy_type, [self.chunk_size], self.lerobot_args)):
            raise ValueError(f"--chunk-size {unfit}")
        if chunked and self.n_action_steps is not None and self.n_action_steps > self.max_action_steps():
            if self.policy_type in CHUNK_FIELD:  # (its checkpoint would be refused by every evaluation)
                raise ValueError(f"--n-action-steps ({self.n_action_steps}) cannot exceed {self.max_action_steps()} "
                                 f"for {self.policy_type}: it executes at most --chunk-size ({self.chunk_size}) - "
                                 "n_obs_steps + 1 actions of a chunk")
            raise ValueError(f"--n-action-steps ({self.n_action_steps}) cannot exceed --chunk-size "
                             f"({self.chunk_size})")
        check_seed(self.train_seed, "--train-seed")  # lerobot-train seeds numpy with it too
        if self.device is not None and not TORCH_DEVICE.fullmatch(self.device):
            raise ValueError(f"--device {self.device!r}: allowed: cpu, cuda, cuda:N, mps")
        if self.device is not None:  # (LeRobot would train on the CPU, saying so in a warning only)
            check_torch_device(self.device, f"--device {self.device}", "use --device cpu, or leave it out (LeRobot "
                               "picks)")
        if self.num_workers < 0:
            raise ValueError(f"--num-workers must be >= 0 (0: load data in the training process), got "
                             f"{self.num_workers}")
        # `out` is checked by train(), not here: a grid or study builds configs for runs that already exist.

    # ------------------------------------------------------------------ lerobot-train flags
    def max_action_steps(self, chunk_size: int | None = None) -> int:
        """max_action_steps of this policy type for `chunk_size` (default: this run's), with its --policy flags."""
        return max_action_steps(self.policy_type, self.chunk_size if chunk_size is None else chunk_size,
                                self.lerobot_args)

    def chunk_field(self) -> str | None:
        """chunk_field of this policy type."""
        return chunk_field(self.policy_type)

    def policy_flags(self) -> list[str]:
        """--policy.* flags, without the leading "policy." (the form PreTrainedConfig overrides take)."""
        names = config_fields(self.policy_type)
        flags = {"push_to_hub": "false"}
        if field := self.chunk_field():
            flags[field] = str(self.chunk_size)
        if "n_action_steps" in names and self.n_action_steps is not None:
            flags["n_action_steps"] = str(self.n_action_steps)
        flags.update(POLICY_PRESETS.get(self.policy_type, {}))
        if "pretrained_backbone_weights" in names and _offline():
            flags["pretrained_backbone_weights"] = "null"  # torchvision would download ImageNet weights
        if self.device:
            flags["device"] = self.device
        return [f"--{k}={v}" for k, v in flags.items()]

    def pipeline_flags(self, rename: dict[str, str] | None = None) -> list[str]:
        """`rename`: the camera rename map the built config has (a hub checkpoint's is known once it is read)."""
        flags = [
            f"--dataset.repo_id=local/{self.dataset.resolve().name}",
            f"--dataset.root={self.dataset.resolve()}",
            f"--output_dir={self.out.resolve()}",
            f"--job_name={self.policy_type}",
            f"--batch_size={self.batch_size}",
            f"--steps={self.steps}",
            f"--save_freq={self.save_freq}",
            f"--log_freq={self.log_freq}",
            f"--num_workers={self.num_workers}",
            f"--seed={self.train_seed}",
            f"--wandb.enable={'true' if self.wandb else 'false'}",
        ]
        rename = self.camera_rename_map() if rename is None else rename
        if rename:
            flags.append(f"--rename_map={json.dumps(rename)}")
        return flags

    def camera_rename_map(self) -> dict[str, str]:
        """Dataset camera -> checkpoint camera, when fine-tuning a checkpoint with other camera names."""
        if self.rename_map is not None or self.pretrained is None:
            return dict(self.rename_map or {})
        config_path = Path(self.pretrained) / "config.json"
        if not config_path.is_file():  # a hub id: build_config maps onto the fetched config's cameras
            return dict(PAPER_RENAME) if self.pretrained in DEFAULT_PRETRAINED.values() else {}
        return _rename_for(json.loads(config_path.read_text()).get("input_features", {}))

    def lerobot_command(self, rename: dict[str, str] | None = None) -> list[str]:
        """The equivalent `lerobot-train` command line (`rename`: as in pipeline_flags)."""
        policy = ([f"--policy.path={self.pretrained}"] if self.pretrained
                  else [f"--policy.type={self.policy_type}"])
        return ["lerobot-train", *self.pipeline_flags(rename), *policy,
                *(f"--policy.{f[2:]}" for f in self.policy_flags()), *self.lerobot_args]

    def build_config(self):
        """LeRobot's TrainPipelineConfig, parsed by LeRobot's own parser from the flags above."""
        said = io.StringIO()
        try:
            with contextlib.redirect_stderr(said):  # argparse's usage of every LeRobot flag: 500 lines
                return self._parse_config()
        except SystemExit:  # draccus's argparse refused a flag (an unknown one after --, a value of another type)
            last = said.getvalue().strip().splitlines()[-1:] or ["it refused the flags"]
            reason = last[0].split("error: ", 1)[-1]
            raise ValueError(f"lerobot-train: {reason} (the flags after -- are lerobot-train's: "
                             "`lerobot-train --help` lists them)") from None
        except Exception as e:
            if isinstance(e, ValueError):
                raise
            # draccus wraps LeRobot's own checks (e.g. n_action_steps > chunk_size) in its DecodingError
            raise ValueError(f"LeRobot rejects this configuration: {' '.join(str(e).split())}") from e

    def _parse_config(self):
        import draccus
        from lerobot.configs.train import TrainPipelineConfig

        extra_policy = [f"--{a[len('--policy.'):]}" for a in self.lerobot_args if a.startswith("--policy.")]
        extra_other = [a for a in self.lerobot_args if not a.startswith("--policy.")]
        policy_flags = self.policy_flags() + extra_policy
        if self.pretrained:
            cfg = draccus.parse(TrainPipelineConfig, args=self.pipeline_flags() + extra_other)
            cfg.policy = pretrained_config(self.pretrained, self.policy_type, policy_flags)
            cfg.policy.pretrained_path = Path(self.pretrained)
            if not cfg.rename_map:
                cfg.rename_map = _rename_for({k: v for k, v in cfg.policy.input_features.items()})
        else:
            cfg = draccus.parse(TrainPipelineConfig, args=self.pipeline_flags() + extra_other
                                + [f"--policy.type={self.policy_type}"]
                                + [f"--policy.{f[2:]}" for f in policy_flags])
        return cfg


def pretrained_config(pretrained: str, policy_type: str, overrides: list[str] | None = None):
    """The LeRobot config of the checkpoint to fine-tune (a local directory or a hub id), or a one-line
    ValueError when it cannot be read or is another policy type. The study calls it before recording."""
    from lerobot.configs.policies import PreTrainedConfig
    try:
        with files.own_tempdir():  # LeRobot leaves a copy of the config in the temp directory otherwise
            cfg = PreTrainedConfig.from_pretrained(pretrained, cli_overrides=list(overrides or []))
    except Exception as e:  # hub errors come in many types; all mean the same here
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"cannot load the pretrained config {pretrained!r} ({reason}); offline, pass a local "
                         "checkpoint directory or --pretrained none") from e
    if cfg.type != policy_type:
        raise ValueError(f"--pretrained {pretrained!r} is a {cfg.type!r} checkpoint, not {policy_type!r}")
    return cfg


def check_offline_assets(policy_cfg) -> None:
    """Offline, fail now (not after loading data and weights) when the policy's tokenizer is unreachable."""
    name_of = TOKENIZER_OF.get(policy_cfg.type)
    if name_of is None or not _offline():
        return
    name = str(name_of(policy_cfg))
    if Path(name).is_dir():
        return
    from huggingface_hub import try_to_load_from_cache

    if not isinstance(try_to_load_from_cache(name, "tokenizer_config.json"), str):
        hint = ("build a local SmolVLM directory with vla_ladder.training.tiny.build_vlm_dir and pass "
                "-- --policy.vlm_model_name=DIR --policy.load_vlm_weights=false"
                if policy_cfg.type == "smolvla" else
                f"LeRobot's {policy_cfg.type} processor loads the tokenizer {name!r} by hub id; download it "
                f"once with network (`hf download {name}`) so it is in the HF cache")
        raise ValueError(f"offline (HF_HUB_OFFLINE=1) and the tokenizer {name!r} of {policy_cfg.type} is "
                         f"neither a local directory nor in the Hugging Face cache: {hint}")


def _offline() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "0").lower() in ("1", "true", "yes")


def _rename_for(input_features: dict) -> dict[str, str]:
    """Map our two cameras onto a checkpoint's image slots in CAMERA_ORDER (fixed view first), unless the
    checkpoint already uses our names."""
    slots = [k for k, v in input_features.items()
             if (v.get("type") if isinstance(v, dict) else getattr(v.type, "value", v.type)) == "VISUAL"]
    if not slots or all(k in slots for k in CAMERA_ORDER):
        return {}
    return dict(zip(CAMERA_ORDER, slots))


def checkpoint_dir(out: str | Path) -> Path:
    """The last checkpoint's pretrained_model directory of a training run."""
    return Path(out) / "checkpoints" / "last" / "pretrained_model"


RUN_FILE = "vla_ladder_train.json"
"""In a finished run's directory: the request, the lerobot-train command, the dataset and the wall time."""
REQUEST_FILE = "vla_ladder_request.json"
"""In a run's directory from its first checkpoint on: the request, so that a re-run resumes only the same one."""
RESUMES_WITH_OTHER = ("num_workers", "log_freq", "wandb", "print_command", "device")
"""Request fields a resumed run may change: where it runs, how it loads and logs, not what it learns."""


PATH_FIELDS = ("out", "dataset")
"""Request fields compared as the directories they name: `--out run` and `--out $PWD/run` are one run."""
ADDED_SINCE = ("dataset_size",)
"""Request fields added since runs were first kept: a request file without them resumes unchecked on them."""


def _request(req: TrainConfig) -> dict:
    request = {k: v for k, v in files.plain(asdict(req)).items() if k not in RESUMES_WITH_OTHER}
    # The data it trains on is what --dataset holds: another recording at the same path is another run.
    request["dataset_size"] = {"episodes": req.info.get("total_episodes"), "frames": req.info.get("total_frames")}
    return _as_dirs(request)


def _as_dirs(request: dict) -> dict:
    """`request` with its PATH_FIELDS as the absolute directories they name."""
    return {**request, **{k: str(Path(request[k]).resolve()) for k in PATH_FIELDS if request.get(k) is not None}}


def resume_point(req: TrainConfig) -> Path | None:
    """Where a re-run of `req` picks up: the checkpoint a killed run of the same request saved last
    (`checkpoints/last`, which LeRobot points to a checkpoint only once it is whole), or None to start afresh (`out`
    absent, empty, or a run of this request killed before its first whole checkpoint). ValueError for a directory
    that holds anything else: another request (named), or files that are not a training run."""
    out = req.out
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {str(out)!r} is a file; give a directory")
    if not out.is_dir() or not any(out.iterdir()):
        return None
    saved = out / REQUEST_FILE
    if not saved.is_file():
        raise ValueError(f"output directory {str(out)!r} exists and holds no training run of vla-ladder (no "
                         f"{REQUEST_FILE}); pick a new --out")
    was, now = _as_dirs(json.loads(saved.read_text())), _request(req)
    if changed := [f"{k} was {was.get(k)!r}, now {now.get(k)!r}" for k in sorted({*was, *now})
                   if was.get(k) != now.get(k) and not (k in ADDED_SINCE and k not in was)]:
        raise ValueError(f"output directory {str(out)!r} holds a training run with other arguments "
                         f"({'; '.join(changed)[:300]}); re-run it with its own, or pick a new --out")
    last = out / "checkpoints" / "last"
    return last.resolve() if (last / "training_state").is_dir() else None


@contextlib.contextmanager
def resuming_from(checkpoint: Path):
    """LeRobot resumes a run from `--config_path` on its command line, which its config reads from sys.argv when it
    validates (TrainPipelineConfig._resolve_resume_checkpoint): give it the checkpoint's there for the call."""
    import sys

    argv = sys.argv
    sys.argv = [argv[0], f"--config_path={checkpoint / 'pretrained_model' / 'train_config.json'}"]
    try:
        yield
    finally:
        sys.argv = argv


def train(req: TrainConfig) -> Path:
    """Run LeRobot training for `req`; returns the final checkpoint's pretrained_model directory. A re-run of a
    killed run (the same request, the same `out`) resumes from its last checkpoint (`resume_point`), with LeRobot's
    own resume: weights, optimizer, scheduler, step and the data order; a finished one does nothing. Another
    training run writing the same `out` meanwhile is refused (files.writing)."""
    from lerobot.scripts.lerobot_train import train as lerobot_train

    if req.out is None:
        raise ValueError("a training run needs an output directory (out)")
    check_output_dir(req.out, "--out")  # now, not when the first checkpoint is saved
    cfg = req.build_config()
    check_offline_assets(cfg.policy)
    cpu_threads(req)
    main_process = int(os.environ.get("RANK", "0")) == 0  # accelerate's other processes leave the lock to rank 0
    with files.writing(req.out, "training run") if main_process else contextlib.nullcontext():
        resume = resume_point(req)  # (read under the lock: another run may have saved or finished meanwhile)
        if resume is not None and (req.out / RUN_FILE).is_file():
            log.info("%s is a finished run of this request: nothing to do", req.out)
            return checkpoint_dir(req.out)
        if resume is None and req.out.exists():
            # Empty, or this request's run killed before a whole checkpoint (resume_point): nothing to keep, and
            # LeRobot refuses to start a run in an existing directory.
            files.remove_dir(req.out)
        if resume is not None:
            cfg.resume = True
            # LeRobot sets the optimizer and scheduler presets only for new runs; a resumed one loads their state
            # into the same ones: the policy's presets where the first run used them, else the ones its flags set.
            if cfg.use_policy_training_preset:
                cfg.optimizer, cfg.scheduler = cfg.policy.get_optimizer_preset(), cfg.policy.get_scheduler_preset()
            log.info("resuming %s from %s", req.out, resume)
        # The rename map the run uses: a hub checkpoint's cameras are known once build_config has read its config.
        command = shlex.join(req.lerobot_command(dict(cfg.rename_map or {})))
        log.info("training %s on %s for %d steps (batch %d, chunk %d): %s", req.policy_type, req.dataset,
                 req.steps, req.batch_size, req.chunk_size, command)
        start = time.time()
        try:
            with stamp_checkpoints(req.contract, req.out, _request(req)), \
                    (resuming_from(resume) if resume is not None else contextlib.nullcontext()):
                lerobot_train(cfg)
        except URLError as e:  # a download without network (ACT's ImageNet backbone, a tokenizer, a hub checkpoint)
            raise ValueError(f"lerobot-train tried to download something and could not ({e.reason}); on a machine "
                             "without network export HF_HUB_OFFLINE=1, so that ACT's backbone trains from scratch "
                             "and tokenizers and checkpoints are looked up locally") from None
        if main_process:
            files.write_json(req.out / RUN_FILE, {
                "request": asdict(req),
                "lerobot_train_command": command,
                "dataset": {"root": str(req.dataset), "condition": req.condition and req.condition.key,
                            "episodes": req.info.get("total_episodes"), "frames": req.info.get("total_frames"),
                            "contract": req.contract},
                "checkpoint": str(checkpoint_dir(req.out)),
                "wall_s": round(time.time() - start, 1),
                "provenance": files.provenance(),
            })
        return checkpoint_dir(req.out)


@contextlib.contextmanager
def stamp_checkpoints(contract: dict | None, out: Path, request: dict):
    """While LeRobot trains, every checkpoint it saves gets TRAINED_CONTRACT_FILE (the data's task contract) before
    `checkpoints/last` points to it, so that each checkpoint says what it was trained on wherever it is copied to,
    and a run killed after any save leaves checkpoints that `lerobot:` checks, not ones it takes on trust; the run
    directory gets REQUEST_FILE, so that a re-run resumes it only with the same request. And `checkpoints/last`
    moves in one step: LeRobot unlinks it and then links the new checkpoint, and a run killed in between had whole
    checkpoints but no `last`, which a re-run took for a run with nothing to keep. LeRobot's loop offers no hook, so
    its module's save_checkpoint and update_last_checkpoint are replaced for the call (the main process saves)."""
    import lerobot.scripts.lerobot_train as loop
    from lerobot.utils.constants import PRETRAINED_MODEL_DIR

    save, update_last = loop.save_checkpoint, loop.update_last_checkpoint

    def save_with_contract(checkpoint_dir, *args, **kwargs):
        if not (out / REQUEST_FILE).is_file():  # first, so that a kill during the first save leaves a run of ours
            out.mkdir(parents=True, exist_ok=True)
            files.write_json(out / REQUEST_FILE, request)
        result = save(checkpoint_dir, *args, **kwargs)
        if contract is not None:  # None: data recorded before contracts were kept, nothing to say
            files.write_json(Path(checkpoint_dir) / PRETRAINED_MODEL_DIR / TRAINED_CONTRACT_FILE, contract)
        return result

    loop.save_checkpoint, loop.update_last_checkpoint = save_with_contract, move_last
    try:
        yield
    finally:
        loop.save_checkpoint, loop.update_last_checkpoint = save, update_last


def move_last(checkpoint_dir: Path) -> None:
    """Point `checkpoints/last` at `checkpoint_dir`, as LeRobot's update_last_checkpoint does, in one step: a new
    link beside it renamed over it."""
    checkpoint_dir = Path(checkpoint_dir)
    last = checkpoint_dir.parent / "last"
    new = last.with_name(f".last.{os.getpid()}")
    new.unlink(missing_ok=True)
    os.symlink(checkpoint_dir.name, new)
    os.replace(new, last)


def cpu_threads(req: TrainConfig) -> None:
    """On a CPU, give torch the cores the data-loader workers leave free. With more threads than free cores,
    OpenMP threads spin waiting for each other: a small SmolVLA step took 14 s instead of 0.9 s on 2 busy cores.
    An explicit OMP_NUM_THREADS wins."""
    import torch

    from vla_ladder.machine import cores
    if "OMP_NUM_THREADS" not in os.environ and not (req.device or "").startswith("cuda"):
        torch.set_num_threads(max(1, cores() - req.num_workers))


def run(cfg: TrainConfig) -> int:
    if cfg.out is None:
        raise ValueError("--out DIR is required: the training run directory")
    if cfg.print_command:
        print(shlex.join(cfg.lerobot_command()))
        return 0
    print(train(cfg))
    return 0
