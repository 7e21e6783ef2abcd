"""Seeded evaluation of a policy in GraspObject-v1, one condition (regime, split, object count) at a time.

Episode j of every condition plays seed `first_seed + j`, so every policy meets the same layouts. Episodes run
`num_envs` at a time (physx_cuda batches them; physx_cpu runs one env) and the final step's decomposed
metrics become one row each. `iter_episodes` yields those rows for any caller (recording, experiments);
`run_evaluation` writes the run directory: episodes.parquet, summary.json, config.json, videos/.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Iterator, Sequence

import numpy as np
import torch
import tyro

from vla_ladder import files
from vla_ladder.conditions import Condition, ConditionGrid
from vla_ladder.evaluation.rundir import EPISODE_COLUMNS
from vla_ladder.contract import CAMERA_NAMES, CONTROL_HZ, ENV_ID, EPISODE_STEPS
from vla_ladder.policies import POLICY_KINDS, Policy, load_policy, parse_spec
from vla_ladder.task.objects import OBJECT_NAMES

SIM_BACKENDS = ("physx_cpu", "physx_cuda")
OBJECT_SETS = ("auto", "ycb", "standin")


@dataclass
class EvalConfig:
    """Evaluate a policy on seeded episodes of every condition and write a run directory (`vla-ladder eval`)."""

    policy: str | None = None
    """policy spec: scripted, ppo:PATH, lerobot:DIR[?n_action_steps=H], nearest, layout-prior, random (required on
    the command line; the grid and the study set it per model)"""
    out: Path | None = None
    """run directory to write: episodes.parquet, summary.json, config.json, videos/ (required on the command line)"""
    grid: Annotated[ConditionGrid, tyro.conf.arg(name="")] = field(default_factory=ConditionGrid)
    """the conditions evaluated (every regime of the ladder, canonical, five objects by default)"""
    episodes: int = 100
    """episodes per condition"""
    first_seed: int = 0
    """episode j of every condition plays seed first_seed + j, so every policy meets the same layouts"""
    num_envs: int = 1
    """episodes simulated at once (more than one needs physx_cuda)"""
    sim_backend: str = "physx_cpu"
    """physx_cpu or physx_cuda"""
    videos: int = 0
    """write MP4s of both cameras for the first K episodes of each condition"""
    object_set: str = "auto"
    """ycb, standin, or auto (YCB when its meshes are on disk)"""

    def __post_init__(self):
        self.out = None if self.out is None else Path(self.out)
        if not isinstance(self.grid, ConditionGrid):
            self.grid = ConditionGrid(**self.grid)
        for name in ("episodes", "num_envs"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if isinstance(self.videos, bool) or not isinstance(self.videos, (int, np.integer)) or self.videos < 0:
            raise ValueError(f"videos must be an integer >= 0, got {self.videos!r}")
        if self.first_seed < 0:
            raise ValueError(f"first_seed must be >= 0, got {self.first_seed}")
        if self.sim_backend not in SIM_BACKENDS:
            raise ValueError(f"unknown sim_backend {self.sim_backend!r}; allowed: {', '.join(SIM_BACKENDS)}")
        if self.sim_backend == "physx_cpu" and self.num_envs != 1:
            raise ValueError(f"physx_cpu runs one env at a time (num_envs=1); got num_envs={self.num_envs}; "
                             "use sim_backend=physx_cuda for batched evaluation")
        if self.sim_backend == "physx_cuda" and not torch.cuda.is_available():
            raise ValueError("sim_backend=physx_cuda needs a CUDA GPU; allowed here: physx_cpu")
        if self.object_set not in OBJECT_SETS:
            raise ValueError(f"unknown object_set {self.object_set!r}; allowed: {', '.join(OBJECT_SETS)}")

    @property
    def conditions(self) -> list[Condition]:
        return self.grid.conditions

    @property
    def seeds(self) -> list[int]:
        return [self.first_seed + j for j in range(self.episodes)]


def make_env(policy: Policy, condition: Condition, num_envs: int = 1, sim_backend: str = "physx_cpu",
             render: bool = False, object_set: str = "auto"):
    """GraspObject-v1 in the policy's obs_mode; `render` adds a renderer so videos can be taken on demand
    (state policies pay for pictures only in the episodes that are filmed)."""
    import gymnasium as gym

    import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1)

    kwargs = {}
    if render:
        kwargs["render_backend"] = "gpu" if sim_backend == "physx_cuda" else "cpu"
    return gym.make(ENV_ID, obs_mode=policy.obs_mode, regime=condition.regime, split=condition.split,
                    num_objects=condition.num_objects, num_envs=num_envs, sim_backend=sim_backend,
                    object_set=object_set, **kwargs)


def camera_frames(env, obs, rows: Sequence[int]) -> np.ndarray:
    """(len(rows), H, 2W, 3) uint8 of the given envs: wrist camera | front camera, taken from the
    observation when it holds images, else rendered now."""
    data = obs.get("sensor_data") if isinstance(obs, dict) else None
    if not data or "rgb" not in data.get("hand_camera", {}):
        data = env.unwrapped.get_sensor_images()
    return torch.cat([data[cam]["rgb"][rows] for cam in CAMERA_NAMES], dim=2).cpu().numpy()


def iter_episodes(env, policy: Policy, seeds: Sequence[int], film: int = 0) -> Iterator[dict]:
    """Play one episode per seed, `num_envs` at a time, and yield per episode (in seed order) a dict with
    the final-step metrics, its layout, and "frames" ((T, H, 2W, 3) uint8) for the first `film` seeds
    (None for the others). The env's episode length (50 steps) ends each batch."""
    u = env.unwrapped
    n = u.num_envs
    horizon = env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else EPISODE_STEPS
    seeds = [int(s) for s in seeds]
    for start in range(0, len(seeds), n):
        chunk = seeds[start:start + n]
        # A short last batch is padded with the seeds that follow; their episodes are discarded.
        batch = chunk + [chunk[-1] + 1 + k for k in range(n - len(chunk))]
        obs, _ = env.reset(seed=batch)
        policy.reset(batch)
        instructions = u.instructions
        filmed = [k for k in range(len(chunk)) if start + k < film]  # keep only these envs' frames
        frames = [camera_frames(env, obs, filmed)] if filmed else None
        info = {}
        for _ in range(horizon):
            obs, _, _, truncated, info = env.step(policy.act(obs, instructions))
            if frames is not None:
                frames.append(camera_frames(env, obs, filmed))
            if bool(torch.as_tensor(truncated).all()):
                break
        clips = dict(zip(filmed, np.stack(frames, axis=1))) if frames is not None else {}
        for k, seed in enumerate(chunk):
            held = int(info["held"][k])
            yield dict(
                seed=seed, target=u.layouts[k].target, instruction=instructions[k],
                held=OBJECT_NAMES[held] if held >= 0 else "none",
                success=bool(info["success"][k]), grasp_any=bool(info["grasp_any"][k]),
                reach=bool(info["reach"][k]), reach_dist=float(info["reach_dist"][k]),
                object_set=u.object_set, layout=u.layouts[k], frames=clips.get(k),
            )


