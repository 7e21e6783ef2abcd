"""`vla-ladder record`: draw expert episodes from simulation servers, keep the successful ones in a
LeRobotDataset v3. Rerunning the same command resumes; see docs/recording.md."""

from __future__ import annotations

import argparse
import logging
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

from vla_ladder.recording.client import Episode, EpisodeSource, ServerError
from vla_ladder.recording.serve_cli import TOKEN_ENV, setup_logging
from vla_ladder.recording.writer import DatasetStore, RecordingConfig
from vla_ladder.task.layouts import REGIMES, SPLITS, check_args

log = logging.getLogger(__name__)
SERVER_START_TIMEOUT_S = 900


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--policy", default="scripted", help="expert spec: scripted, ppo:PATH, ... (default: scripted)")
    p.add_argument("--regime", required=True, choices=list(REGIMES))
    p.add_argument("--split", default="canonical", choices=list(SPLITS))
    p.add_argument("--num-objects", type=int, default=5, help="objects per scene, 1..5 (default: 5)")
    p.add_argument("--episodes", type=int, required=True, help="successful episodes the dataset should hold")
    p.add_argument("--out", required=True, help="dataset directory (created, or resumed when it exists)")
    p.add_argument("--server", action="append", default=[], metavar="URL",
                   help="ws://HOST:PORT of a `vla-ladder serve`; repeat to draw from several "
                   "(default: start one locally)")
    p.add_argument("--seed", type=int, default=0, help="first episode seed; later ones never repeat (default: 0)")
    p.add_argument("--images", action="store_true", help="store camera frames as PNG images, not MP4 video")
    p.add_argument("--token", default=os.environ.get(TOKEN_ENV), help=f"server token (default: ${TOKEN_ENV})")
    p.add_argument("--num-envs", type=int, default=1, help="parallel envs of the local server (GPU for > 1)")
    p.add_argument("--commit-every", type=int, default=50,
                   help="commit to the dataset every N saved episodes (default: 50)")
    p.add_argument("--commit-seconds", type=float, default=600.0,
                   help="... or, at the next saved episode, when the open batch is older than this "
                   "(default: 600)")


def run(args: argparse.Namespace) -> int:
    check_args(args.regime, args.split, args.num_objects)
    if args.episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    for url in args.server:
        if not url.startswith(("ws://", "wss://")):
            raise ValueError(f"--server {url!r}: expected ws://HOST:PORT or wss://HOST:PORT")
    from vla_ladder.policies import parse_spec
    parse_spec(args.policy)
    setup_logging("record")
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its whole configuration per video otherwise
    config = RecordingConfig(policy=args.policy, regime=args.regime, split=args.split,
                             num_objects=args.num_objects, seed=args.seed, video=not args.images)
    store = DatasetStore(args.out, config, commit_every=args.commit_every, commit_seconds=args.commit_seconds)
    if store.saved >= args.episodes:
        log.info("%s already holds %d episodes (asked for %d); nothing to do", args.out, store.saved, args.episodes)
        store.close()
        return 0
    if store.saved:
        log.info("resuming %s at %d/%d episodes, next seed %d", args.out, store.saved, args.episodes,
                 store.next_seed)
    local = None
    source = None
    try:
        if args.server:
            urls = args.server
        else:
            local = LocalServer(args)
            urls = [local.url]
        source = EpisodeSource(urls, store.reserve_seeds, args.episodes - store.saved,
                               check_server=lambda url, info: check_server(config, url, info),
                               token=args.token).start()
        progress = Progress(args.episodes, store.saved)
        while store.saved + store.pending < args.episodes:
            episode = source.get()
            store.count(episode.success)
            if episode.success and episode.has_frames:
                store.add(episode)
            progress.update(episode, store)
        store.close()
        progress.report(store, final=True)
        return 0
    except KeyboardInterrupt:
        log.info("interrupted: committing the %d pending episodes", store.pending)
        store.close()
        return 130
    except ServerError as e:
        log.error("%s", e)
        log.info("committing the %d episodes received complete; rerun the same command to continue",
                  store.pending)
        store.close()
        return 1
    except BaseException:
        store.close(commit=False)
        raise
    finally:
        if source is not None:
            source.stop()
        if local is not None:
            local.stop()


def check_server(config: RecordingConfig, url: str, info: dict) -> None:
    """A server must simulate exactly the condition and expert this dataset records."""
    wrong = [f"{k}={info.get(k)!r} (recording: {getattr(config, k)!r})"
             for k in ("policy", "regime", "split", "num_objects") if info.get(k) != getattr(config, k)]
    if wrong:
        raise ValueError(f"server {url} runs " + ", ".join(wrong) + "; start it with the recording's arguments")


@dataclass
class Progress:
    """Episodes saved / attempted, the expert's success rate, frames/s and ETA, logged every few seconds."""

    target: int
    start_saved: int
    every_s: float = 10.0
    attempted: int = 0
    successes: int = 0
    frames: int = 0
    started: float = field(default_factory=time.monotonic)
    last: float = 0.0

    def update(self, episode: Episode, store: DatasetStore) -> None:
        self.attempted += 1
        self.successes += episode.success
        self.frames += episode.num_frames
        if time.monotonic() - self.last >= self.every_s:
            self.report(store)

    def report(self, store: DatasetStore, final: bool = False) -> None:
        self.last = now = time.monotonic()
        elapsed = max(now - self.started, 1e-9)
        done = store.saved + store.pending - self.start_saved
        rate = done / elapsed
        left = self.target - store.saved - store.pending
        eta = time.strftime("%H:%M:%S", time.gmtime(left / rate)) if rate > 0 else "?"
        log.info("%s %d/%d saved (+%d pending) | attempted %d, expert success %.0f%% | %.1f frames/s simulated, "
                 "%.3f demos/s saved | ETA %s", "done:" if final else "progress:", store.saved, self.target,
                 store.pending, self.attempted, 100 * self.successes / max(self.attempted, 1),
                 self.frames / elapsed, rate, eta)


class LocalServer:
    """`vla-ladder serve` as a child process on 127.0.0.1 with a free port, tied to this process: it exits
    when our end of its stdin closes, so even a kill -9 of the recorder does not leave it behind."""

    def __init__(self, args: argparse.Namespace):
        cmd = [sys.executable, "-m", "vla_ladder.cli", "serve", "--policy", args.policy, "--regime", args.regime,
               "--split", args.split, "--num-objects", str(args.num_objects), "--seed", str(args.seed),
               "--num-envs", str(args.num_envs), "--host", "127.0.0.1", "--port", "0", "--exit-on-stdin-close"]
        log.info("starting a local server: %s", " ".join(cmd[2:]))
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.url = self._wait_ready()
        threading.Thread(target=self._forward, daemon=True).start()

    def _wait_ready(self) -> str:
        deadline = time.monotonic() + SERVER_START_TIMEOUT_S
        result: list[str] = []

        def read():
            for line in self.proc.stdout:
                if line.startswith("listening on "):
                    result.append(line.split()[-1])
                    return

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        reader.join(timeout=max(0.0, deadline - time.monotonic()))
        if not result:
            self.stop()
            raise ServerError("local server", f"did not start (exit code {self.proc.poll()}); see its log above")
        return result[0]

    def _forward(self) -> None:
        for line in self.proc.stdout:
            sys.stderr.write(line)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
