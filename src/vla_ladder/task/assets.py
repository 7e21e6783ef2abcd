"""Builds the five objects in a ManiSkill scene: YCB meshes when on disk, else project-made stand-ins.

Stand-ins keep each YCB object's real size, mass and the feature that makes it hard to grasp (a mug
wider than the gripper with a handle, a thin marker lying down, 75 mm fruit in an 80 mm gripper).
Visual shapes are only added when the scene can render, so physics-only runs need no Vulkan device.

YCB meshes are read the way ManiSkill reads them (`get_actor_builder("ycb:<id>")`), from its asset directory
($MS_ASSET_DIR/data, default ~/.maniskill/data, read once when mani_skill is imported):
assets/mani_skill2_ycb/info_pick_v0.json (per model: bbox min/max in the model's frame, scales, optional
density) and models/<id>/collision.ply (split into convex parts) and textured.obj (the visual mesh).
Both object sets get the same contact material, so the set changes shapes and looks, not friction.
"""

from __future__ import annotations

import json

import numpy as np
import sapien
import sapien.render

from vla_ladder.task.object_sets import ycb_dir
from vla_ladder.task.objects import OBJECTS, ObjectSpec

# Rubik's cube sticker colours: white, yellow, red, orange, blue, green.
_STICKERS = ((1, 1, 1), (1, 0.85, 0), (0.8, 0, 0), (1, 0.45, 0), (0, 0.3, 0.9), (0, 0.6, 0.2))


def _material(rgba) -> sapien.render.RenderMaterial:
    return sapien.render.RenderMaterial(base_color=list(rgba), roughness=0.6)


def _upright() -> sapien.Pose:
    # SAPIEN cylinders lie along local x: rotate about y to stand them up.
    return sapien.Pose(q=[np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0])


def _add_box(b, half, pose, spec, render, rgba=None, collide=True, phys=None):
    if collide:
        b.add_box_collision(pose, half, material=phys, density=spec.density)
    if render:
        b.add_box_visual(pose, half, material=_material(rgba or spec.rgba))


def standin_builder(scene, spec: ObjectSpec, render: bool, phys):
    b = scene.create_actor_builder()
    sx, sy, sz = spec.size
    if spec.name in ("apple", "orange"):
        r = sx / 2
        b.add_sphere_collision(radius=r, material=phys, density=spec.density)
        # A small flat base, as real fruit have, so a touch does not roll it across the table.
        b.add_cylinder_collision(sapien.Pose([0, 0, -r + 0.002], _upright().q), radius=0.015,
                                 half_length=0.002, material=phys, density=spec.density)
        if render:
            b.add_sphere_visual(radius=r, material=_material(spec.rgba))
            stem = (0.35, 0.2, 0.05, 1) if spec.name == "apple" else (0.2, 0.5, 0.1, 1)
            b.add_cylinder_visual(sapien.Pose([0, 0, r], _upright().q), radius=0.003, half_length=0.008,
                                  material=_material(stem))
    elif spec.name == "rubiks_cube":
        h = sx / 2
        _add_box(b, [h, h, h], sapien.Pose(), spec, render, phys=phys)
        if render:  # 3x3 stickers on the five visible faces
            cell = sx / 3
            for face, (axis, sign) in enumerate([(2, 1), (0, 1), (0, -1), (1, 1), (1, -1)]):
                for i in range(3):
                    for j in range(3):
                        p = np.zeros(3)
                        p[axis] = sign * (h + 0.0005)
                        others = [a for a in range(3) if a != axis]
                        p[others[0]] = (i - 1) * cell
                        p[others[1]] = (j - 1) * cell
                        half = np.full(3, cell * 0.42)
                        half[axis] = 0.0008
                        color = _STICKERS[(face + i + j) % 6] + (1.0,)
                        b.add_box_visual(sapien.Pose(p), half, material=_material(color))
    elif spec.name == "mug":
        r_out, wall, n = sy / 2, 0.006, 12
        cx = -sx / 2 + r_out  # body axis (the handle extends the bounding box towards +x)
        seg = 2 * r_out * np.tan(np.pi / n) + 0.002
        for k in range(n):
            a = 2 * np.pi * k / n
            # Walls stop 2 mm above the base so only the base disc touches the table (fewer contacts).
            p = [cx + (r_out - wall / 2) * np.cos(a), (r_out - wall / 2) * np.sin(a), 0.001]
            q = [np.cos(a / 2), 0, 0, np.sin(a / 2)]
            _add_box(b, [wall / 2, seg / 2, sz / 2 - 0.001], sapien.Pose(p, q), spec, render, phys=phys)
        if render:
            b.add_cylinder_visual(sapien.Pose([cx, 0, -sz / 2 + 0.003], _upright().q), radius=r_out - wall / 2,
                                  half_length=0.003, material=_material(spec.rgba))
        b.add_cylinder_collision(sapien.Pose([cx, 0, -sz / 2 + 0.003], _upright().q), radius=r_out - wall / 2,
                                 half_length=0.003, material=phys, density=spec.density)
        hx0, hx1 = cx + r_out, sx / 2
        _add_box(b, [(hx1 - hx0) / 2, 0.006, 0.005], sapien.Pose([(hx0 + hx1) / 2, 0, 0.022]), spec, render,
                 phys=phys)
        _add_box(b, [(hx1 - hx0) / 2, 0.006, 0.005], sapien.Pose([(hx0 + hx1) / 2, 0, -0.022]), spec, render,
                 phys=phys)
        _add_box(b, [0.005, 0.006, 0.027], sapien.Pose([hx1 - 0.005, 0, 0]), spec, render, phys=phys)
    elif spec.name == "large_marker":
        r, hl = sy / 2, sx / 2
        b.add_cylinder_collision(radius=r, half_length=hl, material=phys, density=spec.density)
        if render:
            b.add_cylinder_visual(radius=r, half_length=hl - 0.02, material=_material(spec.rgba))
            b.add_cylinder_visual(sapien.Pose([hl - 0.02, 0, 0]), radius=r * 1.05, half_length=0.02,
                                  material=_material((0.85, 0.85, 0.85, 1)))
            b.add_cylinder_visual(sapien.Pose([-hl + 0.003, 0, 0]), radius=r * 0.6, half_length=0.004,
                                  material=_material((0.1, 0.2, 0.9, 1)))
    else:  # pragma: no cover - OBJECTS is fixed
        raise ValueError(spec.name)
    return b


