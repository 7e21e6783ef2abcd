"""`vla-ladder record`: draw expert episodes from simulation servers, keep the successful ones in a
LeRobotDataset v3. Rerunning the same command resumes; see docs/recording.md."""

from __future__ import annotations

import asyncio
import logging
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from vla_ladder.checks import SEED_LIMIT, check_count, check_distinct_ws_urls, check_ws_url
from vla_ladder.conditions import Condition
from vla_ladder.machine import auto_workers, auto_writers, check_workers
from vla_ladder.recording.card import missing_targets, target_counts
from vla_ladder.recording.client import Episode, EpisodeClient, EpisodeSource, ServerError
from vla_ladder.recording.serve import setup_logging
from vla_ladder.recording.server import TOKEN_ENV
from vla_ladder.task.object_sets import resolve_object_set
from vla_ladder.task.robot import check_robot_mesh
from vla_ladder.recording.store import DatasetStore, Recording
from vla_ladder.recordings import DEFAULT_VCODEC, RECORD_FIRST_SEED, VCODECS, read_provenance, read_recording

log = logging.getLogger(__name__)
SERVER_START_TIMEOUT_S = 900


@dataclass
class RecordConfig:
    """Record successful expert episodes into a LeRobotDataset v3 (rerunning the same command resumes)."""

    out: Path
    """dataset directory (created, or resumed when it exists)"""
    episodes: int
    """successful episodes the dataset should hold"""
    server: Annotated[tuple[str, ...], tyro.conf.arg(metavar="URL [URL ...]", help_behavior_hint="(default: none)")] \
        = ()
    """ws://HOST:PORT of running `vla-ladder serve`s to draw from; the dataset records the condition and expert
    they serve (all must serve the same; --regime, --split, --num-objects given too must match it). Without it,
    local servers are started with the options below."""
    condition: Annotated[Condition, tyro.conf.arg(name="")] = field(default_factory=Condition)
    """condition of the local server (with --server, the servers' condition; a different one given here is an
    error)"""
    policy: str = "scripted"
    """the local servers' expert: scripted, ppo:PATH or a policy plugin's KIND[:ARG] (with --server, the servers'
    expert)"""
    workers: int = 0
    """local servers, each simulating in its own process (0: one per core, capped by memory)"""
    num_envs: int = 1
    """parallel envs of each local server (more than one needs a GPU)"""
    robot_mesh: str = "lite"
    """the local servers' robot meshes: lite (decimated visual meshes, fast on a CPU renderer) or full (ManiSkill's);
    physics is the same"""
    rebuild_scenes: bool = True
    """local servers rebuild the CPU scene every episode, so that every recorded episode replays bit for bit from
    its seed and actions (~2% of a demo's simulation); --no-rebuild-scenes reuses it (replays may drift by mm)"""
    instructions: str = "canonical"
    """how the local servers word instructions: canonical, paraphrase-train (record these to evaluate on held-out
    paraphrases) or paraphrase-heldout"""
    first_seed: Annotated[int | None, tyro.conf.arg(
        metavar="INT", help_behavior_hint="(default: 1000000, or the dataset's own when resuming it)")] = None
    """first episode seed; later ones follow and never repeat, across servers and resumes (1000000 is far from the
    evaluation seeds 0..., so that no evaluated scene is a demonstration's)"""
    video: bool = True
    """store camera frames as MP4 video (LeRobot's default); --no-video stores PNG images"""
    vcodec: str = DEFAULT_VCODEC
    """video codec of the cameras: libsvtav1 (AV1, LeRobot's default) or h264 (a quarter less of the writer's CPU
    time, half the bytes, ~2 dB lower PSNR; docs/recording.md); fixed for the dataset's life"""
    # read from the environment in __post_init__, so that --help never prints it
    token: Annotated[str | None, tyro.conf.arg(metavar="STR", help_behavior_hint="(default: $VLA_LADDER_TOKEN)")] = None
    """the token the servers require (`vla-ladder serve --token`)"""
    commit_every: int = 50
    """commit to the dataset every N saved episodes (each commit starts new video files; within a batch LeRobot
    rewrites its file for every episode, so thousands cost more than they save: docs/recording.md)"""
    commit_seconds: float = 600.0
    """... or, at the next saved episode, when the open batch is older than this"""
    give_up_after: int = 200
    """stop when none of a run's first N episodes succeeded and the dataset holds none (0 of 200: a success rate
    under 1.9%, 95% Wilson bound): the expert cannot do this condition, or is no expert; 0: never"""
    writers: int = 0
    """dataset writers, each a process of its own drawing blocks of seeds from its share of the servers into shards
    that are merged into --out, in seed order, at the end: the dataset one writer records (LeRobot's writer takes
    ~0.4 CPU s a demo on 2 idle cores, docs/recording.md); 0: one per two servers"""
    encoder_threads: int = 0
    """threads of each camera's video encoder (SVT-AV1's lp); 0: the encoder's choice (on 2 cores one thread was up
    to 17% faster with one writer, no faster with two; see docs/recording.md)"""
    ledger: Path | None = None
    """the ledger shared with other writers (set by `record --writers` for the writer processes it starts, whose --out
    is then its shards directory)"""

    def __post_init__(self):
        if self.token is None:
            self.token = os.environ.get(TOKEN_ENV)
        self.out = Path(self.out)
        if not self.out.resolve().name:  # (its work directory is a hidden sibling: the root has none)
            raise ValueError(f"--out {str(self.out)!r} is the file system's root; give a directory for the dataset")
        self.condition = Condition.of(self.condition)
        self.server = tuple(self.server)
        if self.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {self.episodes}")
        if self.num_envs < 1:
            raise ValueError(f"--num-envs must be >= 1, got {self.num_envs}")
        if self.num_envs > 1 and not self.server:  # the local servers' own check, before any of them starts
            from vla_ladder.task.physx_gpu import check_physx_cuda
            check_physx_cuda("--num-envs > 1 batches each local server on physx_cuda (a CUDA GPU); on a CPU use "
                             "--num-envs 1 and --workers N")
        if not self.server:  # the local servers' objects ($VLA_LADDER_OBJECT_SET), before any of them starts
            resolve_object_set("auto")
        if self.give_up_after < 0:
            raise ValueError(f"--give-up-after must be >= 0 (0: never), got {self.give_up_after}")
        check_count(self.commit_every, "--commit-every")
        if not self.commit_seconds > 0:  # (nan too)
            raise ValueError(f"--commit-seconds must be > 0, got {self.commit_seconds}")
        if self.first_seed is None:  # (record, eval and the grid all began at seed 0: models were scored on demos)
            made = read_recording(self.out) if self.out.is_dir() else None
            self.first_seed = made.first_seed if made is not None else RECORD_FIRST_SEED
        if self.first_seed < 0 or self.first_seed + self.episodes > SEED_LIMIT:
            raise ValueError(f"--first-seed must be >= 0 and --first-seed + --episodes <= 2**32 (each demo takes "
                             f"a seed of its own, a numpy seed), got {self.first_seed} + {self.episodes}")
        check_workers(self.workers)
        if self.writers < 0:
            raise ValueError(f"--writers must be >= 0 (0: one per two servers), got {self.writers}")
        if self.vcodec not in VCODECS:
            raise ValueError(f"--vcodec {self.vcodec!r}: allowed: {', '.join(VCODECS)}")
        if not self.video and self.vcodec != DEFAULT_VCODEC:
            raise ValueError(f"--vcodec {self.vcodec} needs video; --no-video stores PNG images, no codec")
        if self.encoder_threads < 0:
            raise ValueError(f"--encoder-threads must be >= 0 (0: the encoder's choice), got {self.encoder_threads}")
        if self.ledger is not None and not self.server:
            raise ValueError("--ledger is for the writers `record --writers` starts: it needs their --server URLs")
        if self.server and len(self.server) < self.writers:
            raise ValueError(f"--writers {self.writers} needs at least {self.writers} --server URLs (each writer "
                             f"draws from its own), got {len(self.server)}")
        if self.workers and self.workers < self.writers:
            raise ValueError(f"--writers {self.writers} needs at least {self.writers} local servers, got --workers "
                             f"{self.workers}")
        check_robot_mesh(self.robot_mesh)
        from vla_ladder.task.instructions import check_instruction_set
        check_instruction_set(self.instructions)
        for url in self.server:
            check_ws_url(url, "--server")
        # Two connections to one server (however spelt): its episodes drawn twice as fast, not two servers' worth.
        check_distinct_ws_urls(self.server, "--server")
        from vla_ladder.policies import check_expert, check_spec, parse_spec
        # The local servers' expert is checked here, before they start (each refused it, and the recorder said to
        # rerun); with --server the servers' expert is the one recorded.
        (parse_spec if self.server else check_spec)(self.policy)
        if not self.server:  # a demonstration is an expert's
            check_expert(self.policy, f"--policy {self.policy}")


