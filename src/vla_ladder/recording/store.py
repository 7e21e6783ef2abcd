"""A LeRobotDataset v3 that only ever holds whole, committed episodes, whatever kills the writer.

LeRobot writes a dataset through open Parquet writers, an episode-metadata buffer and in-place rewrites of
info.json/stats.json: a process killed half-way leaves files that do not load. So episodes go into a
*staging* copy of the dataset and reach DATASET_DIR only by commit:

1. staging = hard links of DATASET_DIR's immutable files (data/, videos/, meta/episodes/ and our own
   sidecar shards; LeRobot's resume never rewrites those, it starts new files) plus copies of the small
   files LeRobot rewrites (meta/info.json, stats.json, tasks.parquet) -- no bulk copying;
2. LeRobotDataset.resume(staging) (or .create for the first batch), add_frame/save_episode per episode;
3. commit: finalize, write the batch's provenance shard and our recording state, fsync, then swap
   staging and DATASET_DIR with one atomic renameat2(RENAME_EXCHANGE) and delete the old version.

A reader therefore always sees either the previous or the next commit. Staging leftovers of a killed
writer are deleted when the next writer starts. Seeds are reserved (and persisted) before any server sees
them, so a seed is never written twice; the recording state keeps the seed after the last one written or counted
failed (`played_to`), where a resume plays on, so a recording resumed after a kill -9 is the one made in one go.

Parallel writers (`record --writers N`) each record blocks of consecutive seeds, each block into a *shard*, a
DatasetStore of its own under the work directory, and keep only demos that the ledger (ledger.py) says are among the
dataset's; `settle` then joins the shards that continue the dataset, in seed order, to DATASET_DIR with LeRobot's
aggregate_datasets and the same atomic swap.

The work directory next to the dataset, `.<name>.recording/`, holds the lock, the staging copy, the seed
reservation, and the ledger and shards of parallel writers; it may be deleted whenever no recorder runs and no shard
waits to be merged (a rerun of the same `record` command merges them).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import json
import logging
import os
import shutil
import signal
import threading
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

import pandas as pd

from vla_ladder import files
from vla_ladder.checks import SEED_LIMIT, ascii_digits
from vla_ladder.conditions import Condition
from vla_ladder.recording.ledger import Block, Ledger
from vla_ladder.recordings import (FORMAT_VERSION, PROVENANCE_DIR, RECORDING_FILE, Recording, played_to,
                                   read_provenance, read_recording_state)
from vla_ladder.contract import (ACTION_KEY, CAMERAS, CONTROL_HZ, EPISODE_STEPS, METRICS, STATE_KEY,
                                  contract_changes, dataset_features, fingerprint)

log = logging.getLogger(__name__)

# Directories whose files LeRobot never modifies after writing them (resume opens new chunk files).
IMMUTABLE_DIRS = ("data", "videos", "meta/episodes", PROVENANCE_DIR)
# LeRobot's resume reads every meta/episodes file through `datasets` (each commit adds one), about 18 ms a file on 2
# cores: 1.2 s to open a batch of a 2000-demo recording, a minute at 100k demos (benchmarks/commit_scaling.py). A
# batch's staging copy joins them into one file when there are more than this many (_join_meta_files).
MAX_META_FILES = 8


class DatasetStore:
    """Owns DATASET_DIR while recording: reserve seeds, add successful episodes, commit atomically."""

    def __init__(self, root: str | os.PathLike, config: Recording, commit_every: int = 50,
                 commit_seconds: float = 600.0, repo_id: str | None = None,
                 seeds_from: int = 0, encoder_threads: int | None = None):
        if commit_every < 1:
            raise ValueError(f"commit_every must be >= 1, got {commit_every}")
        self.root = Path(root).resolve()
        self.config = config
        self.commit_every, self.commit_seconds = commit_every, commit_seconds
        self.encoder_threads = encoder_threads  # per camera encoder (SVT-AV1's lp); None: the codec's choice
        self.repo_id = repo_id or f"vla-ladder/{self.root.name}"
        self.work = self.root.parent / files.sibling_name(self.root, ".recording")
        self.staging = self.work / "staging"
        made = not self.work.exists()
        self.work.mkdir(parents=True, exist_ok=True)
        self._lock_file = open(self.work / "lock", "a+")
        try:
            fcntl.flock(self._lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._lock_file.close()
            raise ValueError(f"another recorder is writing {self.root} (lock {self.work / 'lock'} is held)")
        # A killed writer may have left a half-written staging copy or, killed right after a commit's
        # swap, the previous version there: neither is ever needed again.
        shutil.rmtree(self.staging, ignore_errors=True)
        shutil.rmtree(self.work / "hf-cache", ignore_errors=True)
        self._ds = None
        self._rows: list[dict] = []
        self._writing = False  # inside add(): staging holds a half-written episode
        self._batch_started = time.monotonic()
        try:
            state = self._load_committed()
        except (ValueError, OSError):  # another dataset, or none (a file: NotADirectoryError): leave no work directory
            self._lock_file.close()
            if made:
                shutil.rmtree(self.work, ignore_errors=True)
            raise
        self.saved = int(state["counters"]["saved"]) if state else 0
        self.counters = dict(state["counters"]) if state else {"saved": 0, "attempted": 0, "failed": 0,
                                                                "commits": 0}
        self._published = dict(self.counters)  # the counters DATASET_DIR's recording state holds
        self.object_set: str | None = state.get("object_set") if state else None
        # The frames stats.json's quantiles are over (None: not known, computed again at the next commit), and the
        # provenance columns the card reads, kept from commit to commit: both read the whole dataset otherwise.
        self._quantile_frames: int | None = state.get("quantile_frames") if state else None
        self._card_rows: pd.DataFrame | None = None
        # A resume plays again from the seed after the last one committed (written or counted failed): those a kill
        # left in flight were never written, and played again they make the dataset the one recorded in one go.
        floor = max(config.first_seed, seeds_from, played_to(state) if state else 0)
        self.seeds = SeedBook(self.work / "seeds.json", config, floor)
        self._unused_from = floor  # after the last seed written or counted failed: none from there reached the dataset
        self.pending = 0
        # Shards of a merge that was killed after its swap are in the dataset already. (Removing them removes the
        # work directories of writers that never committed: a killed run's writer may still be making its first.)
        if merged := (state or {}).get("merged_shards", []):
            self._wait_for_writers()
        for name in merged:
            _remove_shard(self.shards_dir / name)

    # ------------------------------------------------------------------ state on disk
    def _not_the_same(self, state: dict) -> tuple[str, str] | None:
        """Why the recording whose state this is cannot go on as this one (a resume) or join it (a shard), as
        ("arguments" or "contract", the reason); None when it can."""
        if diff := self.config.differences(Recording.from_dict(state["config"], state["format"])):
            return "arguments", "was recorded with " + ", ".join(diff)
        if changed := contract_changes(state.get("contract")):
            return "contract", f"was recorded under another task contract ({'; '.join(changed)})"
        return None

    def _load_committed(self) -> dict | None:
        if not self.root.exists() or not any(self.root.iterdir()):
            return None
        state = read_recording_state(self.root)
        if state is None or not (self.root / "meta/info.json").exists():
            raise ValueError(f"{self.root} exists and is not a vla-ladder recording; choose a new --out")
        if state.get("format") not in (1, FORMAT_VERSION):
            raise ValueError(f"{self.root} was written by recording format {state.get('format')}; this version "
                             f"reads formats 1 and {FORMAT_VERSION}")
        if found := self._not_the_same(state):
            kind, why = found
            raise ValueError(f"{self.root} {why}; " + ("resume with the same arguments or " if kind == "arguments"
                                                      else "") + "record into a new --out")
        info = json.loads((self.root / "meta/info.json").read_text())
        if info["total_episodes"] != state["counters"]["saved"]:
            raise ValueError(f"{self.root}: info.json has {info['total_episodes']} episodes but the recording "
                             f"state says {state['counters']['saved']}; the dataset was modified outside vla-ladder")
        return state

    @property
    def next_seed(self) -> int:
        return self.seeds.next_seed

    @property
    def played_to(self) -> int:
        """The seed after the last one written or counted failed (where a resume plays on)."""
        return self._unused_from

    def reserve_seeds(self, n: int) -> list[int]:
        """n seeds never handed out before for this dataset; persisted before they are returned."""
        return self.seeds.reserve(n)

    @property
    def shards_dir(self) -> Path:
        """Where parallel writers (`record --writers`) keep their shards, one per block of seeds, until `settle`."""
        return self.work / "shards"

    @property
    def ledger_path(self) -> Path:
        return self.work / "ledger.json"

    def shard(self, start: int) -> Path:
        """The shard of the block of seeds that starts at `start`; shards sort by name as by seed."""
        return self.shards_dir / f"{start:010d}"

    def done_blocks(self) -> list[Block]:
        """The blocks of seeds above the dataset's that parallel writers played and committed, by first seed: the
        ledger's finished blocks, and the committed part of the others (a writer killed mid-block) from their shards.
        Waits for writers a killed recorder left to commit first (they get SIGINT when it dies)."""
        if not self.shards_dir.is_dir():
            return []
        self._wait_for_writers()
        found: dict[int, Block] = {}
        if self.ledger_path.is_file():
            ledger = json.loads(self.ledger_path.read_text())
            if ledger.get("config") == self.config.to_dict():
                for b in map(lambda b: Block(**b), ledger["blocks"]):
                    if b.done and (b.saved == 0 or self.shard(b.start).is_dir()):
                        found[b.start] = Block(b.start, b.played_to, b.played_to, b.saved, b.attempted, b.failed, True)
        for shard in self.shards_dir.iterdir():
            if not ascii_digits(shard.name) or int(shard.name) in found:
                continue
            state = read_recording_state(shard)
            if state is not None:
                c = state["counters"]
                found[int(shard.name)] = Block(int(shard.name), played_to(state), played_to(state), c["saved"],
                                               c["attempted"], c["failed"], True)
        return [b for _, b in sorted(found.items()) if b.start >= self.played_to and b.played_to > b.start]

    def _wait_for_writers(self) -> None:
        """Return once no writer holds a shard's lock (writers of a killed recorder commit what they hold first)."""
        for work in self.shards_dir.glob(".*.recording"):
            wait_for_writer(self.shards_dir / work.name[1:-len(".recording")])

    def begin_ledger(self, target: int, writers: int) -> Ledger:
        """The ledger of a sharded recording of `target` demos by `writers` writers, from what is on disk."""
        return Ledger.begin(self.ledger_path, self.config.to_dict(), target, writers, self.played_to, self.saved,
                            self.done_blocks())

    def settle(self, target: int) -> None:
        """Merge into the dataset, in seed order, the blocks that continue it seed after seed, until it holds
        `target` demos. A block that would overshoot the target (recorded for a larger --episodes) is deleted with the
        ones after it: its first demos are played again. Blocks after a gap wait for a run to play the gap."""
        take, cursor, saved = [], self.played_to, self.saved
        for i, b in enumerate(blocks := self.done_blocks()):
            if b.start != cursor or saved >= target:
                break
            if saved + b.saved > target:
                log.info("dropping %d shards recorded for a larger --episodes: %d demos from seed %d on would "
                         "overshoot %d", len(blocks) - i, b.saved, b.start, target)
                for later in blocks[i:]:
                    _remove_shard(self.shard(later.start))
                break
            take.append(b)
            cursor, saved = b.played_to, saved + b.saved
        if take:
            self.merge(take)

    # ------------------------------------------------------------------ writing
    def count(self, success: bool, seed: int | None = None) -> None:
        """Account for an attempted episode in the recording state; `seed`, its seed, for where a resume plays on. A
        failure counts (and uses its seed) here, a success once add() has written it: Ctrl-C between the two would
        otherwise skip a demo never written, or count an attempt that the resume plays and counts again."""
        if success:
            return
        self.counters["attempted"] += 1
        self.counters["failed"] += 1
        if seed is not None:
            self._unused_from = max(self._unused_from, seed + 1)

    def add(self, episode) -> int:
        """Write one successful episode (a client.Episode) into staging; returns its episode_index."""
        if not episode.success or not episode.has_frames:
            raise ValueError(f"only successful episodes with frames are recorded (seed {episode.seed})")
        object_set = episode.header["object_set"]
        if self.object_set is None:
            self.object_set = object_set
        elif object_set != self.object_set:
            raise ValueError(f"episode {episode.seed} used object set {object_set!r} but {self.root} holds "
                             f"{self.object_set!r}; all servers must use the same assets")
        from lerobot.utils.utils import SuppressProgressBars

        ds = self._dataset()
        task = episode.header["instruction"]
        with _sigint_held():  # Ctrl-C mid-episode would leave LeRobot's files out of step and cost the whole batch
            self._writing = True
            for t in range(episode.num_frames):
                ds.add_frame({**{c.key: episode.images[c.name][t] for c in CAMERAS},
                              STATE_KEY: episode.state[t], ACTION_KEY: episode.action[t], "task": task})
            with SuppressProgressBars():
                ds.save_episode()
            self._writing = False
            index = self.saved + self.pending
            self._rows.append(_provenance_row(index, episode))
            self.pending += 1
            self.counters["attempted"] += 1
            self._unused_from = max(self._unused_from, episode.seed + 1)
        if self.pending >= self.commit_every or time.monotonic() - self._batch_started >= self.commit_seconds:
            self.commit()
        return index

    def _dataset(self):
        if self._ds is not None:
            return self._ds
        from lerobot.configs.video import RGBEncoderConfig
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        from vla_ladder.recording import image_stats
        image_stats.install()  # the cameras' per-frame statistics, ten times cheaper (image_stats.py)
        _quiet_ffmpeg()
        self._batch_started = time.monotonic()
        shutil.rmtree(self.staging, ignore_errors=True)
        # Episodes are whole when they reach the writer, so the encoder queue may take a full episode at
        # once; LeRobot's streaming encoder drops frames when its queue stays full for 0.1 s.
        opts = dict(streaming_encoding=self.config.video, encoder_queue_maxsize=4 * EPISODE_STEPS,
                    image_writer_threads=0 if self.config.video else 2, encoder_threads=self.encoder_threads,
                    rgb_encoder=RGBEncoderConfig(vcodec=self.config.vcodec) if self.config.video else None)
        if self.saved == 0:
            self._ds = LeRobotDataset.create(self.repo_id, fps=CONTROL_HZ, features=dataset_features(self.config.video),
                                             root=self.staging, robot_type="panda", use_videos=self.config.video,
                                             **opts)
        else:
            _link_copy(self.root, self.staging)
            _join_meta_files(self.staging)
            with _private_datasets_cache(self.work / "hf-cache"):
                self._ds = LeRobotDataset.resume(self.repo_id, root=self.staging, **opts)
        return self._ds

    def commit(self) -> None:
        """Make every episode added so far part of DATASET_DIR, atomically."""
        if self.pending == 0:
            published = read_recording_state(self.root) if (self.root / RECORDING_FILE).is_file() else None
            moved = {"next_seed": self.next_seed, "played_to": self.played_to}
            if published and (self.counters != self._published or any(published.get(k) != v for k, v in moved.items())):
                # Failed attempts since the last commit, or seeds given back: only the counters and the next seed
                # change, in our own file, replaced atomically (a recorder that ends on failures would otherwise
                # report too few attempts).
                files.write_json(self.root / RECORDING_FILE, {**published, "counters": self.counters, **moved})
                self._published = dict(self.counters)
                self._card_rows = self._write_card(self.root)  # (it says how many were played and failed)
            return
        t0 = time.perf_counter()
        # Ctrl-C waits for the commit's end: cut short after the swap, the store took the committed episodes for
        # pending ones, and the recorder's closing commit failed on them.
        with _sigint_held():
            self._ds.finalize()
            self._ds = None
            self.counters["commits"] += 1
            self.counters["saved"] = self.saved + self.pending
            rows = pd.DataFrame(self._rows)
            files.write_parquet(self.staging / PROVENANCE_DIR / f"commit-{self.counters['commits']:06d}.parquet",
                                rows)
            self._publish(self._state(), rows)
            self.saved += self.pending
            self.pending = 0
            self._rows = []
        log.info("committed: %d episodes in %s (%.2f s)", self.saved, self.root, time.perf_counter() - t0)

    def merge(self, blocks: list[Block]) -> None:
        """Make the demos of `blocks` (the shards of parallel writers, consecutive blocks of seeds that continue the
        dataset's) part of DATASET_DIR, after its own and in seed order, in one atomic step; the dataset then goes on
        from the last block's end.

        LeRobot's aggregate_datasets writes the union into staging (a copy of DATASET_DIR's files, which is
        what a merge costs); each shard's provenance follows its episodes under their new indices. The shard
        names are recorded in the new state, so shards that a kill leaves behind after the swap are deleted,
        never merged twice; a kill before the swap leaves DATASET_DIR as it was and the shards to merge again.
        """
        if self.pending:
            self.commit()
        counters, unused_from = dict(self.counters), self._unused_from
        try:
            self._merge(blocks)
        except BaseException:  # DATASET_DIR is as it was: so is this store
            self.counters, self._unused_from = counters, unused_from
            self.seeds.start_at(unused_from)
            raise

    def _merge(self, blocks: list[Block]) -> None:
        full = [self.shard(b.start) for b in blocks if b.saved > 0]
        states = {s: read_recording_state(s) for s in full}
        for s in full:
            if found := self._not_the_same(states[s]):
                raise ValueError(f"shard {s} {found[1]}; it cannot join {self.root}")
            if states[s]["object_set"] != (self.object_set or states[s]["object_set"]):
                raise ValueError(f"shard {s} used object set {states[s]['object_set']!r} but {self.root} holds "
                                 f"{self.object_set!r}")
            self.object_set = states[s]["object_set"]
        for b in blocks:  # the blocks' attempts count, kept or not
            self.counters["attempted"] += b.attempted
            self.counters["failed"] += b.failed
        self._unused_from = blocks[-1].played_to
        self.seeds.start_at(self._unused_from)
        if not full:  # failures only: the counters and the next seed change
            self.commit()
            for b in blocks:
                _remove_shard(self.shard(b.start))
            return
        from lerobot.datasets.aggregate import aggregate_datasets
        from lerobot.utils.utils import SuppressProgressBars

        _quiet_ffmpeg()

        t0 = time.perf_counter()
        shutil.rmtree(self.staging, ignore_errors=True)
        sources = ([self.root] if self.saved else []) + full
        with _private_datasets_cache(self.work / "hf-cache"), SuppressProgressBars(), _aggregate_without_bars():
            aggregate_datasets([f"{self.repo_id}-part{i}" for i in range(len(sources))], self.repo_id,
                               roots=sources, aggr_root=self.staging)
        _own_meta_indices(self.staging)
        provenance = self.staging / PROVENANCE_DIR
        provenance.mkdir(parents=True, exist_ok=True)
        if self.saved:
            for path in (self.root / PROVENANCE_DIR).glob("*.parquet"):
                os.link(path, provenance / path.name)
        rows, offset = [], self.saved
        for s in full:
            shard_rows = read_provenance(s)
            shard_rows["episode_index"] += offset
            rows.append(shard_rows)
            offset += int(states[s]["counters"]["saved"])
        total = json.loads((self.staging / "meta/info.json").read_text())["total_episodes"]
        if total != offset:
            raise RuntimeError(f"merging {len(full)} shards into {self.root} gave {total} episodes, expected {offset}")
        self.counters["commits"] += 1
        files.write_parquet(provenance / f"commit-{self.counters['commits']:06d}.parquet",
                            pd.concat(rows, ignore_index=True))
        self.counters["saved"] = offset
        self._card_rows = None  # (the shards' rows: read with the dataset's)
        self._publish({**self._state(), "merged_shards": sorted(self.shard(b.start).name for b in blocks)},
                      exact=True)
        for b in blocks:
            _remove_shard(self.shard(b.start))
        log.info("merged %d shards: %d episodes in %s (%.2f s)", len(full), offset, self.root,
                 time.perf_counter() - t0)
        self.saved = offset

    def _publish(self, state: dict, rows: pd.DataFrame | None = None, exact: bool = False) -> None:
        """Write the quantiles over the frames, the recording state and the card into staging, flush it, and swap
        it with DATASET_DIR in one atomic step. `rows`: the provenance rows staging adds to DATASET_DIR's. The
        quantiles are computed again over all frames when `exact`, or when the dataset has grown
        by more than stats.REFRESH_GROWTH since they last were; otherwise DATASET_DIR's are kept (each computation
        reads every frame: 9 s for 100k demos, benchmarks/commit_scaling.py)."""
        from vla_ladder.recording import stats

        frames = json.loads((self.staging / "meta/info.json").read_text())["total_frames"]
        over = self._quantile_frames
        if exact or over is None or frames > over * (1 + stats.REFRESH_GROWTH) or not self.root.exists():
            stats.write_exact_quantiles(self.staging)
            over = frames
        else:
            stats.copy_quantiles(self.root, self.staging)
        state = {**state, "quantile_frames": over}
        files.write_json(self.staging / RECORDING_FILE, state)
        self._published = dict(state["counters"])
        card_rows = self._write_card(self.staging, rows)
        _fsync_tree(self.staging)
        if self.root.exists():
            if not any(self.root.iterdir()):
                self.root.rmdir()
        if self.root.exists():
            _exchange(self.staging, self.root)
        else:
            os.rename(self.staging, self.root)
        _fsync_dir(self.root.parent)
        self._quantile_frames, self._card_rows = over, card_rows
        shutil.rmtree(self.staging, ignore_errors=True)  # the previous version, after an exchange
        shutil.rmtree(self.work / "hf-cache", ignore_errors=True)

    def _write_card(self, root: Path, added: pd.DataFrame | None = None) -> pd.DataFrame:
        """Write the card of `root` (DATASET_DIR, or staging adding the provenance rows `added`) from the rows kept
        between commits (read from `root` once a process, and after a merge); returns its rows."""
        from vla_ladder.recording import card

        if self._card_rows is None:
            rows = read_provenance(root)
        else:
            rows = pd.concat([self._card_rows, added], ignore_index=True) if added is not None else self._card_rows
        rows = rows[[c for c in card.COLUMNS if c in rows]]
        card.write_card(root, rows, name=self.root.name)
        return rows

    def _exact_quantiles(self) -> None:
        """Publish stats.json's quantiles over all frames where the last commits kept those over fewer (_publish):
        a recording that stops leaves them exact."""
        if self._quantile_frames is None:  # nothing published, or by a version whose every commit was exact
            return
        if self._quantile_frames == json.loads((self.root / "meta/info.json").read_text())["total_frames"]:
            return
        with _sigint_held():
            shutil.rmtree(self.staging, ignore_errors=True)
            _link_copy(self.root, self.staging)
            self._publish(self._state(), exact=True)

    def _state(self) -> dict:
        return {"format": FORMAT_VERSION, "config": self.config.to_dict(), "next_seed": self.next_seed,
                "played_to": self.played_to, "counters": self.counters, "object_set": self.object_set,
                "updated": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "provenance": files.provenance(self.object_set), "contract": fingerprint()}

    def close(self, commit: bool = True, give_back: bool = False) -> None:
        """Commit what is pending (or drop it) and release the dataset. Episodes pending when an exception
        interrupted add() are dropped: LeRobot's files may then be out of step (Ctrl-C waits for add() to end).
        `give_back`: the seeds after the last one written or counted failed, reserved but in flight when the recording
        stopped, are the next seeds handed out (a resume plays on from there in any case); only where episodes are
        counted in seed order (`record`'s writer). Closing a closed store does nothing: a Ctrl-C after the recorder
        closed it (while it reports) closes it again, when the lock may be another recorder's."""
        if self._lock_file.closed:
            return
        if commit and self._writing:
            log.warning("interrupted while writing an episode: dropping the %d pending episodes", self.pending)
            commit = False
        try:
            if commit:
                if give_back:
                    self.seeds.give_back(self._unused_from)
                self.commit()
                self._exact_quantiles()
            elif self._ds is not None:
                with contextlib.suppress(Exception):  # staging is discarded: only release threads and files
                    self._ds.finalize()
        finally:
            self._ds = None
            shutil.rmtree(self.staging, ignore_errors=True)
            fcntl.flock(self._lock_file, fcntl.LOCK_UN)
            self._lock_file.close()


