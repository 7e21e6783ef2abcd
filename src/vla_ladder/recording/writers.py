"""Parallel dataset writers (`record --writers K`): the recorder starts K writer processes, each drawing from its
share of the servers, and merges their shards into the dataset in seed order at the end (`write_shards`); each
writer takes blocks of seeds from the ledger and keeps a block's demos that are the dataset's in a shard of its own
(`write_blocks`, `record --ledger`). The dataset is the one a single writer records (ledger.py)."""

from __future__ import annotations

import logging
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from functools import partial

from vla_ladder.checks import SEED_LIMIT
from vla_ladder.machine import signal_on_parent_death
from vla_ladder.recording.client import EpisodeSource, ServerError
from vla_ladder.recording.ledger import STOP, WAIT, Ledger
from vla_ladder.recording.record import RecordConfig, check_server, eta_text, report_targets, sticky_sigint
from vla_ladder.recording.server import TOKEN_ENV
from vla_ladder.recording.store import DatasetStore
from vla_ladder.recordings import Recording

log = logging.getLogger(__name__)
PROGRESS_EVERY_S = 10.0


def write_shards(cfg: RecordConfig, store: DatasetStore, urls: list[str], writers: int) -> int:
    """`writers` writer processes (`record --ledger`), each drawing from its share of `urls`, then one merge of
    their shards into the dataset. Interrupted, the writers commit what they hold and what continues the dataset is
    merged; killed, the shards wait for the next run. A writer that fails stops the others (they could wait for
    seeds it held): the command says to rerun."""
    before = store.saved
    ledger = store.begin_ledger(cfg.episodes, writers)
    # What earlier runs left: the dataset and the shards after a gap, which the ledger counts as kept. The progress
    # lines' rate is this run's alone (it counted those shards' demos as this run's: a resumed run's ETA started
    # short).
    at_start = ledger.tally()
    env = dict(os.environ, **({TOKEN_ENV: cfg.token} if cfg.token else {}))  # a token stays off command lines
    started = time.monotonic()
    procs = []
    for i in range(writers):
        cmd = [sys.executable, "-m", "vla_ladder.cli", "record", "--out", str(store.shards_dir),
               "--episodes", str(cfg.episodes), "--first-seed", str(cfg.first_seed),
               "--commit-every", str(cfg.commit_every), "--commit-seconds", str(cfg.commit_seconds),
               "--ledger", str(ledger.path), "--writers", "1", "--encoder-threads", str(cfg.encoder_threads),
               "--vcodec", cfg.vcodec, *([] if cfg.video else ["--no-video"]),
               "--server", *urls[i::writers]]
        # A writer gets SIGINT (commit, exit) when the recorder dies, even by kill -9.
        procs.append(subprocess.Popen(cmd, env=env, preexec_fn=partial(signal_on_parent_death, signal.SIGINT)))
    log.info("%d writers record %d episodes into shards of %s", writers, cfg.episodes - before, store.shards_dir)
    codes: list[int | None] = [None] * writers
    interrupted, ctrl_c = False, sticky_sigint()
    try:
        # The merge below runs LeRobot's aggregation, whose import (6 s on 2 cores) came after the last writer had
        # finished: the merged dataset followed it by 8 s on 2 cores and 14 s on the H200 machine, of which the merge
        # itself took 1 and 3.6 s. Imported here, it overlaps the writers.
        import lerobot.datasets.aggregate  # noqa: F401
        last_report, stopping, gave_up = time.monotonic(), False, False
        while any(c is None for c in codes):
            if ctrl_c.is_set():  # (a Ctrl-C whose KeyboardInterrupt was lost: sticky_sigint)
                raise KeyboardInterrupt
            codes = [p.poll() for p in procs]
            if not stopping and any(c not in (None, 0) for c in codes):
                log.error("a writer stopped (exit codes %s): stopping the others", [c for c in codes if c is not None])
                _interrupt(procs)
                stopping = True
            if not stopping and cfg.give_up_after and not before:
                kept, played, _ = ledger.tally()
                if not kept and played >= cfg.give_up_after:
                    log.error("%s succeeded in none of the first %d episodes of %s: nothing to record; check --policy "
                              "and the condition (--give-up-after 0 never gives up)", store.config.policy, played,
                              store.config.condition.key)
                    _interrupt(procs)
                    stopping = gave_up = True
            if time.monotonic() - last_report >= PROGRESS_EVERY_S:
                last_report = time.monotonic()
                log.info("%s", progress_line(ledger.tally(), at_start, cfg.episodes, time.monotonic() - started))
            time.sleep(0.2)
    except KeyboardInterrupt:  # the writers commit what they hold, and what continues the dataset is merged below
        _interrupt(procs)
        codes, interrupted = [p.wait() for p in procs], True
    elapsed = time.monotonic() - started
    kept = ledger.tally()[0] - at_start[0]  # (the merge below may take earlier runs' shards in too)
    store.settle(cfg.episodes)
    log.info("%s %d/%d saved in %s | %.3f demos/s saved by %d writers",
             "done:" if store.saved >= cfg.episodes else "stopped:", store.saved, cfg.episodes, cfg.out,
             kept / elapsed, writers)
    store.close()
    if store.saved:
        report_targets(cfg.out)
    if gave_up:
        return 1
    if store.saved >= cfg.episodes:
        return 0
    if not interrupted and all(c == 0 for c in codes):  # (the writers end short only when the seeds ran out)
        log.error("no seeds left: the recording has used every seed from --first-seed %d to 2**32 - 1; record the "
                  "missing demos into another --out with a lower --first-seed", cfg.first_seed)
        return 1
    log.info("the recording stopped early (%s); rerun the same command to continue",
             "interrupted" if interrupted else f"writers' exit codes {codes}")
    return 130 if interrupted or 130 in codes else 1