def recording_of(cfg: RecordConfig) -> tuple[Recording, str | None]:
    """What the dataset will be a recording of: the local server's settings, or what the servers say they
    serve (from their welcome messages); and the object set they simulate (None: a server that does not say)."""
    if not cfg.server:
        return Recording(cfg.policy, cfg.condition, cfg.first_seed, cfg.video, cfg.robot_mesh, cfg.instructions,
                         cfg.vcodec), resolve_object_set("auto")  # (the local servers' environment is ours)
    from vla_ladder.policies import check_expert
    served = {url: asyncio.run(_welcome(url, cfg.token)) for url in cfg.server}
    for url, info in served.items():
        if not (isinstance(info, dict) and all(isinstance(info.get(k), str) for k in ("policy", "condition"))):
            raise ValueError(f"--server {url}: its welcome does not say what it serves (server.policy and "
                             f"server.condition, strings): {str(info)[:200]}")
        check_expert(info["policy"], f"--server {url} serves {info['policy']!r}, which")
    # The object set too ("auto" is ycb where the YCB models are on disk, else standin): a dataset holds one, and
    # writers' shards of two could never merge (each rerun refused the merge anew).
    kinds = {(info["policy"], info["condition"], info.get("robot_mesh", "full"), info.get("instructions", "canonical"),
              info.get("object_set")) for info in served.values()}
    if len(kinds) > 1:
        raise ValueError("the servers serve different things: " + "; ".join(
            f"{url}: {info['policy']} on {info['condition']}, object set {info.get('object_set')}"
            for url, info in served.items()))
    policy, key, robot_mesh, instructions, object_set = kinds.pop()
    condition = Condition.parse(key)
    if cfg.condition not in (Condition(), condition):
        raise ValueError(f"--server {cfg.server[0]} serves {condition} but the command asks for {cfg.condition}; "
                         "drop the condition flags (the servers' condition is recorded) or start matching servers")
    # The local server's options, given with --server: what the servers serve is recorded, so a flag that says
    # otherwise is refused rather than ignored (only one left at its default cannot be told from one not given).
    for name, served_value in (("policy", policy), ("robot_mesh", robot_mesh), ("instructions", instructions)):
        given = getattr(cfg, name)
        if given not in (RecordConfig.__dataclass_fields__[name].default, served_value):
            raise ValueError(f"--server {cfg.server[0]} serves {name.replace('_', '-')} {served_value!r} but the "
                             f"command asks for {given!r}; drop --{name.replace('_', '-')} (the servers' is recorded) "
                             "or start matching servers")
    return Recording(policy, condition, cfg.first_seed, cfg.video, robot_mesh, instructions, cfg.vcodec), object_set


