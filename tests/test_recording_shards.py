"""Parallel writers: a seed book shared by processes hands every seed out once, shards written by separate
DatasetStores merge into the dataset with LeRobot's aggregate_datasets (episodes, frames, videos and
provenance in step; atomic; never merged twice), and `record --writers 2` does it all with real servers."""

from __future__ import annotations

import contextlib
import hashlib
import multiprocessing
import shutil
from pathlib import Path

import numpy as np
import pytest

from vla_ladder.recording.store import DatasetStore, SeedBook
from vla_ladder.recordings import Recording, read_provenance, read_recording_state
from test_recording_store import CONFIG, synthetic_episode

FRAMES = 12


def _succeeds(seed: int) -> bool:
    """A stand-in expert: an episode's outcome is a function of its seed, as the simulator's is."""
    return int(hashlib.sha256(str(seed).encode()).hexdigest(), 16) % 3 == 0


def _write_blocks(path: str, index: int, queue) -> None:
    """A writer as `record --ledger` runs one (writers.write_blocks), episodes played in random time: take blocks,
    ask the ledger about each seed in order, report, stop when told or once the ledger is done."""
    import random
    import time

    from vla_ladder.recording.ledger import STOP, WAIT, Ledger

    rng, ledger, kept = random.Random(index), Ledger(path), []
    while not ledger.done():
        if (block := ledger.take()) is None:  # the seeds in play should hold the missing demos: ask again later
            time.sleep(0.005)
            continue
        saved = attempted = 0
        for seed in range(*block):
            time.sleep(rng.uniform(0, 0.004))
            verdict = ledger.verdict(seed, _succeeds(seed))
            if verdict == WAIT:
                ledger.report(block[0], seed, saved, attempted, attempted - saved)
                while (verdict := ledger.verdict(seed, _succeeds(seed))) == WAIT:
                    time.sleep(0.001)
            if verdict == STOP:
                ledger.report(block[0], seed, saved, attempted, attempted - saved, done=True)
                queue.put(kept)
                return
            attempted += 1
            if _succeeds(seed):
                saved += 1
                kept.append(seed)
            ledger.report(block[0], seed + 1, saved, attempted, attempted - saved)
        ledger.report(block[0], block[1], saved, attempted, attempted - saved, done=True)
    queue.put(kept)


@pytest.mark.parametrize("writers", [1, 2, 4])
def test_writers_sharing_a_ledger_keep_the_first_successes_whatever_their_number(tmp_path, writers):
    """Writer processes playing blocks of seeds at random speeds keep exactly the first 30 successful seeds from
    --first-seed, none twice and none beyond (what one writer keeps), and the ledger's blocks tile the seeds they
    played; a second run (an extension to 45) starts with the seeds the first left unplayed in a block it stopped."""
    from vla_ladder.recording.ledger import Block, Ledger

    first = 1000
    successes = [s for s in range(first, first + 1000) if _succeeds(s)]
    path = tmp_path / "ledger.json"
    Ledger.begin(path, {"recording": 1}, target=30, writers=writers, base_seed=first, base_saved=0, blocks=[])
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_write_blocks, args=(str(path), i, queue)) for i in range(writers)]
    for p in procs:
        p.start()
    kept = sorted(s for _ in procs for s in queue.get(timeout=120))
    for p in procs:
        p.join()
    assert kept == successes[:30]
    blocks = sorted(Ledger(path).blocks(), key=lambda b: b.start)
    assert all(b.done for b in blocks) and blocks[0].start == first
    assert all(a.end == b.start for a, b in zip(blocks, blocks[1:])), "blocks overlap or leave a gap"
    prefix, cursor = [], first
    for b in blocks:  # what the recorder merges: blocks seed after seed until 30 demos
        if b.start != cursor or sum(p.saved for p in prefix) >= 30:
            break
        prefix.append(b)
        cursor = b.played_to
    assert sum(b.saved for b in prefix) == 30 and cursor == successes[29] + 1
    assert sum(b.attempted for b in prefix) == cursor - first, "a seed of the dataset's was not played, or twice"

    Ledger.begin(path, {"recording": 1}, target=45, writers=writers, base_seed=cursor, base_saved=30,
                 blocks=[Block(cursor + 10, cursor + 20, cursor + 20, 4, 10, 6, True)])
    again = Ledger(path)
    assert again.take()[0] == cursor, "the seeds between the dataset and a shard left behind come first"


