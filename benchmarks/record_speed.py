"""Recording throughput on this machine: demos/s end to end against worker processes, and stage by stage.

    .venv/bin/python benchmarks/record_speed.py [--episodes 8] [--workers 1 2] [--writers 1 2] [--num-objects 2]

End to end: `vla-ladder record --workers N` for each N (N local `vla-ladder serve` processes simulate and
render, the recorder receives and writes): successful demos/s with start-up included, and as the recorder
reports it once its servers are up. Then each stage alone, in this process, on the same kind of
episodes, with and without the per-episode scene rebuild (ServeConfig.rebuild_scenes: `record` and evaluation
rebuild, so that episodes replay bit for bit; --no-rebuild-scenes reuses the scene), to say where the time goes:
  physics  - physics + the scripted expert on a state-only env, per episode (reset included);
  render   - the server's Simulator.run (physics + expert + both 256x256 cameras) minus physics;
  transfer - a real episode message: protocol.encode -> WebSocket over 127.0.0.1 -> decode;
  encode   - DatasetStore.add: LeRobot add_frame/save_episode, --vcodec video (and PNG images for comparison), and
             the video encoder alone on the same frames (what LeRobot's per-frame work around it costs); the video
             writer again with LeRobot's own per-frame image statistics instead of recording/image_stats.py's;
  write    - DatasetStore commit (finalize, statistics, card, fsync, atomic swap), per episode it held.
The servers run in parallel and each writer is one process (`--writers K`), so the pipeline runs at its slowest
stage, with simulation divided among N workers and writing among K writers, and no faster than the cores
allow (cores / the process CPU seconds a demo costs in all stages, each stage's measured with os.times in this
process, its threads included: lavapipe renders in threads, LeRobot encodes each camera in one): the result names
that bottleneck. The writer stage is also measured alone with K processes at once,
with the merge of their shards.

Writes benchmarks/results/record_speed_cpu.json (record_speed_cuda.json where a CUDA GPU renders; _h264 before
.json with --vcodec h264), or --out.
"""

from __future__ import annotations

import asyncio
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Iterable

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MS_SKIP_ASSET_DOWNLOAD_PROMPT", "1")
os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its configuration for every video otherwise

import numpy as np  # noqa: E402
import torch  # noqa: E402
import tyro  # noqa: E402

from vla_ladder import files  # noqa: E402
from vla_ladder.conditions import Condition  # noqa: E402
from vla_ladder.contract import EPISODE_STEPS  # noqa: E402
from vla_ladder.machine import cores  # noqa: E402
from vla_ladder.recordings import DEFAULT_VCODEC, VCODECS  # noqa: E402

RESULTS = Path(__file__).parent / "results"


@dataclass
class Args:
    """Recording demos/s end to end against workers, and seconds per episode of each stage."""

    episodes: int = 8
    """successful demos per end-to-end run"""
    stage_episodes: int | None = None
    """episodes per stage measurement (default: --episodes)"""
    workers: tuple[int, ...] = (1, 2)
    """`record --workers` counts to measure end to end"""
    writers: tuple[int, ...] = (1, 2)
    """`record --writers` counts: end to end with the most workers, and the writer stage alone"""
    regime: str = "small_jitter"
    """placement regime"""
    num_objects: int = 2
    """objects on the table"""
    robot_mesh: str = "lite"
    """lite or full robot visual meshes"""
    end_to_end: bool = True
    """run `vla-ladder record` (--no-end-to-end: the stages only)"""
    encoder_threads: tuple[int, ...] = (0,)
    """`record --encoder-threads` values (threads of each camera's encoder; 0: the encoder's choice): the first
    for end to end and the stages, each for the writer stage"""
    vcodec: str = DEFAULT_VCODEC
    """`record --vcodec`: the cameras' video codec everywhere it is written (benchmarks/video_codec.py compares)"""
    out: Path | None = None
    """result JSON (default: benchmarks/results/record_speed_<cpu|cuda>[_h264].json)"""

    def __post_init__(self):
        if not self.encoder_threads or min(self.encoder_threads) < 0:
            raise SystemExit(f"--encoder-threads: one or more values >= 0 (0: the encoder's choice), got "
                             f"{self.encoder_threads}")
        if self.vcodec not in VCODECS:
            raise SystemExit(f"--vcodec {self.vcodec!r}: allowed: {', '.join(VCODECS)}")
        if self.stage_episodes is None:
            self.stage_episodes = self.episodes
        # checked before any work: 0 divides by zero (rates, seconds per demo) once every stage has run
        for flag, n in (("--episodes", self.episodes), ("--stage-episodes", self.stage_episodes)):
            if n < 1:
                raise SystemExit(f"{flag} must be >= 1, got {n}")
        for flag, values in (("--workers", self.workers), ("--writers", self.writers)):
            if not values or min(values) < 1:
                raise SystemExit(f"{flag}: one or more values >= 1, got {' '.join(map(str, values)) or 'none'}")