async def _welcome(url: str, token: str | None) -> dict:
    client = EpisodeClient(url, token)
    try:
        return (await client.connect())["server"]
    finally:
        await client.close()


def run(cfg: RecordConfig) -> int:
    setup_logging(f"writer {os.getpid()}" if cfg.ledger else "record")
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its whole configuration per video otherwise
    try:
        recording, object_set = recording_of(cfg)
    except ServerError as e:
        raise ValueError(f"cannot reach the server: {e}") from None
    if cfg.ledger:
        from vla_ladder.recording.writers import write_blocks
        return write_blocks(cfg, recording)
    store = DatasetStore(cfg.out, recording, commit_every=cfg.commit_every, commit_seconds=cfg.commit_seconds,
                         encoder_threads=cfg.encoder_threads or None)
    if leftovers := store.done_blocks():
        log.info("merging the shards a stopped recording left (%d blocks of seeds)", len(leftovers))
        store.settle(cfg.episodes)
    if store.saved >= cfg.episodes:
        log.info("%s already holds %d episodes (asked for %d); nothing to do", cfg.out, store.saved, cfg.episodes)
        store.close()
        return 0
    # Before, the first demo of other objects failed the batch it was in, and writers' shards of them never merged.
    if object_set and store.object_set not in (None, object_set):
        store.close(commit=False)
        raise ValueError(f"{cfg.out} holds episodes of object set {store.object_set!r} but the "
                         f"{'servers simulate' if cfg.server else 'local servers would simulate'} {object_set!r}; "
                         "record with the same objects (ycb: ManiSkill's YCB models on disk, $MS_ASSET_DIR; "
                         "$VLA_LADDER_OBJECT_SET picks one) or into a new --out")
    if store.saved:
        log.info("resuming %s at %d/%d episodes, next seed %d", cfg.out, store.saved, cfg.episodes,
                 store.next_seed)
    local: list[LocalServer] = []
    source = None
    # (put back at the end, sticky_sigint's changes: a study's unit calls run() in-process)
    sigint, unraisablehook = signal.getsignal(signal.SIGINT), sys.unraisablehook

    def close_giving_back() -> None:
        if source is not None:
            source.stop()  # first: it would reserve seeds past the ones given back
        store.close(give_back=True)

    try:
        if cfg.server:
            urls = list(cfg.server)
        else:
            n = max(auto_workers(cfg.workers), cfg.writers)
            local = [LocalServer(recording, cfg.num_envs, threads=1 if n > 1 else 0, rebuild=cfg.rebuild_scenes)
                     for _ in range(n)]
            urls = [s.wait_ready() for s in local]  # they start side by side
        writers = auto_writers(len(urls), cfg.writers)
        if writers > 1 or store.done_blocks():  # (shards after a gap: writers play the gap)
            from vla_ladder.recording.writers import write_shards
            return write_shards(cfg, store, urls, writers)
        ctrl_c = sticky_sigint()
        source = EpisodeSource(urls, store.reserve_seeds, cfg.episodes - store.saved,
                               check_server=lambda url, info: check_server(recording, url, info),
                               token=cfg.token).start()
        progress = Progress(cfg.episodes, store.saved)
        while store.saved + store.pending < cfg.episodes:
            if ctrl_c.is_set():  # (a Ctrl-C whose KeyboardInterrupt was lost: sticky_sigint)
                raise KeyboardInterrupt
            try:
                episode = source.get(timeout=0.5)  # in seed order, so the seeds after the last one used are all unused
            except queue.Empty:
                continue
            store.count(episode.success, episode.seed)
            if episode.success and episode.has_frames:
                store.add(episode)
            progress.update(episode, store)
            if not store.saved and not progress.successes and progress.attempted == cfg.give_up_after:
                log.error("%s succeeded in none of the first %d episodes of %s: nothing to record; check --policy "
                          "and the condition (--give-up-after 0 never gives up)", recording.policy,
                          progress.attempted, recording.condition.key)
                close_giving_back()
                return 1
        close_giving_back()
        progress.report(store, final=True)
        report_targets(cfg.out)
        return 0
    except KeyboardInterrupt:
        # A second Ctrl-C (or the recorder passing its own on to its writers) must not cut the commit short.
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            log.info("interrupted: committing the %d pending episodes", store.pending)
            close_giving_back()
        finally:
            signal.signal(signal.SIGINT, previous)
        return 130
    except ServerError as e:
        log.error("%s", e)
        log.info("committing the %d episodes received complete%s", store.pending,
                 # (a server that refused us, e.g. a message limit, refuses a rerun too)
                 "; rerun the same command to continue" if store.next_seed < SEED_LIMIT and not e.permanent else "")
        close_giving_back()
        return 1
    except BaseException:
        store.close(commit=False)
        raise
    finally:
        if source is not None:
            source.stop()
        for server in local:
            server.stop()
        if signal.getsignal(signal.SIGINT) is not sigint:
            signal.signal(signal.SIGINT, sigint)
        sys.unraisablehook = unraisablehook


