"""The YCB path: ManiSkill's mani_skill2_ycb layout (info_pick_v0.json, models/<id>/collision.ply and
textured.obj), built here from meshes of the stand-in shapes, is found, loaded, simulated, rendered and reported
as object_set="ycb" by the env and by `vla-ladder eval`.

ManiSkill reads its asset directory from MS_ASSET_DIR when it is imported, so everything that loads the meshes
runs in a subprocess with MS_ASSET_DIR pointing at the directory built here. The meshes differ from the
stand-ins' frames on purpose, as real scans do: some have their origin off the bounding-box centre, one is
stored at twice its size with scales [0.5], the mug is several convex parts in one file.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vla_ladder.task.objects import OBJECTS

pytestmark = pytest.mark.slow  # the real simulator, rendering, subprocess CLIs

SCALE = {"077_rubiks_cube": 0.5}
"""Models stored at 1/scale of their size, as ManiSkill's scales entry allows."""
ORIGIN_SHIFT = {"017_orange": (0.0, 0.0, 0.0365), "025_mug": (0.02, 0.0, 0.0405), "040_large_marker": (0.03, 0, 0)}
"""Where the model's origin sits relative to its bounding-box centre (scan frames are rarely centred)."""


def _parts(spec) -> list:
    """The stand-in's shape as trimesh convex parts centred on the bounding box (object frame, metres)."""
    import trimesh

    sx, sy, sz = spec.size
    if spec.name in ("apple", "orange"):
        return [trimesh.creation.icosphere(subdivisions=3, radius=sx / 2)]
    if spec.name == "rubiks_cube":
        return [trimesh.creation.box(extents=spec.size)]
    if spec.name == "large_marker":
        cyl = trimesh.creation.cylinder(radius=sy / 2, height=sx, sections=24)
        cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        return [cyl]
    if spec.name == "mug":  # body wall segments, a base, a handle: disjoint convex parts, grasped by the rim
        r_out, wall, n = sy / 2, 0.006, 12
        cx = -sx / 2 + r_out
        seg = 2 * r_out * np.tan(np.pi / n) + 0.002
        parts = []
        for k in range(n):
            a = 2 * np.pi * k / n
            box = trimesh.creation.box(extents=[wall, seg, sz - 0.002])
            box.apply_transform(trimesh.transformations.rotation_matrix(a, [0, 0, 1]))
            box.apply_translation([cx + (r_out - wall / 2) * np.cos(a), (r_out - wall / 2) * np.sin(a), 0.001])
            parts.append(box)
        base = trimesh.creation.cylinder(radius=r_out - wall, height=0.006, sections=24)
        base.apply_translation([cx, 0, -sz / 2 + 0.003])
        handle = trimesh.creation.box(extents=[sx / 2 - (cx + r_out) - 0.001, 0.012, 0.054])
        handle.apply_translation([(cx + r_out + sx / 2) / 2 + 0.0005, 0, 0])
        return [*parts, base, handle]
    raise ValueError(spec.name)


def build_ycb_dir(asset_dir: Path) -> Path:
    """An MS_ASSET_DIR holding the five objects' models where ManiSkill's YCB download puts them."""
    import trimesh

    root = asset_dir / "data" / "assets" / "mani_skill2_ycb"  # ManiSkill's ASSET_DIR is $MS_ASSET_DIR/data
    info = {}
    for spec in OBJECTS:
        scale = SCALE.get(spec.ycb_id, 1.0)
        shift = np.asarray(ORIGIN_SHIFT.get(spec.ycb_id, (0.0, 0.0, 0.0)))
        parts = [p.copy() for p in _parts(spec)]
        for p in parts:
            p.apply_translation(shift)
            p.apply_scale(1 / scale)
        whole = trimesh.util.concatenate(parts)
        model = root / "models" / spec.ycb_id
        model.mkdir(parents=True)
        whole.export(model / "collision.ply")
        # The visual mesh carries the stand-in's colour in a material, as the real textured.obj carries a texture.
        (model / "textured.mtl").write_text("newmtl body\nKd {} {} {}\n".format(*spec.rgba[:3]))
        obj = trimesh.exchange.obj.export_obj(whole, include_normals=False, include_color=False,
                                              include_texture=False)
        (model / "textured.obj").write_text("mtllib textured.mtl\nusemtl body\n" + obj)
        lo, hi = whole.bounds
        info[spec.ycb_id] = {"bbox": {"min": lo.tolist(), "max": hi.tolist()}, "scales": [scale],
                             "density": spec.density}
    (root / "info_pick_v0.json").write_text(json.dumps(info, indent=2))
    return asset_dir


