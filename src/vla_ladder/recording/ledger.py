"""The ledger of a recording made by several writers (`record --writers K`): which blocks of seeds the writers
took, how far each block is played and how many demos it kept, in one JSON file under a file lock.

An episode is determined by its seed, so "the successful episodes of the first N successful seeds from
--first-seed, in seed order" is one dataset whoever plays and writes it; one writer records exactly that. Several
writers each play blocks of consecutive seeds into a shard of their own, and before keeping a success they ask the
ledger whether its seed is among the first N successes (`verdict`): certainly (keep it), certainly not (stop), or
not yet known while an earlier block is still being played (wait). Every kept demo is then one of the dataset's,
no block keeps one too many, and the shards, joined in the order of their first seeds, are the dataset one writer
records (tests/test_recording_shards.py), for any number of writers.

The ledger is rebuilt by the recorder at the start of every run from what is on disk (the dataset and the shards'
committed states, `Block`s), so what a killed run left is used, and the seeds it had not played are played again.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator

from vla_ladder import files
from vla_ladder.checks import SEED_LIMIT

KEEP, STOP, WAIT = "keep", "stop", "wait"
# Blocks are sized so that the writers' blocks together should hold the demos still missing, at the success rate
# seen so far, at most this many seeds: each block is a shard, one more source for the merge at the end (0.32-0.37 s
# a shard on 2 cores, benchmarks/results/merge_speed_cpu.json).
MAX_BLOCK = 1000


@dataclass
class Block:
    """Seeds [start, end) taken by one writer: those below `played_to` were played, and `saved` of them kept."""

    start: int
    end: int
    played_to: int
    saved: int = 0
    attempted: int = 0
    failed: int = 0
    done: bool = False
    """its writer committed its shard and will play no more of it"""


class Ledger:
    """One recording's ledger file; every method reads it (and writes it) under its lock, so writer processes
    sharing it see each other's progress."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.run = self._read()["run"]  # a writer left over from a killed run reports to its own run only

    @classmethod
    def begin(cls, path: str | Path, config: dict, target: int, writers: int, base_seed: int, base_saved: int,
              blocks: list[Block]) -> "Ledger":
        """A new run's ledger: the dataset holds `base_saved` demos of the seeds below `base_seed`, and `blocks`
        (shards on disk, all done) hold more above it; the seeds between them are played again."""
        blocks = sorted(blocks, key=lambda b: b.start)
        next_seed = max([base_seed] + [b.end for b in blocks])
        with _locked(Path(path)):  # (a writer of a killed run reporting late would write its run's ledger back)
            files.write_json(path, {"run": uuid.uuid4().hex, "config": config, "target": target, "writers": writers,
                                    "base": [base_seed, base_saved], "next_seed": next_seed,
                                    "blocks": [asdict(b) for b in blocks]})
        return cls(path)

    def _locked(self):
        return _locked(self.path)

    def _read(self) -> dict:
        return json.loads(self.path.read_text())

    def _state(self) -> tuple[dict, list[Block], int]:
        """The ledger (read under the caller's lock), its blocks, and the demos kept in all, the dataset's and
        theirs."""
        led = self._read()
        blocks = [Block(**b) for b in led["blocks"]]
        return led, blocks, led["base"][1] + sum(b.saved for b in blocks)

    def blocks(self) -> list[Block]:
        with self._locked():
            return self._state()[1]

    def tally(self) -> tuple[int, int, int]:
        """(demos kept in all, seeds played in its blocks, blocks), blocks of earlier runs (shards on disk) included."""
        with self._locked():
            _, blocks, saved = self._state()
        return saved, sum(b.played_to - b.start for b in blocks), len(blocks)

    def take(self) -> tuple[int, int] | None:
        """A block of seeds for a writer, the lowest unplayed first; None while the seeds in play are expected to
        hold the demos still missing (at the success rate so far, as one writer asks for seeds), and once `done`."""
        with self._locked():
            led, blocks, saved = self._state()
            if led["run"] != self.run:
                return None
            played = sum(b.played_to - b.start for b in blocks)
            rate = (sum(b.saved for b in blocks) + 1) / (played + 1)  # (with one success and one seed assumed)
            in_play = sum(b.end - b.played_to for b in blocks if not b.done)
            short = led["target"] - saved - rate * in_play  # demos the seeds in play are not expected to hold
            if short <= 0:
                return None
            # a writer's share of what is missing, and near the end no more than the shortfall
            size = max(1, min(MAX_BLOCK, math.ceil((led["target"] - saved) / rate / led["writers"]),
                              math.ceil(short / rate)))
            start, end = self._first_unplayed(led["base"][0], blocks, led["next_seed"], size)
            if start >= SEED_LIMIT:
                return None
            led["next_seed"] = max(led["next_seed"], end)
            led["blocks"] = [asdict(b) for b in sorted([*blocks, Block(start, end, start)], key=lambda b: b.start)]
            files.write_json(self.path, led)
            return start, end

    @staticmethod
    def _first_unplayed(base_seed: int, blocks: list[Block], next_seed: int, size: int) -> tuple[int, int]:
        """The lowest seeds no block holds: a gap between blocks (seeds a killed run did not play), else new ones."""
        seed = base_seed
        for b in sorted(blocks, key=lambda b: b.start):
            if b.start > seed:
                return seed, min(b.start, seed + size)
            seed = max(seed, b.end)
        start = max(seed, next_seed)
        return start, min(start + size, SEED_LIMIT)

    def done(self) -> bool:
        """Whether the demos kept reached the target (or the seeds below 2**32 ran out): no block will be handed
        out again in this run."""
        with self._locked():
            led, blocks, saved = self._state()
        return (led["run"] != self.run or saved >= led["target"]
                or self._first_unplayed(led["base"][0], blocks, led["next_seed"], 1)[0] >= SEED_LIMIT)

    def report(self, start: int, played_to: int, saved: int, attempted: int, failed: int, done: bool = False) -> None:
        """A writer's progress in its block `start`: played below `played_to`, `saved` kept."""
        with self._locked():
            led = self._read()
            if led["run"] != self.run:
                return
            for b in led["blocks"]:
                if b["start"] == start and not b["done"]:
                    b.update(played_to=played_to, saved=saved, attempted=attempted, failed=failed, done=done)
            files.write_json(self.path, led)

    def verdict(self, seed: int, success: bool) -> str:
        """KEEP when seed's episode (a success, or a failure to count) is among those of the first `target`
        successes, STOP when they all lie below it, WAIT while earlier blocks still in play may decide either.
        Asked in seed order by the writer of seed's block, which has reported everything below it."""
        with self._locked():
            led = self._read()
        base_seed, base_saved = led["base"]
        below = [Block(**b) for b in led["blocks"] if b["start"] < seed]
        kept = base_saved + sum(b.saved for b in below)  # successes below seed, certainly
        if kept >= led["target"]:
            return STOP
        if not success:
            return KEEP
        # (seed's own block is played up to seed: its writer asks in seed order)
        unplayed = (seed - base_seed) - sum((seed if seed < b.end else min(b.played_to, seed)) - b.start
                                            for b in below)
        return KEEP if kept + unplayed < led["target"] else WAIT


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """The ledger file's lock, held for one read or read-modify-write."""
    with open(path.with_suffix(".lock"), "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield
