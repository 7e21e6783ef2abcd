"""What a study runs: the datasets to record, the policies to train on them, the grid, and how to evaluate.

A study config is a JSON file (the presets ship in vla_ladder/configs/study/: micro, cpu-mini, gpu-session,
gpu-scratch, paper). Every section is a dataclass validated when loaded: an unknown field, regime, policy type
or a grid that cannot run is refused before any work, with the field's path named ("policies[1].type: ...").
"""

from __future__ import annotations

import json
import re
import types
import typing
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path

from vla_ladder.checks import SEED_LIMIT, check_count, check_seed
from vla_ladder.conditions import Condition, ConditionGrid
from vla_ladder.recordings import RECORD_FIRST_SEED

PRESETS_PACKAGE = "vla_ladder.configs.study"


@dataclass
class DatasetSpec:
    """One recorded training dataset."""

    name: str
    """short name used in unit ids and tables, e.g. sj"""
    condition: str
    """the condition recorded, as its key regime/split/num_objects"""
    episodes: int
    """successful demonstrations the dataset holds"""
    expert: str = "scripted"
    """the expert recorded: scripted or ppo:PATH"""
    first_seed: int = RECORD_FIRST_SEED
    """first episode seed; far from the evaluation seeds (0...) so no evaluation layout is trained on"""

    def __post_init__(self):
        _check_name(self.name)
        Condition.parse(self.condition)
        _positive(self, "episodes")
        if self.first_seed < 0:
            raise ValueError(f"first_seed must be >= 0, got {self.first_seed}")
        from vla_ladder.policies import check_expert
        check_expert(self.expert, f"expert {self.expert!r}")

    @property
    def cond(self) -> Condition:
        return Condition.parse(self.condition)


NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
STUDY_FLAGS = ("--output_dir", "--job_name", "--steps", "--batch_size", "--seed", "--policy.type", "--policy.path",
               "--policy.chunk_size", "--policy.n_action_steps", "--resume", "--config_path")
"""lerobot-train flags the study sets for each training unit (a policy's lerobot_args may not)."""


def _check_name(name: str) -> None:
    # Names become folder names under --out: nothing that climbs out of it or hides.
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise ValueError(f"name {name!r}: use letters, digits, '.', '_' and '-', starting with a letter or digit")


