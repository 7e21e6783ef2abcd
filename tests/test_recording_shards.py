"""Parallel writers: a seed book shared by processes hands every seed out once, shards written by separate
DatasetStores merge into the dataset with LeRobot's aggregate_datasets (episodes, frames, videos and
provenance in step; atomic; never merged twice), and `record --writers 2` does it all with real servers."""

from __future__ import annotations

import contextlib
import multiprocessing
import shutil
from pathlib import Path

import numpy as np
import pytest

from vla_ladder.recording.store import DatasetStore, SeedBook
from vla_ladder.recordings import Recording, read_provenance, read_recording_state
from test_recording_store import CONFIG, synthetic_episode

FRAMES = 12


def _reserve_many(path: str, blocks: int, queue) -> None:
    book = SeedBook(Path(path), Recording(**CONFIG), floor=0)
    queue.put([s for _ in range(blocks) for s in book.reserve(3)])


def test_seed_book_hands_each_seed_out_once_across_processes(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_reserve_many, args=(str(tmp_path / "seeds.json"), 40, queue)) for _ in range(4)]
    for p in procs:
        p.start()
    seeds = [s for _ in procs for s in queue.get(timeout=120)]
    for p in procs:
        p.join()
    assert sorted(seeds) == list(range(4 * 40 * 3)), "a seed was handed out twice or skipped"
    book = SeedBook(tmp_path / "seeds.json", Recording(**CONFIG), floor=1000)
    assert book.reserve(2) == [1000, 1001], "the floor (seeds a committed dataset used) comes first"
    other = SeedBook(tmp_path / "seeds.json", Recording(**{**CONFIG, "video": False}), floor=5)
    assert other.next_seed == 5, "a book kept for another recording says nothing about this one"


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
def test_a_shard_of_several_commits_merges_into_a_dataset_that_merges_and_resumes_again(tmp_path):
    """A shard committed in three batches has three meta/episodes files; merged into an empty dataset they become
    one, whose rows must name that file (LeRobot's aggregate kept the shard's file indices 1 and 2, and the next
    merge failed on meta/episodes/chunk-000/file-001.parquet, as a killed two-writer recording did in CI)."""
    import pandas as pd

    root = tmp_path / "ds"
    main = DatasetStore(root, Recording(**CONFIG), commit_every=1)

    def shard(name: str, n: int) -> Path:
        store = DatasetStore(main.shards_dir / name, Recording(**CONFIG), commit_every=1, seed_book=main.seeds.path)
        written.extend(_fill(store, n))
        store.close()
        return main.shards_dir / name

    written: list[int] = []
    first = shard("a", 3)
    assert len(list((first / "meta/episodes").glob("*/*.parquet"))) == 3
    main.merge([first])
    main.close()
    for path in (root / "meta/episodes").glob("chunk-*/file-*.parquet"):
        meta = pd.read_parquet(path)
        assert (meta["meta/episodes/file_index"] == int(path.stem.split("-")[1])).all(), path
    main = DatasetStore(root, Recording(**CONFIG), commit_every=1)
    main.merge([shard("b", 1), shard("c", 1)])
    resumed = _fill(main, 1)  # and a single writer resumes it
    main.close()
    _check_dataset(root, written + resumed)


def test_shards_merge_after_the_dataset_and_resume(tmp_path):
    root = tmp_path / "ds"
    main = DatasetStore(root, Recording(**CONFIG), commit_every=2)
    own = _fill(main, 2)
    shards = [main.shards_dir / "a", main.shards_dir / "b"]
    written = []
    for shard, n in zip(shards, (3, 2)):
        store = DatasetStore(shard, Recording(**CONFIG), commit_every=2, seed_book=main.seeds.path)
        written.append(_fill(store, n))
        store.close()
    assert not set(written[0]) & set(written[1]) and min(written[0]) > max(own)
    assert main.unmerged_shards() == shards
    counted = [read_recording_state(s)["counters"] for s in [root, *shards]]

    # Killed before the swap: the dataset is as it was and the shards are merged by the next try.
    import vla_ladder.recording.store as store_module

    real_exchange = store_module._exchange

    def killed(a, b):
        raise KeyboardInterrupt

    store_module._exchange = killed
    try:
        with pytest.raises(KeyboardInterrupt):
            main.merge(shards)
    finally:
        store_module._exchange = real_exchange
    _check_dataset(root, own)
    assert main.unmerged_shards() == shards
    main.saved = read_recording_state(root)["counters"]["saved"]
    main.counters = dict(read_recording_state(root)["counters"])
    main.merge(shards)
    main.close()
    _check_dataset(root, own + written[0] + written[1])
    counters = read_recording_state(root)["counters"]
    for key in ("attempted", "failed", "saved"):
        assert counters[key] == sum(c[key] for c in counted), key
    assert not any(s.exists() for s in shards)

    # A shard found again after its merge (killed between the swap and the clean-up) is not merged twice.
    shutil.copytree(root, shards[0])
    store = DatasetStore(root, Recording(**CONFIG), commit_every=1)
    assert not shards[0].exists() and store.unmerged_shards() == []
    # A single writer resumes the merged dataset.
    more = _fill(store, 1)
    store.close()
    assert more[0] > max(written[0] + written[1])
    _check_dataset(root, own + written[0] + written[1] + more)


@pytest.mark.slow
def test_record_with_two_writers_killed_then_rerun(tmp_path):
    """`record --writers 2` (real servers, real writer processes) killed by SIGKILL once a shard committed: the
    writers commit and exit, nothing reaches the dataset half-merged; the same command merges what they left and
    records the rest. Every episode is whole and every seed played once. In H.264 (`--vcodec h264`): the writers
    are told the codec and LeRobot's merge concatenates their H.264 files."""
    import subprocess

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
                if "--seed-book" in argv and any(a.startswith(str(shards)) for a in argv):
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
    assert f"merging the {n_left} shards a stopped recording left" in rerun.stderr
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


def test_a_shard_of_another_recording_or_task_contract_cannot_join(tmp_path):
    """A shard recorded with other arguments, or under another task contract, is refused before LeRobot merges
    anything, the difference named; the dataset stays as it was."""
    from vla_ladder.contract import EPISODE_STEPS
    from vla_ladder.files import write_json
    from vla_ladder.recordings import RECORDING_FILE

    root = tmp_path / "ds"
    main = DatasetStore(root, Recording(**CONFIG), commit_every=1)
    own = _fill(main, 1)
    other = DatasetStore(main.shards_dir / "other", Recording(**{**CONFIG, "robot_mesh": "full"}), commit_every=1,
                         seed_book=main.seeds.path)
    _fill(other, 1)
    other.close()
    with pytest.raises(ValueError, match=r"shard .*other was recorded with robot_mesh='full' \(this command: 'lite'\); "
                                         r"it cannot join"):
        main.merge([main.shards_dir / "other"])
    same = DatasetStore(main.shards_dir / "same", Recording(**CONFIG), commit_every=1, seed_book=main.seeds.path)
    _fill(same, 1)
    same.close()
    state = read_recording_state(main.shards_dir / "same")
    write_json(main.shards_dir / "same" / RECORDING_FILE,
               {**state, "contract": {**state["contract"], "episode_steps": 2 * EPISODE_STEPS}})
    with pytest.raises(ValueError, match=rf"shard .*same was recorded under another task contract \(episode_steps "
                                         rf"was {2 * EPISODE_STEPS}, now {EPISODE_STEPS}\); it cannot join"):
        main.merge([main.shards_dir / "same"])
    main.close()
    assert sorted(read_provenance(root)["seed"]) == sorted(own)