def test_the_ledger_keeps_waits_and_stops(tmp_path):
    """Blocks are handed out lowest seeds first, sized by what is missing; a success is kept when even all seeds
    still unplayed below it could not push it out of the first `target`, waited on while they could, and
    refused (stop) once the successes below it reach the target; a writer of an earlier run cannot report."""
    from vla_ladder.recording.ledger import KEEP, STOP, WAIT, Block, Ledger

    path = tmp_path / "ledger.json"
    ledger = Ledger.begin(path, {}, target=5, writers=2, base_seed=100, base_saved=2,
                          blocks=[Block(110, 120, 120, saved=1, attempted=10, failed=9, done=True)])
    # 2 demos missing (2 in the dataset, 1 in a shard left at 110), 2 in 11 seeds succeeded (one assumed): 6 seeds a
    # writer, from the gap before 110
    assert ledger.take() == (100, 106) and ledger.take() == (106, 110)
    assert ledger.verdict(100, True) == KEEP  # 2 demos below it, no seed unplayed: the dataset's third
    assert ledger.verdict(106, True) == WAIT  # seeds 100-105, unplayed, may hold the 2 missing demos
    ledger.report(100, 103, saved=1, attempted=3, failed=2)
    assert ledger.verdict(106, True) == WAIT and ledger.verdict(106, False) == KEEP  # (a failure is counted)
    ledger.report(100, 106, saved=1, attempted=6, failed=5, done=True)
    assert ledger.verdict(106, True) == KEEP
    ledger.report(106, 110, saved=1, attempted=4, failed=3, done=True)
    assert ledger.verdict(121, False) == STOP and ledger.verdict(121, True) == STOP
    assert ledger.take() is None, "5 demos kept: no new block"
    stale = Ledger(path)
    Ledger.begin(path, {}, target=5, writers=2, base_seed=100, base_saved=2, blocks=[])
    stale.report(100, 110, saved=3, attempted=10, failed=7, done=True)  # a writer of a killed run reports late
    assert Ledger(path).blocks() == [] and stale.take() is None


def test_the_ledger_hands_out_no_seed_past_the_last_numpy_seed(tmp_path):
    """Writers near 2**32 get the seeds that are left, then the ledger is done (the recorder says no seeds are
    left), never a seed >= 2**32."""
    from vla_ladder.recording.ledger import Ledger

    ledger = Ledger.begin(tmp_path / "ledger.json", {}, target=5, writers=2, base_seed=2**32 - 3, base_saved=0,
                          blocks=[])
    assert not ledger.done() and ledger.take() == (2**32 - 3, 2**32)
    assert ledger.done() and ledger.take() is None


def test_seed_book_stops_at_the_last_numpy_seed(tmp_path):
    """Failed attempts use seeds too, so a recording that starts near 2**32 can run out: the book hands out the
    seeds that are left, then refuses in a line that says what to do, never a seed >= 2**32."""
    last = 2**32 - 1
    book = SeedBook(tmp_path / "seeds.json", Recording(**CONFIG, first_seed=last - 2), floor=last - 2)
    assert book.reserve(5) == [last - 2, last - 1, last]
    with pytest.raises(ValueError, match="no seeds left: .* --first-seed 4294967293 to 2\\*\\*32 - 1; record the "
                                         "missing demos into another --out with a lower --first-seed"):
        book.reserve(1)
    assert book.next_seed == 2**32


def test_one_writer_per_two_servers_unless_asked():
    from vla_ladder.machine import auto_writers

    assert [auto_writers(n) for n in (1, 2, 3, 4, 16)] == [1, 1, 1, 2, 8]
    assert auto_writers(16, 3) == 3 and auto_writers(2, 2) == 2


def test_an_eta_of_days_says_its_days(monkeypatch):
    """The progress line's ETA of a long recording (100k demos at 0.5 demos/s: 2 days 7 h) read 07:33:20."""
    import time
    from types import SimpleNamespace

    from vla_ladder.recording import record

    lines = []
    monkeypatch.setattr(record.log, "info", lambda fmt, *args: lines.append(fmt % args))
    progress = record.Progress(100_001, 0, started=time.monotonic() - 2.0)
    progress.report(SimpleNamespace(saved=0, pending=1))  # one demo in 2 s, 100000 to go
    assert "ETA 2d 07:33:" in lines[-1], lines[-1]
    assert record.eta_text(59) == "00:00:59" and record.eta_text(86400 + 61) == "1d 00:01:01"


def test_a_ctrl_c_whose_keyboardinterrupt_is_lost_is_still_seen_by_the_writers_loops():
    """A KeyboardInterrupt raised inside a weakref callback is printed as "Exception ignored" and lost: a writer then
    waited 300 s for episodes after the Ctrl-C. sticky_sigint remembers it for the loops to raise again; a process
    started with SIGINT ignored keeps ignoring it."""
    import os
    import signal
    import time

    from vla_ladder.recording.record import sticky_sigint

    previous = signal.getsignal(signal.SIGINT)
    try:
        ctrl_c = sticky_sigint()
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)  # (the handler runs at the next bytecode boundary)
        except KeyboardInterrupt:
            pass  # lost, as in a weakref callback
        assert ctrl_c.is_set()
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        ignored = sticky_sigint()
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.2)
        assert not ignored.is_set() and signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_ctrl_c_lost_in_a_weakref_callback_is_remembered_without_a_traceback():
    """A Ctrl-C whose KeyboardInterrupt is raised inside a weakref's callback, for real: Python printed it ("Exception
    ignored in ... Traceback ... KeyboardInterrupt"), which came with the Ctrl-C that stopped a writer in
    test_record_with_two_writers_stopped_by_ctrl_c_then_rerun (a Ctrl-C ends without a traceback). Remembered by
    sticky_sigint, it is not printed; any other exception lost in a callback still is."""
    import subprocess
    import sys

    code = """if True:
        import os, signal, weakref
        from vla_ladder.recording.record import sticky_sigint
        ctrl_c = sticky_sigint()
        class Junk: pass
        def ctrl_c_in_here(_):
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(100000): pass  # (the handler runs at a bytecode boundary in here)
        def error_in_here(_):
            raise ValueError("not a Ctrl-C")
        a, b = Junk(), Junk()
        refs = weakref.ref(a, ctrl_c_in_here), weakref.ref(b, error_in_here)
        del a, b
        print("remembered", ctrl_c.is_set())
    """
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "remembered True", (r.stdout, r.stderr)
    assert "KeyboardInterrupt" not in r.stderr and "ValueError: not a Ctrl-C" in r.stderr, r.stderr


