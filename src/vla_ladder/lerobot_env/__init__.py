"""GraspObject-v1 as a LeRobot env plugin, so LeRobot's own tools run on it:

    lerobot-eval --env.type=grasp_object --env.condition=full_random/canonical/5 \
        --policy.path=RUN/checkpoints/last/pretrained_model --eval.n_episodes=10 --eval.batch_size=1 \
        --env.episode_metrics=OUT/episodes.jsonl

Importing this module registers `GraspObjectEnvConfig` under the type "grasp_object" in LeRobot's
EnvConfig registry and a gymnasium id "vla_ladder/GraspObject-v1" for a single-env adapter that speaks
LeRobot's env convention (numpy observations {"pixels": {camera: HWC uint8}, "agent_pos": state},
info["is_success"] every step, `task_description`). LeRobot vectorises it with gymnasium's vector envs.
LeRobot imports it by itself: the set-up installs the distribution lerobot_env_grasp_object
(plugins/lerobot_env_grasp_object), and LeRobot's CLIs import every installed lerobot_env_* distribution.

Metrics. lerobot-eval scores an episode as a success when info["is_success"] was true at *any* step, and its
eval_info.json holds only sum_reward, max_reward, success and seed per episode. GraspObject-v1 judges success
at the final step, so is_success is the final step's success (false before it): LeRobot's pc_success is then
vla-ladder's success rate. The decomposed metrics are in every step's info (grasp_any: some object grasped so
far; reach: TCP within 5 cm of the target now), so the final step's info (LeRobot's final_info) holds the
episode's values; at each episode's end the adapter also logs them and, with --env.episode_metrics=FILE,
appends them as one JSON line (seed, instruction, success, grasp_any, reach, ...), which joins
eval_info.json's per_episode on the seed. LeRobot's loop has no place for them in eval_info.json itself.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig

from vla_ladder import files
from vla_ladder.conditions import Condition
from vla_ladder.contract import (ACTION_DIM, ACTION_KEY, CAMERAS, CONTROL_HZ, ENV_ID, EPISODE_STEPS, METRICS,
                                 STATE_DIM, STATE_KEY)
from vla_ladder.task.objects import OBJECT_NAMES
from vla_ladder.task.object_sets import resolve_object_set
from vla_ladder.task.physx_gpu import check_sim_backend

GYM_ID = f"vla_ladder/{ENV_ID}"
log = logging.getLogger(__name__)


class LeRobotGraspObject(gym.Env):
    """One GraspObject-v1 episode at a time with LeRobot's observation and info conventions."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}

    def __init__(self, regime: str = "small_jitter", split: str = "canonical", num_objects: int = 5,
                 object_set: str = "auto", sim_backend: str = "physx_cpu", render_mode: str = "rgb_array",
                 episode_metrics: str | None = None, robot_mesh: str = "lite", instructions: str = "canonical"):
        import vla_ladder.task.env  # noqa: F401  (registers the ManiSkill env)

        self.env = gym.make(ENV_ID, regime=regime, split=split, num_objects=num_objects, object_set=object_set,
                            robot_mesh=robot_mesh, instructions=instructions, obs_mode="rgb",
                            sim_backend=sim_backend, num_envs=1)
        self.render_mode = render_mode
        self.episode_metrics = episode_metrics
        self.observation_space = gym.spaces.Dict({
            "pixels": gym.spaces.Dict({c.name: gym.spaces.Box(0, 255, c.shape, np.uint8) for c in CAMERAS}),
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32),
        })
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)
        self._last: dict | None = None

    @property
    def task_description(self) -> str:
        return self.env.unwrapped.instructions[0]

    @property
    def task(self) -> str:
        return self.task_description

    def _convert(self, obs) -> dict:
        self._last = {
            "pixels": {c.name: obs["sensor_data"][c.name]["rgb"][0].cpu().numpy() for c in CAMERAS},
            "agent_pos": obs["extra"]["proprio"][0].cpu().numpy().astype(np.float32),
        }
        return self._last

    @staticmethod
    def _info(info: dict, final: bool = False) -> dict:
        """ManiSkill's info for env 0 as Python scalars; is_success only at the final step (see the module doc)."""
        out = {k: v[0].item() for k, v in info.items() if isinstance(v, torch.Tensor) and v.ndim == 1}
        out["is_success"] = final and bool(out.get("success", False))
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, info = self.env.reset(seed=seed)
        return self._convert(obs), self._info(info)

    def step(self, action):
        # Clamped to the action space, as `vla-ladder eval` plays a policy: ManiSkill clips only the rotation's norm,
        # so a rotation component past 1 turned the wrist otherwise here than there.
        action = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(1, ACTION_DIM).clamp(-1, 1)
        obs, reward, terminated, truncated, info = self.env.step(action)
        done = bool(terminated[0]) or bool(truncated[0])
        info = self._info(info, final=done)
        if done:
            self._report(info)
        return self._convert(obs), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def episode_record(self, info: dict) -> dict:
        """The finished episode's decomposed metrics, keyed like vla-ladder's own episode rows."""
        env, held = self.env.unwrapped, int(info.get("held", -1))
        return {"seed": env.episode_seeds[0], "instruction": self.task_description, "target": env.layouts[0].target,
                "condition": env.condition.key, "object_set": env.object_set,
                **{m: bool(info[m]) for m in METRICS}, "held": OBJECT_NAMES[held] if held >= 0 else "none",
                "reach_dist": float(info["reach_dist"])}

    def _report(self, info: dict) -> None:
        record = self.episode_record(info)
        log.info("%s episode seed=%s %r: %s", ENV_ID, record["seed"], record["instruction"],
                 " ".join(f"{m}={int(record[m])}" for m in METRICS))
        if self.episode_metrics:
            # One write of one line with O_APPEND: whole lines even from several async env processes.
            fd = os.open(self.episode_metrics, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
            try:
                os.write(fd, (files.dumps(record) + "\n").encode())  # (strict JSON: a NaN distance as null)
            finally:
                os.close(fd)

    def render(self):
        """The fixed camera's current picture (what LeRobot writes into its eval videos)."""
        return None if self._last is None else self._last["pixels"]["fixed_camera"]

    def close(self):
        self.env.close()


if GYM_ID not in gym.registry:
    gym.register(GYM_ID, entry_point=LeRobotGraspObject, max_episode_steps=EPISODE_STEPS)


@EnvConfig.register_subclass("grasp_object")
@dataclass
class GraspObjectEnvConfig(EnvConfig):
    """GraspObject-v1 for lerobot-eval / lerobot-train's env evaluation."""

    task: str | None = ENV_ID
    fps: int = CONTROL_HZ
    episode_length: int = EPISODE_STEPS
    condition: str = Condition().key
    """the condition, as its key regime/split/num_objects, e.g. --env.condition=full_random/canonical/5"""
    object_set: str = "auto"
    sim_backend: str = "physx_cpu"
    episode_metrics: str | None = None
    """append each finished episode's seed, instruction, success, grasp_any and reach to this JSON-lines file"""
    robot_mesh: str = "lite"
    """the Panda's visual mesh, as the policy's recording had it: lite (vla-ladder's default) or full"""
    instructions: str = "canonical"
    """the instruction set: canonical ("grasp the mug"), or a paraphrase set (vla-ladder's --instructions)"""
    features: dict[str, PolicyFeature] = field(default_factory=lambda: {
        ACTION_KEY: PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,)),
        "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
        **{f"pixels/{c.name}": PolicyFeature(type=FeatureType.VISUAL, shape=c.shape) for c in CAMERAS},
    })
    features_map: dict[str, str] = field(default_factory=lambda: {
        ACTION_KEY: ACTION_KEY,
        "agent_pos": STATE_KEY,
        **{f"pixels/{c.name}": c.key for c in CAMERAS},
    })

    def __post_init__(self):
        Condition.parse(self.condition)
        if self.episode_length != EPISODE_STEPS:
            raise ValueError(f"episode_length must be {EPISODE_STEPS} (GraspObject-v1 judges success at its final "
                             f"step), got {self.episode_length}")
        self._check_backend()
        from vla_ladder.task.instructions import check_instruction_set
        from vla_ladder.task.robot import check_robot_mesh
        for flag, check, value in (("robot_mesh", check_robot_mesh, self.robot_mesh),
                                   ("instructions", check_instruction_set, self.instructions)):
            try:
                check(value)
            except ValueError as e:
                raise ValueError(f"--env.{flag}: {e}") from None
        if self.episode_metrics is not None:
            self._check_episode_metrics()

    def _check_backend(self) -> None:
        """What the simulator would refuse only once it starts, after LeRobot has loaded the policy: an unknown
        object set or backend, YCB without its meshes."""
        try:
            resolve_object_set(self.object_set)
        except ValueError as e:
            raise ValueError(f"--env.object_set: {e}") from None
        check_sim_backend(self.sim_backend, "--env.sim_backend")

    def _check_episode_metrics(self) -> None:
        """A file the adapter appends to at each episode's end: a directory there failed after the first episode."""
        path = os.path.abspath(self.episode_metrics)
        if os.path.isdir(path):
            raise ValueError(f"--env.episode_metrics {self.episode_metrics} is a directory; give a file name "
                             "(JSON lines, appended to)")
        if not os.path.isdir(os.path.dirname(path)):
            raise ValueError(f"--env.episode_metrics: directory {os.path.dirname(path)} does not exist")

    @property
    def package_name(self) -> str:
        return __name__

    @property
    def gym_id(self) -> str:
        return GYM_ID

    @property
    def gym_kwargs(self) -> dict:
        c = Condition.parse(self.condition)
        return {"regime": c.regime, "split": c.split, "num_objects": c.num_objects, "object_set": self.object_set,
                "sim_backend": self.sim_backend, "episode_metrics": self.episode_metrics,
                "robot_mesh": self.robot_mesh, "instructions": self.instructions,
                "max_episode_steps": self.episode_length}
