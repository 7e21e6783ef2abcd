"""Simulation server: runs an expert in GraspObject-v1 with both cameras and streams whole episodes.

One simulation thread owns the env and the policy and runs batches of up to `num_envs` requested seeds in
lock step (episodes all last 50 steps); the asyncio side speaks the protocol of `protocol.py` to any number
of clients. The server never simulates a seed nobody asked for and caps what each client may have
outstanding, so a slow writer slows the simulation down instead of filling memory.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import os
import queue
import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Annotated, Any, Callable

import numpy as np
import tyro

from vla_ladder import contract
from vla_ladder.checks import check_count, check_port_free, check_seed, is_loopback, refuse_past_max_clients
from vla_ladder.conditions import Condition
from vla_ladder.contract import (ACTION_DIM, CAMERA_NAMES, CONTROL_HZ, EPISODE_STEPS, IMAGE_SHAPE, METRICS,
                                  STATE_DIM)
from vla_ladder.policies import check_spec
from vla_ladder.recording import protocol as P
from vla_ladder.task.instructions import check_instruction_set
from vla_ladder.task.object_sets import resolve_object_set
from vla_ladder.task.robot import check_robot_mesh
from vla_ladder.task.objects import OBJECT_NAMES

log = logging.getLogger(__name__)
TOKEN_ENV = "VLA_LADDER_TOKEN"


@dataclass
class ServeConfig:
    """Serve expert episodes of GraspObject-v1 over WebSockets (`vla-ladder serve`)."""

    condition: Annotated[Condition, tyro.conf.arg(name="")] = field(default_factory=Condition)
    """the condition every episode is played in"""
    policy: str = "scripted"
    """the expert, a policy spec: scripted, ppo:PATH or a policy plugin's KIND[:ARG] (`record` takes only an
    expert's episodes)"""
    rng_seed: int = 0
    """seeds the server's global torch/numpy RNGs (stochastic experts); episode seeds always come from clients"""
    num_envs: int = 1
    """parallel envs simulated in lock step; more than one needs a GPU (physx_cuda)"""
    host: str = "127.0.0.1"
    """address to bind; anything but loopback needs --token"""
    port: int = 8765
    """port; 0 picks a free one (the URL is printed once listening)"""
    # read from the environment in __post_init__, so that --help never prints it
    token: Annotated[str | None, tyro.conf.arg(metavar="STR", help_behavior_hint="(default: $VLA_LADDER_TOKEN)")] = None
    """shared secret every client must send in its hello; required off loopback"""
    max_outstanding: int = 0
    """episodes one client may have requested but not yet received (0: 4 x num_envs, at least 8)"""
    max_clients: int = 8
    """connections served at once (a recorder opens one per server); more are refused (HTTP 503) until one leaves:
    each may hold max_outstanding episodes of frames, 20 MB apiece"""
    lazy: bool = False
    """build the simulator on the first request instead of at start (cheap start for protocol checks)"""
    rebuild_scenes: bool = True
    """rebuild the CPU scene every episode, as evaluation does, so that every recorded episode replays bit for bit
    from its seed and recorded actions (`vla-ladder check-dataset` replays some): ~0.02 s of a ~1 s episode on the
    2-core machine. --no-rebuild-scenes reuses the scene: PhysX keeps solver caches across resets, so a replay may
    then drift by millimetres (the layout, target and instruction of a seed never differ). physx_cuda envs
    (--num-envs > 1) never rebuild and do not replay on the CPU."""
    robot_mesh: str = "lite"
    """lite (decimated visual meshes, fast on a CPU renderer) or full (ManiSkill's); physics is the same"""
    instructions: str = "canonical"
    """how episodes are worded: canonical ("grasp the <object>"), paraphrase-train or paraphrase-heldout"""
    exit_on_stdin_close: bool = False
    """exit when stdin closes (how `record` ties the local server it starts to its own life)"""

    def __post_init__(self):
        if self.token is None:
            self.token = os.environ.get(TOKEN_ENV)
        self.condition = Condition.of(self.condition)
        check_seed(self.rng_seed, "--rng-seed")
        check_robot_mesh(self.robot_mesh)
        check_instruction_set(self.instructions)
        check_spec(self.policy)
        if self.num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {self.num_envs}")
        if self.num_envs > 1:
            from vla_ladder.task.physx_gpu import check_physx_cuda
            check_physx_cuda("num_envs > 1 needs a CUDA GPU (physx_cuda); on CPU use --num-envs 1 and run several "
                             "servers instead")
        if not 0 <= self.port < 65536:
            raise ValueError(f"port must be in 0..65535, got {self.port}")
        if not self.token and not is_loopback(self.host):
            raise ValueError(f"binding to {self.host!r} (not loopback) needs --token; allowed without a "
                             "token: 127.0.0.1, ::1, localhost")
        if self.max_outstanding < 0:
            raise ValueError(f"max_outstanding must be >= 0 (0: 4 x num_envs, at least 8), got {self.max_outstanding}")
        if self.max_outstanding == 0:
            self.max_outstanding = max(8, 4 * self.num_envs)
        check_count(self.max_clients, "--max-clients")
        check_port_free(self.host, self.port)  # before the simulator starts, not after