class SeedBook:
    """The seeds handed out for one dataset, in a JSON file in its work directory: `reserve` persists a block before
    returning it, under a file lock, so that the threads of a writer never get a seed twice. `floor` is the first
    seed the dataset may still use: the book starts there whatever it held (seeds a killed writer had in flight
    were never written)."""

    def __init__(self, path: Path, config: Recording, floor: int):
        self.path, self.config, self.floor = Path(path), config, floor
        self.start_at(floor)

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        with open(self.path.with_suffix(".lock"), "a+") as lock:  # one open file each: threads exclude too
            fcntl.flock(lock, fcntl.LOCK_EX)
            yield

    def _booked(self) -> int:
        """The next seed the book holds for this recording; -1 when it holds none (or another recording's)."""
        if self.path.exists():
            booked = json.loads(self.path.read_text())
            if booked.get("config") == self.config.to_dict():
                return int(booked["next_seed"])
        return -1

    @property
    def next_seed(self) -> int:
        return max(self.floor, self._booked())

    def start_at(self, next_seed: int) -> None:
        """Make next_seed the next seed handed out, and the floor."""
        with self._locked():
            self.floor = next_seed
            files.write_json(self.path, {"config": self.config.to_dict(), "next_seed": next_seed})

    def give_back(self, next_seed: int) -> None:
        """Make next_seed the next seed handed out, when it is below it and not below the floor: the seeds from
        there on were reserved but never reached the dataset."""
        with self._locked():
            if self.floor <= next_seed < self._booked():
                files.write_json(self.path, {"config": self.config.to_dict(), "next_seed": next_seed})

    def reserve(self, n: int) -> list[int]:
        """Up to n new seeds: fewer when the seeds below 2**32 run out (failed attempts use seeds too, so the
        last demos of a recording that starts near the limit may find none; then ValueError)."""
        if n < 1:
            raise ValueError(f"reserve at least one seed, got {n}")
        with self._locked():
            first = self.next_seed
            n = min(n, SEED_LIMIT - first)
            if n < 1:
                raise ValueError(f"no seeds left: the recording has used every seed from --first-seed "
                                 f"{self.config.first_seed} to 2**32 - 1; record the missing demos into another "
                                 "--out with a lower --first-seed")
            files.write_json(self.path, {"config": self.config.to_dict(), "next_seed": first + n})
        return list(range(first, first + n))


