"""`vla-ladder serve`: run an expert in GraspObject-v1 and serve its episodes over WebSockets."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import sys
import threading

from vla_ladder.recording.server import EpisodeServer, ServerConfig
from vla_ladder.task.layouts import REGIMES, SPLITS

TOKEN_ENV = "VLA_LADDER_TOKEN"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--policy", default="scripted", help="expert spec: scripted, ppo:PATH, ... (default: scripted)")
    p.add_argument("--regime", required=True, choices=list(REGIMES))
    p.add_argument("--split", default="canonical", choices=list(SPLITS))
    p.add_argument("--num-objects", type=int, default=5, help="objects per scene, 1..5 (default: 5)")
    p.add_argument("--seed", type=int, default=0, help="seeds the server's own RNGs; episode seeds come from "
                   "the clients (default: 0)")
    p.add_argument("--num-envs", type=int, default=1, help="parallel envs in lock step; > 1 needs a GPU")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default: 127.0.0.1, loopback only)")
    p.add_argument("--port", type=int, default=8765, help="port (0: any free port; default: 8765)")
    p.add_argument("--token", default=os.environ.get(TOKEN_ENV),
                   help=f"shared secret clients must present; required off loopback (default: ${TOKEN_ENV})")
    p.add_argument("--max-outstanding", type=int, default=0,
                   help="episodes a client may request ahead (default: 4 x num-envs, at least 8)")
    p.add_argument("--lazy", action="store_true", help="build the simulator on the first request")
    p.add_argument("--exit-on-stdin-close", action="store_true",
                   help="exit when stdin closes (how `record` ties an embedded server to its own life)")


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is when a record is emitted (test runners swap it)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):
        pass


def setup_logging(prefix: str) -> None:
    logger = logging.getLogger("vla_ladder.recording")
    if not logger.handlers:
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter(f"[{prefix} %(asctime)s] %(message)s", "%H:%M:%S"))
        logger.addHandler(handler)
        logger.propagate = False
    logger.setLevel(logging.INFO)


def run(args: argparse.Namespace) -> int:
    cfg = ServerConfig(policy=args.policy, regime=args.regime, split=args.split, num_objects=args.num_objects,
                       seed=args.seed, num_envs=args.num_envs, host=args.host, port=args.port, token=args.token,
                       max_outstanding=args.max_outstanding, lazy=args.lazy)
    from vla_ladder.policies import parse_spec
    parse_spec(cfg.policy)
    setup_logging("serve")
    server = EpisodeServer(cfg)
    if args.exit_on_stdin_close:
        threading.Thread(target=_exit_on_eof, daemon=True).start()

    def ready(url: str) -> None:
        print(f"listening on {url}", flush=True)

    async def main() -> None:
        task = asyncio.current_task()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, task.cancel)
        await server.serve(ready)

    try:
        asyncio.run(main())
    except asyncio.CancelledError:
        pass
    logging.getLogger(__name__).info("stopped after serving %d episodes", server.episodes_served)
    return 0


def _exit_on_eof() -> None:
    sys.stdin.buffer.read()
    os._exit(0)  # the parent is gone: do not wait for the episode in progress