@dataclass
class EpisodeResult:
    seed: int
    header: dict[str, Any]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)


class Simulator:
    """GraspObject-v1 with both cameras plus the expert; `run(seeds)` plays whole episodes."""

    def __init__(self, cfg: ServeConfig):
        import gymnasium as gym
        import torch

        import vla_ladder.task.env  # noqa: F401  (registers GraspObject-v1)
        from vla_ladder.policies import load_policy

        torch.manual_seed(cfg.rng_seed)
        np.random.seed(cfg.rng_seed % 2**32)
        self.cfg = cfg
        self.policy = load_policy(cfg.policy)
        # The expert reads privileged state, the dataset needs pixels: ManiSkill renders both in one obs
        # ("state_dict+rgb"); a pixel policy ("rgb") already gets the cameras.
        mode = self.policy.obs_mode
        obs_mode = "rgb" if mode == "rgb" else "state_dict+rgb"
        self._flatten = mode == "state"
        backend = "physx_cuda" if cfg.num_envs > 1 else "physx_cpu"
        # What an episode promises: a rebuilt physx_cpu scene replays from (seed, actions) to the last bit.
        self.backend, self.replayable = backend, backend == "physx_cpu" and cfg.rebuild_scenes
        c = cfg.condition
        self.env = gym.make(contract.ENV_ID, obs_mode=obs_mode, regime=c.regime, split=c.split,
                            num_objects=c.num_objects, num_envs=cfg.num_envs, sim_backend=backend,
                            robot_mesh=cfg.robot_mesh, instructions=cfg.instructions,
                            reconfiguration_freq=1 if self.replayable else 0)
        self.base = self.env.unwrapped
        self.steps = EPISODE_STEPS
        self.object_set = self.base.object_set
        self.expert = {"spec": cfg.policy, **self.policy.describe()}

    def _policy_obs(self, obs):
        if self._flatten:
            from mani_skill.utils import common
            return common.flatten_state_dict({"agent": obs["agent"], "extra": obs["extra"]}, use_torch=True)
        return obs

    def run(self, seeds: list[int]) -> list[EpisodeResult]:
        """Play one episode per seed (at most num_envs), padding the batch with repeats of the first."""
        import torch

        n, real = self.cfg.num_envs, len(seeds)
        batch = list(seeds) + [seeds[0]] * (n - real)
        obs, _ = self.env.reset(seed=batch)
        self.policy.reset(batch)
        instructions = self.base.instructions
        layouts = [lay.to_dict() for lay in self.base.layouts]
        T = self.steps
        frames = {cam: np.empty((n, T, *IMAGE_SHAPE), np.uint8) for cam in CAMERA_NAMES}
        state = np.empty((n, T, obs["extra"]["proprio"].shape[1]), np.float32)
        action = np.empty((n, T, ACTION_DIM), np.float32)
        t0 = time.perf_counter()
        with torch.no_grad():
            for t in range(T):
                for cam in CAMERA_NAMES:
                    frames[cam][:, t] = obs["sensor_data"][cam]["rgb"].cpu().numpy()
                state[:, t] = obs["extra"]["proprio"].cpu().numpy()
                a = self.policy.act(self._policy_obs(obs), instructions).to(torch.float32)
                action[:, t] = a.cpu().numpy()
                obs, _, _, _, info = self.env.step(a)
        sim_s = (time.perf_counter() - t0) / real
        held = info["held"].cpu().numpy()
        results = []
        for i, seed in enumerate(seeds):
            metrics = {
                **{m: bool(info[m][i]) for m in METRICS}, "lifted": bool(info["lifted"][i]),
                "held": OBJECT_NAMES[held[i]] if held[i] >= 0 else "none",
                "reach_dist": float(info["reach_dist"][i]),
            }
            header = {
                "type": "episode", "seed": int(seed), "instruction": instructions[i], "layout": layouts[i],
                "target": layouts[i]["target"], "condition": self.cfg.condition.key, "object_set": self.object_set,
                "robot_mesh": self.cfg.robot_mesh, "instructions": self.cfg.instructions,
                "expert": self.expert, "metrics": metrics, "num_frames": T, "sim_seconds": sim_s,
                "sim_backend": self.backend, "replayable": self.replayable,
            }
            arrays = {**{f"images.{cam}": frames[cam][i] for cam in CAMERA_NAMES},
                      "state": state[i], "action": action[i]}
            results.append(EpisodeResult(int(seed), header, arrays))
        return results

    def close(self):
        self.env.close()