@contextlib.contextmanager
def _sigint_held() -> Iterator[None]:
    """Hold back SIGINT (Ctrl-C) for the block and raise KeyboardInterrupt once it ends, so that an episode is
    written whole or not at all. Only the main thread receives signals; elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)
    if held and callable(previous):
        previous(signal.SIGINT, None)  # Python's own handler raises KeyboardInterrupt
    elif held and previous == signal.SIG_DFL:
        raise KeyboardInterrupt


def _join_meta_files(root: Path) -> None:
    """Rewrite the episodes' metadata of `root` (a staging copy, whose files are links to DATASET_DIR's) as one file,
    meta/episodes/chunk-000/file-000.parquet, when it is spread over more than MAX_META_FILES files; LeRobot's resume
    then writes the next batch's into file-001. Every row says which file holds it, as LeRobot reads it."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    paths = sorted((root / "meta/episodes").glob("chunk-*/file-*.parquet"))
    if len(paths) <= MAX_META_FILES:
        return
    # (a merge writes vectors as fixed-size lists, LeRobot's writer as lists: one list type for all)
    table = pa.concat_tables([pq.read_table(p) for p in paths], promote_options="permissive").sort_by("episode_index")
    table = _in_meta_file(table, 0, 0)
    for path in paths:  # (links: DATASET_DIR keeps its files)
        path.unlink()
    joined = root / "meta/episodes/chunk-000/file-000.parquet"
    joined.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, joined)
    for chunk in (root / "meta/episodes").glob("chunk-*"):
        if not any(chunk.iterdir()):
            chunk.rmdir()