def sticky_sigint() -> threading.Event:
    """Make SIGINT (Ctrl-C) raise KeyboardInterrupt, as Python's own handler does, and remember it in the returned
    event, which the caller's loop checks at each turn (`if ctrl_c.is_set(): raise KeyboardInterrupt`). A
    KeyboardInterrupt raised while the garbage collector runs a weakref's callback is printed as "Exception ignored"
    and lost: a writer went on waiting 300 s for episodes from the servers the same Ctrl-C had stopped (seen in CI,
    test_record_with_two_writers_stopped_by_ctrl_c_then_rerun); the single writer's loop (run) records on, or waits
    so. Only where Ctrl-C raises KeyboardInterrupt now (Python's handler, in the main thread): a process started with
    SIGINT ignored (`cmd &` in a script) keeps it so. The lost KeyboardInterrupt, remembered, is not printed either
    (sys.unraisablehook): its "Exception ignored" traceback came with the Ctrl-C that stopped a writer."""
    ctrl_c = threading.Event()
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return ctrl_c

    def handler(signum, frame):
        ctrl_c.set()
        raise KeyboardInterrupt

    def unraisable(info, previous=sys.unraisablehook):
        if not (ctrl_c.is_set() and issubclass(info.exc_type, KeyboardInterrupt)):
            previous(info)

    signal.signal(signal.SIGINT, handler)
    sys.unraisablehook = unraisable
    return ctrl_c


