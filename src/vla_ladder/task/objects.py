"""The five graspable objects of GraspObject-v1: names, YCB ids, real dimensions, colours.

Pure data (no simulator import) so that layout sampling, plots and metrics can use it anywhere.
Dimensions are the published YCB measurements (Calli et al., 2015); the stand-in meshes the project
builds when ManiSkill's YCB assets are absent are made from these numbers.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    """Name used in instructions and result files."""
    ycb_id: str
    """ManiSkill / YCB model id (under mani_skill2_ycb/models)."""
    size: tuple[float, float, float]
    """Axis-aligned extent (x, y, z) in metres of the object resting in its canonical pose."""
    rgba: tuple[float, float, float, float]
    """Stand-in colour; distinctive so that a policy can tell the objects apart."""
    footprint_radius: float
    """Radius of the disc that bounds the object on the table, used for collision-free placement."""
    density: float
    """kg/m^3 chosen so the stand-in weighs what the YCB object weighs."""
    grasp_point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Where a top-down grasp closes, in the object frame (origin at the bounding-box centre)."""
    closing_axis: str = "any"
    """Object-frame axis the fingers should close along: "x", "y", or "any" (round objects)."""

    @property
    def phrase(self) -> str:
        return self.name.replace("_", " ").replace("rubiks", "Rubik's")


OBJECTS: tuple[ObjectSpec, ...] = (
    # 75 mm apple, 73 mm orange: both just fit the Panda's 80 mm opening, as in the real YCB set.
    ObjectSpec("apple", "013_apple", (0.075, 0.075, 0.075), (0.78, 0.06, 0.06, 1.0), 0.0375, 310.0),
    ObjectSpec("orange", "017_orange", (0.073, 0.073, 0.073), (1.0, 0.55, 0.0, 1.0), 0.0365, 230.0),
    ObjectSpec("rubiks_cube", "077_rubiks_cube", (0.057, 0.057, 0.057), (0.1, 0.1, 0.1, 1.0), 0.0403, 510.0,
               closing_axis="x"),
    # Mug: 81 mm body (wider than the gripper: it is grasped by the rim, opposite the +x handle),
    # 117 mm with the handle. Its bounding-box centre is offset from the body axis by the handle.
    ObjectSpec("mug", "025_mug", (0.117, 0.081, 0.081), (0.15, 0.35, 0.85, 1.0), 0.0585, 715.0,
               grasp_point=(-0.0585 + 0.003, 0.0, 0.0205), closing_axis="x"),
    # Marker lies on its side along its local x axis: 121 mm long, 18 mm thick.
    ObjectSpec("large_marker", "040_large_marker", (0.121, 0.018, 0.018), (0.08, 0.08, 0.08, 1.0), 0.0605,
               510.0, closing_axis="y"),
)
OBJECT_NAMES: tuple[str, ...] = tuple(o.name for o in OBJECTS)
NUM_OBJECTS = len(OBJECTS)


def object_index(name: str) -> int:
    if name not in OBJECT_NAMES:
        raise ValueError(f"unknown object {name!r}; allowed: {', '.join(OBJECT_NAMES)}")
    return OBJECT_NAMES.index(name)


def instruction_for(name: str) -> str:
    """The paper's instruction template, "grasp the <object>"."""
    return f"grasp the {OBJECTS[object_index(name)].phrase}"