def ycb_builder(scene, spec: ObjectSpec, render: bool, phys=None):
    """ManiSkill's own YCB builder; its collision shapes get `phys` (ManiSkill leaves them on the scene's
    default material, friction 0.3, where the stand-ins have 1.0)."""
    from mani_skill.utils.building.actors.common import get_actor_builder
    builder = get_actor_builder(scene, id=f"ycb:{spec.ycb_id}", add_visual=render)
    if phys is not None:
        for record in builder.collision_records:
            record.material = phys
    return builder


def build_objects(scene, object_set: str, render: bool) -> list:
    """One dynamic actor per object in every parallel sub-scene, in OBJECTS order."""
    phys = sapien.physx.PhysxMaterial(static_friction=1.0, dynamic_friction=1.0, restitution=0.0)
    actors = []
    for i, spec in enumerate(OBJECTS):
        build = ycb_builder if object_set == "ycb" else standin_builder
        builder = build(scene, spec, render, phys)
        builder.set_initial_pose(sapien.Pose(p=[0.0, 1.8, 0.1 + 0.2 * i]))
        actors.append(builder.build(name=spec.name))
    return actors


def object_geometry(object_set: str) -> dict[str, np.ndarray]:
    """Per-object (5, 3) half extents, bounding-box centre in the actor frame, grasp point (relative to
    that centre), and (5,) the actor-origin height when resting on the table."""
    half = np.array([np.asarray(o.size) / 2 for o in OBJECTS])
    center = np.zeros((len(OBJECTS), 3))
    if object_set == "ycb":
        info = json.loads((ycb_dir() / "info_pick_v0.json").read_text())
        for i, o in enumerate(OBJECTS):
            meta = info[o.ycb_id]
            scale = meta.get("scales", [1.0])[0]
            lo, hi = np.asarray(meta["bbox"]["min"]) * scale, np.asarray(meta["bbox"]["max"]) * scale
            half[i], center[i] = (hi - lo) / 2, (hi + lo) / 2
    rest_z = half[:, 2] - center[:, 2] + 1e-3
    grasp = np.array([o.grasp_point for o in OBJECTS])
    return dict(half_extents=half, center_offset=center, rest_z=rest_z, grasp_point=grasp)
