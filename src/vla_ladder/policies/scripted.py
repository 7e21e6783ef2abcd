"""A scripted grasp expert on privileged state: approach, align, descend, close, lift, hold.

Batched over parallel envs: every env runs the same phase machine, held in tensors, so one call drives one
CPU env or thousands of physx_cuda envs. It reads the instructed object's grasp site and pose from the
"state_dict" observation and outputs pd_ee_delta_pose actions (root-frame translation, root-aligned rotation,
both normalised by 0.1 m / 0.1 rad). Per-episode randomness (approach height, speed, a small offset along
the fingers, lift height) comes from the episode seed, so demonstrations differ but replay exactly.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Sequence

import numpy as np
import torch
from mani_skill.utils.geometry.rotation_conversions import (
    matrix_to_axis_angle,
    quaternion_apply,
    quaternion_to_matrix,
)

from vla_ladder.contract import ACTION_DIM, EPISODE_STEPS
from vla_ladder.policies import Policy
from vla_ladder.task.objects import NUM_OBJECTS, OBJECTS, object_index

APPROACH, DESCEND, CLOSE, LIFT = range(4)
ACTION_SCALE = 0.1  # pd_ee_delta_pose maps [-1, 1] to +-0.1 m and +-0.1 rad
FINGER_MIN, FINGER_MAX = -0.01, 0.04  # Panda gripper joint target range behind the normalised action
# Object-frame closing direction: x, y, or none (round: keep the current wrist yaw).
_CLOSING = {"x": 0.0, "y": np.pi / 2}


@dataclass
class ScriptedConfig:
    """Tuning of the scripted expert. Ranges are sampled per episode from its seed."""

    approach_height: tuple[float, float] = (0.06, 0.10)
    """Height above the grasp site of the pre-grasp waypoint (m)."""
    cruise_height: float = 0.13
    """Lowest TCP height while travelling to the object (m); clears the tallest object (the mug)."""
    lift_height: tuple[float, float] = (0.08, 0.12)
    """How far to lift the object after closing (m)."""
    gain: tuple[float, float] = (1.6, 2.0)
    """Proportional gain on the position error (1 = command the whole error each step, before clipping;
    the arm covers ~40% of a commanded step in one control period)."""
    rot_gain: float = 2.0
    """Proportional gain on the orientation error."""
    offset: float = 0.002
    """Largest random grasp offset along the fingers' width (m), perpendicular to the closing axis."""
    finger_clearance: float = 0.018
    """Opening beyond the object's width along the closing axis before the grasp (m)."""
    rim_opening: float = 0.045
    """Gripper opening around the mug's rim wall before the grasp (m)."""
    close_steps: int = 5
    """Control steps spent closing the gripper before lifting."""
    xy_tol: float = 0.006
    """Horizontal error below which the approach ends and the descent starts (m)."""
    yaw_tol: float = 0.06
    """Wrist yaw error below which the descent may start (rad)."""
    site_tol: float = 0.005
    """Distance to the grasp site at which the gripper closes (m)."""
    mug_min_angle_deg: float = 100.0
    """Smallest angle between the handle and the rim point the mug is grasped at (degrees)."""
    latest_close: int = EPISODE_STEPS - 8
    """Step by which the gripper closes whatever the error, so the lift ends inside the episode (42 of 50: closing
    takes close_steps, the lift the last 3)."""

    def __post_init__(self):
        for name in ("approach_height", "lift_height", "gain"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name} must be a range 0 < lo <= hi, got {(lo, hi)}")
        if self.close_steps < 1 or not 0 < self.latest_close < EPISODE_STEPS - self.close_steps:
            raise ValueError(f"need close_steps >= 1 and latest_close + close_steps < {EPISODE_STEPS}")


def _gripper_action(width: torch.Tensor) -> torch.Tensor:
    """Normalised gripper action that opens the fingers to `width` metres in total."""
    return ((width / 2 - FINGER_MIN) / (FINGER_MAX - FINGER_MIN) * 2 - 1).clamp(-1, 1)