@dataclass
class PolicySpec:
    """One LeRobot policy type trained on every dataset."""

    name: str
    """label in tables, e.g. SmolVLA-scratch"""
    type: str
    """LeRobot policy type whose chunk and horizon the grid sweeps: smolvla, act, pi05, diffusion, ...
    (training.train.sweepable_types)"""
    steps: int
    """training steps"""
    pretrained: str = "none"
    """none (from scratch), a local checkpoint directory, or a hub id"""
    vlm: str | None = None
    """smolvla from scratch offline: build a local VLM of this size (training/tiny.py SIZES: tiny, small, small64,
    smolvlm2-500m) as its backbone"""
    image_size: int | None = None
    """smolvla: side of the square images its vision tower sees (resize_imgs_with_padding); default: the VLM's"""
    lerobot_args: list[str] = field(default_factory=list)
    """further lerobot-train flags, e.g. --policy.optimizer_lr=3e-4"""
    datasets: list[str] = field(default_factory=list)
    """names of the datasets this policy is trained on (empty: every dataset of the study)"""
    blind: bool = False
    """train and evaluate without the instruction (every episode's instruction is contract.BLIND_INSTRUCTION):
    the instruction-blind control of the same architecture, which scores what the layout alone allows"""
    train_seed: int | None = None
    """lerobot-train's --seed for every model of this policy (initialisation, data order, augmentation); null:
    `vla-ladder train`'s default (1000). The same policy listed again under another name with another train_seed
    trains a replicate, which shows how much a number owes to the training run (`vla-ladder compare` pairs their
    episodes)"""

    def __post_init__(self):
        _check_name(self.name)
        from vla_ladder.training.train import own_flag, policy_types, sweep_problem
        allowed = policy_types()
        if self.type not in allowed:
            raise ValueError(f"type: unknown policy type {self.type!r}; allowed: {', '.join(allowed)}")
        if unsweepable := sweep_problem(self.type):  # (the study trains per chunk size, selects per horizon)
            raise ValueError(f"type: {unsweepable}")
        _positive(self, "steps")
        from vla_ladder.training.tiny import SIZES
        if self.vlm is not None and self.vlm not in SIZES:
            raise ValueError(f"vlm: unknown size {self.vlm!r}; allowed: {', '.join(SIZES)}")
        if self.image_size is not None and (self.vlm is None or isinstance(self.image_size, bool)
                                            or not isinstance(self.image_size, int) or self.image_size < 1):
            raise ValueError(f"image_size must be a positive integer, for a policy with a vlm (it sizes that VLM's "
                             f"images), got {self.image_size!r}" + ("" if self.vlm else " without vlm"))
        if self.train_seed is not None:
            check_seed(self.train_seed, "train_seed")
        if self.vlm is not None and self.type != "smolvla":
            raise ValueError(f"vlm: only smolvla has a VLM backbone, not {self.type!r}")
        if not all(isinstance(a, str) and a.startswith("--") for a in self.lerobot_args):
            raise ValueError(f"lerobot_args: expected --flag=value strings, got {self.lerobot_args}")
        for a in self.lerobot_args:
            flag = a.split("=", 1)[0]
            if flag in STUDY_FLAGS or flag.startswith("--dataset."):
                raise ValueError(f"lerobot_args: {flag} is the study's to set (where each unit writes and what it "
                                 f"trains on: {', '.join(STUDY_FLAGS)}, --dataset.*); use the study's own fields "
                                 "(steps, train_seed, the grid's batch and chunk sizes)")
        if flag := own_flag(self.type, self.lerobot_args):  # (train's check, which the train units would fail)
            raise ValueError(f"lerobot_args: {flag} is set by `vla-ladder train`, which trains the study's models "
                             "and refuses it; use the study's own fields (steps, train_seed, device, num_workers, the "
                             "grid's batch and chunk sizes)")


@dataclass
class GridSpec:
    """The paper's grid: every (batch size, chunk size) is trained, every execution horizon <= the chunk size
    (diffusion: <= what it executes of a chunk, training.train.max_action_steps) is tried on validation episodes of
    the training condition, and the best (success, then grasp-any, then reach) is evaluated. Validation seeds are
    disjoint from the evaluation seeds, so the reported numbers are not the ones the choice was made on."""

    batch_sizes: list[int] = field(default_factory=lambda: [64])
    chunk_sizes: list[int] = field(default_factory=lambda: [16])
    horizons: list[int] = field(default_factory=lambda: [8])
    select_episodes: int = 20
    """validation episodes per horizon (0: no selection, the first horizon that fits is used)"""
    select_first_seed: int = 500_000
    """first validation seed"""

    def __post_init__(self):
        _unique(self, "batch_sizes", "chunk_sizes", "horizons")
        for name in ("batch_sizes", "chunk_sizes", "horizons"):
            values = getattr(self, name)
            if not values or not all(isinstance(v, int) and v >= 1 for v in values):
                raise ValueError(f"{name}: expected positive integers, got {values}")
        if not any(h <= c for h in self.horizons for c in self.chunk_sizes):
            raise ValueError(f"horizons: no horizon in {self.horizons} fits a chunk size in {self.chunk_sizes}")
        if self.select_episodes < 0:
            raise ValueError(f"select_episodes must be >= 0, got {self.select_episodes}")


