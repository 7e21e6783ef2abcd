"""Reference policies that calibrate the metrics: each fails in one known way.

- `nearest`: ignores the instruction, grasps the object nearest the gripper (grasp-any high, success
  about 1/#objects).
- `layout-prior`: ignores perception, grasps at the instructed object's canonical region centre (the
  location shortcut: strong under small jitter, collapsing under full random and held-out pairings).
- `random`: uniform random actions, seeded per episode (the floor).
- `committed`: the expert reading its target once, at the episode's first step, and keeping it: grounded in
  the scene, but deaf to a later instruction (the profile an instruction switch tells apart from re-reading).

nearest and layout-prior reuse the scripted expert's controller unchanged: they hand it an observation
in which the "target" is a different object (nearest) or a made-up pose at the canonical location
(layout-prior). The expert reads the target from `target_onehot`, `target_site` and that object's row of
`obj_pose`, so rewriting those three fields is the whole hook.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch
from mani_skill.utils.geometry.rotation_conversions import quaternion_apply

from vla_ladder.policies.scripted import ScriptedPolicy
from vla_ladder.contract import ACTION_DIM
from vla_ladder.policies import Policy
from vla_ladder.task import assets, object_sets
from vla_ladder.task.layouts import REGION_CENTERS
from vla_ladder.task.instructions import parse_instruction
from vla_ladder.task.objects import NUM_OBJECTS, object_index


def _retarget(obs: dict, obj: torch.Tensor, site: torch.Tensor, quat: torch.Tensor | None = None) -> dict:
    """A copy of a state_dict observation whose target is object `obj` (N,) graspable at `site` (N, 3),
    optionally with that object's orientation replaced by `quat` (N, 4 wxyz)."""
    extra = dict(obs["extra"])
    n = site.shape[0]
    extra["target_onehot"] = torch.nn.functional.one_hot(obj, NUM_OBJECTS).to(site.dtype)
    extra["target_site"] = site
    extra["tcp_to_target"] = site - extra["tcp_pose"][:, :3]
    if quat is not None:
        poses = extra["obj_pose"].reshape(n, NUM_OBJECTS, 7).clone()
        poses[torch.arange(n, device=site.device), obj, 3:] = quat
        extra["obj_pose"] = poses.reshape(n, -1)
    return {**obs, "extra": extra}


def _follow(policy: Policy, obs: dict) -> None:
    """Move `policy`'s tensors to the device the simulator keeps its state on (a CUDA GPU under physx_cuda), as
    the scripted expert does: built on the CPU, the sites were subtracted from CUDA observations."""
    device = obs["extra"]["tcp_pose"].device
    if device != policy.device:
        for name, value in vars(policy).items():
            if torch.is_tensor(value):
                setattr(policy, name, value.to(device))
        policy.device = device


def _geometry(object_set: str, device) -> dict[str, torch.Tensor]:
    geo = assets.object_geometry(object_sets.resolve_object_set(object_set))
    return {k: torch.as_tensor(v, dtype=torch.float32, device=device) for k, v in geo.items()}


class NearestObjectPolicy(Policy):
    """Grasps whichever present object is nearest the gripper (horizontally) at the episode's first
    step; the instruction is never read."""

    obs_mode = "state_dict"
    name = "nearest"

    def __init__(self, object_set: str = "auto", device: str | torch.device = "cpu", **expert_kwargs):
        self.device = torch.device(device)
        self.expert = ScriptedPolicy(device=self.device, **expert_kwargs)
        geo = _geometry(object_set, self.device)
        self._site_local = geo["center_offset"] + geo["grasp_point"]  # (5, 3) in the actor frame
        self.choice = torch.zeros(0, dtype=torch.long, device=self.device)

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> None:
        self.expert.reset(seeds, env_ids)
        if env_ids is None:
            self.choice = torch.full((len(seeds),), -1, dtype=torch.long, device=self.device)
        else:
            self.choice[torch.as_tensor(list(env_ids), dtype=torch.long, device=self.device)] = -1

    def sites(self, extra: dict) -> torch.Tensor:
        """Every object's grasp site in the world frame, (N, 5, 3), from the observed object poses."""
        n = extra["tcp_pose"].shape[0]
        poses = extra["obj_pose"].to(self.device).reshape(n, NUM_OBJECTS, 7)
        return poses[..., :3] + quaternion_apply(poses[..., 3:], self._site_local.expand(n, -1, -1))

    def act(self, obs: Any, instructions: Sequence[str] | None = None) -> torch.Tensor:
        _follow(self, obs)
        extra = obs["extra"]
        n = extra["tcp_pose"].shape[0]
        sites = self.sites(extra)
        tcp = extra["tcp_pose"].to(self.device)[:, :3]
        dist = torch.linalg.norm(sites[..., :2] - tcp[:, None, :2], dim=-1)
        dist = torch.where(extra["obj_present"].to(self.device) > 0.5, dist, torch.full_like(dist, torch.inf))
        # Commit once per episode: re-choosing every step would dither between two near objects.
        fresh = self.choice < 0
        self.choice = torch.where(fresh, dist.argmin(dim=1), self.choice)
        rows = torch.arange(n, device=self.device)
        return self.expert.act(_retarget(obs, self.choice, sites[rows, self.choice]), instructions)

    def describe(self) -> dict:
        return {"name": self.name, "controller": self.expert.describe()}


