"""What a policy server costs: one action chunk in-process (`lerobot:`) against the same chunk through
`vla-ladder serve-policy` and `remote:` on this machine's loopback.

Starts `vla-ladder serve-policy` on a free port for CHECKPOINT, sends it REPEATS requests of one episode's
observation (both 256x256 cameras, the 15-d state, the instruction, seed and chunk index) as `remote:` sends
them, and times the round trip; the server reports the inference part of each (`server_timing.infer_ms`), so
round trip minus inference is the protocol: packing, the loopback WebSocket and unpacking. The same
observation then goes through the checkpoint loaded in this process (`LeRobotPolicy.predict_chunk`).

Then, for each B of --batches, what B envs' chunks cost on one connection (`remote:` with --num-envs B): asked
one at a time (what an openpi server gets), and pipelined (all B sent, as one window, before any answer is read:
what `remote:` sends vla-ladder's server), with the batch sizes the server's passes had.

    .venv/bin/python benchmarks/remote_overhead.py CHECKPOINT [--repeats 20] [--batches 1 4 16] [--out FILE]

Writes benchmarks/results/remote_overhead_<cpu|cuda>.json.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from vla_ladder import files
from vla_ladder.contract import CAMERAS, STATE_DIM, STATE_KEY
from vla_ladder.machine import cores
from vla_ladder.policies.remote import CHUNK_KEY, PROMPT_KEY, SEED_KEY, WINDOW_KEY, connect, pack, unpack

RESULTS = Path(__file__).parent / "results"


@dataclass
class Args:
    checkpoint: tyro.conf.Positional[str]
    """a LeRobot checkpoint `serve-policy` can serve (SmolVLA, pi0, pi0.5, ACT)"""
    repeats: int = 20
    """requests timed (after one untimed warm-up)"""
    batches: tuple[int, ...] = (1, 4, 16)
    """envs whose chunks one connection asks for at once, one at a time and pipelined (each timed --repeats // 4
    times, at least 3)"""
    device: str = "cpu"
    """where the model runs, in the server and in this process"""
    out: Path | None = None
    """result file (default benchmarks/results/remote_overhead_<device>.json)"""

    def __post_init__(self):
        # checked before the server loads the model: no timed request would leave an empty median after the load
        if self.repeats < 1:
            raise ValueError(f"--repeats must be >= 1, got {self.repeats}")


def observation(seed: int = 0) -> dict:
    g = np.random.default_rng(seed)
    obs = {c.key: g.integers(0, 256, c.shape, dtype=np.uint8) for c in CAMERAS}
    obs.update({STATE_KEY: g.standard_normal(STATE_DIM).astype(np.float32), PROMPT_KEY: "grasp the mug",
                SEED_KEY: 0, CHUNK_KEY: 0})
    return obs


def median_ms(xs: list[float]) -> float:
    return round(statistics.median(xs) * 1000, 3)


def envs_on_one_connection(ws, envs: int, repeats: int) -> dict:
    """Milliseconds for `envs` chunks (each env its own observation and seed), asked one at a time and pipelined."""
    row: dict = {"envs": envs}
    for mode in ("one_at_a_time", "pipelined"):
        window = {WINDOW_KEY: envs} if mode == "pipelined" and envs > 1 else {}  # as `remote:` names its windows
        messages = [pack({**observation(seed), SEED_KEY: seed, **window}) for seed in range(envs)]
        times, passes = [], []
        for _ in range(repeats + 1):  # the first untimed: a new batch size builds caches
            t0 = time.perf_counter()
            if mode == "pipelined":
                for m in messages:
                    ws.send(m)
                answers = [unpack(ws.recv(timeout=600)) for _ in messages]
            else:
                answers = []
                for m in messages:
                    ws.send(m)
                    answers.append(unpack(ws.recv(timeout=600)))
            times.append(time.perf_counter() - t0)
            passes.append(sorted({(a["server_timing"]["infer_ms"], a["server_timing"]["batch"]) for a in answers}))
        row[f"{mode}_ms"] = median_ms(times[1:])
        row[f"{mode}_pass_batches"] = sorted((b for _, b in passes[-1]), reverse=True)  # the last repeat's passes
    row["speedup"] = round(row["one_at_a_time_ms"] / row["pipelined_ms"], 2)
    return row


def main(args: Args) -> dict:
    load_before = os.getloadavg()[0]
    spec = f"lerobot:{args.checkpoint}?device={args.device}"
    server = subprocess.Popen([sys.executable, "-m", "vla_ladder.cli", "serve-policy", "--policy", spec,
                               "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = server.stdout.readline()
        while line and not line.startswith("listening on "):
            line = server.stdout.readline()
        url = line.split()[-1]
        ws, metadata = connect(url)
        obs = observation()
        message = pack(obs)
        ws.send(message)
        unpack(ws.recv(timeout=600))  # warm-up: the first chunk builds caches
        trips, infers, packs, unpacks = [], [], [], []
        reply = b""
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            message = pack(obs)
            t1 = time.perf_counter()
            ws.send(message)
            reply = ws.recv(timeout=600)
            t2 = time.perf_counter()
            answer = unpack(reply)
            t3 = time.perf_counter()
            packs.append(t1 - t0)
            trips.append(t3 - t0)
            unpacks.append(t3 - t2)
            infers.append(answer["server_timing"]["infer_ms"] / 1000)
        batched = [envs_on_one_connection(ws, b, max(3, args.repeats // 4)) for b in args.batches]
        ws.close()
    finally:
        server.terminate()
        server.wait(timeout=30)

    import torch

    from vla_ladder.policies import load_policy
    from vla_ladder.policies.lerobot import NOISE_PER_EPISODE
    from vla_ladder.policies.serving import read_request

    policy = load_policy(spec)
    batch, prompt, seed, chunk = read_request(obs)  # what the server hands the model for this request
    noise = policy.episode_noise(seed, chunk)[None] if policy.config.type in NOISE_PER_EPISODE else None
    policy.predict_chunk(batch, [prompt], noise=noise)
    local = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        policy.predict_chunk(batch, [prompt], noise=noise)
        local.append(time.perf_counter() - t0)

    protocol = [t - i for t, i in zip(trips, infers)]
    result = {
        "benchmark": "remote_overhead", "device": args.device,
        "policy": metadata.get("policy", {}).get("type"), "chunk": list(answer["actions"].shape),
        "repeats": args.repeats, "request_bytes": len(message), "reply_bytes": len(reply),
        "in_process_chunk_ms": median_ms(local), "remote_round_trip_ms": median_ms(trips),
        "server_infer_ms": median_ms(infers), "protocol_ms": median_ms(protocol),
        "pack_request_ms": median_ms(packs), "unpack_reply_ms": median_ms(unpacks),
        "envs_on_one_connection": batched,
        "machine": {"cores": cores(), "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
                    "load_average_1min": [load_before, os.getloadavg()[0]]},
        "provenance": files.provenance(),
        "note": "medians; protocol = round trip - the server's own inference time (packing, loopback WebSocket, "
                "unpacking and the server's request checks)",
    }
    out = args.out or RESULTS / f"remote_overhead_{args.device.split(':')[0]}.json"
    files.write_json(out, result)
    for k, v in result.items():
        print(f"{k}: {v}")
    print(f"wrote {out}")
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
