"""A server that stops answering is reconnected like one that dropped the connection.

websockets pings the server and, when no pong comes back in time, fails the connection itself with close code
1011 "keepalive ping timeout" — the code a server sends when its simulation fails, after which retrying is
pointless. Here real servers on 127.0.0.1 freeze their event loop (as a server stuck in a long blocking call or
a frozen VM does): the client must take that for a lost connection, not a refusal."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import threading
import time

import pytest

from vla_ladder.recording import protocol as P
from vla_ladder.recording.client import EpisodeClient, EpisodeSource, ServerError

PING = dict(ping_interval=0.2, ping_timeout=0.5)


class LoopThread:
    """An asyncio event loop in a thread of its own, running one server coroutine until stopped; `freeze(s)` blocks
    that loop for s seconds, so the server answers nothing, pings included."""

    def __init__(self, serve):
        self._serve, self.loop, self.url = serve, None, None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)

    async def _main(self):
        self.loop = asyncio.get_running_loop()
        self._task = asyncio.current_task()
        try:
            await self._serve(self._started)
        except asyncio.CancelledError:
            pass

    def _started(self, url: str) -> None:
        self.url = url
        self._ready.set()

    def __enter__(self) -> "LoopThread":
        self._thread.start()
        assert self._ready.wait(300), "the server did not start"
        return self

    def __exit__(self, *exc) -> None:
        self.loop.call_soon_threadsafe(self._task.cancel)
        self._thread.join(timeout=120)

    def freeze(self, seconds: float) -> None:
        self.loop.call_soon_threadsafe(time.sleep, seconds)


async def _greeting_server(ready, serves: dict | None = None, limits: dict | None = None) -> None:
    """The handshake of protocol.py and nothing more: enough for a client to be connected and waiting. It answers
    pings and never sends an episode, as a server whose simulation thread is stuck."""
    from websockets.asyncio.server import serve

    async def handle(ws):
        P.decode(await ws.recv())  # the hello
        await ws.send(P.encode({"type": "welcome", "protocol": P.PROTOCOL_VERSION, "server": serves or {},
                                "limits": limits or {}}))
        await ws.wait_closed()

    async with serve(handle, "127.0.0.1", 0) as server:
        ready(f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}")
        await asyncio.Future()


def test_a_server_that_never_greets_is_not_waited_for_forever():
    """A WebSocket server that reads the hello and answers pings but sends no welcome (not a `vla-ladder serve`):
    connect() waited for the welcome forever, and so did `record --server` at its start."""

    async def silent(ready):
        from websockets.asyncio.server import serve

        async def handle(ws):
            await ws.recv()
            await ws.wait_closed()

        async with serve(handle, "127.0.0.1", 0) as server:
            ready(f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}")
            await asyncio.Future()

    async def connect(url):
        client = EpisodeClient(url, **PING)
        with pytest.raises(ServerError, match="no welcome within 1 s of the hello"):
            await asyncio.wait_for(client.connect(open_timeout=1.0), 30)

    with LoopThread(silent) as server:
        asyncio.run(connect(server.url))


def test_a_loopback_server_is_reached_directly_where_the_environment_names_a_proxy(monkeypatch):
    """websockets sends every connection through $https_proxy / $http_proxy unless no_proxy names the host, so on a
    machine with a proxy (a cluster's login node) `record` reached none of the servers it started on 127.0.0.1."""
    for name in ("https_proxy", "http_proxy", "HTTPS_PROXY", "HTTP_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.setenv(name, "http://127.0.0.1:9")  # (the discard port: nothing listens there)
    for name in ("no_proxy", "NO_PROXY"):
        monkeypatch.delenv(name, raising=False)

    async def connect(url):
        client = EpisodeClient(url, **PING)
        welcome = await asyncio.wait_for(client.connect(open_timeout=5.0), 30)
        await client.ws.close()
        return welcome

    with LoopThread(_greeting_server) as server:
        assert asyncio.run(connect(server.url))["protocol"] == P.PROTOCOL_VERSION


def test_the_proxy_choice_and_the_duplicate_check_read_a_host_alike():
    """ws_proxy (connect directly or through the environment's proxy) and ws_endpoint (`--server` given twice) read
    a URL's host one way: an IPv4-mapped loopback literal, `ws://[::ffff:127.0.0.1]:P`, was 127.0.0.1 to the
    duplicate check but went through the proxy, which cannot reach this machine's loopback (cannot connect)."""
    import ipaddress

    from vla_ladder.checks import ws_endpoint, ws_proxy

    for url in ("ws://[::1]:8000", "ws://LOCALHOST:1", "ws://u@127.0.0.1:1", "ws://u:p@localhost.:1/a",
                "ws://[::ffff:127.0.0.1]:1", "ws://[0:0:0:0:0:0:0:1]:1", "ws://127.0.0.2:1"):
        names = ws_endpoint(url)[0]
        assert ws_proxy(url) is None and all(ipaddress.ip_address(n).is_loopback for n in names), (url, names)
    for url in ("ws://gpu-node.example:1", "ws://U@GPU-node.example.:1", "ws://10.0.0.1:1", "ws://[::ffff:10.0.0.1]:1",
                "ws://[2001:db8::1]:1"):
        names = ws_endpoint(url)[0]
        assert ws_proxy(url) is True and names in ({"gpu-node.example"}, {"10.0.0.1"}, {"2001:db8::1"}), (url, names)


def test_a_server_that_stops_answering_is_a_lost_connection_not_a_refusal():
    async def receive_while_frozen(server: LoopThread) -> ServerError:
        client = EpisodeClient(server.url, **PING)
        await client.connect()
        server.freeze(3)
        try:
            with pytest.raises(ServerError) as e:
                await asyncio.wait_for(client.receive(), 10)
        finally:
            await client.close()
        return e.value

    with LoopThread(_greeting_server) as server:
        error = asyncio.run(receive_while_frozen(server))
    assert "stopped answering (keepalive ping timeout)" in str(error) and error.code == P.CLOSE_INTERNAL
    assert not error.permanent  # so EpisodeSource reconnects, as after a dropped connection
    assert ServerError("ws://x", "simulation failed", P.CLOSE_INTERNAL).permanent  # a server's own 1011 stays final


def test_a_server_that_answers_pings_but_sends_no_episode_is_not_waited_for_forever():
    """Pings find a frozen server, not one whose simulation is stuck: receive() gives up after `episode_timeout`
    (a lost connection, reconnected like one); and a welcome whose limits allow no episode in flight is refused at
    once, instead of a source that asks for nothing and waits for it."""
    import functools

    async def receive_from_stuck(server: LoopThread) -> tuple[ServerError, float]:
        client = EpisodeClient(server.url, episode_timeout=1.0, **PING)
        await client.connect()
        await client.request([1])
        start = time.monotonic()
        try:
            with pytest.raises(ServerError) as e:
                await client.receive()
        finally:
            await client.close()
        return e.value, time.monotonic() - start

    with LoopThread(_greeting_server) as server:
        error, waited = asyncio.run(receive_from_stuck(server))
    assert "no episode in 1 s from a server that answers pings" in str(error) and not error.permanent
    assert 0.9 < waited < 10

    nothing = functools.partial(_greeting_server, serves={"num_envs": 1},
                                limits={"max_outstanding": 0, "max_seeds_per_request": 16})
    with LoopThread(nothing) as server:
        source = EpisodeSource([server.url], lambda n: list(range(n)), successes_needed=1, **PING).start()
        try:
            with pytest.raises(ServerError, match="allows no episode in flight") as e:
                source.get(timeout=60)
        finally:
            source.stop()
    assert e.value.permanent


async def _episode_server(ready, delay: float, drop: str = "never", dropped: list | None = None) -> None:
    """The protocol's server side without a simulator: every requested seed comes back after `delay` seconds as a
    failed episode (no frames). With drop="first" ("every"), the first connection (every one) is closed (1001, going
    away: worth a reconnect) as soon as its first request arrives, and that request's seeds are kept in `dropped`."""
    from websockets.asyncio.server import serve
    from websockets.exceptions import ConnectionClosed

    metrics = {"success": False, "grasp_any": False, "reach": False, "lifted": False, "held": "", "reach_dist": 0.1}
    connections = itertools.count()

    async def handle(ws):
        first = next(connections) == 0
        P.decode(await ws.recv())  # the hello
        await ws.send(P.encode({"type": "welcome", "protocol": P.PROTOCOL_VERSION, "server": {"num_envs": 1},
                                "limits": {"max_outstanding": 8, "max_seeds_per_request": 16}}))
        with contextlib.suppress(ConnectionClosed):  # the source stops once it has what it needs
            async for data in ws:
                seeds = P.decode(data).header["seeds"]
                if drop == "every" or (drop == "first" and first):
                    dropped.extend(seeds)
                    await ws.close(P.CLOSE_GOING_AWAY, "going away")
                    return
                for seed in seeds:
                    await asyncio.sleep(delay)
                    await ws.send(P.encode({"type": "episode", "seed": seed, "instruction": "grasp the apple",
                                            "target": "apple", "layout": {}, "metrics": metrics,
                                            "expert": {"spec": "scripted"}, "condition": "small_jitter/canonical/2",
                                            "object_set": "standin", "num_frames": 50, "has_frames": False}))

    async with serve(handle, "127.0.0.1", 0) as server:
        ready(f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}")
        await asyncio.Future()


def _draw(urls: list[str], n: int, max_held: int = 0, retries: int = 3) -> list[int]:
    seeds = itertools.count()
    source = EpisodeSource(urls, lambda k: [next(seeds) for _ in range(k)], successes_needed=1, max_held=max_held,
                           retries=retries, **PING).start()
    try:
        return [source.get(timeout=60).seed for _ in range(n)]
    finally:
        source.stop()


def test_episodes_come_out_in_seed_order_from_servers_of_unequal_speed():
    """A server 15x faster than the other delivers its seeds first; the source hands them on in seed order (the
    dataset of a recording is then the same for any number of servers). With at most one episode held, the fast
    server waits instead of running ahead. The seeds of a dropped connection are played again by the next server
    to ask, so nothing is missing; a seed lost twice is given up, and what waited behind it goes on."""
    import functools

    slow, fast = functools.partial(_episode_server, delay=0.3), functools.partial(_episode_server, delay=0.02)
    with LoopThread(slow) as a, LoopThread(fast) as b:
        assert _draw([a.url, b.url], 16) == list(range(16))
        assert _draw([a.url, b.url], 8, max_held=1) == list(range(8))

    dropped: list[int] = []
    dropping = functools.partial(_episode_server, delay=0.02, drop="first", dropped=dropped)
    with LoopThread(slow) as a, LoopThread(dropping) as b:
        assert _draw([a.url, b.url], 16) == list(range(16)) and dropped

    dropped.clear()
    failing = functools.partial(_episode_server, delay=0.02, drop="every", dropped=dropped)
    with LoopThread(slow) as a, LoopThread(failing) as b:
        seeds = _draw([a.url, b.url], 12, retries=1)  # b: dropped, reconnected, dropped, given up
    twice = {s for s in dropped if dropped.count(s) == 2}
    assert dropped and seeds == [s for s in range(max(seeds) + 1) if s not in twice]


@pytest.mark.slow
def test_recording_goes_on_after_the_expert_server_froze(caplog):
    """The real episode server (scripted expert, both cameras) freezes once its first episode has arrived; the source
    notices within seconds, reconnects when the server is back and still delivers every episode asked for.

    Not frozen earlier: SAPIEN's first camera picture with lavapipe (compiling its pipelines, in the simulator's
    build) holds the GIL for 7.5 s here, during which the client's own pings cannot go out, so a freeze inside it
    would go unseen (1 run in 8 on 2 loaded cores)."""
    from vla_ladder.conditions import Condition
    from vla_ladder.recording.server import EpisodeServer, ServeConfig

    server = EpisodeServer(ServeConfig(condition=Condition("small_jitter", "canonical", 2), port=0))
    seeds = itertools.count(300)
    caplog.set_level(logging.INFO, logger="vla_ladder.recording")
    with LoopThread(server.serve) as running:
        source = EpisodeSource([running.url], lambda n: [next(seeds) for _ in range(n)], successes_needed=3,
                               ping_interval=0.5, ping_timeout=2.0).start()
        try:
            deadline = time.monotonic() + 120
            while running.url not in source.welcomes:
                assert time.monotonic() < deadline, "the source never connected"
                time.sleep(0.1)
            episodes = [source.get(timeout=600)]
            running.freeze(6)
            while sum(e.success for e in episodes) < 3:  # 2 or more still to come: the source stays connected
                episodes.append(source.get(timeout=600))
        finally:
            source.stop()
    warnings = [r.getMessage() for r in caplog.records if r.name == "vla_ladder.recording.client"]
    assert any("stopped answering (keepalive ping timeout)" in w and "reconnecting" in w for w in warnings), warnings
    assert all(e.has_frames for e in episodes if e.success)
    assert len({e.seed for e in episodes}) == len(episodes)
