"""Seeded evaluation of a policy in GraspObject-v1, one condition (regime, split, object count) at a time.

Episode j of every condition plays seed `seed + j`, so every policy meets the same layouts. Episodes run
`num_envs` at a time (physx_cuda batches them; physx_cpu runs one env) and the final step's decomposed
metrics become one row each. `iter_episodes` yields those rows for any caller (recording, experiments);
`run_evaluation` writes the run directory: episodes.parquet, summary.json, config.json, videos/.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import torch

from vla_ladder import io
from vla_ladder.policies import Policy, load_policy, parse_spec
from vla_ladder.task.layouts import REGIMES, check_args, parse_regimes
from vla_ladder.task.objects import OBJECT_NAMES

SIM_BACKENDS = ("physx_cpu", "physx_cuda")
EPISODE_COLUMNS = ("policy", "regime", "split", "num_objects", "episode", "seed", "target", "instruction",
                   "held", "success", "grasp_any", "reach", "reach_dist", "object_set", "layout", "video")
VIDEO_FPS = 20  # the control frequency: videos play in real time


@dataclass
class EvalConfig:
    """What to evaluate; validated before any simulator starts."""

    policy: str
    """Policy spec for `load_policy` ("scripted", "ppo:PATH", "lerobot:DIR", ...)."""
    regimes: tuple[str, ...] = ("small_jitter",)
    """Placement regimes to evaluate, in order."""
    split: str = "canonical"
    """Object-region pairing split."""
    num_objects: int = 5
    """Objects on the table (1-5)."""
    episodes: int = 100
    """Episodes per condition; episode j uses seed `seed + j`."""
    seed: int = 0
    """First episode seed."""
    num_envs: int = 1
    """Episodes simulated at once (more than one needs physx_cuda)."""
    sim_backend: str = "physx_cpu"
    """ManiSkill physics backend."""
    videos: int = 0
    """Write MP4s of both cameras for the first `videos` episodes of each condition."""
    object_set: str = "auto"
    """"ycb", "standin", or "auto" (YCB when its meshes are on disk)."""
    policy_kwargs: dict = field(default_factory=dict)
    """Extra keyword arguments for the policy factory."""

    def __post_init__(self):
        if isinstance(self.regimes, str):
            self.regimes = parse_regimes(self.regimes)
        self.regimes = tuple(self.regimes)
        if not self.regimes:
            raise ValueError(f"no regime given; allowed: {', '.join(REGIMES)} or all")
        for regime in self.regimes:
            check_args(regime, self.split, self.num_objects)
        for name in ("episodes", "num_envs"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if isinstance(self.videos, bool) or not isinstance(self.videos, (int, np.integer)) or self.videos < 0:
            raise ValueError(f"videos must be an integer >= 0, got {self.videos!r}")
        if self.sim_backend not in SIM_BACKENDS:
            raise ValueError(f"unknown sim_backend {self.sim_backend!r}; allowed: {', '.join(SIM_BACKENDS)}")
        if self.sim_backend == "physx_cpu" and self.num_envs != 1:
            raise ValueError(f"physx_cpu runs one env at a time (num_envs=1); got num_envs={self.num_envs}; "
                             "use sim_backend=physx_cuda for batched evaluation")
        if self.sim_backend == "physx_cuda" and not torch.cuda.is_available():
            raise ValueError("sim_backend=physx_cuda needs a CUDA GPU; allowed here: physx_cpu")
        if self.object_set not in ("auto", "ycb", "standin"):
            raise ValueError(f"unknown object_set {self.object_set!r}; allowed: auto, ycb, standin")

    @property
    def conditions(self) -> list[tuple[str, str, int]]:
        return [(r, self.split, self.num_objects) for r in self.regimes]


def make_env(policy: Policy, regime: str, split: str, num_objects: int, num_envs: int = 1,
             sim_backend: str = "physx_cpu", render: bool = False, object_set: str = "auto"):
    """GraspObject-v1 in the policy's obs_mode; `render` adds a renderer so videos can be taken on demand
    (state policies pay for pictures only in the episodes that are filmed)."""
    import gymnasium as gym

    import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1)

    kwargs = {}
    if render:
        kwargs["render_backend"] = "gpu" if sim_backend == "physx_cuda" else "cpu"
    return gym.make("GraspObject-v1", obs_mode=policy.obs_mode, regime=regime, split=split,
                    num_objects=num_objects, num_envs=num_envs, sim_backend=sim_backend, object_set=object_set,
                    **kwargs)


def camera_frames(env, obs, rows: Sequence[int]) -> np.ndarray:
    """(len(rows), H, 2W, 3) uint8 of the given envs: wrist camera | front camera, taken from the
    observation when it holds images, else rendered now."""
    data = obs.get("sensor_data") if isinstance(obs, dict) else None
    if not data or "rgb" not in data.get("hand_camera", {}):
        data = env.unwrapped.get_sensor_images()
    return torch.cat([data["hand_camera"]["rgb"][rows], data["fixed_camera"]["rgb"][rows]], dim=2).cpu().numpy()


def iter_episodes(env, policy: Policy, seeds: Sequence[int], film: int = 0) -> Iterator[dict]:
    """Play one episode per seed, `num_envs` at a time, and yield per episode (in seed order) a dict with
    the final-step metrics, its layout, and "frames" ((T, H, 2W, 3) uint8) for the first `film` seeds
    (None for the others). The env's episode length (50 steps) ends each batch."""
    u = env.unwrapped
    n = u.num_envs
    horizon = env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else 50
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