@dataclass
class _Work:
    conn: "_Connection"
    seed: int
    failed_frames: bool


class _Connection:
    def __init__(self, ws, loop: asyncio.AbstractEventLoop):
        self.ws, self.loop = ws, loop
        self.outbox: asyncio.Queue = asyncio.Queue()
        self.outstanding = 0
        self.closed = False

    def deliver(self, item) -> None:
        """Called from the simulation thread."""
        if not self.closed:
            self.loop.call_soon_threadsafe(self.outbox.put_nowait, item)


class EpisodeServer:
    """The WebSocket front end and the simulation thread behind it."""

    def __init__(self, cfg: ServeConfig):
        self.cfg = cfg
        self._work: queue.Queue[_Work] = queue.Queue()
        self._stop = threading.Event()
        self._sim: Simulator | None = None
        self._thread: threading.Thread | None = None
        self.url: str | None = None
        self.episodes_served = 0
        # Resolved here, before the simulation thread exists: importing mani_skill from two threads at
        # once trips over its circular imports.
        self.object_set = resolve_object_set("auto")

    # ------------------------------------------------------------------ simulation thread
    def _simulate(self) -> None:
        try:
            if not self.cfg.lazy:
                with contextlib.suppress(Exception):  # logged; every request will report it
                    self._build()
            while not self._stop.is_set():
                batch = self._next_batch()
                if not batch:
                    continue
                try:
                    if self._sim is None:
                        self._build()
                    results = self._sim.run([w.seed for w in batch])
                except Exception as e:  # a broken episode must not take other clients down with it
                    log.error("simulation failed for seeds %s:\n%s", [w.seed for w in batch], traceback.format_exc())
                    error = P.ProtocolError(f"simulation failed: {type(e).__name__}: {e}", P.CLOSE_INTERNAL)
                    for w in batch:
                        w.conn.deliver(error)
                    continue
                for w, r in zip(batch, results):
                    w.conn.deliver((r, w.failed_frames))
        finally:
            if self._sim is not None:
                self._sim.close()

    def _next_batch(self) -> list[_Work]:
        """Up to num_envs requested seeds of clients still connected (empty after a short wait)."""
        try:
            batch = [self._work.get(timeout=0.2)]
        except queue.Empty:
            return []
        while len(batch) < self.cfg.num_envs:
            try:
                batch.append(self._work.get_nowait())
            except queue.Empty:
                break
        return [w for w in batch if not w.conn.closed]

    def _build(self) -> None:
        # SAPIEN's first camera picture holds the GIL while lavapipe compiles its pipelines (7.5 s on 2 CPU cores),
        # so this server's event loop answers no ping meanwhile: well inside a client's 20 s ping timeout, and a
        # client that times out anyway reconnects.
        t0 = time.perf_counter()
        try:
            self._sim = Simulator(self.cfg)
        except Exception:
            log.error("simulator could not start:\n%s", traceback.format_exc())
            raise
        log.info("simulator ready in %.1f s (%s, %s, object set %s)", time.perf_counter() - t0,
                 self.cfg.policy, self.cfg.condition, self._sim.object_set)

    # ------------------------------------------------------------------ protocol
    def _welcome(self) -> bytes:
        # What the server simulates: a recorder takes its dataset's condition and expert from here.
        server = {"policy": self.cfg.policy, "condition": self.cfg.condition.key, "num_envs": self.cfg.num_envs,
                  "robot_mesh": self.cfg.robot_mesh, "instructions": self.cfg.instructions,
                  "object_set": self.object_set, "fps": CONTROL_HZ, "episode_steps": EPISODE_STEPS,
                  "cameras": list(CAMERA_NAMES), "image_shape": list(IMAGE_SHAPE), "state_dim": STATE_DIM,
                  "action_dim": ACTION_DIM}
        limits = {"max_client_message": P.MAX_CLIENT_MESSAGE, "max_outstanding": self.cfg.max_outstanding,
                  "max_seeds_per_request": P.MAX_SEEDS_PER_REQUEST}
        return P.encode({"type": "welcome", "protocol": P.PROTOCOL_VERSION, "server": server, "limits": limits})

    def _episode_bytes(self) -> int:
        return P.episode_message_size(EPISODE_STEPS, {c: IMAGE_SHAPE for c in CAMERA_NAMES}, STATE_DIM, ACTION_DIM)

    async def _handshake(self, ws) -> None:
        try:
            raw = await asyncio.wait_for(ws.recv(), P.HANDSHAKE_TIMEOUT_S)
        except TimeoutError:
            raise P.ProtocolError(f"no hello within {P.HANDSHAKE_TIMEOUT_S:.0f} s", P.CLOSE_HANDSHAKE_TIMEOUT)
        msg = P.decode(raw)
        if msg.type != "hello":
            raise P.ProtocolError(f"expected 'hello' first, got {msg.type!r}", P.CLOSE_UNEXPECTED)
        version = P.require(msg.header, "protocol", int)
        if version != P.PROTOCOL_VERSION:
            raise P.ProtocolError(f"protocol version {version} not supported; this server speaks "
                                  f"{P.PROTOCOL_VERSION}", P.CLOSE_VERSION)
        if self.cfg.token:
            token = msg.header.get("token")
            if not isinstance(token, str) or not hmac.compare_digest(token.encode(), self.cfg.token.encode()):
                raise P.ProtocolError("unauthorised: missing or wrong token", P.CLOSE_UNAUTHORISED)
        limit = P.require(msg.header, "max_message", int)
        if limit < self._episode_bytes():
            raise P.ProtocolError(f"episodes need up to {self._episode_bytes()} bytes per message but the "
                                  f"client accepts {limit}", P.CLOSE_LIMIT)
        await ws.send(self._welcome())

    async def _send_results(self, conn: _Connection) -> None:
        while True:
            item = await conn.outbox.get()
            if isinstance(item, P.ProtocolError):
                await conn.ws.close(item.code, item.close_reason)
                return
            result, failed_frames = item
            with_frames = result.header["metrics"]["success"] or failed_frames
            header = {**result.header, "has_frames": with_frames}
            data = await asyncio.to_thread(P.encode, header, result.arrays if with_frames else None)
            await conn.ws.send(data)  # waits while the client's socket is full: backpressure
            conn.outstanding -= 1
            self.episodes_served += 1

    def _admit(self, connection, request):
        """HTTP 503 for a connection past --max-clients, before its handshake: the queued seeds and frames of every
        connection are in this process's memory."""
        return refuse_past_max_clients(connection, self.cfg.max_clients, log)

    async def _handle(self, ws) -> None:
        peer = ws.remote_address
        conn = _Connection(ws, asyncio.get_running_loop())
        sender = None
        try:
            await self._handshake(ws)
            log.info("client %s connected", peer)
            sender = asyncio.create_task(self._send_results(conn))
            async for raw in ws:
                msg = P.decode(raw)
                if msg.type == "bye":
                    await ws.close(P.CLOSE_NORMAL, "bye")
                    break
                if msg.type != "run":
                    raise P.ProtocolError(f"unexpected message type {msg.type!r}; expected 'run' or 'bye'",
                                          P.CLOSE_UNEXPECTED)
                seeds = P.check_seeds(msg.header.get("seeds"))
                if conn.outstanding + len(seeds) > self.cfg.max_outstanding:
                    raise P.ProtocolError(f"{conn.outstanding + len(seeds)} episodes outstanding; the limit is "
                                          f"{self.cfg.max_outstanding}", P.CLOSE_LIMIT)
                conn.outstanding += len(seeds)
                failed_frames = msg.header.get("failed_frames", False)
                if not isinstance(failed_frames, bool):
                    raise P.ProtocolError("'run' message: field 'failed_frames' not bool")
                for s in seeds:
                    self._work.put(_Work(conn, s, failed_frames))
        except P.ProtocolError as e:
            log.warning("closing %s: %s (%d)", peer, e.reason, e.code)
            await ws.close(e.code, e.close_reason)
        except Exception as e:  # ConnectionClosed and friends: the client is gone, keep serving others
            log.info("client %s gone: %s", peer, e)
        finally:
            conn.closed = True  # the simulation thread drops this client's queued seeds
            if sender is not None:
                sender.cancel()
        log.info("client %s disconnected", peer)

    # ------------------------------------------------------------------ lifecycle
    async def serve(self, ready: Callable[[str], None] | None = None) -> None:
        """Listen until cancelled; `ready(url)` is called once the socket is bound. The socket is bound first: a
        port in use fails (OSError) before the simulator starts."""
        from websockets.asyncio.server import serve

        try:
            async with serve(self._handle, self.cfg.host, self.cfg.port, max_size=P.MAX_CLIENT_MESSAGE,
                             compression=None, max_queue=4, process_request=self._admit) as server:
                self._thread = threading.Thread(target=self._simulate, name="simulator", daemon=True)
                self._thread.start()
                sock = next(iter(server.sockets))
                host, port = sock.getsockname()[:2]
                self.url = f"ws://{_url_host(host)}:{port}"
                if ready is not None:
                    ready(self.url)
                await asyncio.Future()  # until cancelled
        finally:
            self._stop.set()
            if self._thread is not None:
                self._thread.join(timeout=60)


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host

