"""Recording throughput on this machine, end to end and stage by stage.

End to end: `vla-ladder record` with its embedded server (simulation and writing in two processes, video
encoding on CPU): successful demos/s and frames/s. Then each stage alone, in this process, on the same
kind of episodes, to say where the time goes:
  render   - Simulator.run: physics + expert + both 256x256 cameras, per episode; physics + expert alone
             is timed on a state-only env, the difference is rendering;
  transfer - a real episode message (protocol.encode -> WebSocket over 127.0.0.1 -> decode);
  encode   - DatasetStore.add (LeRobot add_frame/save_episode: AV1 video by default) plus the commit.

    python benchmarks/record_speed.py [--episodes 4] [--num-objects 2] [--out benchmarks/results/record_speed_cpu.json]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MS_SKIP_ASSET_DOWNLOAD_PROMPT", "1")
os.environ.setdefault("SVT_LOG", "1")

from vla_ladder import io  # noqa: E402

REGIME = "small_jitter"


def end_to_end(episodes: int, num_objects: int, work: Path) -> dict:
    out = work / "e2e"
    cmd = [sys.executable, "-m", "vla_ladder.cli", "record", "--regime", REGIME, "--num-objects", str(num_objects),
           "--episodes", str(episodes), "--out", str(out), "--commit-every", "1"]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = time.perf_counter() - t0
    from vla_ladder.recording.writer import read_recording_state
    c = read_recording_state(out)["counters"]
    return {"episodes_saved": c["saved"], "episodes_attempted": c["attempted"], "wall_s": wall,
            "demos_per_s": c["saved"] / wall, "frames_per_s": 50 * c["saved"] / wall,
            "note": "includes start-up: imports and building the simulator (~30-50 s here)"}


def render(episodes: int, num_objects: int) -> tuple[dict, list]:
    import torch

    from vla_ladder.policies import load_policy
    from vla_ladder.recording.client import Episode
    from vla_ladder.recording.protocol import decode, encode
    from vla_ladder.recording.server import ServerConfig, Simulator

    t0 = time.perf_counter()
    sim = Simulator(ServerConfig(regime=REGIME, num_objects=num_objects))
    build = time.perf_counter() - t0
    results, times = [], []
    for seed in range(episodes):
        t = time.perf_counter()
        (r,) = sim.run([seed])
        times.append(time.perf_counter() - t)
        results.append(Episode.from_message(decode(encode({**r.header, "has_frames": True}, r.arrays)), "local"))
    sim.close()
    # The same episodes without cameras: physics + expert only.
    import gymnasium as gym
    env = gym.make("GraspObject-v1", obs_mode="state_dict", regime=REGIME, num_objects=num_objects)
    expert = load_policy("scripted")
    state_times = []
    for seed in range(episodes):
        t = time.perf_counter()
        obs, _ = env.reset(seed=seed)
        expert.reset([seed])
        for _ in range(50):
            obs, *_ = env.step(expert.act(obs, env.unwrapped.instructions).to(torch.float32))
        state_times.append(time.perf_counter() - t)
    env.close()
    per_ep = sum(times) / len(times)
    physics = sum(state_times) / len(state_times)
    return {"simulator_build_s": build, "s_per_episode": per_ep, "physics_and_expert_s_per_episode": physics,
            "rendering_s_per_episode": per_ep - physics, "steps_per_s": 50 / per_ep,
            "successes": sum(e.success for e in results)}, results


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
            async with connect(f"ws://127.0.0.1:{port}", max_size=P.MAX_EPISODE_MESSAGE, compression=None) as ws:
                times = []
                for _ in range(repeats):
                    t = time.perf_counter()
                    await ws.send(b"next")
                    P.decode(await ws.recv())
                    times.append(time.perf_counter() - t)
        return times

    times = asyncio.run(main())
    size = len(P.encode(header, arrays))
    per = sorted(times)[len(times) // 2]
    return {"message_bytes": size, "s_per_episode": per, "MB_per_s": size / per / 1e6}


def encode(episodes: list, work: Path, video: bool) -> dict:
    from vla_ladder.recording.writer import DatasetStore, RecordingConfig

    store = DatasetStore(work / ("video" if video else "images"), RecordingConfig(
        regime=REGIME, num_objects=episodes[0].header["num_objects"], video=video), commit_every=10**6)
    t0 = time.perf_counter()
    for e in episodes:
        store.count(True)
        store.add(e)
    added = time.perf_counter() - t0
    t = time.perf_counter()
    store.close()
    commit = time.perf_counter() - t
    size = sum(f.stat().st_size for f in store.root.rglob("*") if f.is_file())
    return {"s_per_episode": (added + commit) / len(episodes), "add_s_per_episode": added / len(episodes),
            "commit_s": commit, "bytes_per_episode": size / len(episodes)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--num-objects", type=int, default=2)
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "record_speed_cpu.json"))
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        print("end to end ...", flush=True)
        e2e = end_to_end(args.episodes, args.num_objects, work)
        print("render ...", flush=True)
        rend, eps = render(args.episodes, args.num_objects)
        ok = [e for e in eps if e.success] or eps  # encoding cost does not depend on success
        print("transfer ...", flush=True)
        trans = transfer(eps[0])
        print("encode ...", flush=True)
        enc_video = encode(ok, work, video=True)
        enc_images = encode(ok, work, video=False)
    stages = {"render": rend["s_per_episode"], "transfer": trans["s_per_episode"], "encode": enc_video["s_per_episode"]}
    # Server and writer are separate processes, so once started the pipeline runs at its slowest stage
    # (given a core each); the writer keeps only the expert's successes.
    success_rate = e2e["episodes_saved"] / e2e["episodes_attempted"]
    steady = success_rate / max(stages.values())
    result = {
        "machine": f"{os.cpu_count()} CPU cores, no GPU (software Vulkan rendering); load average "
                   f"{os.getloadavg()[0]:.1f} at the end",
        "condition": {"regime": REGIME, "num_objects": args.num_objects, "policy": "scripted", "num_envs": 1},
        "end_to_end": e2e, "render": rend, "transfer": trans, "encode_video": enc_video, "encode_images": enc_images,
        "stage_s_per_episode": stages, "bottleneck": max(stages, key=stages.get),
        "steady_state_bound": {"demos_per_s": steady, "frames_per_s": 50 * steady,
                               "how": "expert success rate / slowest stage's s per episode"},
        "provenance": io.provenance(),
    }
    io.write_json(args.out, result)
    print(f"end to end: {e2e['demos_per_s']:.3f} successful demos/s, {e2e['frames_per_s']:.1f} frames/s "
          f"({e2e['episodes_saved']} saved of {e2e['episodes_attempted']} in {e2e['wall_s']:.0f} s with start-up); "
          f"steady-state bound {steady:.3f} demos/s, {50 * steady:.1f} frames/s")
    print("per episode: " + ", ".join(f"{k} {v:.2f} s" for k, v in stages.items())
          + f" (rendering {rend['rendering_s_per_episode']:.2f} s of the render stage)")
    print(f"bottleneck: {result['bottleneck']}; wrote {args.out}")


if __name__ == "__main__":
    main()
