"""`vla-ladder render`: both camera images of an episode's first frame, as PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

from vla_ladder.task.layouts import SPLITS, check_args, parse_regimes
from vla_ladder.task.objects import NUM_OBJECTS

CAMERAS = ("hand_camera", "fixed_camera")


def render_first_frames(regime: str, seed: int, out: str | Path, split: str = "canonical",
                        num_objects: int = NUM_OBJECTS, object_set: str = "auto", env=None) -> dict[str, Path]:
    """Reset GraspObject-v1 with `seed` and write DIR/<regime>_seed<seed>_<camera>.png for both cameras, and
    DIR/<regime>_seed<seed>.json with the episode's layout and the object set used."""
    import gymnasium as gym
    from PIL import Image

    import vla_ladder.task.env  # noqa: F401
    from vla_ladder.io import atomic_path, provenance, write_json

    own = env is None
    if own:
        env = gym.make("GraspObject-v1", obs_mode="rgb", regime=regime, split=split, num_objects=num_objects,
                       object_set=object_set)
    try:
        obs, _ = env.reset(seed=seed)
        out = Path(out)
        paths = {}
        for cam in CAMERAS:
            path = out / f"{regime}_seed{seed}_{cam}.png"
            with atomic_path(path) as tmp:
                Image.fromarray(obs["sensor_data"][cam]["rgb"][0].cpu().numpy()).save(tmp, format="PNG")
            paths[cam] = path
        u = env.unwrapped
        paths["episode"] = write_json(out / f"{regime}_seed{seed}.json", {
            **u.layouts[0].to_dict(), "num_objects": num_objects, "cameras": list(CAMERAS),
            "provenance": provenance(u.object_set)})
        return paths
    finally:
        if own:
            env.close()


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--regime", required=True, help="a regime, a comma list, or all")
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--split", default="canonical", help=f"one of {', '.join(SPLITS)}")
    p.add_argument("--num-objects", type=int, default=NUM_OBJECTS)
    p.add_argument("--object-set", default="auto", help="auto, ycb or standin")


def run(args: argparse.Namespace) -> int:
    regimes = parse_regimes(args.regime)
    for r in regimes:
        check_args(r, args.split, args.num_objects)
    for r in regimes:
        for what, path in render_first_frames(r, args.seed, args.out, args.split, args.num_objects,
                                             args.object_set).items():
            print(f"{r} {what}: {path}")
    return 0