@dataclass
class EvaluationSpec:
    """How every trained model (and every reference policy) is evaluated."""

    episodes: int = 100
    """episodes per cell"""
    first_seed: int = 0
    """episode j of every cell plays seed first_seed + j"""
    regimes: list[str] = field(default_factory=lambda: ["all"])
    """the ladder each canonically trained model is evaluated on (the train x eval regime matrix)"""
    num_objects: list[int] = field(default_factory=lambda: [5])
    """object counts evaluated"""
    videos: int = 1
    """filmed episodes per cell (for the report)"""
    reference_policies: list[str] = field(default_factory=lambda: ["layout-prior", "nearest"])
    """privileged-state reference policies evaluated on the same cells, for the tables"""
    curve_episodes: int = 0
    """evaluate every saved checkpoint on this many validation episodes of the training condition (the
    learning curve; 0: none)"""
    probes: list[str] = field(default_factory=list)
    """grounding probes (vla-ladder probe) run on every instruction-reading model in its training condition:
    instruction-swap, paraphrase, appearance-swap, absent-object, position-swap, instruction-switch,
    distractor-removal; each plays the object count nearest the training data's that it can (absent-object four
    where the data have five, so that one is off the table; the swaps, the switch and the removal two where the
    data have one); blind models are skipped: they cannot follow an instruction"""
    probe_episodes: int = 20
    """scenes per probe"""

    def __post_init__(self):
        _positive(self, "episodes")
        _unique(self, "regimes", "num_objects", "reference_policies", "probes")
        ConditionGrid(tuple(self.regimes), ("canonical",), tuple(self.num_objects))
        from vla_ladder.experiments.probes import PROBES
        from vla_ladder.policies import reference_kinds
        for p in self.reference_policies:
            if p not in reference_kinds():
                raise ValueError(f"reference_policies: unknown {p!r}; allowed: {', '.join(reference_kinds())}")
        for p in self.probes:
            if p not in PROBES:
                raise ValueError(f"probes: unknown {p!r}; allowed: {', '.join(PROBES)}")
        for name in ("videos", "curve_episodes", "first_seed"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        _positive(self, "probe_episodes")


@dataclass
class StudyConfig:
    """A learned policy diagnosed end to end: record, train, evaluate, report."""

    name: str
    description: str = ""
    datasets: list[DatasetSpec] = field(default_factory=list)
    policies: list[PolicySpec] = field(default_factory=list)
    grid: GridSpec = field(default_factory=GridSpec)
    evaluation: EvaluationSpec = field(default_factory=EvaluationSpec)
    device: str = "auto"
    """where training and policy inference run: auto (cuda when present), cpu or cuda"""
    num_workers: int = 0
    """data-loader workers of LeRobot training"""

    def __post_init__(self):
        if not self.datasets or not self.policies:
            raise ValueError("a study needs at least one dataset and one policy")
        for what, items in (("datasets", self.datasets), ("policies", self.policies)):
            names = [x.name for x in items]
            if len(set(names)) != len(names):
                raise ValueError(f"{what}: names must be unique, got {names}")
        names = [d.name for d in self.datasets]
        # A blind policy's copy of dataset D is data/D-blind (Study.blind_dir): a dataset of that name was recorded
        # there and then replaced by the copy, its models trained on D's demonstrations.
        blinded = {d for p in self.policies if p.blind for d in (p.datasets or names)}
        for name in names:
            if name.endswith("-blind") and name.removesuffix("-blind") in blinded:
                raise ValueError(f"datasets[{name}]: name taken by the instruction-blind copy of "
                                 f"{name.removesuffix('-blind')} (data/{name}); rename the dataset")
        for p in self.policies:
            for name in p.datasets:
                if name not in names:
                    raise ValueError(f"policies[{p.name}].datasets: unknown dataset {name!r}; allowed: "
                                     f"{', '.join(names)}")
        self._check_models(names)
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device: unknown {self.device!r}; allowed: auto, cpu, cuda")
        if self.num_workers < 0:
            raise ValueError(f"num_workers must be >= 0, got {self.num_workers}")
        self._check_seeds()

    def _check_models(self, names: list[str]) -> None:
        """Every (policy, dataset) the study trains: one the grid's horizons can evaluate, trained once, under ids of
        its own. Unit ids and directories join the names with '-' (Study: models/P-D-bBcC, eval/P-D, ...), so policy
        A-sj on dataset x and policy A on sj-x would write one directory; a new separator would rename the committed
        studies' directories, so such names are refused instead."""
        from vla_ladder.training.train import DEFAULT_TRAIN_SEED, unfit_chunks, unfit_horizons
        trained: dict[tuple, str] = {}
        joined: dict[str, tuple[str, str]] = {}
        for p in self.policies:
            if unfit := unfit_chunks(p.type, self.grid.chunk_sizes, p.lerobot_args):
                raise ValueError(f"policies[{p.name}]: grid.chunk_sizes {unfit}")
            if unfit := unfit_horizons(p.type, self.grid.chunk_sizes, self.grid.horizons, p.lerobot_args):
                raise ValueError(f"policies[{p.name}]: grid.horizons: {unfit}")
            # Replicates differ in train_seed: alike but for the name and the same seed (null: train's default), a
            # policy trains the same models again, and the report took their agreement for a replicate's.
            seed = DEFAULT_TRAIN_SEED if p.train_seed is None else p.train_seed
            recipe = json.dumps({f.name: getattr(p, f.name) for f in fields(p)
                                 if f.name not in ("name", "train_seed", "datasets")}, sort_keys=True)
            for d in p.datasets or names:
                if (other := trained.setdefault((recipe, seed, d), p.name)) != p.name:
                    raise ValueError(f"policies[{other}] and policies[{p.name}] would train the same models on "
                                     f"datasets[{d}]: alike but for the name, with train_seed {seed}"
                                     + (" (null is `vla-ladder train`'s)" if seed == DEFAULT_TRAIN_SEED else "")
                                     + "; give a replicate another train_seed, or drop one")
                key = f"{p.name}-{d}"
                if (was := joined.setdefault(key, (p.name, d))) != (p.name, d):
                    raise ValueError(f"policies[{was[0]}] on datasets[{was[1]}] and policies[{p.name}] on "
                                     f"datasets[{d}] would share the unit ids and directories named {key} (eval/{key}, "
                                     f"models/{key}-bBcC, ...: names are joined with '-'); rename one")
                if ref := next((r for r in self.evaluation.reference_policies
                                if key.startswith(f"reference-{r}-")), None):
                    raise ValueError(f"policies[{p.name}] on datasets[{d}]: its evaluation eval/{key} would be read "
                                     f"as one of the reference policy {ref}'s (eval/reference-{ref}-N); rename one")

    def _check_seeds(self):
        """No seed serves two purposes: the evaluation's and probes' scenes, the validation episodes that select
        checkpoints, the learning curves' episodes and the recorded demonstrations are disjoint ranges, so no
        reported number is measured on a layout a model was trained or selected on."""
        ev, sel = self.evaluation, self.grid
        uses = {"evaluation and probe": range(ev.first_seed, ev.first_seed + max(
                    ev.episodes, ev.probe_episodes if ev.probes else 0)),
                "validation (grid.select_first_seed)": range(sel.select_first_seed,
                                                             sel.select_first_seed + sel.select_episodes),
                "learning-curve": range(sel.select_first_seed + sel.select_episodes,
                                        sel.select_first_seed + sel.select_episodes + ev.curve_episodes)}
        # Recorded seeds run upwards from first_seed (failures skip seeds, so allow 4x the episodes).
        uses.update({f"datasets[{d.name}]": range(d.first_seed, d.first_seed + 4 * d.episodes) for d in self.datasets})
        # Every range a unit will play must be numpy seeds, said here rather than after recording and training
        # (a recording needs first_seed + episodes of them at least, as `vla-ladder record` checks).
        needed = {name: r for name, r in uses.items() if not name.startswith("datasets[")}
        needed.update({f"datasets[{d.name}]": range(d.first_seed, d.first_seed + d.episodes) for d in self.datasets})
        for name, r in needed.items():
            if r.start < 0 or r.stop > SEED_LIMIT:
                raise ValueError(f"the {name} seeds ({r.start}-{r.stop - 1}) must lie in 0..2**32-1 (numpy seeds); "
                                 "move its first_seed")
        names = list(uses)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                ra, rb = uses[a], uses[b]
                if a.startswith("datasets[") and b.startswith("datasets["):
                    continue  # two training sets may share seeds
                if len(ra) and len(rb) and ra.start < rb.stop and rb.start < ra.stop:
                    raise ValueError(f"the {a} seeds ({ra.start}-{ra.stop - 1}) overlap the {b} seeds "
                                     f"({rb.start}-{rb.stop - 1}); move a first_seed so that they are disjoint")

    @classmethod
    def load(cls, name_or_path: str) -> "StudyConfig":
        """A preset name (micro, cpu-mini, gpu-session, gpu-scratch, paper) or a path to a JSON file."""
        path = Path(name_or_path)
        if path.suffix == ".json" and path.is_file():
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError) as e:
                raise ValueError(f"{path}: not a JSON study config ({e})") from None
        else:
            known = presets()
            if name_or_path not in known:
                raise ValueError(f"unknown study {name_or_path!r}; allowed: {', '.join(known)} or a JSON file")
            data = json.loads(resources.files(PRESETS_PACKAGE).joinpath(f"{name_or_path}.json").read_text())
        return from_dict(cls, data, "")