def write_video(path: str | Path, frames: np.ndarray, fps: int = VIDEO_FPS) -> Path:
    """(T, H, W, 3) uint8 frames -> H.264 MP4 (yuv420p, plays in browsers), written atomically."""
    import imageio.v3 as iio
    # Encoded in memory: the encoder picks its container from the file name, which a temp file lacks.
    data = iio.imwrite("<bytes>", frames, extension=".mp4", plugin="pyav", codec="libx264", fps=fps,
                       out_pixel_format="yuv420p")
    with io.atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def run_evaluation(policy: str | Policy, regimes: Sequence[str] | str = ("small_jitter",),
                   split: str = "canonical", num_objects: int = 5, episodes: int = 100, seed: int = 0,
                   out: str | Path | None = None, num_envs: int = 1, sim_backend: str = "physx_cpu",
                   videos: int = 0, object_set: str = "auto", progress: bool = True,
                   policy_kwargs: dict | None = None) -> dict:
    """Evaluate `policy` (a spec or a Policy) on every condition and return the summary dict; with `out`,
    also write the run directory (results are rewritten atomically after each condition, so an
    interrupted run leaves the finished conditions readable)."""
    spec = policy if isinstance(policy, str) else getattr(policy, "spec", policy.name)
    if isinstance(policy, str):
        parse_spec(policy)  # fail on an unknown spec before any simulator starts
    cfg = EvalConfig(policy=spec, regimes=regimes, split=split, num_objects=num_objects, episodes=episodes,
                     seed=seed, num_envs=num_envs, sim_backend=sim_backend, videos=videos,
                     object_set=object_set, policy_kwargs=dict(policy_kwargs or {}))
    if isinstance(policy, str):
        policy = load_policy(policy, **cfg.policy_kwargs)
    out = Path(out) if out is not None else None
    if out is not None:
        io.write_json(out / "config.json", asdict(cfg))

    import pandas as pd
    from tqdm.auto import tqdm

    from vla_ladder.evaluation.metrics import summarize

    rows: list[dict] = []
    summary: dict = {}
    bar = tqdm(total=len(cfg.conditions) * cfg.episodes, desc=f"eval {spec}", unit="ep", disable=not progress)
    for regime, split_, k in cfg.conditions:
        env = make_env(policy, regime, split_, k, cfg.num_envs, cfg.sim_backend, render=cfg.videos > 0,
                       object_set=cfg.object_set)
        try:
            seeds = [cfg.seed + j for j in range(cfg.episodes)]
            for j, ep in enumerate(iter_episodes(env, policy, seeds, film=cfg.videos)):
                frames, layout = ep.pop("frames"), ep.pop("layout")
                video = ""
                if frames is not None and out is not None:
                    video = f"videos/{regime}-{split_}-{k}obj-ep{j:03d}-seed{ep['seed']}.mp4"
                    write_video(out / video, frames)
                rows.append(dict(policy=spec, regime=regime, split=split_, num_objects=k, episode=j, **ep,
                                 layout=json.dumps(layout.to_dict()), video=video))
                bar.update(1)
                bar.set_postfix(regime=regime, success=f"{np.mean([r['success'] for r in rows]):.2f}")
        finally:
            env.close()
        df = pd.DataFrame(rows, columns=list(EPISODE_COLUMNS))
        summary = {"policy": policy.describe(), "provenance": io.provenance(df["object_set"].iloc[0]),
                   "seed": cfg.seed, "episodes_per_condition": cfg.episodes, "conditions": summarize(df)}
        if out is not None:
            io.write_parquet(out / "episodes.parquet", df)
            io.write_json(out / "summary.json", summary)
    bar.close()
    return summary