def write_video(path: str | Path, frames: np.ndarray, fps: int = CONTROL_HZ) -> Path:
    """(T, H, W, 3) uint8 frames -> H.264 MP4 (yuv420p, plays in browsers), written atomically."""
    import imageio.v3 as iio
    # Encoded in memory: the encoder picks its container from the file name, which a temp file lacks.
    data = iio.imwrite("<bytes>", frames, extension=".mp4", plugin="pyav", codec="libx264", fps=fps,
                       out_pixel_format="yuv420p")
    with files.atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def run_evaluation(cfg: EvalConfig, policy: Policy | None = None, progress: bool = True) -> dict:
    """Evaluate cfg.policy (or `policy`, labelled cfg.policy) on every condition and return the summary dict;
    with cfg.out, also write the run directory (results are rewritten atomically after each condition, so an
    interrupted run leaves the finished conditions readable)."""
    import pandas as pd
    from tqdm.auto import tqdm

    from vla_ladder.evaluation.metrics import summarize

    if policy is None:
        if not cfg.policy:
            raise ValueError("--policy SPEC is required; allowed: " + ", ".join(POLICY_KINDS))
        parse_spec(cfg.policy)  # an unknown spec fails before any simulator starts or file is written
        policy = load_policy(cfg.policy)
    spec, out = cfg.policy or policy.name, cfg.out
    if out is not None:
        files.write_json(out / "config.json", asdict(cfg))
    rows: list[dict] = []
    summary: dict = {}
    bar = tqdm(total=len(cfg.conditions) * cfg.episodes, desc=f"eval {spec}", unit="ep", disable=not progress)
    for cond in cfg.conditions:
        env = make_env(policy, cond, cfg.num_envs, cfg.sim_backend, render=cfg.videos > 0, object_set=cfg.object_set)
        try:
            for j, ep in enumerate(iter_episodes(env, policy, cfg.seeds, film=cfg.videos)):
                frames, layout = ep.pop("frames"), ep.pop("layout")
                video = ""
                if frames is not None and out is not None:
                    video = f"videos/{cond.slug}-ep{j:03d}-seed{ep['seed']}.mp4"
                    write_video(out / video, frames)
                rows.append(dict(policy=spec, regime=cond.regime, split=cond.split, num_objects=cond.num_objects,
                                 episode=j, **ep, layout=json.dumps(layout.to_dict()), video=video))
                bar.update(1)
                bar.set_postfix(condition=cond.key, success=f"{np.mean([r['success'] for r in rows]):.2f}")
        finally:
            env.close()
        df = pd.DataFrame(rows, columns=list(EPISODE_COLUMNS))
        summary = {"policy": policy.describe(), "provenance": files.provenance(df["object_set"].iloc[0]),
                   "first_seed": cfg.first_seed, "episodes_per_condition": cfg.episodes,
                   "conditions": summarize(df)}
        if out is not None:
            files.write_parquet(out / "episodes.parquet", df)
            files.write_json(out / "summary.json", summary)
    bar.close()
    return summary


def run(cfg: EvalConfig) -> int:
    if cfg.out is None:
        raise ValueError("--out DIR is required: the run directory to write")
    summary = run_evaluation(cfg)
    for key, c in summary["conditions"].items():
        print(f"{key}: n={c['n']} success={c['success']:.3f} grasp_any={c['grasp_any']:.3f} "
              f"reach={c['reach']:.3f}")
    print(f"wrote {cfg.out}/episodes.parquet, summary.json, config.json")
    return 0
