"""Does each camera see every object whole? For each regime and object count (canonical split), over many seeds:
the layouts in which some object's footprint (the disc of its footprint radius around its centre, which
`task/layouts.py` keeps collision-free) sticks partly out of a camera's 256x256 frame, in which the instructed
object's does, and in which some object's centre is out of view. A footprint is `--rim-points` points on its rim at
table height; `..._with_top` also counts the same ring at the object's top (the cylinder it bounds).

The fixed camera's pose, field of view and size are the env's own (`GraspObjectEnv._default_sensor_configs`, read
without building an env); the wrist camera's pose is its mount link's after a reset with each seed (the robot's
start is noisy; a state-only env, no rendering), its fov and size the contract's, as the env sets them. A pinhole
projection as SAPIEN's (fx = fy = (H/2) / tan(fovy/2), principal point at the frame's centre): the frame is
[0, W] x [0, H] in pixel edges. `--render-layouts N` renders the fixed camera (rgb and segmentation, lavapipe on a
CPU) for N layouts of each kind the projection tells apart, in the condition clipped most often, and holds the
projection to the pictures: the env's camera matrices are the script's, every object's pixels lie inside its
projected cylinder, a footprint past an edge has pixels on that edge, a clear layout has none on any.

    python benchmarks/camera_coverage.py        # 10000 seeds a condition, ~100 s on 2 cores (45 s: the wrist camera)

writes benchmarks/results/camera_coverage.json.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import tyro

from vla_ladder import contract, files
from vla_ladder.conditions import Condition
from vla_ladder.contract import CAMERAS, LAYOUTS
from vla_ladder.stats import wilson
from vla_ladder.task import assets, object_sets
from vla_ladder.task.env import GraspObjectEnv
from vla_ladder.task.layouts import sample_layout
from vla_ladder.task.objects import OBJECT_NAMES, OBJECTS, object_index

HAND, FIXED = (c.name for c in CAMERAS)


@dataclass
class Args:
    seeds: int = 10000
    """layouts per condition (seeds 0 .. seeds - 1)"""
    regimes: tuple[str, ...] = ("small_jitter", "medium_jitter", "large_jitter", "full_random")
    objects: tuple[int, ...] = (1, 2, 3, 4, 5)
    rim_points: int = 32
    """points on each footprint's rim"""
    hand_camera: bool = True
    """also the wrist camera at each seed's start (one state-only env reset per seed)"""
    render_layouts: int = 20
    """render the fixed camera for this many layouts of each kind (footprint partly out, only the top out, clear; in
    the condition clipped most often) and check the projection against the pictures (0: none)"""
    out: Path = Path(__file__).parent / "results" / "camera_coverage.json"

    def __post_init__(self):  # checked before any work
        for regime in self.regimes:
            for k in self.objects:
                try:
                    Condition(regime, "canonical", k)
                except ValueError as e:
                    raise SystemExit(f"--regimes/--objects: {e}") from None
        for flag, n, least in (("--seeds", self.seeds, 1), ("--rim-points", self.rim_points, 3),
                               ("--render-layouts", self.render_layouts, 0)):
            if n < least:
                raise SystemExit(f"{flag} must be >= {least}, got {n}")


@dataclass
class Camera:
    K: np.ndarray
    """(3, 3) intrinsics, OpenCV convention"""
    world_to_cam: np.ndarray
    """(..., 3, 4) extrinsics, OpenCV convention (x right, y down, z forward); one per seed for the wrist camera"""
    width: int
    height: int


# SAPIEN's camera frame is (forward, left, up) = (x, y, z); OpenCV's (right, down, forward).
_SAPIEN_TO_CV = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def intrinsics(fov: float, width: int, height: int) -> np.ndarray:
    f = (height / 2) / np.tan(fov / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])


def extrinsics(raw_pose: np.ndarray) -> np.ndarray:
    """(..., 3, 4) world-to-camera (OpenCV) of SAPIEN camera poses (..., 7): position, quaternion wxyz."""
    p, (w, x, y, z) = raw_pose[..., :3], np.moveaxis(raw_pose[..., 3:], -1, 0)
    rot = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                    np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                    np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)
    r = _SAPIEN_TO_CV @ np.swapaxes(rot, -1, -2)
    return np.concatenate([r, -(r @ p[..., None])], axis=-1)


def fixed_camera() -> Camera:
    """The env's front camera as its config gives it (the property reads module constants only: no env is built)."""
    (cfg,) = [c for c in GraspObjectEnv._default_sensor_configs.fget(None) if c.uid == FIXED]
    raw = cfg.pose.raw_pose.double().numpy()[0]
    return Camera(intrinsics(cfg.fov, cfg.width, cfg.height), extrinsics(raw), cfg.width, cfg.height)