def _interrupt(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)


def progress_line(tally: tuple[int, int, int], at_start: tuple[int, int, int], target: int, elapsed: float) -> str:
    """The recorder's progress line from the ledger's `tally` now and at the run's start: demos kept in all, and
    this run's seeds played, blocks taken and rate (what earlier runs left is not this run's work)."""
    (kept, played, blocks), (kept0, played0, blocks0) = tally, at_start
    rate = (kept - kept0) / max(elapsed, 1e-9)
    eta = eta_text((target - kept) / rate) if rate > 0 else "?"
    return (f"progress: {kept}/{target} saved | {played - played0} seeds played in {blocks - blocks0} blocks | "
            f"{rate:.3f} demos/s saved | ETA {eta}")


class _BlockSeeds:
    """A writer's seeds: consecutive ones from the blocks it takes from the ledger, one block after another
    (`reserve`, called from the episode source's thread)."""

    def __init__(self, ledger: Ledger):
        self.ledger = ledger
        self.taken: list[tuple[int, int]] = []
        self.issued = 0
        self.spent = threading.Event()  # the ledger will hand out no block again
        self.lock = threading.Lock()  # (the writer reads taken and issued while the source's thread reserves)
        self._next = 0

    def reserve(self, n: int) -> list[int]:
        with self.lock:
            return self._reserve(n)

    def handed_out(self) -> tuple[int, list[tuple[int, int]]]:
        """(seeds handed out, the blocks whose every seed was), read together."""
        with self.lock:
            whole = self.taken if self.taken and self._next >= self.taken[-1][1] else self.taken[:-1]
            return self.issued, list(whole)

    def _reserve(self, n: int) -> list[int]:
        seeds: list[int] = []
        while len(seeds) < n and not self.spent.is_set():
            if not self.taken or self._next >= self.taken[-1][1]:
                block = self.ledger.take()
                if block is None:  # asked again when the source next wants seeds (every second while it has none)
                    if self.ledger.done():
                        self.spent.set()
                    break
                self.taken.append(block)
                self._next = block[0]
            k = min(n - len(seeds), self.taken[-1][1] - self._next)
            seeds.extend(range(self._next, self._next + k))
            self._next += k
        self.issued += len(seeds)
        return seeds

    def block_of(self, seed: int) -> tuple[int, int]:
        return next(b for b in reversed(self.taken) if b[0] <= seed < b[1])