def _own_meta_indices(root: Path) -> None:
    """Make every row of meta/episodes/chunk-C/file-F.parquet say chunk C, file F. LeRobot 0.6's aggregate_datasets
    offsets a source's meta/episodes indices but may append its rows to the current file, so a shard committed in
    several batches (one meta file each) left its episodes pointing at meta files the merge never wrote; the next
    merge or resume of the dataset then failed on the missing file (tests/test_recording_shards.py)."""
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    for path in sorted((root / "meta/episodes").glob("chunk-*/file-*.parquet")):
        table = pq.read_table(path)
        chunk, file = int(path.parent.name.split("-")[1]), int(path.stem.split("-")[1])
        if all(pc.all(pc.equal(table[k], v)).as_py() for k, v in zip(_META_FILE_KEYS, (chunk, file))):
            continue
        with files.atomic_path(path) as tmp:
            pq.write_table(_in_meta_file(table, chunk, file), tmp)


_META_FILE_KEYS = ("meta/episodes/chunk_index", "meta/episodes/file_index")


def _in_meta_file(table, chunk: int, file: int):
    """The episodes' metadata `table` with every row saying it is in meta/episodes/chunk-<chunk>/file-<file>."""
    import pyarrow as pa

    for key, value in zip(_META_FILE_KEYS, (chunk, file)):
        field = table.schema.field(key)
        table = table.set_column(table.schema.get_field_index(key), field, pa.array([value] * len(table), field.type))
    return table


