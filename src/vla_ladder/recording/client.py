"""Client side of the episode protocol: one connection (`EpisodeClient`) and a pool drawing episodes from
several servers at once (`EpisodeSource`), which runs its own event loop in a background thread so that
the (blocking) dataset writer simply calls `get()`."""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import logging
import math
import queue
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from vla_ladder import files
from vla_ladder.checks import refusal_body, ws_proxy
from vla_ladder.conditions import Condition
from vla_ladder.contract import ACTION_DIM, CAMERA_NAMES, EPISODE_STEPS, IMAGE_SHAPE, METRICS, STATE_DIM
from vla_ladder.recording import protocol as P

log = logging.getLogger(__name__)
# Close codes after which reconnecting cannot help: the server refused this client or its messages.
PERMANENT = {P.CLOSE_TOO_BIG, P.CLOSE_INTERNAL} | set(range(4000, 5000))
# websockets pings the server every PING_INTERVAL_S and gives up when a pong takes longer than PING_TIMEOUT_S
# (its defaults): a server that stops answering is then found out instead of waited for forever.
PING_INTERVAL_S = 20.0
PING_TIMEOUT_S = 20.0
# A server that answers pings but sends no episode for this long has a stuck simulation (an episode takes seconds,
# building the simulator well under a minute on 2 busy cores): a lost connection, not a wait forever.
EPISODE_TIMEOUT_S = 600.0


class ServerError(RuntimeError):
    """A server closed the connection, stopped answering, or could not be reached."""

    def __init__(self, url: str, message: str, code: int | None = None, permanent: bool | None = None):
        super().__init__(f"{url}: {message}" + (f" (close code {code})" if code is not None else ""))
        self.url, self.code = url, code
        self._permanent = permanent

    @property
    def permanent(self) -> bool:
        """Whether reconnecting cannot help (by default: the close code says the server refused us)."""
        return self.code in PERMANENT if self._permanent is None else self._permanent


@dataclass
class Episode:
    """One simulated episode as received: metadata header plus, when sent, its frames."""

    seed: int
    header: dict
    images: dict[str, np.ndarray]
    """camera -> (T, 256, 256, 3) uint8"""
    state: np.ndarray | None
    """(T, 15) float32: the 15-d proprioceptive state before each action"""
    action: np.ndarray | None
    """(T, 7) float32"""
    server: str

    @property
    def success(self) -> bool:
        return bool(self.header["metrics"]["success"])

    @property
    def has_frames(self) -> bool:
        return self.state is not None

    @property
    def num_frames(self) -> int:
        return int(self.header["num_frames"])

    @classmethod
    def from_message(cls, msg: P.Message, server: str) -> "Episode":
        """The episode of an "episode" message; ProtocolError for any field the recorder uses that is missing or
        of another type (checked before anything is written: a KeyError inside the writer would lose its batch)."""
        h = msg.header
        seed = P.require(h, "seed", int)
        for key, kind in (("instruction", str), ("target", str), ("layout", dict), ("metrics", dict),
                          ("expert", dict), ("condition", str), ("object_set", str), ("num_frames", int),
                          ("has_frames", bool)):
            P.require(h, key, kind)
        for key, kind in (*((m, bool) for m in METRICS), ("lifted", bool), ("held", str), ("reach_dist", (int, float))):
            if not isinstance(h["metrics"].get(key), kind):
                what = "a number" if isinstance(kind, tuple) else kind.__name__
                raise P.ProtocolError(f"episode {seed}: metrics[{key!r}] missing or not {what}")
        if not isinstance(h["expert"].get("spec"), str):
            raise P.ProtocolError(f"episode {seed}: expert['spec'] missing or not str")
        for key in ("layout", "expert"):  # kept as JSON in the provenance: bytes there failed in the writer
            try:
                files.dumps(h[key])
            except (TypeError, ValueError) as e:
                raise P.ProtocolError(f"episode {seed}: {key} is not JSON ({e})") from None
        try:
            Condition.parse(h["condition"])
        except ValueError as e:
            raise P.ProtocolError(f"episode {seed}: condition {h['condition']!r}: {e}") from None
        if h["num_frames"] != EPISODE_STEPS:
            raise P.ProtocolError(f"episode {seed}: {h['num_frames']} frames; the task's episodes have "
                                  f"{EPISODE_STEPS}")
        if not h["has_frames"]:
            if h["metrics"]["success"]:  # the recorder counts it towards the demos and would wait for it forever
                raise P.ProtocolError(f"episode {seed}: a successful episode sent without its frames")
            return cls(seed, h, {}, None, None, server)
        T = h["num_frames"]
        expected = {**{f"images.{c}": ((T, *IMAGE_SHAPE), np.uint8) for c in CAMERA_NAMES},
                    "state": ((T, STATE_DIM), np.float32), "action": ((T, ACTION_DIM), np.float32)}
        for name, (shape, dtype) in expected.items():
            a = msg.arrays.get(name)
            if a is None or a.shape != shape or a.dtype != dtype:
                got = None if a is None else (a.shape, a.dtype.name)
                raise P.ProtocolError(f"episode {seed}: array {name!r} should be {shape} {np.dtype(dtype).name}, "
                                      f"got {got}")
        return cls(seed, h, {c: msg.arrays[f"images.{c}"] for c in CAMERA_NAMES}, msg.arrays["state"],
                   msg.arrays["action"], server)


class EpisodeClient:
    """One protocol connection: hello/welcome, then `request(seeds)` and `receive()`."""

    def __init__(self, url: str, token: str | None = None, max_message: int = P.MAX_EPISODE_MESSAGE,
                 ping_interval: float = PING_INTERVAL_S, ping_timeout: float = PING_TIMEOUT_S,
                 episode_timeout: float = EPISODE_TIMEOUT_S):
        self.url, self.token, self.max_message = url, token, max_message
        self.ping_interval, self.ping_timeout, self.episode_timeout = ping_interval, ping_timeout, episode_timeout
        self.ws = None
        self.welcome: dict | None = None
        self.requested: set[int] = set()  # seeds asked for on this connection and not yet delivered

    async def connect(self, open_timeout: float = 30.0) -> dict:
        from websockets.asyncio.client import connect
        from websockets.exceptions import InvalidStatus, WebSocketException

        try:
            self.ws = await connect(self.url, max_size=self.max_message, compression=None, max_queue=2,
                                    proxy=ws_proxy(self.url), open_timeout=open_timeout,
                                    ping_interval=self.ping_interval, ping_timeout=self.ping_timeout)
        except InvalidStatus as e:  # a busy server (503, at its --max-clients) may take us later; anything else won't
            status, said = e.response.status_code, refusal_body(e)
            raise ServerError(self.url, f"refused the connection (HTTP {status}{': ' + said if said else ''})",
                              permanent=status != 503) from None
        except (OSError, TimeoutError, WebSocketException) as e:
            raise ServerError(self.url, f"cannot connect: {e}") from None
        await self._send(P.hello(self.token, self.max_message))
        try:  # open_timeout covers the HTTP upgrade only: a server that answers pings but never greets was waited for
            msg = await asyncio.wait_for(self._recv(), open_timeout)  # forever (`record --server` hung at its start)
        except TimeoutError:
            await self.close()
            raise ServerError(self.url, f"no welcome within {open_timeout:g} s of the hello; is it a `vla-ladder "
                                        "serve`?") from None
        if msg.type != "welcome" or msg.header.get("protocol") != P.PROTOCOL_VERSION:
            await self.close()
            raise ServerError(self.url, f"expected a protocol {P.PROTOCOL_VERSION} welcome, got {msg.header}")
        self.welcome = msg.header
        return msg.header

    async def request(self, seeds: list[int], failed_frames: bool = False) -> None:
        self.requested.update(seeds)  # first: the seeds of a request lost with the connection count as in flight
        await self._send(P.run(seeds, failed_frames))

    async def receive(self) -> Episode:
        """The next episode; ServerError (permanent) for a malformed one or one of a seed not asked for on this
        connection, or delivered already: each seed is played once for a dataset, which the server must not undo.
        ServerError (not permanent, as for a lost connection) when none comes within `episode_timeout`."""
        try:
            msg = await asyncio.wait_for(self._recv(), self.episode_timeout)
        except TimeoutError:
            raise ServerError(self.url, f"no episode in {self.episode_timeout:g} s from a server that answers pings "
                                        "(its simulation is stuck)", permanent=False) from None
        if msg.type != "episode":
            raise ServerError(self.url, f"unexpected message {msg.type!r}")
        try:
            episode = Episode.from_message(msg, self.url)
            if episode.seed not in self.requested:
                raise P.ProtocolError(f"episode {episode.seed} was not asked for, or was sent already")
        except P.ProtocolError as e:
            await self.ws.close(e.code, e.close_reason)
            raise ServerError(self.url, f"malformed episode: {e.reason}", e.code) from None
        self.requested.discard(episode.seed)
        return episode

    async def close(self) -> None:
        if self.ws is not None:
            await self.ws.close()

    async def _send(self, data: bytes) -> None:
        from websockets.exceptions import ConnectionClosed
        try:
            await self.ws.send(data)
        except ConnectionClosed as e:
            raise self._closed(e) from None

    async def _recv(self) -> P.Message:
        from websockets.exceptions import ConnectionClosed
        try:
            data = await self.ws.recv()
        except ConnectionClosed as e:
            raise self._closed(e) from None
        try:
            return P.decode(data)
        except P.ProtocolError as e:
            await self.ws.close(e.code, e.close_reason)
            raise ServerError(self.url, f"malformed message: {e.reason}", e.code) from None

    def _closed(self, e) -> ServerError:
        if e.rcvd is None and e.sent is not None and e.sent.code == P.CLOSE_INTERNAL:
            # websockets itself fails the connection with 1011 "keepalive ping timeout" when the server stops
            # answering pings. The server refused nothing (a server's own 1011 arrives in e.rcvd): it froze or
            # its network went away, so this is a lost connection, worth reconnecting to like a dropped one.
            return ServerError(self.url, f"server stopped answering ({e.sent.reason or 'keepalive ping timeout'})",
                               e.sent.code, permanent=False)
        frame = e.rcvd or e.sent
        code = frame.code if frame else 1006
        reason = (frame.reason if frame else "") or "connection lost"
        return ServerError(self.url, f"server closed the connection: {reason}", code)