def _run(code: str, asset_dir: Path, *args: str, timeout: int = 900) -> subprocess.CompletedProcess:
    env = {**os.environ, "MS_ASSET_DIR": str(asset_dir), "HF_HUB_OFFLINE": "1", "MS_SKIP_ASSET_DOWNLOAD_PROMPT": "1"}
    env.pop("VLA_LADDER_OBJECT_SET", None)
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env,
                          timeout=timeout)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-5000:]
    return done


@pytest.fixture(scope="module")
def ycb_assets(tmp_path_factory) -> Path:
    return build_ycb_dir(tmp_path_factory.mktemp("maniskill"))


ENV_CHECK = r"""
import json, sys
import gymnasium as gym
import numpy as np
import torch
import vla_ladder.task.env  # noqa: F401
from vla_ladder.task import assets, object_sets
from vla_ladder.task.objects import OBJECTS

out = {"available": object_sets.ycb_available(), "auto": object_sets.resolve_object_set("auto"),
       "ycb_dir": str(object_sets.ycb_dir())}
geo = assets.object_geometry("ycb")
out["half_extents"] = geo["half_extents"].tolist()
env = gym.make("GraspObject-v1", regime="small_jitter", split="canonical", num_objects=5, obs_mode="rgb",
               sim_backend="physx_cpu", num_envs=1)
u = env.unwrapped
obs, info = env.reset(seed=3)
out["metadata_object_set"] = u.metadata["object_set"]
out["object_set"] = u.object_set
# Resting on the table: each present object's bounding box bottom at z ~ 0 after settling.
for _ in range(5):
    obs, _, _, _, info = env.step(torch.zeros(1, 7))
out["settle_dz"] = [float(obj.pose.p[0, 2]) - float(geo["rest_z"][k])
                   for k, obj in enumerate(u.objs) if bool(u.present[0, k])]
out["masses"] = [float(obj.mass[0]) for obj in u.objs]
out["frictions"] = sorted({s.physical_material.static_friction for obj in u.objs
                           for s in obj._bodies[0].collision_shapes})
img = obs["sensor_data"]["fixed_camera"]["rgb"][0].numpy()
out["image_shape"] = list(img.shape)
out["info_keys"] = sorted(k for k in info)
apple_red = (img[..., 0] > 90) & (img[..., 1] < 50) & (img[..., 2] < 50)
out["apple_red_pixels"] = int(apple_red.sum())
np.save(sys.argv[1], img)
env.close()
print("RESULT " + json.dumps(out))
"""