def test_a_resumed_sharded_recording_rates_only_its_own_demos():
    """`record --writers K` resumed over an earlier run's shard after a gap (4 demos, 4 seeds, 1 block: the ledger
    counts them kept) said 0.088 demos/s, ETA 8 min, before its writers had kept one demo."""
    from vla_ladder.recording.writers import progress_line

    at_start = (16, 4, 1)  # 12 demos in the dataset, 4 in the shard left after a gap
    assert progress_line((16, 4, 3), at_start, 60, 45.0) == \
        "progress: 16/60 saved | 0 seeds played in 2 blocks | 0.000 demos/s saved | ETA ?"
    assert progress_line((26, 16, 3), at_start, 60, 100.0) == \
        "progress: 26/60 saved | 12 seeds played in 2 blocks | 0.100 demos/s saved | ETA 00:05:40"


def test_an_out_that_is_a_file_leaves_no_work_directory_beside_it(tmp_path):
    """`record --out FILE` said the path is not a directory, and left .FILE.recording/ (its lock) beside the file."""
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(NotADirectoryError):
        DatasetStore(tmp_path / "notes.txt", Recording(**CONFIG))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_record_refuses_servers_of_other_objects_before_recording(tmp_path, monkeypatch):
    """Servers simulate the object set their machine has (auto: ycb where the YCB models are on disk, else standin).
    Servers of two object sets, or of another one than the dataset's, were found at the first demo of the other set
    (its batch lost) or, with --writers, by the merge, which refused the shards at that and at every rerun."""
    import functools
    import threading

    from test_reconnect import LoopThread, _greeting_server
    from vla_ladder.recording import record

    monkeypatch.setattr(record, "setup_logging", lambda prefix: None)
    serves = dict(policy="scripted", condition="small_jitter/canonical/2", robot_mesh="lite", instructions="canonical",
                  num_envs=1)

    def run(cfg):  # in a thread: a recorder that does not refuse waits for episodes the servers never send
        out = []
        worker = threading.Thread(target=lambda: out.append(_raised(record.run, cfg)), daemon=True)
        worker.start()
        worker.join(60)
        assert out, "the recorder did not refuse the servers"
        return out[0]

    ycb = functools.partial(_greeting_server, serves={**serves, "object_set": "ycb"})
    standin = functools.partial(_greeting_server, serves={**serves, "object_set": "standin"})
    with LoopThread(ycb) as a, LoopThread(standin) as b:
        error = run(record.RecordConfig(out=tmp_path / "new", episodes=2, server=(a.url, b.url)))
        assert isinstance(error, ValueError) and "object set ycb" in str(error) and "object set standin" in str(error)
        root = tmp_path / "data"
        store = DatasetStore(root, Recording(**CONFIG))
        store.add(synthetic_episode(store.reserve_seeds(1)[0], FRAMES))  # a standin demo
        store.close()
        error = run(record.RecordConfig(out=root, episodes=2, server=(a.url,)))
        assert isinstance(error, ValueError) and "holds episodes of object set 'standin'" in str(error)
        assert "servers simulate 'ycb'" in str(error), error
        assert not (tmp_path / ".data.recording" / "staging").exists()
        store = DatasetStore(root, Recording(**CONFIG))  # (the lock was let go)
        store.close()