class CommittedPolicy(NearestObjectPolicy):
    """The scripted expert, reading its target once: the object the first observation names (`target_onehot`)
    is kept for the whole episode and followed wherever it stands, so it behaves as `scripted` unless the
    instruction changes mid-episode, which it never notices."""

    name = "committed"

    def act(self, obs: Any, instructions: Sequence[str] | None = None) -> torch.Tensor:
        _follow(self, obs)
        extra = obs["extra"]
        now = extra["target_onehot"].to(self.device).argmax(dim=1)
        self.choice = torch.where(self.choice < 0, now, self.choice)
        if bool((self.choice == now).all()):  # nothing switched: the expert's own observation, to the bit
            return self.expert.act(obs, instructions)
        rows = torch.arange(now.shape[0], device=self.device)
        moved = _retarget(obs, self.choice, self.sites(extra)[rows, self.choice])
        # Envs whose target did not switch keep the env's own target fields (the site computed here differs from
        # the env's by float rounding, which would move the gripper by a fraction of a millimetre).
        keep = (self.choice == now)[:, None]
        for key in ("target_onehot", "target_site", "tcp_to_target"):
            moved["extra"][key] = torch.where(keep, extra[key].to(moved["extra"][key].dtype), moved["extra"][key])
        return self.expert.act(moved, instructions)


class LayoutPriorPolicy(Policy):
    """Grasps at the instructed object's canonical training location (the centre of region i for
    object i, at its resting grasp height, unrotated); object poses are never read."""

    obs_mode = "state_dict"
    name = "layout-prior"

    def __init__(self, object_set: str = "auto", device: str | torch.device = "cpu", **expert_kwargs):
        self.device = torch.device(device)
        self.expert = ScriptedPolicy(device=self.device, **expert_kwargs)
        geo = _geometry(object_set, self.device)
        sites = torch.zeros(NUM_OBJECTS, 3, device=self.device)
        sites[:, :2] = torch.as_tensor(REGION_CENTERS, dtype=torch.float32, device=self.device)
        # Canonical pose: yaw 0, bounding-box centre resting on the table (as layouts place it).
        sites[:, 2] = geo["half_extents"][:, 2] + 1e-3
        self.sites = sites + geo["grasp_point"]

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> None:
        self.expert.reset(seeds, env_ids)

    def target_from(self, instructions: Sequence[str]) -> torch.Tensor:
        """Object index named by each instruction: "grasp the <object>" or any wording of the shipped
        paraphrase set ("pick up the red fruit"), so the prior is a perfect language reader."""
        idx = [object_index(parse_instruction(text).object) for text in instructions]
        return torch.as_tensor(idx, dtype=torch.long, device=self.device)

    def act(self, obs: Any, instructions: Sequence[str]) -> torch.Tensor:
        _follow(self, obs)
        tgt = self.target_from(instructions)
        quat = torch.tensor([1.0, 0, 0, 0], device=self.device).expand(len(tgt), 4)
        return self.expert.act(_retarget(obs, tgt, self.sites[tgt], quat), instructions)

    def describe(self) -> dict:
        return {"name": self.name, "sites": self.sites.tolist(), "controller": self.expert.describe()}


class RandomPolicy(Policy):
    """Uniform random actions in [-1, 1]^7, reproducible from each episode's seed."""

    obs_mode = "state_dict"
    name = "random"

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.rngs: list[np.random.Generator] = []

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> None:
        fresh = [np.random.default_rng([int(s), 0x4A2D]) for s in seeds]
        if env_ids is None:
            self.rngs = fresh
        else:
            for i, rng in zip(env_ids, fresh):
                self.rngs[int(i)] = rng

    def act(self, obs: Any, instructions: Sequence[str] | None = None) -> torch.Tensor:
        a = np.stack([rng.uniform(-1.0, 1.0, ACTION_DIM) for rng in self.rngs]).astype(np.float32)
        return torch.from_numpy(a).to(self.device)


def make_nearest(arg: str | None = None, **kwargs) -> NearestObjectPolicy:
    return NearestObjectPolicy(**kwargs)


def make_committed(arg: str | None = None, **kwargs) -> CommittedPolicy:
    return CommittedPolicy(**kwargs)


def make_layout_prior(arg: str | None = None, **kwargs) -> LayoutPriorPolicy:
    return LayoutPriorPolicy(**kwargs)


def make_random(arg: str | None = None, **kwargs) -> RandomPolicy:
    return RandomPolicy(**kwargs)

