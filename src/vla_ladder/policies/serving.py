"""`vla-ladder serve-policy`: serve a LeRobot checkpoint over WebSockets in openpi's policy-server protocol.

The server side of policies/remote.py (whose docstring is the protocol): load the checkpoint once, send its
metadata to every client that connects, answer every observation with a whole action chunk. Requests are
independent (the client runs the chunk), so any number of clients (`eval --workers N` opens N) share one copy of
the model, and the requests that arrive while it runs are answered together by its next forward pass (dynamic
batching, at most --max-batch; a batch that fails is run again request by request, a window together, so that
one client's failure is its own). One connection may also have up to --max-batch requests in flight (its metadata
says "max_pipelined"): `eval --num-envs N` sends its envs' requests together, each naming the size of their window
("vla_ladder/window"), and reads the answers in order; the server runs a window in one forward pass, so N envs cost
one pass, with the rows `eval --num-envs N` computes in-process. A request carrying "vla_ladder/episode_seed" and
"vla_ladder/chunk_index" gets the flow-matching noise `lerobot:` draws for that chunk of that episode, so `eval
--policy remote:URL` plays what `eval --policy lerobot:CHECKPOINT` plays: to the bit with one client, its envs
alone or together (each window a pass of its own; with as many torch threads as in-process, where batches use
one), to float rounding when clients' requests share passes.

The forward passes run on the main thread, the WebSocket event loop on another: torch's OpenMP workers belong to
the thread that made them, and a second thread's workers outnumber the cores and sleep between matmuls (a SmolVLA
chunk: 11.5 ms on the main thread of 2 idle cores, 33-38 ms on another; cli.py leaves this command libgomp's
default wait policy for the same reason; benchmarks/openmp_wait.py).

Use it to put the model on a GPU machine and the simulation elsewhere, to serve a checkpoint to openpi-style
clients, or to check the remote path against the in-process one. It listens on 127.0.0.1 unless told otherwise;
anywhere else needs --api-key, which clients send as openpi's does (`Authorization: Api-Key KEY`;
remote.py reads it from $VLA_LADDER_API_KEY). Nothing received is unpickled and every message is bounded.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import hmac
import http
import logging
import os
import queue
import signal
import threading
import time
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
import torch
import tyro

from vla_ladder.checks import SEED_LIMIT, check_count, check_port_free, is_loopback, refuse_past_max_clients
from vla_ladder.contract import ACTION_DIM, CAMERAS, STATE_DIM, STATE_KEY
from vla_ladder.policies import MAX_PROMPT, check_spec, parse_spec
from vla_ladder.policies.remote import (API_KEY_ENV, CHUNK_KEY, CONTRACT_KEY, MAX_MESSAGE, PROMPT_KEY, SEED_KEY,
                                        WINDOW_KEY, pack, unpack)

log = logging.getLogger(__name__)


@dataclass
class ServePolicyConfig:
    """Serve a LeRobot checkpoint to remote clients (`vla-ladder serve-policy`; `eval --policy remote:URL`)."""

    policy: Annotated[str, tyro.conf.arg(metavar="SPEC", help_behavior_hint="(required)")] = ""
    """lerobot:CHECKPOINT[?device=D&n_action_steps=H&use_amp=B&noise_seed=K&instruction=TEXT]: the checkpoint to
    serve; its n_action_steps is the default horizon clients run (they may ask for another)"""
    host: str = "127.0.0.1"
    """address to listen on; anything but loopback needs --api-key"""
    port: int = 8000
    """port; 0 picks a free one (the URL is printed once listening)"""
    # read from the environment in __post_init__, so that --help never prints it
    api_key: Annotated[str | None, tyro.conf.arg(metavar="STR", help_behavior_hint="(default: $VLA_LADDER_API_KEY)")] \
        = None
    """secret clients send as `Authorization: Api-Key KEY`; required off loopback"""
    max_batch: int = 16
    """most requests one forward pass answers (those that arrived while the model ran: eval --workers N sends N,
    eval --num-envs N up to N on one connection), and most one connection may have in flight"""
    max_clients: int = 128
    """connections served at once (eval --workers N opens N); more are refused (HTTP 503) until one leaves: each may
    hold --max-batch parsed observations and two unread messages of up to 4 MiB"""

    def __post_init__(self):
        if self.api_key is None:
            self.api_key = os.environ.get(API_KEY_ENV)
        if not self.policy:
            raise ValueError("--policy lerobot:CHECKPOINT is required (the checkpoint to serve)")
        kind, arg = parse_spec(self.policy)
        if kind != "lerobot":
            raise ValueError(f"--policy {self.policy!r}: serve-policy serves LeRobot checkpoints, lerobot:CHECKPOINT "
                             "(the reference and PPO experts read privileged state: evaluate them in-process)")
        if not 0 <= self.port < 65536:
            raise ValueError(f"port must be in 0..65535, got {self.port}")
        if self.max_batch < 1:
            raise ValueError(f"max_batch must be >= 1, got {self.max_batch}")
        check_count(self.max_clients, "--max-clients")
        if not self.api_key and not is_loopback(self.host):
            raise ValueError(f"listening on {self.host!r} (not loopback) needs --api-key (or ${API_KEY_ENV}); "
                             "allowed without one: 127.0.0.1, ::1, localhost")
        check_spec(self.policy)
        from vla_ladder.policies.lerobot import parse_arg, read_saved_config, resolve_checkpoint
        saved = read_saved_config(resolve_checkpoint(parse_arg(arg)[0]))
        check_servable(saved.get("type"), saved.get("temporal_ensemble_coeff"))
        check_port_free(self.host, self.port)  # before the model loads, not after


def check_servable(policy_type: str | None, temporal_ensemble_coeff: float | None = None) -> None:
    """Requests are independent (the client runs the chunk), so only a policy whose chunk depends on the current
    observation alone can be served."""
    from vla_ladder.policies.lerobot import ONE_OBSERVATION_CHUNKS, chunks_from_one_observation

    if chunks_from_one_observation(policy_type, temporal_ensemble_coeff):
        return
    if policy_type in ONE_OBSERVATION_CHUNKS:
        raise ValueError(f"an {policy_type} checkpoint with temporal_ensemble_coeff blends chunks step by step and "
                         "cannot be served chunk by chunk; evaluate it in-process with --policy lerobot:CHECKPOINT")
    raise ValueError(f"a {policy_type} checkpoint cannot be served chunk by chunk (its actions depend on past "
                     f"observations); allowed types: {', '.join(ONE_OBSERVATION_CHUNKS)}. Evaluate it in-process "
                     "with --policy lerobot:CHECKPOINT")


def read_request(request: Any) -> tuple[dict, str, int | None, int | None]:
    """(env-like observation batch of one, instruction, episode seed, chunk index) of a request; ValueError naming
    what a request holds when it is not one."""
    if not isinstance(request, dict):
        raise ValueError(f"a request is a map of observations, got a {type(request).__name__}")
    sensors = {}
    for cam in CAMERAS:
        image = request.get(cam.key)
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != cam.shape:
            got = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
            raise ValueError(f"{cam.key} must be a uint8 array of shape {cam.shape} (HWC), got {got}")
        sensors[cam.name] = {"rgb": torch.from_numpy(image.copy())[None]}
    state = request.get(STATE_KEY)
    if not isinstance(state, np.ndarray) or state.dtype.kind != "f" or state.shape != (STATE_DIM,):
        got = f"{state.dtype} {state.shape}" if isinstance(state, np.ndarray) else type(state).__name__
        raise ValueError(f"{STATE_KEY} must be a float array of shape ({STATE_DIM},), got {got}")
    prompt = request.get(PROMPT_KEY)
    if not isinstance(prompt, str) or not 0 < len(prompt) <= MAX_PROMPT:
        raise ValueError(f"{PROMPT_KEY!r} must be the instruction, 1-{MAX_PROMPT} characters")
    seed, chunk = request.get(SEED_KEY), request.get(CHUNK_KEY)
    # Bounded as episode seeds are: numpy splits a larger integer into 32-bit words, so (seed + 2**32 * c, k) would
    # draw the noise of (seed, c, k), another episode's.
    if (seed is None) != (chunk is None) or any(
            v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= v < SEED_LIMIT)
            for v in (seed, chunk)):
        raise ValueError(f"{SEED_KEY!r} and {CHUNK_KEY!r} come together, as integers in 0..{SEED_LIMIT - 1}, or not "
                         "at all")
    obs = {"sensor_data": sensors, "extra": {"proprio": torch.from_numpy(state.astype(np.float32))[None]}}
    return obs, prompt, None if seed is None else int(seed), None if chunk is None else int(chunk)


def read_window(request: dict, max_batch: int) -> int:
    """The size of the window a request belongs to (WINDOW_KEY; 1 without it): the server waits for the window's
    other requests on the connection and runs them in one forward pass, so that a client's batch of envs is one
    batch here too, whatever the timing (and its rows are what `eval --num-envs N` computes in-process)."""
    window = request.get(WINDOW_KEY, 1)
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or not 1 <= window <= max_batch:
        raise ValueError(f"{WINDOW_KEY!r} must be an integer in 1..{max_batch} (this server's max_pipelined), "
                         f"got {window!r}")
    return int(window)


class PolicyServer:
    """One loaded checkpoint, any number of connections. Requests that arrive while the model runs are answered
    together by its next forward pass (at most --max-batch), so N clients cost one batched pass, not N."""

    def __init__(self, cfg: ServePolicyConfig):
        from vla_ladder.policies import load_policy, weights_identity
        from vla_ladder.policies.lerobot import trained_contract

        self.cfg = cfg
        self.policy = load_policy(cfg.policy)
        self.metadata = {
            "server": "vla-ladder", "policy": self.policy.describe(),
            # what an evaluation's run directory keeps of the weights, so that it refuses to resume with others
            "weights_sha256": weights_identity(cfg.policy)["sha256"],
            "n_action_steps": self.policy.n_action_steps, "action_dim": ACTION_DIM, "max_pipelined": cfg.max_batch,
            "max_clients": cfg.max_clients,
            "observation": {"cameras": {c.key: list(c.shape) for c in CAMERAS}, "state": [STATE_KEY, STATE_DIM],
                            "prompt": PROMPT_KEY, "episode_seed": SEED_KEY, "chunk_index": CHUNK_KEY},
        }
        # What the checkpoint was trained under, when it says (loading it checked it against this server's): the
        # client refuses it if its own vla-ladder plays another task.
        if (contract := trained_contract(self.policy.path)) is not None:
            self.metadata[CONTRACT_KEY] = contract
        self.requests = 0
        self.batches: collections.Counter[int] = collections.Counter()  # forward passes by batch size
        self._pending: asyncio.Queue | None = None  # groups of requests waiting for a forward pass
        self._passes: queue.Queue = queue.Queue()  # batches handed from the event loop to serve_forever's thread

    def chunks(self, requests: list[tuple]) -> list[np.ndarray]:
        """One forward pass for several `read_request` results: each one's whole chunk. A flow-matching policy's row
        gets its episode's noise (`LeRobotPolicy.episode_noise`) when the request names its seed and chunk, else
        noise from torch's generator; a row's chunk is what it would be alone, up to float rounding."""
        from vla_ladder.policies.lerobot import NOISE_PER_EPISODE

        obs = {"sensor_data": {c.name: {"rgb": torch.cat([r[0]["sensor_data"][c.name]["rgb"] for r in requests])}
                               for c in CAMERAS},
               "extra": {"proprio": torch.cat([r[0]["extra"]["proprio"] for r in requests])}}
        noise = None
        if self.policy.config.type in NOISE_PER_EPISODE:
            shape = (self.policy.config.chunk_size, self.policy.config.max_action_dim)
            noise = torch.stack([torch.randn(shape) if seed is None else self.policy.episode_noise(seed, chunk)
                                 for _, _, seed, chunk in requests]).to(self.policy.device)
        actions = self.policy.predict_chunk(obs, [r[1] for r in requests], noise=noise)
        return list(actions.to(torch.float32).cpu().numpy())

    async def _answer_pending(self) -> None:
        """Forever: wait for a group (one request, or a client's window: `read_window`), add every other group
        already waiting while the batch stays within --max-batch, have the main thread run them as one batch, hand
        each its chunk. It waits for nothing it was not told of: a lone request runs at once. A batch of several
        groups that fails is run again group by group, so that only the group that fails gets the error (one
        client's request closed every connection of its batch) and the others get what they get alone."""
        held = None  # a group that did not fit the last batch: it opens the next
        while True:
            groups = [held or await self._pending.get()]
            held = None
            while not self._pending.empty():
                group = self._pending.get_nowait()
                if sum(map(len, groups)) + len(group) > self.cfg.max_batch:
                    held = group
                    break
                groups.append(group)
            batch = [request for group in groups for request in group]
            try:
                await self._answer(batch)
            except Exception as e:
                if len(groups) == 1:
                    log.exception("inference failed for a batch of %d", len(batch))
                    self._fail(batch, e)
                    continue
                log.warning("inference failed for a batch of %d from %d groups (%s: %s); running each group alone",
                            len(batch), len(groups), type(e).__name__, e)
                for group in groups:
                    try:
                        await self._answer(group)
                    except Exception as e:
                        log.exception("inference failed for a group of %d", len(group))
                        self._fail(group, e)

    async def _answer(self, batch: list[tuple]) -> None:
        """One forward pass on the main thread for `batch` ((parsed request, answer future) pairs), each answered its
        chunk; the pass's exception, answering none, when it fails."""
        start = time.perf_counter()
        done: concurrent.futures.Future = concurrent.futures.Future()
        self._passes.put(([parsed for parsed, _ in batch], done))
        chunks = await asyncio.wrap_future(done)
        timing = {"infer_ms": (time.perf_counter() - start) * 1000, "batch": len(batch)}
        self.batches[len(batch)] += 1
        for (_, answer), chunk in zip(batch, chunks):
            if not answer.done():  # its client may have gone
                answer.set_result((chunk, timing))

    @staticmethod
    def _fail(batch: list[tuple], error: Exception) -> None:
        for _, answer in batch:
            if not answer.done():
                answer.set_exception(error)

    def _admit(self, connection, request):
        """Before the handshake: openpi's health check, the client's key, and room under --max-clients."""
        if request.path == "/healthz":  # openpi's health check
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        if self.cfg.api_key:
            sent = request.headers.get("Authorization", "")
            if not hmac.compare_digest(sent.encode(), f"Api-Key {self.cfg.api_key}".encode()):
                return connection.respond(http.HTTPStatus.UNAUTHORIZED, "missing or wrong Api-Key\n")
        return refuse_past_max_clients(connection, self.cfg.max_clients, log)

    async def handle(self, ws) -> None:
        """One connection: its requests are read as they come (up to --max-batch in flight, so that a client's
        batch of envs can share a forward pass) and answered in the order they came."""
        from websockets.exceptions import ConnectionClosed

        peer = ws.remote_address
        log.info("client %s connected", peer)
        replies: asyncio.Queue = asyncio.Queue(self.cfg.max_batch)  # full: stop reading, TCP holds the client back
        reader = asyncio.create_task(self._read(ws, replies))
        try:
            await ws.send(pack(self.metadata))
            while (reply := await replies.get()) is not None:
                kind, value = reply
                if kind == "answer":
                    await asyncio.wait([value])  # (a cancel of this task still ends it here)
                    if value.cancelled():  # its window never completed: the error or the end follows
                        continue
                    try:
                        actions, timing = value.result()
                    except Exception as e:
                        await ws.send(f"inference failed: {type(e).__name__}: {e}")
                        await ws.close(1011, "inference failed")
                        break
                    self.requests += 1
                    await ws.send(pack({"actions": actions, "server_timing": timing}))
                elif kind == "bad":  # after the answers to what came before it
                    await ws.send(value)
                    await ws.close(1008, "bad request")
                    break
                else:
                    await ws.send(value)
        except ConnectionClosed:
            pass
        finally:
            reader.cancel()
        log.info("client %s disconnected", peer)

    async def _read(self, ws, replies: asyncio.Queue) -> None:
        """The connection's requests, in order, onto `replies`: an inference's future, an acknowledgement, or the
        error that ends the connection; None once the client has gone."""
        from websockets.exceptions import ConnectionClosed

        group: list[tuple] = []  # the requests of an open window
        expected = 1

        def abandon() -> None:
            # A window that will not complete (a bad request inside it, or its client gone): its answers will not
            # come, and `handle`, waiting for the first, would wait for ever.
            for _, answer in group:
                answer.cancel()

        try:
            async for message in ws:
                try:
                    request = unpack(message)
                    if isinstance(request, dict) and "__ctrl__" in request:  # openpi's episode markers: nothing to do
                        if group:  # (its acknowledgement would queue behind answers that wait for the window)
                            raise ValueError("an episode marker inside an open window of requests")
                        await replies.put(("ack", pack({"__ack__": str(request["__ctrl__"])[:64]})))
                        continue
                    parsed = read_request(request)  # a bad request is the client's mistake: no inference
                    window = read_window(request, self.cfg.max_batch)
                except ValueError as e:
                    log.info("client %s sent a bad request: %s", ws.remote_address, e)
                    abandon()
                    await replies.put(("bad", f"bad request: {e}"))
                    return
                del message, request  # what was parsed is kept, not the raw message while the next one is awaited
                answer = asyncio.get_running_loop().create_future()
                if not group:
                    expected = window
                group.append((parsed, answer))
                await replies.put(("answer", answer))
                if len(group) >= expected:  # the window is complete: its requests share one forward pass
                    await self._pending.put(group)
                    group = []
        except ConnectionClosed:
            pass
        abandon()
        await replies.put(None)

    async def _serve(self, ready) -> None:
        from websockets.asyncio.server import serve

        self._pending = asyncio.Queue()
        answering = asyncio.create_task(self._answer_pending())
        try:
            # max_queue: frames a connection may have received and not yet read (websockets' default is 16).
            async with serve(self.handle, self.cfg.host, self.cfg.port, max_size=MAX_MESSAGE, max_queue=2,
                             compression=None, process_request=self._admit) as server:
                port = server.sockets[0].getsockname()[1]
                host = f"[{self.cfg.host}]" if ":" in self.cfg.host else self.cfg.host
                if ready is not None:
                    ready(f"ws://{host}:{port}")
                await server.serve_forever()
        finally:
            answering.cancel()

    def serve_forever(self, ready=None) -> None:
        """Serve until KeyboardInterrupt: the event loop on a thread of its own, the forward passes on this one (the
        main thread; the module docstring says why). `ready(url)` is called once listening."""
        started: dict[str, Any] = {}

        def loop_thread() -> None:
            async def main() -> None:
                started["loop"], started["task"] = asyncio.get_running_loop(), asyncio.current_task()
                await self._serve(ready)
            try:
                asyncio.run(main())
            except asyncio.CancelledError:
                pass
            except BaseException as e:  # re-raised on the main thread
                started["error"] = e

        thread = threading.Thread(target=loop_thread, name="websockets", daemon=True)
        thread.start()
        try:
            while thread.is_alive():
                try:
                    requests, done = self._passes.get(timeout=0.2)
                except queue.Empty:
                    continue
                try:
                    done.set_result(self.chunks(requests))
                except Exception as e:  # answered to the batch's clients; the server goes on
                    done.set_exception(e)
        finally:
            if "loop" in started and thread.is_alive():
                started["loop"].call_soon_threadsafe(started["task"].cancel)
            thread.join(timeout=30)
        if "error" in started:
            raise started["error"]


def run(cfg: ServePolicyConfig) -> int:
    if not log.handlers:  # LeRobot configures the root logger on import; this command's lines go to stderr as is
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("[serve-policy %(asctime)s] %(message)s", "%H:%M:%S"))
        log.addHandler(handler)
        log.propagate = False
    log.setLevel(logging.INFO)
    server = PolicyServer(cfg)
    for sig in (signal.SIGINT, signal.SIGTERM):  # both stop it as Ctrl-C does, even where a shell ignored SIGINT
        signal.signal(sig, signal.default_int_handler)
    try:
        server.serve_forever(lambda url: print(f"listening on {url}", flush=True))
    except KeyboardInterrupt:
        pass
    log.info("stopped after %d requests in %d forward passes (by batch size: %s)", server.requests,
             sum(server.batches.values()), dict(sorted(server.batches.items())))
    return 0
