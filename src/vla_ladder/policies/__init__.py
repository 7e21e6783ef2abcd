"""Every policy vla-ladder runs, behind one interface: an observation batch and instructions in, actions out.

The interface and the registry live here (the policies stage, below recording, evaluation and the experiments);
each kind lives in its own module of this package: scripted.py (the scripted expert), reference.py (nearest,
layout-prior, random, committed), ppo.py (the PPO expert's network, checkpoint format and policy), lerobot.py (any
LeRobot checkpoint), remote.py (a policy served by another process, in openpi's protocol; serving.py serves one).
Recording and evaluation never care which kind they run. `load_policy("kind[:arg]")` builds one from a
command-line spec; a kind's module is imported only when that kind is asked for. Installed distributions add
kinds of their own through the `vla_ladder.policies` entry-point group (`policy_kinds`).
"""

from __future__ import annotations

import functools
import multiprocessing
import sys
from abc import ABC, abstractmethod
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence
from urllib.parse import parse_qsl

if TYPE_CHECKING:  # (torch costs 1.2 s to import: the checks of a command line before any work need none of it)
    import torch

from vla_ladder.checks import ascii_digits


class Policy(ABC):
    """A batched policy for GraspObject-v1 (contract.ACTION_DIM pd_ee_delta_pose actions in [-1, 1])."""

    obs_mode: str = "state_dict"
    """The env obs_mode it needs: "state_dict" (privileged experts) or "rgb" (VLAs)."""
    name: str = "policy"

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> None:
        """Start new episodes in the given envs (all when env_ids is None); seeds make any
        randomness of the policy reproducible per episode."""

    @abstractmethod
    def act(self, obs: Any, instructions: Sequence[str]) -> torch.Tensor:
        """Return a (num_envs, 7) float tensor of actions."""

    def describe(self) -> dict:
        """What to record about this policy in result files."""
        return {"name": self.name}


# kind -> "module:factory"; factory(arg: str | None, **kwargs) -> Policy. Imported lazily so that a
# command pays only for the policy it runs.
POLICY_KINDS: dict[str, str] = {
    "scripted": "vla_ladder.policies.scripted:make_policy",
    "ppo": "vla_ladder.policies.ppo:make_policy",
    "lerobot": "vla_ladder.policies.lerobot:make_policy",
    "nearest": "vla_ladder.policies.reference:make_nearest",
    "layout-prior": "vla_ladder.policies.reference:make_layout_prior",
    "random": "vla_ladder.policies.reference:make_random",
    "committed": "vla_ladder.policies.reference:make_committed",
    "remote": "vla_ladder.policies.remote:make_policy",
}
PLUGIN_GROUP = "vla_ladder.policies"
"""The entry-point group of policy plugins: a distribution that declares `[project.entry-points."vla_ladder.policies"]
KIND = "module:factory"` adds `--policy KIND[:ARG]` to every command that plays a policy, in every worker process;
factory(arg: str | None, **kwargs) -> Policy, as for the kinds above. Optional, on the factory: check(arg), run
before any work (check_spec), and weights_file(arg), the file whose hash a run directory keeps (weights_identity).
docs/evaluation.md, "Your own policy"; examples/policy_plugin."""


@functools.cache
def _plugins() -> tuple[dict[str, str], dict[str, tuple[str, ...]]]:
    """The kinds installed plugins declare (PLUGIN_GROUP), kind -> "module:factory"; and the kinds that plugins
    declare more than once, each with the factories declared (which one entry_points() lists first is down to the
    file system's order: neither is used). A plugin cannot replace a built-in kind, nor take a name that a spec
    cannot hold (it is skipped, with a warning on stderr)."""
    declared: dict[str, dict[str, str]] = {}  # kind -> factory -> its distribution
    for ep in entry_points(group=PLUGIN_GROUP):
        if ep.name in POLICY_KINDS or not ep.name or any(c in ep.name for c in ":?/ "):
            why = "a built-in kind's" if ep.name in POLICY_KINDS else "not one a spec can hold (no ':', '?', '/', ' ')"
            if multiprocessing.parent_process() is None:  # said once, not again by each of --workers N
                print(f"[vla-ladder] warning: policy plugin {ep.name!r} ({ep.value}) skipped: its name is {why}",
                      file=sys.stderr)
        else:
            declared.setdefault(ep.name, {})[ep.value] = ep.dist.name if ep.dist else "?"
    kinds = {k: next(iter(f)) for k, f in declared.items() if len(f) == 1}
    clashes = {k: tuple(f"{dist} ({value})" for value, dist in f.items()) for k, f in declared.items() if len(f) > 1}
    return kinds, clashes


def policy_kinds() -> dict[str, str]:
    """POLICY_KINDS and the kinds that installed plugins declare, each by one plugin (_plugins)."""
    return {**POLICY_KINDS, **_plugins()[0]}