def presets() -> list[str]:
    return sorted(p.name[:-5] for p in resources.files(PRESETS_PACKAGE).iterdir() if p.name.endswith(".json"))


def from_dict(cls, data: dict, where: str):
    """`cls` from JSON data, naming the path of a bad or unknown field ("policies[0].steps: ...")."""
    if not isinstance(data, dict):
        raise ValueError(f"{where or 'study'}: expected an object, got {type(data).__name__}")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(f"{where + ': ' if where else ''}unknown field {unknown[0]!r}; allowed: {', '.join(known)}")
    hints = typing.get_type_hints(cls)
    nested = {"datasets": DatasetSpec, "policies": PolicySpec, "grid": GridSpec, "evaluation": EvaluationSpec}
    kwargs = {}
    for key, value in data.items():
        sub = nested.get(key) if cls is StudyConfig else None
        if sub is not None and isinstance(value, list):
            kwargs[key] = [from_dict(sub, v, f"{key}[{i}]") for i, v in enumerate(value)]
        elif sub is not None:
            kwargs[key] = from_dict(sub, value, key)
        else:
            _check_type(value, hints[key], f"{where + '.' if where else ''}{key}")
            kwargs[key] = value
    try:
        return cls(**kwargs)
    except TypeError as e:  # a missing required field
        raise ValueError(f"{where or 'study'}: {e}") from None
    except ValueError as e:
        raise ValueError(f"{where}: {e}" if where and not str(e).startswith(where) else str(e)) from None