def _result(done: subprocess.CompletedProcess) -> dict:
    line = [ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def test_env_builds_steps_and_renders_ycb_meshes(ycb_assets, tmp_path):
    r = _result(_run(ENV_CHECK, ycb_assets, str(tmp_path / "frame.npy")))
    assert r["available"] and r["auto"] == "ycb" and r["ycb_dir"].startswith(str(ycb_assets))
    assert r["metadata_object_set"] == r["object_set"] == "ycb"
    # Geometry comes from info_pick_v0.json's bbox times its scale: the stand-in sizes the meshes were made with.
    np.testing.assert_allclose(r["half_extents"], [np.asarray(o.size) / 2 for o in OBJECTS], atol=1.5e-3)
    # Objects rest where the env put them (origin offsets and the scale handled), not sunk or dropped.
    assert max(abs(dz) for dz in r["settle_dz"]) < 5e-3, r["settle_dz"]
    assert r["frictions"] == [1.0]  # the stand-ins' contact material, not ManiSkill's default 0.3
    # Rendered from textured.obj: the apple's material colour is in the picture.
    assert r["image_shape"] == [256, 256, 3] and r["apple_red_pixels"] > 30
    assert {"success", "grasp_any", "reach"} <= set(r["info_keys"])


def test_missing_ycb_files_are_named(ycb_assets, tmp_path, monkeypatch):
    """A partial copy is not taken for the YCB set: "auto" falls back to the stand-ins, "ycb" names the file.
    (Only the file checks run here, so ManiSkill's ASSET_DIR is set in-process, as MS_ASSET_DIR sets it.)"""
    import shutil

    import mani_skill

    from vla_ladder.task import object_sets

    partial = tmp_path / "partial"
    shutil.copytree(ycb_assets, partial)
    monkeypatch.delenv("VLA_LADDER_OBJECT_SET", raising=False)
    monkeypatch.setattr(mani_skill, "ASSET_DIR", partial / "data")
    assert object_sets.resolve_object_set("auto") == "ycb"
    (partial / "data/assets/mani_skill2_ycb/models/025_mug/textured.obj").unlink()
    assert object_sets.resolve_object_set("auto") == "standin"
    with pytest.raises(ValueError, match=r"025_mug/textured\.obj.*standin"):
        object_sets.resolve_object_set("ycb")
    info = partial / "data/assets/mani_skill2_ycb/info_pick_v0.json"
    info.write_text(json.dumps({k: v for k, v in json.loads(info.read_text()).items() if k != "013_apple"}))
    with pytest.raises(ValueError, match="entry 013_apple and 1 more"):
        object_sets.resolve_object_set("ycb")


def test_vla_ladder_eval_reports_the_ycb_set(ycb_assets, tmp_path):
    import pandas as pd

    run = tmp_path / "run"
    code = "import sys; from vla_ladder.cli import main; sys.exit(main(sys.argv[1:]))"
    _run(code, ycb_assets, "eval", "--policy", "scripted", "--out", str(run), "--episodes", "2",
         "--regimes", "small_jitter", "--num-objects", "2", "--object-set", "auto", "--workers", "1")
    episodes = pd.read_parquet(run / "episodes.parquet")
    assert len(episodes) == 2 and set(episodes["object_set"]) == {"ycb"}
    summary = json.loads((run / "summary.json").read_text())
    assert summary["provenance"]["object_set"] == "ycb"
    assert episodes["success"].all(), episodes[["seed", "target", "held", "reach_dist"]]


def test_the_object_set_is_resolved_without_the_simulator(ycb_assets):
    """Config checks resolve the object set before any work: without importing SAPIEN or ManiSkill (4 s, all its
    tasks), and to the directory ManiSkill's loader will read ($MS_ASSET_DIR/data, read when it is imported)."""
    code = """
import json, sys
from vla_ladder.task import object_sets
before = (str(object_sets.ycb_dir()), object_sets.resolve_object_set("auto"))
loaded = sorted(m for m in ("sapien", "mani_skill", "torch") if m in sys.modules)
import mani_skill
from vla_ladder.task import assets  # noqa: F401
print("RESULT " + json.dumps({"before": before, "loaded": loaded, "maniskill": str(mani_skill.ASSET_DIR),
                             "after": str(object_sets.ycb_dir())}))
"""
    r = _result(_run(code, ycb_assets))
    assert r["loaded"] == []
    assert r["before"] == [r["after"], "ycb"]
    assert r["after"] == str(Path(r["maniskill"]) / "assets" / "mani_skill2_ycb")