def test_a_ctrl_c_whose_keyboardinterrupt_is_lost_still_stops_a_single_writer_record(tmp_path, monkeypatch):
    """The single writer's loop waits on its servers as the writers' loops do: a KeyboardInterrupt lost in a weakref
    callback (sticky_sigint) left it recording on, or waiting for episodes from servers the same Ctrl-C stopped.
    Here a server that greets and sends no episode, and the recorder's SIGINT handler run where its
    KeyboardInterrupt is lost (another thread): the recorder still stops with 130, and puts Python's handler back."""
    import functools
    import signal
    import sys
    import threading
    import time

    from test_reconnect import LoopThread, _greeting_server
    from vla_ladder.recording import record

    monkeypatch.setattr(record, "setup_logging", lambda prefix: None)
    serves = dict(policy="scripted", condition="small_jitter/canonical/2", robot_mesh="lite", instructions="canonical",
                  num_envs=1)
    limits = dict(max_outstanding=8, max_seeds_per_request=8)
    before, hook = signal.getsignal(signal.SIGINT), sys.unraisablehook
    assert before is signal.default_int_handler  # (pytest leaves Python's)
    server = LoopThread(functools.partial(_greeting_server, serves=serves, limits=limits)).__enter__()
    returned, lost_at = threading.Event(), []

    def lose_a_ctrl_c():
        deadline = time.monotonic() + 20
        while signal.getsignal(signal.SIGINT) is before and time.monotonic() < deadline and not returned.is_set():
            time.sleep(0.05)
        time.sleep(1.0)  # the recorder waits for episodes
        lost_at.append(time.monotonic())
        try:
            signal.getsignal(signal.SIGINT)(signal.SIGINT, None)  # what a Ctrl-C runs in the main thread
        except KeyboardInterrupt:
            pass  # lost, as in a weakref callback
        returned.wait(20)
        server.__exit__(None, None, None)  # (unseen: the server goes, and the recorder gives up on it)

    helper = threading.Thread(target=lose_a_ctrl_c, daemon=True)
    helper.start()
    try:
        rc = record.run(record.RecordConfig(out=tmp_path / "data", episodes=2, server=(server.url,)))
        stopped_at = time.monotonic()
    finally:
        returned.set()
        helper.join(60)
    assert rc == 130 and stopped_at - lost_at[0] < 5, (rc, stopped_at - lost_at[0])
    assert signal.getsignal(signal.SIGINT) is before and sys.unraisablehook is hook


def test_a_writer_waiting_on_an_earlier_block_still_sees_a_lost_ctrl_c(tmp_path):
    """A writer whose success waits on an earlier block still in play (Ledger.verdict says WAIT) loops until that block
    is played. A Ctrl-C whose KeyboardInterrupt was lost there went unseen: the earlier block's writer, stopped by the
    same Ctrl-C, never plays it, so the writer waited for ever, and so did the recorder, for its exit. Here the
    earlier block is played 15 s after the lost Ctrl-C, so that a writer that misses it stops then (too late)."""
    import asyncio
    import signal
    import threading
    import time

    from test_reconnect import LoopThread
    from vla_ladder.contract import EPISODE_STEPS
    from vla_ladder.recording import protocol as P
    from vla_ladder.recording.ledger import Block, Ledger
    from vla_ladder.recording.record import RecordConfig
    from vla_ladder.recording.writers import write_blocks

    async def episodes(ready):  # a server that plays every seed asked for as a success, at once
        from websockets.asyncio.server import serve

        async def handle(ws):
            P.decode(await ws.recv())  # the hello
            serves = dict(policy="scripted", condition="small_jitter/canonical/2", robot_mesh="lite",
                          instructions="canonical", num_envs=1)
            await ws.send(P.encode({"type": "welcome", "protocol": P.PROTOCOL_VERSION, "server": serves,
                                    "limits": dict(max_outstanding=2, max_seeds_per_request=2)}))
            async for raw in ws:
                for seed in P.decode(raw).header["seeds"]:
                    e = synthetic_episode(seed, EPISODE_STEPS)
                    await ws.send(P.encode({"type": "episode", **e.header}, {
                        **{f"images.{c}": a for c, a in e.images.items()}, "state": e.state, "action": e.action}))

        async with serve(handle, "127.0.0.1", 0) as server:
            ready(f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}")
            await asyncio.Future()

    import lerobot.datasets.lerobot_dataset  # noqa: F401  (imported before the clock starts)

    # 5 demos wanted; seeds 0-9 are another writer's, played to 5 (no success yet), so seed 10's success waits on
    # its seeds 5-9: the writer here takes seeds 10-24.
    path = tmp_path / "ledger.json"
    Ledger.begin(path, {}, target=5, writers=2, base_seed=0, base_saved=0,
                 blocks=[Block(0, 10, 5, saved=0, attempted=5, failed=5)])
    other = Ledger(path)
    shards = tmp_path / "shards"
    previous = signal.getsignal(signal.SIGINT)
    assert previous is signal.default_int_handler  # (pytest leaves Python's)
    returned, lost_at = threading.Event(), []

    def lose_a_ctrl_c():
        deadline = time.monotonic() + 120
        while not (shards / ".0000000010.recording").exists() and time.monotonic() < deadline:
            time.sleep(0.05)  # the writer has seed 10's episode and asks the ledger about it
        time.sleep(2.0)
        lost_at.append(time.monotonic())
        try:
            signal.getsignal(signal.SIGINT)(signal.SIGINT, None)  # what a Ctrl-C runs in the main thread
        except KeyboardInterrupt:
            pass  # lost, as in a weakref callback
        if not returned.wait(15):  # (unseen: the earlier block is played, without a demo)
            other.report(0, 10, 0, 10, 10, done=True)

    with LoopThread(episodes) as server:
        cfg = RecordConfig(out=shards, episodes=5, server=(server.url,), ledger=path, first_seed=0)
        helper = threading.Thread(target=lose_a_ctrl_c, daemon=True)
        helper.start()
        try:
            rc = write_blocks(cfg, Recording(**CONFIG))
            stopped_at = time.monotonic()
        finally:
            returned.set()
            helper.join(60)
            signal.signal(signal.SIGINT, previous)  # (the writer ignores a second Ctrl-C while it commits)
    assert rc == 130 and stopped_at - lost_at[0] < 5, (rc, stopped_at - lost_at[0])
    assert Ledger(path).blocks()[1].done  # its block given back to the ledger