def report_targets(root: Path) -> None:
    """Log the episodes per instructed object; warn when an object is never instructed: only the expert's
    successes are kept, so an object it cannot grasp drops out of the dataset, and so does its instruction."""
    counts = target_counts(read_provenance(root))
    log.info("episodes by target: %s", ", ".join(f"{name} {n}" for name, n in counts.items()))
    missing = missing_targets(counts)
    if missing:
        log.warning("no episode instructs %s among %d: the expert never succeeded with %s (only successes are "
                    "kept), so a policy trained on %s never hears those instructions; check the expert's success "
                    "by object (`vla-ladder eval --policy EXPERT`: per_object in its summary.json) or record with an "
                    "expert that grasps them",
                    ", ".join(missing), sum(counts.values()), "it" if len(missing) == 1 else "them", root)


def check_server(recording: Recording, url: str, info: dict) -> None:
    """A server must simulate exactly the condition and expert this dataset records."""
    want = {"policy": recording.policy, "condition": recording.condition.key, "robot_mesh": recording.robot_mesh,
            "instructions": recording.instructions}
    wrong = [f"{k}={info.get(k)!r} (recording: {v!r})" for k, v in want.items() if info.get(k) != v]
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
        eta = eta_text(left / rate) if rate > 0 else "?"
        log.info("%s %d/%d saved (+%d pending) | attempted %d, expert success %.0f%% | %.1f frames/s simulated, "
                 "%.3f demos/s saved | ETA %s", "done:" if final else "progress:", store.saved, self.target,
                 store.pending, self.attempted, 100 * self.successes / max(self.attempted, 1),
                 self.frames / elapsed, rate, eta)


def eta_text(seconds: float) -> str:
    """HH:MM:SS, with the days in front from one day on: "%H:%M:%S" of gmtime wraps at 24 h, and a recording toward
    100k demos on a few cores runs for days (its ETA read 07:33:20 where 2 days 07:33:20 were left)."""
    days, rest = divmod(int(seconds), 86400)
    return (f"{days}d " if days else "") + time.strftime("%H:%M:%S", time.gmtime(rest))


class LocalServer:
    """`vla-ladder serve` as a child process on 127.0.0.1 with a free port, tied to this process: it exits
    when our end of its stdin closes, so even a kill -9 of the recorder does not leave it behind."""

    def __init__(self, recording: Recording, num_envs: int = 1, threads: int = 0, rebuild: bool = True):
        c = recording.condition
        cmd = [sys.executable, "-m", "vla_ladder.cli", "serve", "--policy", recording.policy, "--regime", c.regime,
               "--split", c.split, "--num-objects", str(c.num_objects), "--num-envs", str(num_envs),
               "--robot-mesh", recording.robot_mesh, "--instructions", recording.instructions,
               "--host", "127.0.0.1", "--port", "0", "--exit-on-stdin-close",
               "--rebuild-scenes" if rebuild else "--no-rebuild-scenes"]
        env = dict(os.environ)
        if threads:  # several servers on one machine: one renderer thread each instead of all fighting for all
            env.update(LP_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads))
        log.info("starting a local server: %s", " ".join(cmd[2:]))
        # A session of its own: a Ctrl-C at the terminal reaches the recorder alone, which commits, then closes our
        # end of stdin. In the recorder's process group the servers died first, and the recorder logged their lost
        # connections, or (run with SIGINT ignored, as `cmd &` in a script does) lost its servers and stopped.
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
                                     start_new_session=True)
        self.url: str | None = None

    def wait_ready(self) -> str:
        """The server's URL once it listens; from then on its output is forwarded to our stderr."""
        self.url = self._listening()
        threading.Thread(target=self._forward, daemon=True).start()
        return self.url

    def _listening(self) -> str:
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