def _factory(kind: str) -> Callable[..., Policy]:
    try:
        return EntryPoint(kind, policy_kinds()[kind], PLUGIN_GROUP).load()
    except Exception as e:
        if kind in POLICY_KINDS:
            raise
        # someone else's code: whatever went wrong, one line that names the plugin
        raise ValueError(f"policy plugin {kind!r} ({policy_kinds()[kind]}) does not load: "
                         f"{type(e).__name__}: {e}") from None


# Kinds that need an argument, and what it is; every other built-in kind takes none (a plugin's factory checks its
# own).
NEEDS_ARG = {"ppo": "PATH", "lerobot": "PATH", "remote": "URL"}
EXPERT_KINDS = ("scripted", "ppo")


def reference_kinds() -> tuple[str, ...]:
    """The built-in kinds a spec names by their name alone (no checkpoint, path or server): the reference policies
    that `diagnose --references` and a study's `evaluation.reference_policies` may play beside learned ones. Read
    from POLICY_KINDS and NEEDS_ARG, so a kind registered there is a reference everywhere."""
    return tuple(k for k in POLICY_KINDS if k not in NEEDS_ARG)
"""The kinds whose episodes are demonstrations to record (the others are references or learned policies)."""


def check_expert(spec: str, given: str) -> None:
    """ValueError in one line unless `spec` names an expert: EXPERT_KINDS, or a plugin's kind (its author knows
    whether its successes are demonstrations; the built-in references' are not). `given` says where it came from."""
    kind = parse_spec(spec)[0]
    if kind not in EXPERT_KINDS and kind in POLICY_KINDS:
        allowed = ", ".join(map(_spec_form, EXPERT_KINDS))
        raise ValueError(f"{given} is not an expert; allowed: {allowed}, or a policy plugin's KIND[:ARG]")


def parse_spec(spec: str) -> tuple[str, str | None]:
    kind, _, arg = spec.partition(":")
    if kind in (clashes := _plugins()[1]):
        raise ValueError(f"policy {kind!r} is declared by two plugins, {' and '.join(clashes[kind])}; uninstall all "
                         "but one")
    if kind not in policy_kinds():
        raise ValueError(f"unknown policy {spec!r}; allowed: " + allowed_specs())
    if kind in NEEDS_ARG and not arg:
        what = "a server" if kind == "remote" else "a path"
        raise ValueError(f"policy {kind!r} needs {what}: {kind}:{NEEDS_ARG[kind]}")
    if kind in POLICY_KINDS and kind not in NEEDS_ARG and arg:
        raise ValueError(f"policy {kind!r} takes no argument, got {spec!r}; write {kind}")
    return kind, (arg or None)


def _spec_form(kind: str) -> str:
    """How a spec of `kind` is written, for error messages: scripted, ppo:PATH, constant[:ARG] (plugin)."""
    if kind not in POLICY_KINDS:
        return f"{kind}[:ARG] (plugin)"
    return f"{kind}:{NEEDS_ARG[kind]}" if kind in NEEDS_ARG else kind


def allowed_specs() -> str:
    """The kinds a --policy spec may name, with their argument, for error messages."""
    return ", ".join(map(_spec_form, policy_kinds()))


def positive_int(value: str) -> int:
    """An option's parser: an integer >= 1 (an execution horizon, say)."""
    if not ascii_digits(value) or int(value) < 1:
        raise ValueError(f"expected an integer >= 1, got {value!r}")
    return int(value)


MAX_PROMPT = 1000
"""characters of an instruction: what serve-policy accepts, and so what an option may give"""


def instruction_text(value: str) -> str:
    """An option's parser: the words of an instruction (not blank, at most MAX_PROMPT characters)."""
    if not value.strip():
        raise ValueError(f"expected the instruction's words, got {value!r}")
    if len(value) > MAX_PROMPT:
        raise ValueError(f"an instruction has at most {MAX_PROMPT} characters, got {len(value)}")
    return value


def parse_options(kind: str, arg: str, allowed: dict[str, Callable[[str], Any]]) -> tuple[str, dict]:
    """"HEAD?key=value&..." -> (HEAD, {key: allowed[key](value)}): a spec's options, each parsed by its own function
    (whose ValueError names what it expects); an option not in `allowed` names those that are, and one given twice
    is refused rather than one of its values silently kept."""
    head, _, query = arg.partition("?")
    if query and not head:
        raise ValueError(f"{kind}:{arg} gives options but no {NEEDS_ARG.get(kind, 'argument')} before the '?'")
    options = {}
    try:  # blank values kept, so that each option's own parser refuses them (urllib drops them otherwise)
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError:
        raise ValueError(f"{kind}:{arg}: options are key=value pairs joined by '&'; allowed: "
                         f"{', '.join(allowed)}") from None
    for key, value in pairs:
        if key not in allowed:
            raise ValueError(f"unknown option {key!r} in {kind}:{arg}; allowed: {', '.join(allowed)}")
        if key in options:
            raise ValueError(f"option {key} given twice in {kind}:{arg}; give it once")
        try:
            options[key] = allowed[key](value)
        except ValueError as e:
            raise ValueError(f"option {key}={value!r} in {kind}:{arg}: {e}") from None
    return head, options


