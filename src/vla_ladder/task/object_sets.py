"""Which objects a scene holds, decided without loading the simulator: YCB's meshes when on disk, else the stand-ins.

Config checks (`eval`, `record`, the LeRobot env) ask this before any work, and the answer must be the one the env
gets when it builds the scene; importing SAPIEN (0.2 s) or ManiSkill (4 s: its package imports every task) only to
look for five files would slow every command's first line, bad input included. `task/assets.py` builds the objects.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from vla_ladder.task.objects import OBJECTS

OBJECT_SETS = ("auto", "ycb", "standin")
"""ManiSkill's YCB meshes, vla-ladder's stand-ins, or "auto" (YCB when on disk)."""
YCB_MODEL_FILES = ("collision.ply", "textured.obj")
"""What ManiSkill's YCB loader opens for a model: the collision mesh, and the visual mesh when it renders."""


def asset_dir() -> Path:
    """ManiSkill's ASSET_DIR. ManiSkill reads $MS_ASSET_DIR once, when it is imported: once it is, its value is the
    one its loaders use; before, the one it will read (the formula of mani_skill/__init__.py)."""
    mani_skill = sys.modules.get("mani_skill")
    if mani_skill is not None and hasattr(mani_skill, "ASSET_DIR"):
        return Path(mani_skill.ASSET_DIR)
    return Path(os.getenv("MS_ASSET_DIR", os.path.join(os.path.expanduser("~"), ".maniskill"))) / "data"


def ycb_dir() -> Path:
    return asset_dir() / "assets" / "mani_skill2_ycb"


def ycb_missing() -> list[str]:
    """What ManiSkill's YCB loader would need for the five objects and cannot find (empty: all there)."""
    root = ycb_dir()
    info_path = root / "info_pick_v0.json"
    if not info_path.is_file():
        return [str(info_path)]
    try:
        info = json.loads(info_path.read_text())
    except ValueError:
        return [f"{info_path} (not valid JSON)"]
    missing = [f"{info_path}: entry {o.ycb_id}" for o in OBJECTS if "bbox" not in info.get(o.ycb_id, {})]
    return missing + [str(root / "models" / o.ycb_id / f) for o in OBJECTS for f in YCB_MODEL_FILES
                      if not (root / "models" / o.ycb_id / f).is_file()]


def ycb_available() -> bool:
    """True when ManiSkill's YCB models for all five objects are on disk (never downloads)."""
    return not ycb_missing()


def resolve_object_set(object_set: str = "auto") -> str:
    """"auto" picks "ycb" when the meshes are on disk, else "standin"; $VLA_LADDER_OBJECT_SET overrides "auto"."""
    if object_set not in OBJECT_SETS:
        raise ValueError(f"unknown object_set {object_set!r}; allowed: {', '.join(OBJECT_SETS)}")
    if object_set == "auto":
        object_set = os.environ.get("VLA_LADDER_OBJECT_SET", "auto")
        if object_set == "auto":
            return "ycb" if ycb_available() else "standin"
        try:
            return resolve_object_set(object_set)
        except ValueError as e:  # said of the variable, which the command line did not show
            raise ValueError(f"$VLA_LADDER_OBJECT_SET: {e}") from None
    if object_set == "ycb":
        missing = ycb_missing()
        if missing:
            more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
            raise ValueError(f"object_set='ycb' but ManiSkill's YCB models are incomplete: missing {missing[0]}{more}"
                             "; run `python -m mani_skill.utils.download_asset ycb` on a machine with network, "
                             "point $MS_ASSET_DIR at a copy, or use object_set='standin'")
    return object_set