def wait_for_writer(shard: Path, timeout_s: float = 300.0) -> None:
    """Return once no writer holds `shard`'s lock. A writer commits what it holds when its recorder dies (it gets
    SIGINT), and a rerun started at once would otherwise merge the shard while it commits, losing what that writer
    commits later or merging it twice; ValueError when it still holds it after `timeout_s`."""
    lock = shard.parent / files.sibling_name(shard, ".recording") / "lock"
    if not lock.exists():
        return
    deadline, said = time.monotonic() + timeout_s, False
    with open(lock, "a+") as f:
        while True:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise ValueError(f"the writer of shard {shard} still holds its lock after {timeout_s:.0f} s; "
                                     "stop it (or wait for it) and rerun") from None
                if not said:
                    log.info("waiting for the writer of shard %s to commit", shard.name)
                    said = True
                time.sleep(0.2)
        fcntl.flock(f, fcntl.LOCK_UN)


def _remove_shard(shard: Path) -> None:
    """A shard and its writer's work directory, and the work directories of writers that never committed."""
    shutil.rmtree(shard, ignore_errors=True)
    shutil.rmtree(shard.parent / files.sibling_name(shard, ".recording"), ignore_errors=True)
    for work in shard.parent.glob(".*.recording"):
        if not (shard.parent / work.name[1:-len(".recording")]).exists():
            shutil.rmtree(work, ignore_errors=True)