def hand_camera(seeds: int) -> Camera:
    """The wrist camera at the start of each seed's episode: the camera_link's pose (PandaWristCam mounts the camera
    there with an identity pose) after a reset. The robot's start noise is drawn from the seed alone (not the
    condition), so one reset a seed serves every condition; the scene is kept between resets (4 ms each)."""
    spec = CAMERAS[0]
    env = gym.make(contract.ENV_ID, obs_mode="state", num_objects=1, reconfiguration_freq=0)
    link = env.unwrapped.agent.robot.links_map["camera_link"]
    poses = np.zeros((seeds, 7))
    for s in range(seeds):
        env.reset(seed=s)
        poses[s] = link.pose.raw_pose.double().numpy()[0]
    env.close()
    return Camera(intrinsics(np.deg2rad(spec.fov_deg), spec.width, spec.height), extrinsics(poses), spec.width,
                  spec.height)


def project(cam: Camera, points: np.ndarray) -> np.ndarray:
    """(N, ..., 2) pixel coordinates of world points (N, ..., 3), seed n seen by cam.world_to_cam[n] (or the one)."""
    ext = cam.world_to_cam if cam.world_to_cam.ndim == 2 else \
        cam.world_to_cam.reshape(len(points), *(1,) * (points.ndim - 2), 3, 4)
    c = (ext[..., :3] @ points[..., None])[..., 0] + ext[..., 3]
    uv = (cam.K[:2, :2] @ (c[..., :2] / c[..., 2:])[..., None])[..., 0] + cam.K[:2, 2]
    return np.where(c[..., 2:] > 0, uv, np.inf)  # (behind the camera: out of view)


def overhang(cam: Camera, uv: np.ndarray) -> np.ndarray:
    """How far (pixels) each point lies outside the frame; 0 inside."""
    size = np.array([cam.width, cam.height])
    return np.maximum(np.maximum(-uv, uv - size), 0).max(-1)