def end_to_end(args: Args, workers: int, work: Path, writers: int = 1) -> dict:
    out = work / f"e2e-{workers}-{writers}"
    cmd = [sys.executable, "-m", "vla_ladder.cli", "record", "--out", str(out), "--episodes", str(args.episodes),
           "--workers", str(workers), "--writers", str(writers), "--regime", args.regime, "--num-objects",
           str(args.num_objects), "--robot-mesh", args.robot_mesh, "--encoder-threads",
           str(args.encoder_threads[0]), "--vcodec", args.vcodec]
    log = work / f"record-{workers}-{writers}.log"
    started, cpu0 = time.time(), _children_cpu_s()
    with open(log, "w") as f:
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    wall, cpu = time.time() - started, _children_cpu_s() - cpu0
    if proc.returncode != 0:
        sys.exit(f"`{' '.join(cmd[2:])}` failed ({proc.returncode}):\n{log.read_text()[-3000:]}")
    from vla_ladder.recordings import read_provenance, read_recording_state

    c = read_recording_state(out)["counters"]
    first = min(datetime.fromisoformat(t).timestamp() for t in read_provenance(out)["recorded_at"])
    # The recorder's last progress line: demos/s since its servers were ready. With one writer that clock starts
    # when the episode source does; with several it starts before the writer processes are spawned and stops after
    # their shards are merged, so it includes the writers' start-up (imports) and the merge.
    done = re.findall(r"done: .* ([0-9.]+) demos/s saved", log.read_text())
    row = {"workers": workers, "writers": writers, "rebuild_scenes": True,  # `record`'s default, which this runs
           "after_startup_clock": "episode source to last demo" if writers == 1 else
           "writer spawn to merge (writers' start-up and the merge included)",
           "episodes_saved": c["saved"], "episodes_attempted": c["attempted"],
           "wall_s": round(wall, 1), "demos_per_s": round(c["saved"] / wall, 4),
           # the recorder's, its servers' and its writers' CPU seconds (start-up, failed episodes, merge included)
           "process_cpu_s": round(cpu, 1), "process_cpu_s_per_demo": round(cpu / max(c["saved"], 1), 3),
           "frames_per_s": round(EPISODE_STEPS * c["saved"] / wall, 2), "first_demo_after_s": round(first - started, 1),
           "after_startup_demos_per_s": float(done[-1]) if done else None}
    print(f"end to end, --workers {workers} --writers {writers}: {c['saved']} demos ({c['attempted']} attempted) in "
          f"{wall:.0f} s = {row['demos_per_s']} demos/s with start-up (first after {row['first_demo_after_s']} s), "
          f"{row['after_startup_demos_per_s']} demos/s once the servers were up; {row['process_cpu_s_per_demo']} "
          "CPU s a demo in all its processes", flush=True)
    return row


def physics(args: Args, rebuild: bool) -> dict:
    """Physics + expert, no cameras: s per episode, reset apart."""
    import gymnasium as gym

    import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1)
    from vla_ladder.contract import ENV_ID
    from vla_ladder.policies import load_policy

    env = gym.make(ENV_ID, obs_mode="state_dict", regime=args.regime, num_objects=args.num_objects,
                   reconfiguration_freq=1 if rebuild else 0)
    expert = load_policy("scripted")
    env.reset(seed=10**6)  # warm-up
    resets, steps = [], []
    for seed in range(args.stage_episodes):
        t = time.perf_counter()
        obs, _ = env.reset(seed=seed)
        expert.reset([seed])
        t1 = time.perf_counter()
        for _ in range(EPISODE_STEPS):
            obs, *_ = env.step(expert.act(obs, env.unwrapped.instructions).to(torch.float32))
        resets.append(t1 - t)
        steps.append(time.perf_counter() - t1)
    env.close()
    return {"reset_s": sum(resets) / len(resets), "steps_s": sum(steps) / len(steps)}