class SeedOrder:
    """Episodes handed on in the order of their seeds, whatever order the servers deliver them in: an episode waits
    until every seed handed out before it has arrived or was given up (`lose`). The dataset is then
    the same for any number of servers: its episodes in seed order, and its first N successes those of the first
    seeds, not of whichever server was faster (two servers stored 200 demos with 11 neighbours swapped, so a
    model trained again on a new recording of them was trained on other batches)."""

    def __init__(self):
        self._unresolved: list[int] = []  # a heap of the seeds handed out and not yet handed on or skipped
        self._arrived: dict[int, Episode | None] = {}  # None: given up

    def hand_out(self, seeds: list[int]) -> None:
        for seed in seeds:
            heapq.heappush(self._unresolved, seed)

    def arrive(self, episode: Episode) -> None:
        self._arrived[episode.seed] = episode

    def lose(self, seeds) -> None:
        self._arrived.update(dict.fromkeys(seeds))

    @property
    def held(self) -> int:
        """Episodes that arrived and wait for an earlier seed."""
        return sum(e is not None for e in self._arrived.values())

    def ready(self) -> list[Episode]:
        """The episodes whose every earlier seed is resolved, in seed order (a lost seed is skipped)."""
        out = []
        while self._unresolved and self._unresolved[0] in self._arrived:
            episode = self._arrived.pop(heapq.heappop(self._unresolved))
            if episode is not None:
                out.append(episode)
        return out


class _Failed:
    """Queue marker: every server is gone (or, `why` "", the seeds ran out and everything played has come)."""

    def __init__(self, errors: list[Exception], why: str = "no server left to draw episodes from: "):
        self.errors, self.why = errors, why


