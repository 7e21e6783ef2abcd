"""Imported by LeRobot's plugin discovery (any installed distribution named lerobot_env_*): registering
vla-ladder's GraspObject-v1 env config makes `lerobot-eval --env.type=grasp_object` work without
`--env.discover_packages_path`. The env itself lives in vla_ladder.lerobot_env."""

from vla_ladder.lerobot_env import GYM_ID, GraspObjectEnvConfig

__all__ = ["GYM_ID", "GraspObjectEnvConfig"]