def _raised(fn, *args):
    try:
        return fn(*args)
    except Exception as e:
        return e


def _fill(store: DatasetStore, n: int) -> list[int]:
    seeds = store.reserve_seeds(n)
    for seed in seeds:
        store.count(True)
        store.add(synthetic_episode(seed, FRAMES))
    store.count(False)  # an attempt that failed, for the counters
    return seeds


def _check_dataset(root: Path, expect_seeds: list[int]) -> None:
    """Every episode's frames (state, video) belong to the seed its provenance row names."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.datasets.video_utils import _default_decoder_cache

    # LeRobot keeps decoders open by path for the life of a process: a merge rewrites videos/*/file-000.mp4.
    _default_decoder_cache.clear()
    ds = LeRobotDataset("vla-ladder/merged", root=root)
    prov = read_provenance(root)
    assert ds.meta.total_episodes == len(expect_seeds) == len(prov)
    assert prov["episode_index"].tolist() == list(range(len(expect_seeds)))
    assert prov["seed"].tolist() == expect_seeds
    for ep, seed in enumerate(expect_seeds):
        start = ds.meta.episodes[ep]["dataset_from_index"]
        first, last = ds[start], ds[start + FRAMES - 1]
        assert first["observation.state"][0].item() == seed == last["observation.state"][0].item()
        assert first["task"] == prov["instruction"][ep]
        want = synthetic_episode(seed, 1).images["hand_camera"][0].astype(np.float32) / 255
        got = last["observation.images.hand_camera"].permute(1, 2, 0).numpy()
        assert np.abs(got - want).mean() < 0.03, f"episode {ep}: the video frame is not seed {seed}'s"
    state = read_recording_state(root)
    assert state["counters"]["saved"] == len(expect_seeds)


@pytest.mark.slow
def test_a_shard_of_several_commits_merges_into_a_dataset_that_merges_and_resumes_again(tmp_path, capfd):
    """A shard committed in three batches has three meta/episodes files; merged into an empty dataset they become
    one, whose rows must name that file (LeRobot's aggregate kept the shard's file indices 1 and 2, and the next
    merge failed on meta/episodes/chunk-000/file-001.parquet, as a killed two-writer recording did in CI)."""
    import pandas as pd

    root = tmp_path / "ds"
    main = DatasetStore(root, Recording(**CONFIG), commit_every=1)

    def shard(start: int, n: int) -> Path:
        store = DatasetStore(main.shard(start), Recording(**CONFIG), commit_every=1, seeds_from=start)
        written.extend(_fill(store, n))
        store.close()
        return main.shard(start)

    written: list[int] = []
    first = shard(0, 3)
    assert len(list((first / "meta/episodes").glob("*/*.parquet"))) == 3
    capfd.readouterr()
    main.settle(10)
    main.close()
    merge_output = capfd.readouterr()
    assert "it/s]" not in merge_output.err + merge_output.out, "LeRobot's aggregate drew its progress bars"
    import tqdm
    from lerobot.datasets import aggregate
    assert aggregate.tqdm is tqdm, "the merge left LeRobot's aggregate module changed"
    for path in (root / "meta/episodes").glob("chunk-*/file-*.parquet"):
        meta = pd.read_parquet(path)
        assert (meta["meta/episodes/file_index"] == int(path.stem.split("-")[1])).all(), path
    main = DatasetStore(root, Recording(**CONFIG), commit_every=1)
    shard(3, 1), shard(4, 1)
    main.settle(10)
    resumed = _fill(main, 1)  # and a single writer resumes it
    main.close()
    _check_dataset(root, written + resumed)


def test_a_merged_dataset_resumed_past_max_meta_files_joins_the_merges_and_the_writers_metadata(tmp_path):
    """A merge writes the episodes' metadata with fixed-size lists, LeRobot's writer with lists; a single writer
    resuming the merged dataset one commit at a time joins both kinds into one file past MAX_META_FILES, and every
    episode's frames and video still belong to its seed."""
    from vla_ladder.recording.store import MAX_META_FILES

    root = tmp_path / "ds"
    main = DatasetStore(root, Recording(**CONFIG), commit_every=1)
    written = []
    for start, n in ((0, 3), (3, 2)):
        store = DatasetStore(main.shard(start), Recording(**CONFIG), commit_every=1, seeds_from=start)
        written += _fill(store, n)
        store.close()
    main.settle(20)
    counts = []
    for seed in main.reserve_seeds(MAX_META_FILES + 2):
        main.count(True)
        main.add(synthetic_episode(seed, FRAMES))
        written.append(seed)
        counts.append(len(list((root / "meta/episodes").glob("*/*.parquet"))))
    main.close()
    assert max(counts) == MAX_META_FILES + 1 and counts[-1] < max(counts), counts
    _check_dataset(root, written)