def write_blocks(cfg: RecordConfig, recording: Recording) -> int:
    """A writer of `record --writers K` (`record --ledger`): take blocks of seeds from the ledger, play them on
    --server, keep each block's demos that are the dataset's (`Ledger.verdict`) in a shard under --out (the
    recorder's shards directory), and stop when the ledger has no block left or a seed lies beyond the dataset."""
    ledger = Ledger(cfg.ledger)
    seeds = _BlockSeeds(ledger)
    source = EpisodeSource(list(cfg.server), seeds.reserve, SEED_LIMIT,
                           check_server=lambda url, info: check_server(recording, url, info), token=cfg.token).start()
    store: DatasetStore | None = None
    block: tuple[int, int] | None = None
    closed: set[tuple[int, int]] = set()  # blocks reported done to the ledger
    got, ctrl_c = 0, sticky_sigint()

    def close_block(played_to: int | None = None, stopped: bool = False) -> None:
        """Commit the block's shard and tell the ledger it is done (played to `played_to`: by default the seed after
        the last one written or counted; its end once a later block's episode came, all of its seeds resolved);
        `stopped`: the ledger said the dataset's demos all lie below `played_to`."""
        nonlocal store
        if store is None:
            return
        closed.add(block)
        store.close(give_back=True)
        c = store.counters
        played_to = store.played_to if played_to is None else played_to
        ledger.report(block[0], played_to, c["saved"], c["attempted"], c["failed"], done=True)
        if played_to > block[0]:
            log.info("seeds %d-%d: kept %d of %d played", block[0], played_to - 1, c["saved"], c["attempted"])
        elif stopped:
            log.info("seeds from %d on: not needed (the dataset's demos all lie below)", block[0])
        else:  # (interrupted before its first episode came: a rerun plays them)
            log.info("seeds from %d on: none played", block[0])
        store = None

    try:
        while True:
            if ctrl_c.is_set():  # (a Ctrl-C whose KeyboardInterrupt was lost: sticky_sigint)
                raise KeyboardInterrupt
            try:
                episode = source.get(timeout=0.5)
            except queue.Empty:
                if not seeds.spent.is_set() and ledger.done():  # (sooner than the source's next ask for seeds)
                    seeds.spent.set()
                issued, whole = seeds.handed_out()
                if got + source.lost < issued:
                    continue
                if seeds.spent.is_set():
                    close_block(block[1] if block else None)
                    return 0
                # Every seed handed out is resolved, the last ones given up (the servers failed them twice): their
                # blocks are played to their ends, or the ledger would go on counting on their demos, hand out no
                # other block, and every writer would wait for ever.
                for b in whole:
                    if b == block:
                        close_block(b[1])
                        block = None
                    elif b not in closed:  # (not one of its seeds was delivered: no shard)
                        ledger.report(b[0], b[1], 0, 0, 0, done=True)
                        closed.add(b)
                continue
            got += 1
            if block is None or not block[0] <= episode.seed < block[1]:
                close_block(block[1] if block else None)
                block = seeds.block_of(episode.seed)
                store = DatasetStore(cfg.out / f"{block[0]:010d}", recording, commit_every=cfg.commit_every,
                                     commit_seconds=cfg.commit_seconds, seeds_from=block[0],
                                     encoder_threads=cfg.encoder_threads or None)
            verdict = ledger.verdict(episode.seed, episode.success)
            if verdict == WAIT:  # an earlier block still in play decides whether this demo is the dataset's
                c = store.counters  # (seeds given up below this one count as played: the others may wait on us)
                ledger.report(block[0], episode.seed, store.saved + store.pending, c["attempted"], c["failed"])
                while (verdict := ledger.verdict(episode.seed, episode.success)) == WAIT:
                    if ctrl_c.is_set():  # (the earlier block's writer, stopped by the same Ctrl-C, never decides it)
                        raise KeyboardInterrupt
                    time.sleep(0.2)
            if verdict == STOP:
                close_block(episode.seed, stopped=True)
                return 0
            store.count(episode.success, episode.seed)
            if episode.success and episode.has_frames:
                store.add(episode)
            c = store.counters
            ledger.report(block[0], store.played_to, store.saved + store.pending, c["attempted"], c["failed"])
    except KeyboardInterrupt:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not cut the commit short
        close_block()
        return 130
    except ServerError as e:
        log.error("%s", e)
        close_block()
        return 1
    except BaseException:
        if store is not None:
            store.close(commit=False)
        raise
    finally:
        source.stop()