def _provenance_row(index: int, episode) -> dict[str, Any]:
    h, m = episode.header, episode.header["metrics"]
    return {
        "episode_index": index, "seed": int(episode.seed), "policy": h["expert"]["spec"],
        **_condition_columns(Condition.parse(h["condition"])), "target": h["target"],
        "instruction": h["instruction"], "layout": files.dumps(h["layout"]),
        "expert": files.dumps(h["expert"]), "object_set": h["object_set"],
        "robot_mesh": h.get("robot_mesh", "full"), "instructions": h.get("instructions", "canonical"),
        **{k: bool(m[k]) for k in METRICS}, "lifted": bool(m["lifted"]), "held": m["held"],
        "reach_dist": float(m["reach_dist"]),
        "num_frames": int(episode.num_frames), "server": episode.server,
        # Recorded on a rebuilt physx_cpu scene: its seed and actions give back its states to the bit.
        "sim_backend": h.get("sim_backend", "physx_cpu"), "replayable": bool(h.get("replayable", False)),
        "recorded_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def _condition_columns(c: Condition) -> dict[str, Any]:
    return {"regime": c.regime, "split": c.split, "num_objects": c.num_objects}


# ---------------------------------------------------------------------- filesystem primitives
def _link_copy(src: Path, dst: Path) -> None:
    """dst = src with immutable files hard-linked and the rest copied."""
    for dirpath, _, names in os.walk(src):
        rel = Path(dirpath).relative_to(src)
        (dst / rel).mkdir(parents=True, exist_ok=True)
        immutable = any(rel == Path(d) or Path(d) in rel.parents for d in IMMUTABLE_DIRS)
        for f in names:
            (os.link if immutable else shutil.copy2)(Path(dirpath) / f, dst / rel / f)


def _quiet_ffmpeg() -> None:
    """FFmpeg's warnings and errors only. LeRobot hands FFmpeg's logging back to its default printer after every
    video it encodes or concatenates, which then printed each MP4's "moving the moov atom" line, and with --vcodec
    h264 x264's statistics (ten lines a video)."""
    import av

    av.logging.set_libav_level(av.logging.WARNING)


@contextlib.contextmanager
def _aggregate_without_bars() -> Iterator[None]:
    """No tqdm bars from LeRobot's aggregate_datasets, which drew two per merge ("Validate all meta data", "Copy data
    and videos") between the recorder's own lines: it calls `tqdm.tqdm`, which SuppressProgressBars (`datasets`'
    bars) does not reach, and tqdm reads $TQDM_DISABLE only when imported. Only that module's name is replaced."""
    import functools
    import types

    import tqdm
    from lerobot.datasets import aggregate

    saved = aggregate.tqdm
    aggregate.tqdm = types.SimpleNamespace(tqdm=functools.partial(tqdm.tqdm, disable=True))
    try:
        yield
    finally:
        aggregate.tqdm = saved


def _fsync_tree(root: Path) -> None:
    """Flush what this batch wrote (files with one link: new or copied) and every directory entry."""
    for dirpath, _, names in os.walk(root):
        for f in names:
            path = Path(dirpath) / f
            if path.stat().st_nlink == 1:
                fd = os.open(path, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
        _fsync_dir(Path(dirpath))


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


_AT_FDCWD, _RENAME_EXCHANGE = -100, 2


def _exchange(a: Path, b: Path) -> None:
    """Atomically swap two directories (Linux renameat2 with RENAME_EXCHANGE, glibc >= 2.28)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if not hasattr(libc, "renameat2"):
        raise RuntimeError("recording needs renameat2 (Linux, glibc >= 2.28) to commit episodes atomically")
    if libc.renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) != 0:
        err = ctypes.get_errno()
        hint = " (the filesystem does not support RENAME_EXCHANGE)" if err in (errno.EINVAL, errno.ENOSYS) else ""
        raise OSError(err, f"cannot swap {a} and {b}: {os.strerror(err)}{hint}")


@contextlib.contextmanager
def _private_datasets_cache(path: Path) -> Iterator[None]:
    """Point `datasets`' Arrow cache at `path` while LeRobot loads the staging metadata, so the per-commit
    conversions land in a directory deleted after each commit instead of piling up under HF_HOME."""
    import datasets.config

    old = datasets.config.HF_DATASETS_CACHE
    datasets.config.HF_DATASETS_CACHE = path
    try:
        yield
    finally:
        datasets.config.HF_DATASETS_CACHE = old