def test_shards_merge_after_the_dataset_in_seed_order_and_resume(tmp_path):
    """`settle` merges the shards that continue the dataset seed after seed, in seed order, up to the target;
    a shard after a gap waits for the gap to be played, and one that would overshoot is dropped."""
    root = tmp_path / "ds"
    main = DatasetStore(root, Recording(**CONFIG), commit_every=2)
    own = _fill(main, 2)
    assert own == [0, 1] and main.played_to == 2
    written = {}
    for start, n in ((5, 2), (2, 3), (9, 1)):  # 9: after a gap (seeds 7 and 8 unplayed)
        store = DatasetStore(main.shard(start), Recording(**CONFIG), commit_every=2, seeds_from=start)
        written[start] = _fill(store, n)
        store.close()
    assert written == {2: [2, 3, 4], 5: [5, 6], 9: [9]}
    assert [(b.start, b.played_to, b.saved) for b in main.done_blocks()] == [(2, 5, 3), (5, 7, 2), (9, 10, 1)]
    counted = [dict(main.counters)] + [read_recording_state(s)["counters"] for s in [main.shard(2), main.shard(5)]]

    # Killed before the swap: the dataset is as it was and the shards are merged by the next try.
    import vla_ladder.recording.store as store_module

    real_exchange = store_module._exchange

    def killed(a, b):
        raise KeyboardInterrupt

    store_module._exchange = killed
    try:
        with pytest.raises(KeyboardInterrupt):
            main.settle(10)
    finally:
        store_module._exchange = real_exchange
    _check_dataset(root, own)
    assert main.played_to == 2 and main.counters == counted[0] and len(main.done_blocks()) == 3
    main.settle(10)
    main.close()
    _check_dataset(root, own + written[2] + written[5])
    state = read_recording_state(root)
    for key in ("attempted", "failed", "saved"):
        assert state["counters"][key] == sum(c[key] for c in counted), key
    assert state["played_to"] == state["next_seed"] == 7
    assert not main.shard(2).exists() and not main.shard(5).exists() and main.shard(9).exists()

    # A shard found again after its merge (killed between the swap and the clean-up) is not merged twice.
    shutil.copytree(root, main.shard(2))
    store = DatasetStore(root, Recording(**CONFIG), commit_every=1)
    assert not main.shard(2).exists() and [b.start for b in store.done_blocks()] == [9]
    # A single writer plays the gap; then the shard after it joins.
    more = _fill(store, 2)
    assert more == [7, 8]
    store.settle(10)
    store.close()
    _check_dataset(root, own + written[2] + written[5] + more + written[9])

    # A shard kept for a larger target than this run's would overshoot it: dropped, its seeds played again.
    store = DatasetStore(root, Recording(**CONFIG), commit_every=1)
    extra = DatasetStore(store.shard(10), Recording(**CONFIG), commit_every=1, seeds_from=10)
    _fill(extra, 3)
    extra.close()
    store.settle(11)
    assert not store.shard(10).exists() and store.saved == 10 and store.played_to == 10
    store.close()