class ScriptedPolicy(Policy):
    """Top-down grasp of the instructed object, aligned to its closing axis."""

    obs_mode = "state_dict"
    name = "scripted"

    def __init__(self, config: ScriptedConfig | None = None, device: str | torch.device = "cpu"):
        self.config = config or ScriptedConfig()
        self.device = torch.device(device)
        cfg = self.config
        # Per-object constants in OBJECTS order.
        axes = [o.closing_axis for o in OBJECTS]
        self._closing_yaw = torch.tensor([_CLOSING.get(a, 0.0) for a in axes], device=self.device)
        self._round = torch.tensor([a not in _CLOSING for a in axes], device=self.device)
        width = []
        for o in OBJECTS:
            if o.name == "mug":  # straddle the rim wall: one finger inside the cup, one outside
                width.append(cfg.rim_opening)
            else:
                w = o.size[0] if o.closing_axis in ("x", "any") else o.size[1]
                width.append(w + cfg.finger_clearance)
        self._open_width = torch.tensor(width, device=self.device).clamp(max=2 * FINGER_MAX)
        # Yaw period of a valid grasp: a cube can be taken across either pair of faces.
        self._symmetry = torch.tensor([np.pi / 2 if o.name == "rubiks_cube" else np.pi for o in OBJECTS],
                                      device=self.device)
        # Top of each object above its grasp site: the fingers stay above it until the wrist is aligned.
        self._top = torch.tensor([o.size[2] / 2 - o.grasp_point[2] for o in OBJECTS], device=self.device)
        # Mug geometry (object frame, handle towards +x): body axis relative to the grasp site, rim radius.
        mug = OBJECTS[object_index("mug")]
        self._mug = object_index("mug")
        axis_from_site = np.array([-mug.size[0] / 2 + mug.size[1] / 2 - mug.grasp_point[0], -mug.grasp_point[1]])
        self._mug_axis = torch.tensor(axis_from_site, dtype=torch.float32, device=self.device)
        self._mug_radius = float(np.linalg.norm(axis_from_site))
        self._mug_min_angle = np.deg2rad(cfg.mug_min_angle_deg)
        self._num_envs = 0

    # ------------------------------------------------------------------ episodes
    def _allocate(self, n: int) -> None:
        self.phase, self.t, self.phase_t = torch.zeros(3, n, dtype=torch.long, device=self.device)
        self.h_approach, self.h_lift, self.gain, self.offset = torch.zeros(4, n, device=self.device)
        self.lift_from = torch.zeros(n, 3, device=self.device)
        self._num_envs = n

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> None:
        seeds = [int(s) for s in seeds]
        if env_ids is None:
            self._allocate(len(seeds))
            env_ids = range(len(seeds))
        ids = torch.as_tensor(list(env_ids), dtype=torch.long, device=self.device)
        if len(ids) != len(seeds):
            raise ValueError(f"got {len(seeds)} seeds for {len(ids)} envs")
        cfg = self.config
        u = torch.tensor(np.array([np.random.default_rng([s, 0x5C1]).uniform(size=4) for s in seeds]),
                         dtype=torch.float32, device=self.device).reshape(-1, 4)
        for k, (name, (lo, hi)) in enumerate([("h_approach", cfg.approach_height), ("h_lift", cfg.lift_height),
                                              ("gain", cfg.gain), ("offset", (-cfg.offset, cfg.offset))]):
            getattr(self, name)[ids] = lo + (hi - lo) * u[:, k]
        self.phase[ids], self.t[ids], self.phase_t[ids] = APPROACH, 0, 0

    def _move(self, device: torch.device) -> None:
        for name, value in vars(self).items():
            if torch.is_tensor(value):
                setattr(self, name, value.to(device))
        self.device = device

    # ------------------------------------------------------------------ control
    def act(self, obs: Any, instructions: Sequence[str] | None = None) -> torch.Tensor:
        extra = obs["extra"]
        tcp = extra["tcp_pose"]
        if tcp.device != self.device:  # compute where the simulator keeps its state (CPU or GPU)
            self._move(tcp.device)
        n = tcp.shape[0]
        if n != self._num_envs:
            raise RuntimeError(f"reset() was called for {self._num_envs} envs, got observations of {n}")
        cfg = self.config
        rows = torch.arange(n, device=self.device)
        tgt = extra["target_onehot"].argmax(dim=1)
        obj_q = extra["obj_pose"].reshape(n, NUM_OBJECTS, 7)[rows, tgt, 3:]
        site = extra["target_site"].clone()

        # Wrist yaw that puts the TCP's y axis (the closing direction) on the object's closing axis;
        # the two fingers are interchangeable, so take the solution nearest the current yaw. The wrist
        # turns at most ~0.04 rad per step (the PD arm lags its IK target), so every saved radian counts.
        r_cur = quaternion_to_matrix(tcp[:, 3:])
        yaw_cur = torch.atan2(r_cur[:, 1, 0], r_cur[:, 0, 0])
        obj_x = quaternion_apply(obj_q, torch.tensor([1.0, 0, 0], device=self.device).expand(n, 3))
        obj_yaw = torch.atan2(obj_x[:, 1], obj_x[:, 0])
        closing = obj_yaw + self._closing_yaw[tgt]
        closing = torch.where(self._round[tgt], yaw_cur - np.pi / 2, closing)
        # The mug is round too: grasp its rim wall wherever the fingers already point (radially), on the
        # half away from the handle, and turn the wrist only when that spot would be too near the handle.
        mug = tgt == self._mug
        phi = _wrap(yaw_cur - np.pi / 2 - obj_yaw)  # rim angle in the object frame, handle at 0
        phi = torch.where(phi.abs() < np.pi / 2, _wrap(phi + np.pi), phi)
        phi = phi.sign() * phi.abs().clamp(min=self._mug_min_angle)
        rim = obj_yaw + phi
        axis = site[:, :2] + _rot2(obj_yaw, self._mug_axis)
        site[:, :2] = torch.where(mug[:, None], axis + self._mug_radius * torch.stack(
            [torch.cos(rim), torch.sin(rim)], 1), site[:, :2])
        closing = torch.where(mug, rim, closing)
        yaw_des = closing + np.pi / 2
        sym = self._symmetry[tgt]
        yaw_des = yaw_cur + torch.remainder(yaw_des - yaw_cur + sym / 2, sym) - sym / 2
        yaw_err = (yaw_des - yaw_cur).abs()

        # A small seeded offset perpendicular to the closing axis (along the finger pads' width).
        perp = torch.stack([-torch.sin(closing), torch.cos(closing)], dim=1) * \
            torch.where(self._round[tgt], 0.0, self.offset)[:, None]
        site[:, :2] += perp

        # Travel above every object (the 81 mm mug stands taller than most approach waypoints), then
        # come down vertically: a diagonal path sweeps the open fingers through the neighbours.
        above = site.clone()
        above[:, 2] = torch.clamp(above[:, 2] + self.h_approach, min=cfg.cruise_height)
        err_above = above - tcp[:, :3]
        err_site = site - tcp[:, :3]

        # Phase transitions (one per step at most); a late approach still leaves ~8 steps to descend.
        ph = self.phase
        late = self.t >= cfg.latest_close
        to_descend = (ph == APPROACH) & ((err_above[:, :2].norm(dim=1) < cfg.xy_tol)
                                        | (self.t >= cfg.latest_close - 8))
        to_close = (ph == DESCEND) & (((err_site.norm(dim=1) < cfg.site_tol) & (yaw_err < cfg.yaw_tol)) | late)
        to_lift = (ph == CLOSE) & (self.phase_t >= cfg.close_steps)
        self.lift_from = torch.where(to_close[:, None], tcp[:, :3], self.lift_from)
        new = ph.clone()
        new[to_descend], new[to_close], new[to_lift] = DESCEND, CLOSE, LIFT
        self.phase_t = torch.where(new != ph, torch.zeros_like(self.phase_t), self.phase_t + 1)
        self.phase = new

        # Position target per phase.
        lift_goal = self.lift_from.clone()
        lift_goal[:, 2] += self.h_lift
        hover = site.clone()
        hover[:, 2] += self._top[tgt] + 0.015  # fingertips 15 mm above the object while the wrist turns
        aligned = (yaw_err < cfg.yaw_tol) | late
        goal = torch.where((new == APPROACH)[:, None], above, torch.where(aligned[:, None], site, hover))
        goal = torch.where((new == CLOSE)[:, None], self.lift_from, goal)
        goal = torch.where((new == LIFT)[:, None], lift_goal, goal)
        err = goal - tcp[:, :3]

        r_des = _yaw_down(yaw_des)
        rot = matrix_to_axis_angle(r_des @ r_cur.transpose(1, 2))

        action = torch.zeros(n, ACTION_DIM, device=self.device)
        action[:, :3] = (err * self.gain[:, None] / ACTION_SCALE).clamp(-1, 1)
        # ManiSkill 3.0.1 scales the rotation action by the Panda's rot_lower (-0.1 rad), not by +0.1: a positive
        # action turns the TCP the negative way about the root axes (measured), hence the minus sign.
        action[:, 3:6] = (-rot * cfg.rot_gain / ACTION_SCALE).clamp(-1, 1)
        action[:, 6] = torch.where(new <= DESCEND, _gripper_action(self._open_width[tgt]),
                                   torch.full_like(yaw_cur, -1.0))
        self.t += 1
        return action

    def describe(self) -> dict:
        return {"name": self.name, "config": asdict(self.config)}


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a + np.pi, 2 * np.pi) - np.pi


def _rot2(yaw: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate the 2-d vector v by each yaw: (N, 2)."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    return torch.stack([c * v[0] - s * v[1], s * v[0] + c * v[1]], dim=1)


def _yaw_down(yaw: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) TCP orientation pointing straight down (z = -world z) with the given yaw of its x axis."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    o, z = torch.ones_like(yaw), torch.zeros_like(yaw)
    # Rz(yaw) @ diag(1, -1, -1)
    return torch.stack([torch.stack([c, s, z], -1), torch.stack([s, -c, z], -1), torch.stack([z, z, -o], -1)], 1)


def make_policy(arg: str | None = None, **kwargs) -> ScriptedPolicy:
    """Factory for `load_policy("scripted")` (parse_spec has checked that it has no argument)."""
    return ScriptedPolicy(**kwargs)