def cylinders(xy: np.ndarray, names: tuple[str, ...], geo: dict, rim: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, k, 2, rim, 3) each footprint's rim at table height and at the object's top, (N, k, 3) each centre."""
    idx = [object_index(n) for n in names]
    radius = np.array([OBJECTS[i].footprint_radius for i in idx])
    mid = geo["rest_z"] + geo["center_offset"][:, 2]  # the bounding box's centre at rest (1 mm above the table)
    top = mid + geo["half_extents"][:, 2]
    a = np.linspace(0, 2 * np.pi, rim, endpoint=False)
    ring = radius[:, None, None] * np.stack([np.cos(a), np.sin(a)], -1)  # (k, rim, 2)
    heights = np.stack([np.zeros(len(idx)), top[idx]], -1)  # (k, 2): the table, the top
    pts = np.concatenate([np.broadcast_to((xy[:, :, None, None] + ring[None, :, None]),
                                          (*xy.shape[:2], 2, rim, 2)),
                          np.broadcast_to(heights[None, :, :, None, None], (*xy.shape[:2], 2, rim, 1))], -1)
    centres = np.concatenate([xy, np.broadcast_to(mid[idx][None, :, None], (*xy.shape[:2], 1))], -1)
    return pts, centres


def rate(k: int, n: int) -> dict:
    lo, hi = wilson(k, n)
    return {"rate": round(k / n, 4), "ci95": [round(lo, 4), round(hi, 4)], "layouts": int(k)}


FLAGS = ("any_footprint_out", "target_footprint_out", "any_out_with_top", "target_out_with_top", "any_centre_out",
         "target_centre_out")


def measure(condition: Condition, cam: Camera, geo: dict, seeds: int, rim: int) -> tuple[dict, dict, np.ndarray]:
    """Per seed, each of FLAGS and the instructed object's footprint overhang (px); per object, in how many of the
    layouts holding it its footprint is partly out, and in how many it is on the table."""
    by_objects: dict[tuple[str, ...], list] = {}  # the same objects in the same order: one array to project
    for s in range(seeds):
        lay = sample_layout(condition, s)
        by_objects.setdefault(lay.objects, []).append((s, lay.xy))
    flags = {k: np.zeros(seeds, dtype=bool) for k in FLAGS}
    target_px, per_object = np.zeros(seeds), {n: [0, 0] for n in OBJECT_NAMES}
    for names, group in by_objects.items():
        ids = np.array([s for s, _ in group])
        sub = cam if cam.world_to_cam.ndim == 2 else Camera(cam.K, cam.world_to_cam[ids], cam.width, cam.height)
        pts, centres = cylinders(np.stack([xy for _, xy in group]), names, geo, rim)
        over = overhang(sub, project(sub, pts))  # (n, k, 2, rim)
        table, either = over[:, :, 0].max(-1), over.max((-1, -2))  # (n, k)
        centre_out = overhang(sub, project(sub, centres)) > 0
        for key, hit in zip(FLAGS, (table.max(1) > 0, table[:, 0] > 0, either.max(1) > 0, either[:, 0] > 0,
                                    centre_out.any(1), centre_out[:, 0])):
            flags[key][ids] = hit
        target_px[ids] = table[:, 0]
        for j, n in enumerate(names):
            per_object[n][0] += int((table[:, j] > 0).sum())
            per_object[n][1] += len(ids)
    return flags, per_object, target_px


def rendered(env, seed: int, fixed: Camera, hand: Camera | None, geo: dict, rim: int) -> dict:
    """One layout rendered and set against its projection in the fixed camera: whether the env's camera matrices are
    the script's, and per present object its pixels (segmentation), whether they lie inside its projected cylinder's
    bounding box (the footprint bounds the object), which frame edges they touch and which the projection puts the
    object's footprint (at table height) past."""
    obs, _ = env.reset(seed=seed)
    u = env.unwrapped
    params = {cam: {k: v[0].double().numpy() for k, v in obs["sensor_param"][cam].items()} for cam in (FIXED, HAND)}
    seg = obs["sensor_data"][FIXED]["segmentation"][0, ..., 0].numpy()
    lay, ids = u.layouts[0], [int(o.per_scene_id[0]) for o in u.objs]
    pts, _ = cylinders(lay.xy[None], lay.objects, geo, rim)
    uv = project(fixed, pts)[0]  # (k, 2, rim, 2)
    objects = []
    for j, name in enumerate(lay.objects):
        rows, cols = np.nonzero(seg == ids[object_index(name)])
        lo, hi = uv[j].reshape(-1, 2).min(0), uv[j].reshape(-1, 2).max(0)
        # (a pixel's centre is its index + 0.5; one pixel of slack for rasterisation)
        inside = bool(((cols + 0.5 >= lo[0] - 1) & (cols + 0.5 <= hi[0] + 1)
                       & (rows + 0.5 >= lo[1] - 1) & (rows + 0.5 <= hi[1] + 1)).all())
        table = uv[j, 0].reshape(-1, 2)
        past = {"left": -table[:, 0].min(), "right": table[:, 0].max() - fixed.width, "top": -table[:, 1].min(),
                "bottom": table[:, 1].max() - fixed.height}
        objects.append({"object": name, "pixels": int(len(rows)),
                        "footprint_overhang_px": round(float(max(0.0, *past.values())), 1),
                        "cylinder_margin_px": round(float(min(lo.min(), fixed.width - hi[0], fixed.height - hi[1])), 1),
                        "pixels_inside_projected_cylinder": inside,
                        "edge_pixels": {"left": int((cols == 0).sum()), "right": int((cols == fixed.width - 1).sum()),
                                        "top": int((rows == 0).sum()),
                                        "bottom": int((rows == fixed.height - 1).sum())},
                        "footprint_past_edge": [side for side, v in past.items() if v > 0]})
    cams = [(fixed.K, fixed.world_to_cam, params[FIXED])]
    if hand is not None:  # (its pose at this seed's start)
        cams.append((hand.K, hand.world_to_cam[seed], params[HAND]))
    matrices = all(np.allclose(p["intrinsic_cv"], K, atol=1e-3) and np.allclose(p["extrinsic_cv"], ext, atol=1e-4)
                   for K, ext, p in cams)
    return {"seed": seed, "camera_matrices_match": bool(matrices), "objects": objects}


