"""The robot as the cameras see it: ManiSkill's Panda with its wrist camera, with full or lighter visual meshes.

On a CPU renderer (lavapipe) picturing the shipped Panda costs ~0.2 s a step for the two cameras: its visual
meshes hold 135k triangles and the wrist camera's RealSense D415 mesh alone 425k, against a few thousand for
the table and the five objects. `robot_mesh="lite"` renders a copy of the same robot whose *visual* meshes are
decimated to 10% of their faces (quadric decimation, `fast-simplification`), built once from the installed
ManiSkill assets into a cache directory. Collision meshes, kinematics and controllers are ManiSkill's own, so
physics, seeds and metrics are identical; only pictures change, by a few grey levels along the robot's edges
(benchmarks/results/render_speed.json has the figures).
"""

from __future__ import annotations

import functools
import hashlib
import shutil
from importlib.metadata import version
from pathlib import Path

from vla_ladder.machine import cache_root

ROBOT_MESHES = ("lite", "full")


def check_robot_mesh(robot_mesh: str) -> str:
    """`robot_mesh` if it is one of ROBOT_MESHES, else ValueError naming them (every command checks before work)."""
    if robot_mesh not in ROBOT_MESHES:
        raise ValueError(f"unknown robot_mesh {robot_mesh!r}; allowed: {', '.join(ROBOT_MESHES)}")
    return robot_mesh
LITE_UID = "panda_wristcam_lite"
KEEP_FACES = 0.10
"""Fraction of each visual mesh's faces the lite robot keeps."""
CAMERA_MOUNT_FACES = 2000
"""Faces asked of the decimated RealSense D415 (425k in ManiSkill's mesh; the decimation stops near 14k)."""
URDF = "panda_v3.urdf"
_COPIED = ("franka_description", "realsense2_description", URDF, "panda_v3.srdf")


@functools.cache
def _lite_key() -> str:
    # Read once a process: a package metadata lookup costs ~0.8 ms, and a CPU env that rebuilds its scene asks for
    # the URDF 8 times an episode.
    return hashlib.sha256(f"{version('mani-skill')}|{version('fast-simplification')}|{KEEP_FACES}|"
                          f"{CAMERA_MOUNT_FACES}".encode()).hexdigest()[:12]


def lite_urdf() -> Path:
    """The lite Panda's URDF, built on first use. The directory name hashes what decides its contents, so an
    upgrade of ManiSkill or of the decimator builds a fresh copy."""
    root = cache_root() / f"panda_wristcam_lite-{_lite_key()}"
    if not (root / URDF).is_file():
        _build(root)
    return root / URDF


def _build(root: Path) -> None:
    """Build into a temporary directory and rename it into place (files.atomic_dir): parallel workers that build at
    once all end with one whole copy, and a killed build leaves nothing half-written behind the final name."""
    import trimesh
    from mani_skill import PACKAGE_ASSET_DIR

    from vla_ladder.files import atomic_dir

    src = Path(PACKAGE_ASSET_DIR) / "robots" / "panda"
    with atomic_dir(root) as tmp:
        for name in _COPIED:
            (shutil.copytree if (src / name).is_dir() else shutil.copy2)(src / name, tmp / name)
        for path in sorted((tmp / "franka_description" / "meshes" / "visual").glob("*.glb")):
            scene = trimesh.load(path)
            for name, mesh in list(scene.geometry.items()):
                scene.geometry[name] = _decimate(mesh, max(int(len(mesh.faces) * KEEP_FACES), 64))
            scene.export(path)
        mount = tmp / "realsense2_description" / "meshes" / "d415.stl"
        _decimate(trimesh.load(mount), CAMERA_MOUNT_FACES).export(mount)


def _decimate(mesh, faces: int):
    """`mesh` with about `faces` faces, keeping its material. glTF splits vertices along normal and UV seams,
    and decimating such a mesh tears it apart: merge them first."""
    if len(mesh.faces) <= faces:
        return mesh
    material = getattr(mesh.visual, "material", None)
    mesh = mesh.copy()
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    out = mesh.simplify_quadric_decimation(face_count=faces)
    if material is not None:
        out.visual.material = material
    return out


def register_lite_panda() -> str:
    """Register the lite Panda with ManiSkill (once) and return its uid."""
    from mani_skill.agents.registration import REGISTERED_AGENTS, register_agent
    from mani_skill.agents.robots.panda.panda_wristcam import PandaWristCam

    if LITE_UID not in REGISTERED_AGENTS:
        @register_agent()
        class PandaWristCamLite(PandaWristCam):
            """ManiSkill's panda_wristcam with decimated visual meshes (see vla_ladder.task.robot)."""

            uid = LITE_UID

            @property
            def urdf_path(self) -> str:
                return str(lite_urdf())
    return LITE_UID