def load_policy(spec: str, **kwargs) -> Policy:
    kind, arg = parse_spec(spec)
    return _factory(kind)(arg, **kwargs)


def weights_identity(spec: str) -> dict | None:
    """The sha256 of the weights file a ppo:/lerobot: spec names (for remote:, the one its server's metadata gives
    as weights_sha256, as `serve-policy` does), which a run directory keeps so that resuming it with a checkpoint
    retrained at the same path, or another model behind the same URL, is refused instead of mixing two models'
    episodes (a plugin's: the file its factory's `weights_file(arg)` names); None for kinds without weights (the
    scripted and reference policies), servers that do not say and plugins without `weights_file`."""
    kind, arg = parse_spec(spec)
    if kind == "remote":
        from vla_ladder.policies.remote import connect, parse_arg as remote_arg
        url = remote_arg(arg)[0]
        ws, metadata = connect(url)
        ws.close()
        sha = metadata.get("weights_sha256")
        return {"server": url, "sha256": sha} if isinstance(sha, str) else None
    if kind == "lerobot":
        from vla_ladder.policies.lerobot import WEIGHTS_FILE, parse_arg, resolve_checkpoint
        path = resolve_checkpoint(parse_arg(arg)[0]) / WEIGHTS_FILE
    elif kind == "ppo":
        from vla_ladder.policies.ppo import checkpoint_dir
        path = checkpoint_dir(arg) / "model.safetensors"
    else:  # a plugin names the file that holds its weights, if any, with its factory's weights_file(arg)
        weights_file = None if kind in POLICY_KINDS else getattr(_factory(kind), "weights_file", None)
        path = weights_file(arg) if callable(weights_file) else None
        if path is None:
            return None
    stat = Path(path).stat()
    return {"file": str(path), "sha256": _sha256(str(path), stat.st_ino, stat.st_size, stat.st_mtime_ns)}


def selection_episodes(spec: str) -> dict[str, range]:
    """The episodes a ppo: spec's checkpoint was chosen on, {condition key: seeds} (a train-expert run's
    checkpoints/best, the best of its evaluations on them), where its success leans high; {} for the others."""
    kind, arg = parse_spec(spec)
    if kind != "ppo":
        return {}
    from vla_ladder.policies import ppo
    return ppo.selection_episodes(ppo.checkpoint_state(ppo.checkpoint_dir(arg)))


def training_seeds(spec: str) -> set[int]:
    """The seeds of the demonstrations a lerobot: spec's checkpoint was trained on (a seed is a scene: played again,
    its rates lean high), where its training config names a vla-ladder recording on this machine; empty for the
    others."""
    kind, arg = parse_spec(spec)
    if kind != "lerobot":
        return set()
    from vla_ladder.policies import lerobot
    return lerobot.training_seeds(lerobot.resolve_checkpoint(lerobot.parse_arg(arg)[0]))


@functools.lru_cache(maxsize=32)
def _sha256(path: str, inode: int, size: int, mtime_ns: int) -> str:
    # Keyed by inode, size and mtime too: a probe's variants evaluate one checkpoint several times (a 450M model's
    # weights take seconds to hash), and a file replaced or rewritten is hashed again.
    import hashlib

    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def check_spec(spec: str, connections: int = 1) -> tuple[str, str | None]:
    """parse_spec, plus: a ppo: spec must name a readable checkpoint trained under this task contract, a lerobot:
    spec one whose options fit it, whose inputs the env provides and whose training data had this contract
    (lerobot.checked_config), a remote: spec a server that answers and takes `connections` clients. Commands call
    it before any long work (a server would otherwise build its simulator and fail every request; an evaluation
    would write its run directory and fail in its first worker)."""
    kind, arg = parse_spec(spec)
    if kind == "ppo":
        from vla_ladder.policies.ppo import load_agent
        load_agent(arg)  # a small network: read whole, so an unreadable or other-contract checkpoint stops here
    elif kind == "lerobot":
        from vla_ladder.policies.lerobot import (CONFIG_OPTIONS, check_checkpoint, check_noise_seed, checked_config,
                                                 parse_arg)
        path, options = parse_arg(arg)
        check_checkpoint(path)  # first: a copy without its weights says so before its config is parsed
        cfg = checked_config(path, **{k: v for k, v in options.items() if k in CONFIG_OPTIONS})
        check_noise_seed(cfg.type, options.get("noise_seed", 0))
    elif kind == "remote":
        from vla_ladder.policies.remote import check_server
        check_server(arg, connections)
    elif kind not in POLICY_KINDS:  # a plugin: its module must import, and its factory's own check(arg) pass
        check = getattr(_factory(kind), "check", None)
        if callable(check):
            check(arg)
    return kind, arg
