"""`vla-ladder serve`: run an expert in GraspObject-v1 and serve its episodes over WebSockets."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import sys
import threading

from vla_ladder.recording.server import EpisodeServer, ServeConfig


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


def run(cfg: ServeConfig) -> int:
    setup_logging("serve")
    server = EpisodeServer(cfg)
    if cfg.exit_on_stdin_close:
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
    # os.read, not sys.stdin: a daemon thread blocked in the buffered reader holds its lock, and Python's shutdown
    # after Ctrl-C then died on it ("Fatal Python error: _enter_buffered_busy"), aborting the server.
    while os.read(sys.stdin.fileno(), 65536):
        pass
    os._exit(0)  # the parent is gone: do not wait for the episode in progress