def simulate(args: Args, rebuild: bool) -> tuple[dict, list]:
    """The server's Simulator (physics + expert + both cameras): s per episode, reset apart, and its episodes."""
    from vla_ladder.recording.client import Episode
    from vla_ladder.recording.protocol import decode, encode
    from vla_ladder.recording.server import ServeConfig, Simulator

    t0 = time.perf_counter()
    sim = Simulator(ServeConfig(condition=Condition(args.regime, "canonical", args.num_objects), port=0,
                                rebuild_scenes=rebuild, robot_mesh=args.robot_mesh))
    build = time.perf_counter() - t0
    sim.run([10**6])  # warm-up: the first render
    totals, cpus, steps, episodes = [], [], [], []
    for seed in range(args.stage_episodes):
        t, cpu = time.perf_counter(), _cpu_s()
        (r,) = sim.run([seed])
        totals.append(time.perf_counter() - t)
        cpus.append(_cpu_s() - cpu)
        steps.append(r.header["sim_seconds"])
        episodes.append(Episode.from_message(decode(encode({**r.header, "has_frames": True}, r.arrays)), "local"))
    sim.close()
    total = sum(totals) / len(totals)
    step = sum(steps) / len(steps)
    return {"build_s": build, "episode_s": total, "reset_s": total - step, "steps_s": step,
            "episode_cpu_s": sum(cpus) / len(cpus),  # this process's, the renderer's threads included
            "success_rate": sum(e.success for e in episodes) / len(episodes)}, episodes


