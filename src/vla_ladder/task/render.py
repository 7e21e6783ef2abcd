"""`vla-ladder render`: both camera images of an episode's first frame, as PNG."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from vla_ladder.checks import check_output_dir
from vla_ladder.conditions import Condition, parse_regimes
from vla_ladder.contract import CAMERA_NAMES, ENV_ID
from vla_ladder.task.object_sets import resolve_object_set


def render_first_frames(condition: Condition, seed: int, out: str | Path, object_set: str = "auto",
                        env=None) -> dict[str, Path]:
    """Reset GraspObject-v1 with `seed` and write DIR/<regime>_seed<seed>_<camera>.png for both cameras, and
    DIR/<regime>_seed<seed>.json with the episode's layout and the object set used."""
    import gymnasium as gym
    from PIL import Image

    import vla_ladder.task.env  # noqa: F401
    from vla_ladder.files import atomic_path, provenance, write_json

    own = env is None
    regime = condition.regime
    if own:
        env = gym.make(ENV_ID, obs_mode="rgb", regime=regime, split=condition.split,
                       num_objects=condition.num_objects, object_set=object_set)
    try:
        obs, _ = env.reset(seed=seed)
        out = Path(out)
        paths = {}
        for cam in CAMERA_NAMES:
            path = out / f"{regime}_seed{seed}_{cam}.png"
            with atomic_path(path) as tmp:
                Image.fromarray(obs["sensor_data"][cam]["rgb"][0].cpu().numpy()).save(tmp, format="PNG")
            paths[cam] = path
        u = env.unwrapped
        paths["episode"] = write_json(out / f"{regime}_seed{seed}.json", {
            **u.layouts[0].to_dict(), "num_objects": condition.num_objects, "cameras": list(CAMERA_NAMES),
            "provenance": provenance(u.object_set)})
        return paths
    finally:
        if own:
            env.close()


@dataclass
class RenderConfig:
    """Render both cameras of an episode's first frame, as PNG, with its layout as JSON."""

    seed: int
    """the episode's seed (the scene `vla-ladder eval` plays with it)"""
    out: Path
    """output directory: <regime>_seed<seed>_<camera>.png for both cameras and <regime>_seed<seed>.json, per regime"""
    regimes: tuple[str, ...] = ("all",)
    """placement regimes: small_jitter, medium_jitter, large_jitter, full_random, or all"""
    split: str = "canonical"
    """object-region split: canonical (object i in region i), pairings_id or pairings_ood (held-out pairs)"""
    num_objects: int = 5
    """objects on the table, 1-5 (the instructed one and its distractors)"""
    object_set: str = "auto"
    """ycb, standin, or auto (YCB when its meshes are on disk, else standin; $VLA_LADDER_OBJECT_SET overrides
    auto)"""

    def __post_init__(self):
        self.conditions = [Condition(r, self.split, self.num_objects) for r in parse_regimes(self.regimes)]
        if self.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {self.seed}")
        resolve_object_set(self.object_set)  # an unknown set, or ycb without its meshes: said before the simulator
        check_output_dir(self.out, "--out")  # now, not after the simulator is built


def run(cfg: RenderConfig) -> int:
    for c in cfg.conditions:
        for what, path in render_first_frames(c, cfg.seed, cfg.out, cfg.object_set).items():
            print(f"{c.regime} {what}: {path}")
    return 0