class EpisodeSource:
    """Draws episodes from one or more servers until `successes_needed` successful ones have arrived.

    Seeds come from `reserve(n)` (the dataset store, which never hands a seed out twice). Each server gets
    at most `window` seeds ahead of what it has delivered, and received episodes wait in a queue of
    `queue_size`: a slow writer blocks the receivers, which stops the requests, which idles the servers.
    Episodes come out in seed order (`SeedOrder`); one that waits for a slower server's earlier seed is held, and
    while `max_held` are held no new seeds are asked for.
    """

    def __init__(self, urls: list[str], reserve: Callable[[int], list[int]], successes_needed: int,
                 check_server: Callable[[str, dict], None] | None = None, token: str | None = None,
                 queue_size: int = 4, retries: int = 3, failed_frames: bool = False,
                 ping_interval: float = PING_INTERVAL_S, ping_timeout: float = PING_TIMEOUT_S, max_held: int = 0):
        if not urls:
            raise ValueError("need at least one server URL")
        self.urls, self.reserve, self.token = list(urls), reserve, token
        self.ping_interval, self.ping_timeout = ping_interval, ping_timeout
        self.successes_needed, self.check_server = successes_needed, check_server
        self.retries, self.failed_frames = retries, failed_frames
        self.received = self.successes = 0
        self.lost = 0  # seeds given up (never delivered)
        self.outstanding: dict[str, int] = {u: 0 for u in self.urls}
        self.welcomes: dict[str, dict] = {}
        # Held episodes are whole demos in memory (20 MB each): a few per server cover servers of unequal speed.
        self.max_held = max_held or max(16, 4 * len(self.urls))
        self._order = SeedOrder()
        self._retry: list[int] = []  # seeds of lost connections, to play again
        self._retried: set[int] = set()
        self._no_seeds: ValueError | None = None  # reserve's, once the seeds below 2**32 ran out
        self._out: queue.Queue = queue.Queue(maxsize=queue_size)
        self._stopping = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._main: asyncio.Task | None = None
        self._thread = threading.Thread(target=self._run, name="episode-source", daemon=True)
        self._changed: asyncio.Event | None = None
        self._handing_on: asyncio.Lock | None = None

    # ------------------------------------------------------------------ writer-side API
    def start(self) -> "EpisodeSource":
        self._thread.start()
        return self

    def get(self, timeout: float | None = None) -> Episode:
        """The next episode (successful or not); raises ServerError once every server has failed."""
        item = self._out.get(timeout=timeout)
        if isinstance(item, _Failed):
            self._out.put(item)  # later calls fail the same way
            errors = "; ".join(str(e) for e in item.errors)
            # A server that serves something else (check_server's ValueError) or refused us refuses a rerun too.
            permanent = all(isinstance(e, ValueError) or (isinstance(e, ServerError) and e.permanent)
                            for e in item.errors)
            raise ServerError("all servers", f"{item.why}{errors}", permanent=permanent)
        return item

    def stop(self) -> None:
        self._stopping.set()
        if self._loop is not None and self._main is not None and self._thread.is_alive():
            with contextlib.suppress(RuntimeError):  # the loop may have finished on its own meanwhile
                self._loop.call_soon_threadsafe(self._main.cancel)
        self._thread.join(timeout=30)

    # ------------------------------------------------------------------ event loop
    def _run(self) -> None:
        asyncio.run(self._amain())

    async def _amain(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._changed = asyncio.Event()
        self._handing_on = asyncio.Lock()
        self._main = asyncio.current_task()
        if self._stopping.is_set():
            return
        try:
            results = await asyncio.gather(*(self._serve(u) for u in self.urls), return_exceptions=True)
        except asyncio.CancelledError:
            return
        self.lost += len(self._retry)
        self._order.lose(self._retry)  # no server left to play them: what waited behind them goes out
        self._retry.clear()
        await self._hand_on()
        errors = [r for r in results if isinstance(r, Exception)]
        if errors and not self._stopping.is_set():
            self._put(_Failed(errors))
        elif self._no_seeds is not None and not self._stopping.is_set():
            self._put(_Failed([self._no_seeds], why=""))

    def _demand(self, free: int) -> int:
        """How many more seeds to request now: enough that the expected successes of everything
        outstanding cover what is still needed (success rate estimated as it goes)."""
        needed = self.successes_needed - self.successes
        if needed <= 0 or free <= 0 or self._order.held >= self.max_held:
            return 0
        p = (self.successes + 1) / (self.received + 1)
        want = math.ceil(needed / p - sum(self.outstanding.values()))
        return max(0, min(free, want))

    async def _serve(self, url: str) -> None:
        attempt = 0
        while not self._stopping.is_set():
            client = EpisodeClient(url, self.token, ping_interval=self.ping_interval, ping_timeout=self.ping_timeout)
            lost_connection = False
            try:
                welcome = await client.connect()
                if self.check_server is not None:
                    self.check_server(url, welcome["server"])
                self.welcomes[url] = welcome
                attempt = 0
                await self._pump(url, client, welcome)
                return
            except ValueError as e:  # a server simulating something else than this recording: stop all
                await asyncio.to_thread(self._put, _Failed([e]))
                return
            except ServerError as e:
                lost_connection = not e.permanent
                if e.permanent or attempt >= self.retries:
                    log.error("giving up on %s", e)
                    raise
                attempt += 1
                log.warning("%s; reconnecting in %d s (%d/%d)", e, 2 ** (attempt - 1), attempt, self.retries)
                await asyncio.sleep(2 ** (attempt - 1))
            finally:
                self.outstanding[url] = 0
                self._requeue(client.requested, lost_connection)
                self._changed.set()
                await client.close()
                await self._hand_on()

    async def _pump(self, url: str, client: EpisodeClient, welcome: dict) -> None:
        try:
            limits, server = welcome["limits"], welcome["server"]
            window = min(int(limits["max_outstanding"]), max(2, 2 * int(server["num_envs"])),
                         int(limits["max_seeds_per_request"]))
        except (KeyError, TypeError, ValueError):
            window = 0
        if window < 1:  # asked for nothing, it would wait for nothing, forever
            raise ServerError(url, f"its welcome allows no episode in flight ({str(welcome)[:200]})", permanent=True)
        while True:
            free = window - self.outstanding[url]
            # Seeds of a lost connection go first, whatever the demand: later episodes wait for them.
            seeds = self._retry[:max(free, 0)]
            del self._retry[:len(seeds)]
            k = self._demand(free) - len(seeds)
            if k > 0 and self._no_seeds is None:
                try:
                    new = self.reserve(k)  # fewer than k when the seeds run out
                except ValueError as e:  # none left: the episodes in flight still come, then the source ends
                    self._no_seeds, new = e, []
                self._order.hand_out(new)
                seeds += new
            if seeds:
                await client.request(seeds, self.failed_frames)
                self.outstanding[url] += len(seeds)
            if self.outstanding[url] == 0:
                if (self.successes >= self.successes_needed or self._no_seeds is not None) and not self._retry:
                    return
                self._changed.clear()
                try:  # another server's results may change the demand
                    await asyncio.wait_for(self._changed.wait(), 1.0)
                except TimeoutError:
                    pass
                continue
            episode = await client.receive()
            self.outstanding[url] -= 1
            self.received += 1
            self.successes += episode.success
            self._changed.set()
            self._order.arrive(episode)
            await self._hand_on()

    def _requeue(self, seeds: set[int], lost_connection: bool) -> None:
        """The seeds in flight on a closed connection: played again by the next server to ask (once each) when the
        connection was lost, so that the dataset is the one an unbroken connection gives; given up when the server
        refused us, and on a second loss (a seed whose simulation fails is not handed from server to server)."""
        for seed in sorted(seeds):
            if lost_connection and seed not in self._retried:
                self._retried.add(seed)
                self._retry.append(seed)
            else:
                self.lost += 1
                self._order.lose([seed])

    async def _hand_on(self) -> None:
        # One receiver at a time: two putting from their threads side by side could swap two episodes.
        async with self._handing_on:
            for episode in self._order.ready():
                await asyncio.to_thread(self._put, episode)

    def _put(self, item) -> None:
        while not self._stopping.is_set():
            try:
                self._out.put(item, timeout=0.2)
                return
            except queue.Full:
                continue