def transfer(episode, repeats: int = 5) -> dict:
    from websockets.asyncio.client import connect
    from websockets.asyncio.server import serve

    from vla_ladder.recording import protocol as P

    arrays = {**{f"images.{c}": a for c, a in episode.images.items()}, "state": episode.state,
              "action": episode.action}
    header = {**episode.header, "has_frames": True}

    async def main():
        async def handler(ws):
            async for _ in ws:
                await ws.send(P.encode(header, arrays))

        async with serve(handler, "127.0.0.1", 0, compression=None) as server:
            port = next(iter(server.sockets)).getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", max_size=P.MAX_EPISODE_MESSAGE, compression=None,
                               proxy=None) as ws:  # (loopback: never through the environment's proxy)
                times = []
                for _ in range(repeats):
                    t = time.perf_counter()
                    await ws.send(b"next")
                    P.decode(await ws.recv())
                    times.append(time.perf_counter() - t)
        return times

    cpu0 = _cpu_s()
    times = asyncio.run(main())
    cpu = (_cpu_s() - cpu0) / repeats  # both ends': the server's encode and the recorder's decode
    size = len(P.encode(header, arrays))
    per = sorted(times)[len(times) // 2]
    return {"message_bytes": size, "s_per_episode": per, "cpu_s_per_episode": cpu, "MB_per_s": size / per / 1e6}


def encode_and_write(args: Args, episodes: list, work: Path, video: bool, lerobot_stats: bool = False) -> dict:
    """DatasetStore.add for every episode (encode), then one commit of them all (write); `lerobot_stats`: with
    LeRobot's own RunningQuantileStats for the cameras instead of recording/image_stats.py's."""
    from lerobot.datasets import compute_stats

    from vla_ladder.recording import image_stats
    from vla_ladder.recording.store import DatasetStore
    from vla_ladder.recordings import Recording

    recording = Recording(policy="scripted", condition=Condition(args.regime, "canonical", args.num_objects),
                          video=video, robot_mesh=args.robot_mesh, vcodec=args.vcodec if video else DEFAULT_VCODEC)
    store = DatasetStore(work / f"{'video' if video else 'images'}{'_lerobot_stats' if lerobot_stats else ''}",
                         recording, commit_every=10**6, encoder_threads=args.encoder_threads[0] or None)
    install = image_stats.install
    if lerobot_stats:  # (the store installs the counting class when it opens a dataset)
        image_stats.uninstall()
        image_stats.install = lambda: False
    try:
        t0, cpu0 = time.perf_counter(), _cpu_s()
        for e in episodes:
            store.count(True)
            store.add(e)
        added, added_cpu = time.perf_counter() - t0, _cpu_s() - cpu0
        used = compute_stats.RunningQuantileStats.__name__
        t = time.perf_counter()
        store.close()
        commit, writer_cpu = time.perf_counter() - t, _cpu_s() - cpu0
    finally:
        image_stats.install = install
    size = sum(f.stat().st_size for f in store.root.rglob("*") if f.is_file())
    n = len(episodes)
    return {"encode_s_per_episode": added / n, "encode_cpu_s_per_episode": added_cpu / n,
            "write_s_per_episode": commit / n, "commit_s": commit, "writer_cpu_s_per_episode": writer_cpu / n,
            "write_cpu_s_per_episode": (writer_cpu - added_cpu) / n,
            "episodes_per_commit": n, "bytes_per_episode": size / n, "image_statistics": used}


def encode_mp4(dest, frames: Iterable[np.ndarray], config, threads: int = 0) -> None:
    """RGB `frames` (H, W, 3 uint8) into one MP4 at `dest` (a path or a file object) with a LeRobot encoder
    `config` through PyAV, as LeRobot's encoder writes them but without its per-frame work around the codec."""
    from fractions import Fraction

    import av

    from vla_ladder.contract import CONTROL_HZ

    with av.open(dest, "w", format="mp4") as out:
        stream = out.add_stream(config.vcodec, CONTROL_HZ,
                                options=config.get_codec_options(threads or None, as_strings=True))
        stream.time_base = Fraction(1, CONTROL_HZ)
        for i, frame in enumerate(frames):
            if i == 0:
                stream.pix_fmt, stream.width, stream.height = config.pix_fmt, frame.shape[1], frame.shape[0]
            vf = av.VideoFrame.from_ndarray(frame, format="rgb24")
            vf.pts = i
            out.mux(stream.encode(vf))
        out.mux(stream.encode())


def encoder_alone(episodes: list, threads: int, vcodec: str = DEFAULT_VCODEC) -> dict:
    """The video encoder by itself on the same frames: LeRobot's RGB settings for `vcodec` (SVT-AV1 by default)
    through PyAV, one MP4 per camera, without LeRobot's per-frame work around it (image statistics, conversions).
    The difference to `encode` is what that work costs."""
    import io

    from lerobot.configs.video import RGBEncoderConfig

    config = RGBEncoderConfig(vcodec=vcodec)
    t0, cpu0 = time.perf_counter(), _cpu_s()
    size = 0
    for e in episodes:
        for frames in e.images.values():
            buf = io.BytesIO()
            encode_mp4(buf, frames, config, threads)
            size += buf.tell()
    n = len(episodes)
    return {"codec": config.vcodec, "options": config.get_codec_options(threads or None, as_strings=True),
            "s_per_episode": (time.perf_counter() - t0) / n, "cpu_s_per_episode": (_cpu_s() - cpu0) / n,
            "bytes_per_episode": size / n}


def _cpu_s() -> float:
    """CPU seconds of this process, all threads (LeRobot encodes each camera in a thread of its own)."""
    t = os.times()
    return t.user + t.system


def _children_cpu_s() -> float:
    """CPU seconds of this process's children that have ended, and of theirs that they waited for (a `record`'s
    servers and writers)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _write_shard(root: str, episodes: list, vcodec: str, threads: int, ready, go, out) -> None:
    """One parallel writer: a shard DatasetStore adding `episodes` once every writer is ready."""
    import lerobot.datasets.lerobot_dataset  # noqa: F401  (imported before the clock starts)

    from vla_ladder.recording.store import DatasetStore
    from vla_ladder.recordings import Recording

    h = episodes[0].header
    store = DatasetStore(root, Recording("scripted", Condition.parse(h["condition"]), robot_mesh=h["robot_mesh"],
                                         vcodec=vcodec),
                         commit_every=10**6, encoder_threads=threads or None)
    ready.wait()
    go.wait()
    cpu0 = _cpu_s()
    for e in episodes:
        store.count(True)
        store.add(e)
    store.close()
    out.put(_cpu_s() - cpu0)


def writer_scaling(episodes: list, work: Path, writers: int, threads: int, vcodec: str) -> dict:
    """`writers` processes each adding all `episodes` to a shard at once (as `record --writers` runs them):
    demos/s written by all, CPU s per demo; then the merge of the shards into one dataset."""
    import multiprocessing

    from vla_ladder.recording.ledger import Block
    from vla_ladder.recording.store import DatasetStore
    from vla_ladder.recordings import Recording

    ctx = multiprocessing.get_context("spawn")
    ready, go, out = ctx.Barrier(writers + 1), ctx.Barrier(writers + 1), ctx.Queue()
    root = work / f"writers-{writers}-threads-{threads}"
    main = DatasetStore(root, Recording("scripted", Condition.parse(episodes[0].header["condition"]),
                                        robot_mesh=episodes[0].header["robot_mesh"], vcodec=vcodec))
    n = len(episodes)  # writer i's shard stands for the block of seeds [i n, (i + 1) n)
    procs = [ctx.Process(target=_write_shard, args=(str(main.shard(i * n)), episodes, vcodec, threads, ready, go, out))
             for i in range(writers)]
    for p in procs:
        p.start()
    ready.wait()
    t0 = time.perf_counter()
    go.wait()
    cpu = [out.get(timeout=3600) for _ in procs]
    for p in procs:
        p.join()
    wall = time.perf_counter() - t0
    t = time.perf_counter()
    main.merge([Block(i * n, (i + 1) * n, (i + 1) * n, n, n, 0, True) for i in range(writers)])
    merge = time.perf_counter() - t
    main.close()
    n = writers * n
    print(f"writer stage, {writers} writers, --encoder-threads {threads}: {n / wall:.3f} demos/s, "
          f"{sum(cpu) / n:.2f} CPU s per demo, merge {merge:.1f} s", flush=True)
    return {"writers": writers, "encoder_threads": threads, "demos": n, "wall_s": wall, "demos_per_s": n / wall,
            "cpu_s_per_demo": sum(cpu) / n,
            "merge_s": merge, "merge_s_per_demo": merge / n}


def pipeline(stages: dict, cpu_s: dict, success: float, workers: int, n_cores: int, writers: int = 1) -> dict:
    """Seconds per saved demo of each stage given its parallelism, the slowest one, and the bound it sets; and the
    bound the cores set, from `cpu_s`, each stage's process CPU seconds per episode (simulation: physics, the expert
    and both cameras, which one server process runs together)."""
    per_demo = {"physics": stages["physics"] / success / workers, "render": stages["render"] / success / workers,
                "transfer": stages["transfer"] / writers, "encode": stages["encode"] / writers,
                "write": stages["write"] / writers}
    slowest = max(per_demo, key=per_demo.get)
    # (the files before 2026-11-29 held cpu_s_per_demo: wall seconds for every stage but encode)
    cpu = {"simulation": cpu_s["simulation"] / success, **{k: cpu_s[k] for k in ("transfer", "encode", "write")}}
    stage_bound, core_bound = 1 / per_demo[slowest], n_cores / sum(cpu.values())
    return {"workers": workers, "writers": writers, "s_per_demo": per_demo, "process_cpu_s_per_demo": cpu,
            "slowest_stage": slowest,
            "stage_bound_demos_per_s": stage_bound, "cores_bound_demos_per_s": core_bound,
            "demos_per_s_bound": min(stage_bound, core_bound),
            "bottleneck": slowest if stage_bound <= core_bound else f"cores ({max(cpu, key=cpu.get)}: largest share)"}


def main(args: Args) -> None:
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    load_before = os.getloadavg()[0]
    result: dict = {"benchmark": "record_speed", "policy": "scripted", "robot_mesh": args.robot_mesh,
                    "condition": Condition(args.regime, "canonical", args.num_objects).key,
                    "renderer": "cuda" if gpu else "lavapipe (CPU)", "encoder_threads": args.encoder_threads[0],
                    "vcodec": args.vcodec}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if args.end_to_end:
            # each worker count with the fewest writers, then the most workers with every other writer count
            fewest = min(args.writers)
            result["end_to_end"] = [end_to_end(args, n, work, min(fewest, n)) for n in args.workers] + [
                end_to_end(args, max(args.workers), work, k) for k in args.writers
                if fewest < k <= max(args.workers)]
        stages = {}
        for rebuild in (False, True):
            print(f"stages, rebuild_scenes={rebuild} ...", flush=True)
            phys, (sim, episodes) = physics(args, rebuild), simulate(args, rebuild)
            stages[rebuild] = {"physics_and_expert": phys, "simulator": sim}
        ok = [e for e in episodes if e.success] or episodes
        for e in ok:  # encoding does not depend on success, but only successes are written
            e.header["metrics"]["success"] = True
        print("transfer, encode, write ...", flush=True)
        trans = transfer(ok[0])
        encoder = encoder_alone(ok, args.encoder_threads[0], args.vcodec)
        video = encode_and_write(args, ok, work, video=True)
        video_lerobot_stats = encode_and_write(args, ok, work, video=True, lerobot_stats=True)
        images = encode_and_write(args, ok, work, video=False)
    n_cores = cores()
    per_episode, bounds, success = {}, {}, {}
    for rebuild, s in stages.items():
        # Physics: the simulator's own reset (the state-only env's differs: on the H100 it cost 0.65 s against the
        # simulator's 0.29, and episode minus state-only physics came out at -0.09 s of "render") and the state-only
        # env's steps; render: what the simulator's steps cost beyond those.
        sim, state_only = s["simulator"], s["physics_and_expert"]
        key = "rebuild" if rebuild else "no_rebuild"
        # the expert success rate of this setting's own simulator run; none succeeded: as if one had
        success[key] = sim["success_rate"] or 1 / args.stage_episodes
        per_episode[key] = {"physics": sim["reset_s"] + state_only["steps_s"],
                            "render": sim["steps_s"] - state_only["steps_s"],
                            "transfer": trans["s_per_episode"], "encode": video["encode_s_per_episode"],
                            "write": video["write_s_per_episode"]}
        cpu_s = {"simulation": sim["episode_cpu_s"], "transfer": trans["cpu_s_per_episode"],
                 "encode": video["encode_cpu_s_per_episode"], "write": video["write_cpu_s_per_episode"]}
        bounds[key] = [pipeline(per_episode[key], cpu_s, success[key], n, n_cores, k) for n in args.workers
                       for k in args.writers if k <= n]
    result.update({
        "stages": {"no_rebuild": stages[False], "rebuild": stages[True]}, "transfer": trans,
        "encode_and_write_video": video, "encode_and_write_video_lerobot_stats": video_lerobot_stats,
        "encode_and_write_images": images, "video_encoder_alone": encoder,
        "writer_scaling": [],  # filled last
        "stage_s_per_episode": per_episode, "expert_success_rate": success,
        "steady_state_bounds": bounds,
        "how": "s_per_demo: a stage's seconds per episode / expert success rate (expert_success_rate: of the same "
               "no_rebuild or rebuild run) / workers for the simulation stages "
               "(one server process each), / writers for transfer, encode and write (one process each). The "
               "pipeline runs at its slowest stage, and no faster than cores / the CPU seconds one demo costs in all "
               "stages (process_cpu_s_per_demo: each stage's process CPU seconds, its threads included, the "
               "simulation's / expert success rate). end_to_end process_cpu_s_per_demo: the CPU seconds of the "
               "recorder and all its servers and writers per saved demo, start-up included. writer_scaling: the "
               "writer stage alone, N processes at once, and the merge of their shards.",
        "machine": {"cores": n_cores, "gpu": gpu, "load_average_1min": [load_before, os.getloadavg()[0]]},
        "provenance": files.provenance(ok[0].header["object_set"]),
    })
    codec = "" if args.vcodec == DEFAULT_VCODEC else f"_{args.vcodec}"
    out = args.out or RESULTS / f"record_speed_{'cuda' if gpu else 'cpu'}{codec}.json"
    files.write_json(out, result)
    print(f"encode: {video['encode_cpu_s_per_episode']:.2f} CPU s per episode in LeRobot's writer, of which the "
          f"{encoder['codec']} encoder alone {encoder['cpu_s_per_episode']:.2f}; with LeRobot's own image statistics "
          f"{video_lerobot_stats['encode_cpu_s_per_episode']:.2f}")
    for key, stage in per_episode.items():
        print(f"{key}: s per episode: " + ", ".join(f"{k} {v:.2f}" for k, v in stage.items()))
        for b in bounds[key]:
            print(f"  --workers {b['workers']} --writers {b['writers']}: bound {b['demos_per_s_bound']:.3f} demos/s, "
                  f"bottleneck {b['bottleneck']}")
    print(f"wrote {out}")
    # The writer stage alone comes last, the file written again after each row: a time box keeps what finished.
    with tempfile.TemporaryDirectory() as tmp:
        for k in args.writers:
            for t in args.encoder_threads:
                result["writer_scaling"].append(writer_scaling(ok, Path(tmp), k, t, args.vcodec))
                files.write_json(out, result)
                print(f"wrote {out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
