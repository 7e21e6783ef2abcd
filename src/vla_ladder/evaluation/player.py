"""Playing episodes: a policy in GraspObject-v1, one `Job` (condition, seed, reset options) at a time, in this
process or in a pool of worker processes.

A CPU env simulates one episode at a time and rebuilds its scene every episode, so an episode is a function
of its job alone: any number of workers, in any order, play the same episodes bit for bit (tested). Each
worker holds one env and one policy for its whole life; the condition travels with the job through reset
options, so one env serves every condition. Filmed episodes are encoded to MP4 where they were played.
On physx_cuda, one process steps `num_envs` episodes at once instead.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from vla_ladder.conditions import Condition
from vla_ladder.contract import CAMERA_NAMES, CONTROL_HZ, ENV_ID, EPISODE_STEPS, METRICS
from vla_ladder.machine import exit_with_parent, limit_threads

PHASES = ("reset", "policy", "env", "film", "encode")
"""Where an episode's time goes: reset (env reset with its scene rebuild, the policy's reset, the layouts and
instructions read back, and read again at an instruction switch), policy (act: preprocessing, inference, the action
back on the env's device), env (step: physics, the cameras the policy sees, observations out of the env processes),
film (the pictures of filmed episodes: both cameras rendered for a state policy, copied off the GPU), encode (their
MP4s)."""


@dataclass(frozen=True)
class Job:
    """One episode to play: its condition and seed, extra reset options, and where its video goes."""

    condition: Condition
    episode: int
    """index of the episode within its group (episode j of a condition plays seed first_seed + j)"""
    seed: int
    options: tuple[tuple[str, Any], ...] = ()
    """extra env reset options as (name, value) pairs, e.g. (("instruct", "mug"),)"""
    video: str = ""
    """MP4 path to film this episode into ("": not filmed)"""


@dataclass(frozen=True)
class EnvSettings:
    """What every env of a run is made with, besides the condition."""

    sim_backend: str = "physx_cpu"
    num_envs: int = 1
    object_set: str = "auto"
    robot_mesh: str = "lite"
    render: bool = False
    """add a renderer even for a state policy (filmed episodes)"""
    extra: dict = field(default_factory=dict)
    """further gym.make keyword arguments of GraspObject-v1"""


def camera_frames(env, obs, rows: Sequence[int]) -> np.ndarray:
    """(len(rows), H, 2W, 3) uint8 of the given envs: wrist camera | front camera, taken from the
    observation when it holds images, else rendered now."""
    import torch

    data = obs.get("sensor_data") if isinstance(obs, dict) else None
    if not data or "rgb" not in data.get(CAMERA_NAMES[0], {}):
        data = env.unwrapped.get_sensor_images()
    return torch.cat([data[cam]["rgb"][rows] for cam in CAMERA_NAMES], dim=2).cpu().numpy()


def write_video(path: str | Path, frames: np.ndarray, fps: int = CONTROL_HZ) -> Path:
    """(T, H, W, 3) uint8 frames -> H.264 MP4 (yuv420p, plays in browsers), written atomically.

    x264's veryfast preset: a filmed episode is for watching, and with --workers N every core encodes. On an
    episode's 51 frames of both cameras (256x512) it took 0.20 CPU s against 0.55 through imageio with x264's
    default (medium) at the same CRF, for a file 5% smaller and 0.1 grey level further from the frames on average
    (2 cores, 2026-11-27). A filmed run on the H200 machine had spent 2.7 s an episode filming and encoding with
    the default, 80% of its workers' time; timed apart there with this preset (2026-11-28), filming (rendering) took
    2.59 s an episode and encoding 0.13 s (benchmarks/results/eval_speed_scripted_cuda.json)."""
    import io
    from fractions import Fraction

    import av

    from vla_ladder import files

    buf = io.BytesIO()  # encoded in memory, then written atomically
    with av.open(buf, "w", format="mp4") as out:
        stream = out.add_stream("libx264", fps, options={"preset": "veryfast", "crf": "23"})
        stream.time_base = Fraction(1, fps)
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        for i, frame in enumerate(frames):
            picture = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            picture.pts = i
            out.mux(stream.encode(picture))
        out.mux(stream.encode())
    with files.atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())
    return Path(path)


class Stopwatch:
    """Seconds spent in each of PHASES, summed over the `with watch(phase):` blocks timed."""

    def __init__(self):
        self.seconds = dict.fromkeys(PHASES, 0.0)

    @contextmanager
    def __call__(self, phase: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[phase] += time.perf_counter() - start


class Player:
    """One env and one policy; plays jobs, `num_envs` at a time (on the CPU backend: num_envs processes in
    lockstep, task/vector.py)."""

    def __init__(self, policy, settings: EnvSettings):
        import gymnasium as gym
        import torch

        import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1)

        self.policy, self.settings = policy, settings
        # One torch thread, as each --workers copy has, unless OMP_NUM_THREADS says otherwise; close() restores the
        # process's own. Under the passive OpenMP waits every command but serve-policy runs with (cli.py), a second
        # thread is woken for every small matmul: the study's SmolVLA-scratch on 2 cores took 3.9-4.0 ms a step with
        # one thread and 8.1-9.4 with two (`eval --workers 1`, 8 episodes in 16.9-17.5 s against 18.5-18.9), 5.2 and
        # 10.5 acting on two envs (`--num-envs 2`).
        self._threads = torch.get_num_threads()
        if "OMP_NUM_THREADS" not in os.environ:
            torch.set_num_threads(1)
        kwargs = dict(settings.extra)
        if settings.render:  # a state policy's env renders only when asked; filmed episodes need pictures
            kwargs["render_backend"] = "gpu" if torch.cuda.is_available() else "cpu"
        make = dict(obs_mode=policy.obs_mode, object_set=settings.object_set, robot_mesh=settings.robot_mesh, **kwargs)
        if settings.sim_backend == "physx_cpu" and settings.num_envs > 1:
            # One CPU env per process, in lockstep: the policy here acts on all of them as one batch.
            from vla_ladder.task.vector import CPUEnvs
            self.env = CPUEnvs(settings.num_envs, **make)
        else:
            self.env = gym.make(ENV_ID, num_envs=settings.num_envs, sim_backend=settings.sim_backend, **make)

    def close(self) -> None:
        import torch

        self.env.close()
        torch.set_num_threads(self._threads)

    def play(self, jobs: Sequence[Job]) -> list[dict]:
        """Play up to num_envs jobs sharing their options at once; one result row per job, in order."""
        import torch

        env, u, n = self.env, self.env.unwrapped, self.env.unwrapped.num_envs
        jobs = list(jobs)
        # A short batch is padded with copies of its last job; their episodes are discarded.
        batch = jobs + [jobs[-1]] * (n - len(jobs))
        options = {**dict(jobs[0].options), "conditions": [j.condition for j in batch]}
        watch, steps = Stopwatch(), 0
        with watch("reset"):
            obs, _ = env.reset(seed=[j.seed for j in batch], options=options)
            self.policy.reset([j.seed for j in batch])
            instructions = u.instructions
            layouts, object_set = u.layouts, u.object_set  # one query each (CPUEnvs asks every env process)
        # An instruction switch (reset option "switch_at") changes the instructions at its step: they are read
        # again then, and only then (with CPUEnvs every read asks every env process).
        switch = options.get("switch_at")
        reread = {int(k) for k in (switch if isinstance(switch, (list, tuple)) else [switch]) if k is not None}
        filmed = [k for k, j in enumerate(jobs) if j.video]
        with watch("film"):
            frames = [camera_frames(env, obs, filmed)] if filmed else None
        info: dict = {}
        horizon = env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else EPISODE_STEPS
        for _ in range(horizon):
            with watch("policy"):
                # Clamped to the action space here, for every policy (a plugin's included), as the LeRobot env does
                # under lerobot-eval: ManiSkill clips only the rotation's norm, so a component past 1 turned the
                # wrist otherwise. An action inside [-1, 1] is unchanged, bit for bit.
                action = torch.as_tensor(self.policy.act(obs, instructions)).clamp(-1, 1)
            with watch("env"):
                obs, _, _, truncated, info = env.step(action)
            steps += 1
            if steps in reread:
                with watch("reset"):
                    instructions = u.instructions
            if frames is not None:
                with watch("film"):
                    frames.append(camera_frames(env, obs, filmed))
            if bool(torch.as_tensor(truncated).all()):
                break
        if frames is not None:
            with watch("encode"):
                for k, clip in zip(filmed, np.stack(frames, axis=1)):
                    write_video(jobs[k].video, clip)
        # Each episode carries its share of the batch's time, so the rows of a run sum to its totals.
        timing = {"steps": steps / len(jobs), **{f"{p}_s": t / len(jobs) for p, t in watch.seconds.items()}}
        from vla_ladder.task.objects import OBJECT_NAMES

        rows = []
        for k, job in enumerate(jobs):
            held = int(info["held"][k])
            lay = layouts[k]
            rows.append(dict(
                # After an instruction switch: the object and wording in force at the end, which success is
                # judged against; the layout says what came first and when it switched.
                seed=job.seed, target=lay.final_target, instruction=instructions[k],
                held=OBJECT_NAMES[held] if held >= 0 else "none",
                **{m: bool(info[m][k]) for m in METRICS}, reach_dist=float(info["reach_dist"][k]),
                tcp_x=float(info["tcp_xy"][k][0]), tcp_y=float(info["tcp_xy"][k][1]),
                object_set=object_set, layout=lay.to_dict(), policy_info=self.policy.describe(), timing=timing))
        return rows


# ---------------------------------------------------------------------- worker processes
_PLAYER: Player | Exception | None = None


def _start_worker(spec: str, settings: EnvSettings, threads: int) -> None:
    """Runs once in each spawned worker, before any job: `threads` each for the renderer and torch, so N
    workers use N cores instead of fighting over them."""
    from vla_ladder.policies import load_policy

    exit_with_parent()  # an evaluation killed with -9 does not leave its workers behind
    limit_threads(threads)
    global _PLAYER
    try:
        _PLAYER = Player(load_policy(spec), settings)
    except Exception as e:  # raised by the first job instead: an initializer's error only breaks the pool, unsaid
        _PLAYER = e


def _play_in_worker(jobs: tuple[Job, ...]) -> list[dict]:
    if isinstance(_PLAYER, Exception):
        raise _PLAYER
    return _PLAYER.play(jobs)


def play(jobs: Sequence[Job], spec: str, settings: EnvSettings, workers: int = 1, policy=None,
         ) -> Iterator[tuple[Job, dict]]:
    """Play every job and yield (job, result row) as they finish (not in order). `policy` (an instance)
    plays in this process; a spec with workers > 1 loads one copy of the policy per worker process. With
    num_envs > 1 the policy plays here on batches of num_envs (on physx_cpu: one env process each)."""
    n = settings.num_envs
    groups: dict[tuple, list[Job]] = {}
    for job in jobs:
        groups.setdefault(job.options, []).append(job)
    batches = [tuple(g[i:i + n]) for g in groups.values() for i in range(0, len(g), n)]
    if not batches:
        return
    if workers <= 1 or policy is not None or n > 1:
        if policy is None:
            from vla_ladder.policies import load_policy
            policy = load_policy(spec)
        player = Player(policy, settings)
        try:
            for batch in batches:
                yield from zip(batch, player.play(batch))
        finally:
            player.close()
        return
    import multiprocessing
    from concurrent.futures import as_completed

    workers = min(workers, len(batches))
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                             initargs=(spec, settings, 1)) as pool:
        futures = {pool.submit(_play_in_worker, batch): batch for batch in batches}
        try:
            for fut in as_completed(futures):
                yield from zip(futures[fut], fut.result())
        except BaseException:
            for f in futures:
                f.cancel()
            raise