TYPE_WORDS = {int: "an integer", str: "a string", bool: "true or false", float: "a number", type(None): "null"}


def _check_type(value, hint, where: str) -> None:
    """A one-line ValueError naming the field when JSON gave another type ("5" for 5, "all" for ["all"]): the
    checks in __post_init__ would otherwise compare a string with a number or read a string letter by letter."""
    options = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    for option in options:
        if typing.get_origin(option) is list:
            (item,) = typing.get_args(option)
            if isinstance(value, list):
                for i, v in enumerate(value):
                    _check_type(v, item, f"{where}[{i}]")
                return
        elif option is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return
        elif type(value) is option:  # not isinstance: JSON's true is no integer here
            return
    said = " or ".join(f"a list of {TYPE_WORDS[typing.get_args(o)[0]].split(' ', 1)[1]}s"
                       if typing.get_origin(o) is list else TYPE_WORDS[o] for o in options)
    shown = json.dumps(value)
    raise ValueError(f"{where}: expected {said}, got {shown if len(shown) <= 60 else shown[:57] + '...'}")


def _unique(obj, *names: str) -> None:
    # A value twice would train, play or show the same thing twice under one name (the same unit id).
    for name in names:
        values = getattr(obj, name)
        twice = sorted({str(v) for v in values if values.count(v) > 1})
        if twice:
            raise ValueError(f"{name}: {', '.join(twice)} given twice; name each once, got {values}")


def _positive(obj, name: str) -> None:
    check_count(getattr(obj, name), name)
