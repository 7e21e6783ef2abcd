"""GraspObject-v1 as a LeRobot env plugin, so LeRobot's own tools run on it:

    lerobot-eval --env.discover_packages_path=vla_ladder.lerobot_env --env.type=grasp_object \
        --env.condition=full_random/canonical/5 --policy.path=RUN/checkpoints/last/pretrained_model \
        --eval.n_episodes=10 --eval.batch_size=1

Importing this module registers `GraspObjectEnvConfig` under the type "grasp_object" in LeRobot's
EnvConfig registry and a gymnasium id "vla_ladder/GraspObject-v1" for a single-env adapter that speaks
LeRobot's env convention (numpy observations {"pixels": {camera: HWC uint8}, "agent_pos": state},
info["is_success"] every step, `task_description`). LeRobot vectorises it with gymnasium's vector envs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig

from vla_ladder.conditions import Condition
from vla_ladder.contract import (ACTION_DIM, ACTION_KEY, CAMERAS, CONTROL_HZ, ENV_ID, EPISODE_STEPS, STATE_DIM,
                                 STATE_KEY)

GYM_ID = f"vla_ladder/{ENV_ID}"


class LeRobotGraspObject(gym.Env):
    """One GraspObject-v1 episode at a time with LeRobot's observation and info conventions."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}

    def __init__(self, regime: str = "small_jitter", split: str = "canonical", num_objects: int = 5,
                 object_set: str = "auto", sim_backend: str = "physx_cpu", render_mode: str = "rgb_array"):
        import vla_ladder.task.env  # noqa: F401  (registers the ManiSkill env)

        self.env = gym.make(ENV_ID, regime=regime, split=split, num_objects=num_objects,
                            object_set=object_set, obs_mode="rgb", sim_backend=sim_backend, num_envs=1)
        self.render_mode = render_mode
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
    def _info(info: dict) -> dict:
        out = {k: v[0].item() for k, v in info.items() if isinstance(v, torch.Tensor) and v.ndim == 1}
        out["is_success"] = bool(out.get("success", False))
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, info = self.env.reset(seed=seed)
        return self._convert(obs), self._info(info)

    def step(self, action):
        action = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(1, ACTION_DIM)
        obs, reward, terminated, truncated, info = self.env.step(action)
        return (self._convert(obs), float(reward[0]), bool(terminated[0]), bool(truncated[0]),
                self._info(info))

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
                "sim_backend": self.sim_backend,
                "max_episode_steps": self.episode_length}