def render_check(condition: Condition, sets: dict[str, list[int]], worst: int, fixed: Camera, hand: Camera | None,
                 geo: dict, rim: int) -> dict:
    """Render the fixed camera for layouts of each kind the projection tells apart (some footprint partly out at
    table height; only some cylinder's top ring out; every cylinder inside), and the one whose instructed object's
    footprint overhangs the most: the env's camera matrices must be the script's, every object's pixels inside its
    projected cylinder, an object whose footprint the projection puts past an edge must have pixels on that edge,
    and a clear layout none on any. How many layouts of each kind show an object on the frame's edge says how
    often a footprint out of view is an object cut by the frame (the footprint is a disc bounding the object)."""
    env = gym.make(contract.ENV_ID, obs_mode="rgb+segmentation", regime=condition.regime, split=condition.split,
                   num_objects=condition.num_objects)
    frames = {s: rendered(env, s, fixed, hand, geo, rim) for s in dict.fromkeys([worst, *sum(sets.values(), [])])}
    env.close()

    def on_edge(frame: dict) -> bool:
        return any(sum(o["edge_pixels"].values()) > 0 for o in frame["objects"])

    past = [o for f in frames.values() for o in f["objects"] if o["footprint_past_edge"]]
    summary = {
        "layouts_rendered": len(frames),
        "camera_matrices_match": sum(f["camera_matrices_match"] for f in frames.values()),
        "objects_inside_their_projected_cylinder": [sum(o["pixels_inside_projected_cylinder"] for f in frames.values()
                                                        for o in f["objects"] if o["pixels"]),
                                                    sum(bool(o["pixels"]) for f in frames.values()
                                                        for o in f["objects"])],
        "footprints_past_an_edge_with_pixels_on_it": [sum(all(o["edge_pixels"][e] > 0 for e in o["footprint_past_edge"])
                                                          for o in past), len(past)],
        **{f"{kind}_layouts_with_an_object_on_the_edge": [sum(on_edge(frames[s]) for s in seeds), len(seeds)]
           for kind, seeds in sets.items()},
    }
    return {"condition": condition.key, "summary": summary, "worst_target": frames[worst], "seeds": sets}


def main(args: Args) -> None:
    t0 = time.monotonic()
    object_set = object_sets.resolve_object_set("auto")
    geo = assets.object_geometry(object_set)
    cams = {FIXED: fixed_camera()}
    if args.hand_camera:
        cams[HAND] = hand_camera(args.seeds)
        print(f"wrist camera at {args.seeds} seeds' starts ({time.monotonic() - t0:.0f} s)", flush=True)
    rows, flagged = [], {}
    for regime in args.regimes:
        for k in args.objects:
            condition = Condition(regime, "canonical", k)
            row = {"condition": condition.key}
            for name, cam in cams.items():
                flags, per_object, target_px = measure(condition, cam, geo, args.seeds, args.rim_points)
                row[name] = {**{f: rate(int(v.sum()), args.seeds) for f, v in flags.items()},
                             "footprint_out_by_object": {n: round(a / b, 4) for n, (a, b) in per_object.items() if b}}
                if name == FIXED:
                    flagged[condition] = (flags, target_px)
                r = row[name]
                pct = {f: f"{100 * r[f]['rate']:5.1f}%" for f in FLAGS}
                print(f"{condition.key:26s} {name:12s} footprint partly out: any {pct['any_footprint_out']} target "
                      f"{pct['target_footprint_out']} | with the top: any {pct['any_out_with_top']} target "
                      f"{pct['target_out_with_top']} | centre out: any {pct['any_centre_out']} target "
                      f"{pct['target_centre_out']} ({time.monotonic() - t0:.0f} s)", flush=True)
            rows.append(row)
    result = {"seeds": args.seeds, "rim_points": args.rim_points, "layouts": LAYOUTS, "object_set": object_set,
              "cameras": {name: {"intrinsics": cam.K.round(4).tolist(),
                                 "world_to_cam": cam.world_to_cam.round(5).tolist() if cam.world_to_cam.ndim == 2
                                 else "the camera_link's pose after each seed's reset (robot start noise)"}
                          for name, cam in cams.items()},
              "rows": rows}
    if args.render_layouts:
        # The condition clipped most often; in it, the layout whose instructed object overhangs the most.
        condition = max(flagged, key=lambda c: flagged[c][0]["any_out_with_top"].sum())
        flags, target_px = flagged[condition]
        table, top = flags["any_footprint_out"], flags["any_out_with_top"]
        sets = {kind: np.flatnonzero(hit)[:args.render_layouts].tolist()
                for kind, hit in (("footprint_out", table), ("only_top_out", top & ~table), ("clear", ~top))}
        check = render_check(condition, sets, int(target_px.argmax()), cams[FIXED], cams.get(HAND), geo,
                             args.rim_points)
        result["render_check"] = check
        print(f"render check, {check['condition']}: {check['summary']}")
        for o in check["worst_target"]["objects"]:
            print(f"  seed {check['worst_target']['seed']} {o['object']:12s} {o['pixels']:5d} px, footprint "
                  f"{o['footprint_overhang_px']:4.1f} px out {o['footprint_past_edge']}, pixels on the edge "
                  f"{o['edge_pixels']}, inside its projected cylinder: {o['pixels_inside_projected_cylinder']}")
    result["wall_s"] = round(time.monotonic() - t0, 1)
    result["provenance"] = files.provenance(object_set)
    files.write_json(args.out, result)
    print(args.out)


if __name__ == "__main__":
    main(tyro.cli(Args))