@pytest.mark.slow
def test_record_with_two_writers_killed_then_rerun(tmp_path):
    """`record --writers 2` (real servers, real writer processes) killed by SIGKILL once a shard committed: the
    writers commit and exit, nothing reaches the dataset half-merged; the same command merges what they left and
    records the rest. The dataset is the one a single writer records in one go: the same seeds, frames and actions,
    and the same attempts. In H.264 (`--vcodec h264`): the writers are told the codec and LeRobot's merge
    concatenates their H.264 files."""
    import subprocess

    import torch
    from test_recording import CONDITION, ENV, _alive, _cli, _kill_when, _load, _wait_for

    root = tmp_path / "grasp"
    cmd = _cli("record", *CONDITION, "--episodes", "5", "--out", str(root), "--first-seed", "300",
               "--workers", "2", "--writers", "2", "--commit-every", "1", "--encoder-threads", "1",
               "--vcodec", "h264")
    shards = tmp_path / ".grasp.recording" / "shards"

    def left() -> list[Path]:  # shards with a commit (a writer's own work directory is hidden)
        return [s for s in shards.glob("[!.]*") if (s / "meta/vla_ladder_recording.json").exists()]

    def committed() -> int:
        return sum(read_recording_state(s)["counters"]["saved"] for s in left())

    writers: list[list[str]] = []  # the writer processes' command lines, read while they run

    def ready() -> bool:
        if committed() < 1:
            return False
        for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
            with contextlib.suppress(OSError):
                argv = cmdline.read_bytes().decode().split("\0")
                if "--ledger" in argv and any(a.startswith(str(shards)) for a in argv):
                    writers.append(argv)
        return True

    children = _kill_when(cmd, ready, "a writer's first commit")
    assert len(writers) == 2 and all(w[w.index("--encoder-threads") + 1] == "1" for w in writers)
    assert all(w[w.index("--vcodec") + 1] == "h264" for w in writers)
    # Servers see their stdin close, writers get SIGINT from the kernel (PR_SET_PDEATHSIG): all exit.
    _wait_for(lambda: not any(_alive(p) for p in children), 120, "the recorder's children to exit")
    assert len(children) == 4
    assert not root.exists(), "the dataset changed without a merge"
    assert committed() >= 1
    n_left = len(left())

    rerun = subprocess.run(cmd, env=ENV, capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert n_left >= 1 and "merging the shards a stopped recording left" in rerun.stderr
    ds = _load(root)
    prov = read_provenance(root)
    assert ds.meta.total_episodes == 5 == len(prov) and read_recording_state(root)["counters"]["saved"] == 5
    assert prov["seed"].is_unique and prov["seed"].min() >= 300
    assert prov["episode_index"].tolist() == list(range(5))
    assert (prov["num_frames"] == ds.meta.episodes.to_pandas()["length"]).all()
    assert not list(shards.glob("[!.]*")) and not list(shards.glob(".*")), "merged shards were left behind"
    last = ds[len(ds) - 1]
    assert last["task"] == prov["instruction"].iloc[-1] and last["observation.images.fixed_camera"].shape[0] == 3
    assert {ds.meta.features[k]["info"]["video.codec"] for k in ds.meta.video_keys} == {"h264"}
    assert read_recording_state(root)["config"]["vcodec"] == "h264"

    one = tmp_path / "one"
    one_writer = [str(one) if a == str(root) else "1" if prev == "--writers" else a for prev, a in zip(["", *cmd], cmd)]
    single = subprocess.run(one_writer, env=ENV, capture_output=True, text=True)
    assert single.returncode == 0, single.stderr[-3000:]
    assert "writers record" not in single.stderr  # (one writer: no shards)
    alone = read_provenance(one)
    assert prov["seed"].tolist() == alone["seed"].tolist()
    assert (prov["instruction"] == alone["instruction"]).all()
    frames, frames_alone = _load(root).hf_dataset.with_format("numpy"), _load(one).hf_dataset.with_format("numpy")
    for key in ("observation.state", "action", "episode_index", "frame_index"):
        assert np.array_equal(frames[key], frames_alone[key]), key
    for i in (0, len(frames) - 1):  # the videos hold the same pictures (one encoder thread each: the same bytes)
        for camera in ("observation.images.hand_camera", "observation.images.fixed_camera"):
            assert torch.equal(_load(root)[i][camera], _load(one)[i][camera]), (i, camera)
    state, state_alone = read_recording_state(root), read_recording_state(one)
    for key in ("attempted", "failed", "saved"):
        assert state["counters"][key] == state_alone["counters"][key], key
    assert state["played_to"] == state_alone["played_to"] == alone["seed"].max() + 1


@pytest.mark.slow
def test_record_with_two_writers_stopped_by_ctrl_c_then_rerun(tmp_path):
    """A Ctrl-C at the terminal (SIGINT to the recorder's process group: the recorder and its writers) once a writer
    committed: the writers commit what they hold, the recorder merges what continues the dataset and exits with 130,
    saying to rerun; the rerun records the rest. Every seed from --first-seed to where the dataset ends was played
    once, and its successes are the dataset's, in seed order."""
    import os
    import signal
    import subprocess

    from test_recording import CONDITION, ENV, _alive, _children, _cli, _wait_for

    root, log = tmp_path / "grasp", tmp_path / "record.log"
    first = 500
    cmd = _cli("record", *CONDITION, "--episodes", "6", "--out", str(root), "--first-seed", str(first),
               "--workers", "2", "--writers", "2", "--commit-every", "1")
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, env=ENV, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            _wait_for(lambda: "committed: 1 episodes" in log.read_text(), 900, "a writer's first commit", proc)
            children = _children(proc.pid)
            os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does to its foreground group
            assert proc.wait(timeout=300) == 130, log.read_text()[-3000:]
        finally:
            proc.kill()
    text = log.read_text()
    assert "the recording stopped early (interrupted); rerun the same command" in text, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    _wait_for(lambda: not any(_alive(p) for p in children), 60, "the recorder's children to exit")
    if root.exists():  # what continued the dataset from --first-seed was merged, in seed order
        seeds = read_provenance(root)["seed"].tolist()
        assert seeds == sorted(seeds) and seeds[0] == first

    rerun = subprocess.run(cmd, env=ENV, capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    prov, state = read_provenance(root), read_recording_state(root)
    assert len(prov) == 6 == state["counters"]["saved"] and prov["seed"].tolist() == sorted(prov["seed"])
    c = state["counters"]
    assert state["played_to"] == prov["seed"].max() + 1
    assert c["attempted"] == state["played_to"] - first == c["saved"] + c["failed"], "a seed unplayed or played twice"


def test_a_shard_of_another_recording_or_task_contract_cannot_join(tmp_path):
    """A shard recorded with other arguments, or under another task contract, is refused before LeRobot merges
    anything, the difference named; the dataset stays as it was."""
    from vla_ladder.contract import EPISODE_STEPS
    from vla_ladder.files import write_json
    from vla_ladder.recordings import RECORDING_FILE

    root = tmp_path / "ds"
    main = DatasetStore(root, Recording(**CONFIG), commit_every=1)
    own = _fill(main, 1)
    other = DatasetStore(main.shard(1), Recording(**{**CONFIG, "robot_mesh": "full"}), commit_every=1, seeds_from=1)
    _fill(other, 1)
    other.close()
    with pytest.raises(ValueError, match=r"shard .*0000000001 was recorded with robot_mesh='full' \(this command: "
                                         r"'lite'\); it cannot join"):
        main.settle(5)
    shutil.rmtree(main.shard(1))
    same = DatasetStore(main.shard(1), Recording(**CONFIG), commit_every=1, seeds_from=1)
    _fill(same, 1)
    same.close()
    state = read_recording_state(main.shard(1))
    write_json(main.shard(1) / RECORDING_FILE,
               {**state, "contract": {**state["contract"], "episode_steps": 2 * EPISODE_STEPS}})
    with pytest.raises(ValueError, match=rf"shard .*0000000001 was recorded under another task contract \(episode_"
                                         rf"steps was {2 * EPISODE_STEPS}, now {EPISODE_STEPS}\); it cannot join"):
        main.settle(5)
    main.close()
    assert sorted(read_provenance(root)["seed"]) == sorted(own)


class _SyntheticSimulator:
    """The server's simulator without physics: every seed a successful episode of a seed-coloured picture, but the
    seeds in `fail`, whose simulation raises (the server closes the connection with 1011, simulation failed), and
    those in `unsuccessful`, episodes the expert failed."""

    object_set = "standin"

    def __init__(self, fail: set[int] = frozenset(), unsuccessful: set[int] = frozenset()):
        self.fail, self.unsuccessful = fail, unsuccessful

    def run(self, seeds: list[int]):
        from vla_ladder.contract import EPISODE_STEPS
        from vla_ladder.recording.server import EpisodeResult

        out = []
        for seed in seeds:
            if seed in self.fail:
                raise RuntimeError(f"the simulation of seed {seed} failed")
            episode = synthetic_episode(seed, EPISODE_STEPS)
            header = {**episode.header, "type": "episode", "sim_seconds": 0.0, "sim_backend": "physx_cpu",
                      "replayable": True}
            if seed in self.unsuccessful:
                header["metrics"] = {**header["metrics"], "success": False, "lifted": False, "held": "none"}
            arrays = {**{f"images.{c}": episode.images[c] for c in ("hand_camera", "fixed_camera")},
                      "state": episode.state, "action": episode.action}
            out.append(EpisodeResult(seed, header, arrays))
        return out

    def close(self) -> None:
        pass


def _synthetic_server(**simulated):
    """A real episode server (protocol, limits, close codes) whose simulator is _SyntheticSimulator(**simulated)."""
    from vla_ladder.conditions import Condition
    from vla_ladder.recording.server import EpisodeServer, ServeConfig

    server = EpisodeServer(ServeConfig(condition=Condition("small_jitter", "canonical", 2), port=0))
    server._build = lambda: setattr(server, "_sim", _SyntheticSimulator(**simulated))
    return server


@pytest.mark.slow
def test_writers_finish_when_a_block_ends_in_a_seed_the_servers_failed(tmp_path):
    """Seed 3's simulation fails on every server: one writer gives it up and records seeds 0, 1, 2 and 4; so do two
    writers, where seed 3 ends the block [2, 4). That block was never played to its end, so the ledger counted on a
    demo from seed 3 and handed out no other block: both writers waited for ever ('3/4 saved')."""
    import subprocess

    from test_reconnect import LoopThread
    from test_recording import ENV, _cli

    # Two writers of two servers each: one failing server ends a writer.
    servers = [_synthetic_server(fail={3}) for _ in range(4)]
    with contextlib.ExitStack() as stack:
        urls = [stack.enter_context(LoopThread(s.serve)).url for s in servers]
        for writers, out in (("2", tmp_path / "two"), ("1", tmp_path / "one")):
            r = subprocess.run(_cli("record", "--episodes", "4", "--writers", writers, "--first-seed", "0",
                                    "--encoder-threads", "1", "--out", str(out), "--server", *urls), env=ENV,
                               capture_output=True, text=True, timeout=300)
            assert r.returncode == 0, r.stderr[-3000:]
            assert read_provenance(out)["seed"].tolist() == [0, 1, 2, 4], writers
            assert read_recording_state(out)["counters"]["saved"] == 4


def test_a_recording_whose_seeds_run_out_keeps_every_episode_in_flight(tmp_path):
    """Near seed 2**32 a recording can run out of seeds before it has its demos: it ends with 'no seeds left' (exit 1)
    once the episodes it had asked for have come, and keeps them (it stopped at once, losing those in flight: a
    rerun of the same command then found more)."""
    import subprocess

    from test_reconnect import LoopThread
    from test_recording import ENV, _cli

    first = 2**32 - 4
    with LoopThread(_synthetic_server(unsuccessful={first + 1}).serve) as running:
        r = subprocess.run(_cli("record", "--episodes", "4", "--first-seed", str(first), "--encoder-threads", "1",
                                "--out", str(tmp_path / "d"), "--server", running.url), env=ENV, capture_output=True,
                           text=True, timeout=300)
    assert r.returncode == 1 and "no seeds left: the recording has used every seed" in r.stderr, r.stderr[-3000:]
    assert "rerun the same command" not in r.stderr
    assert read_provenance(tmp_path / "d")["seed"].tolist() == [first, first + 2, first + 3]
    counters = read_recording_state(tmp_path / "d")["counters"]
    assert (counters["saved"], counters["attempted"], counters["failed"]) == (3, 4, 1)
