"""The recording pipeline for real: `vla-ladder serve` and `vla-ladder record` processes on 127.0.0.1, the
scripted expert in GraspObject-v1 with both cameras rendered, a LeRobotDataset v3 on disk.

Rendering runs at a few steps/s on CPU, so the tests share two recordings: one dataset recorded through the
embedded server (killed with SIGKILL after its first commit, then resumed), and one token-protected lazy
server that first turns away bad clients and is then killed in the middle of an episode."""

from __future__ import annotations

import json
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from vla_ladder.cli import main
from vla_ladder.contract import EPISODE_STEPS, IMAGE_SHAPE
from vla_ladder.recording import protocol as P
from vla_ladder.recording.client import Episode
from vla_ladder.recordings import read_provenance, read_recording_state

pytestmark = pytest.mark.slow  # the real simulator, rendering, recording or training

TOKEN = "s3cret"
EPISODES = 3
SEED = 100
CONDITION = ["--regime", "small_jitter", "--num-objects", "2"]
ENV = {**os.environ, "SVT_LOG": "1", "PYTHONUNBUFFERED": "1"}


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "vla_ladder.cli", *args]


def _wait_for(predicate, timeout: float, what: str, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"process exited ({proc.returncode}) while waiting for {what}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.5)


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _children(pid: int) -> list[int]:
    return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def _kill_when(cmd: list[str], ready, what: str) -> list[int]:
    """Start `cmd`, SIGKILL it once `ready()` holds; returns the pids its children had then."""
    proc = subprocess.Popen(cmd, env=ENV)
    try:
        _wait_for(ready, 900, what, proc)
        children = _children(proc.pid)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        proc.kill()
    return children


def _saved(root: Path) -> int:
    state = read_recording_state(root) if root.exists() else None
    return state["counters"]["saved"] if state else 0


def _load(root: Path, **kwargs):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    return LeRobotDataset("vla-ladder/test", root=root, **kwargs)


# ---------------------------------------------------------------------- recording with a kill and a resume
@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """`record` (embedded server) killed by SIGKILL after its first commit, checked, then rerun to the end."""
    root = tmp_path_factory.mktemp("rec") / "grasp"
    cmd = _cli("record", *CONDITION, "--episodes", str(EPISODES), "--out", str(root), "--first-seed", str(SEED),
               "--commit-every", "1")
    server_pids = _kill_when(cmd, lambda: _saved(root) >= 1, "the first commit")
    # The embedded server notices its parent is gone (stdin closes) and exits by itself.
    _wait_for(lambda: not any(_alive(p) for p in server_pids), 30, "the orphaned server to exit")
    after_kill = {"saved": _saved(root), "dataset": len(_load(root)), "seeds": set(read_provenance(root)["seed"])}
    assert main(cmd[3:]) == 0  # the same command, in this process (LeRobot is imported here already)
    return root, after_kill


def test_killed_writer_leaves_a_loadable_dataset_and_resumes(recorded):
    root, after_kill = recorded
    assert 1 <= after_kill["saved"] < EPISODES + 1
    assert after_kill["dataset"] == EPISODE_STEPS * after_kill["saved"]  # whole episodes only
    ds = _load(root)
    assert ds.meta.total_episodes == EPISODES and len(ds) == EPISODE_STEPS * EPISODES
    prov = read_provenance(root)
    assert prov["episode_index"].tolist() == list(range(EPISODES))
    assert after_kill["seeds"] <= set(prov["seed"]), "an episode reported saved was lost"
    assert prov["seed"].is_unique and prov["seed"].min() >= SEED
    new = set(prov["seed"]) - after_kill["seeds"]
    assert min(new) > max(after_kill["seeds"]), "the resumed run replayed seeds of the killed one"
    state = read_recording_state(root)
    assert state["counters"]["saved"] == EPISODES and state["next_seed"] > prov["seed"].max()
    # Every seed below where the recording ends was played once, none skipped: those in flight at the kill (never
    # written) were played again, so the dataset is the one recorded in one go.
    assert state["played_to"] == prov["seed"].max() + 1
    assert state["counters"]["attempted"] == state["played_to"] - SEED
    assert state["counters"]["failed"] == state["counters"]["attempted"] - EPISODES
    assert not (root.parent / f".{root.name}.recording" / "staging").exists()


def test_dataset_format_and_contents(recorded):
    root, _ = recorded
    ds = _load(root)
    info = ds.meta.info
    assert ds.meta.robot_type == "panda" and ds.fps == 20
    for cam in ("hand_camera", "fixed_camera"):
        feat = ds.features[f"observation.images.{cam}"]
        assert feat["dtype"] == "video" and tuple(feat["shape"]) == IMAGE_SHAPE
    assert ds.features["observation.state"]["dtype"] == "float32"
    assert tuple(ds.features["observation.state"]["shape"]) == (15,)
    assert tuple(ds.features["action"]["shape"]) == (7,) and info.total_frames == EPISODE_STEPS * EPISODES
    prov = read_provenance(root)
    assert prov["success"].all(), "a failed episode was written"
    # In seed order, as many local servers as cores (two on CI) and a resume notwithstanding.
    assert prov["seed"].is_monotonic_increasing and prov["seed"].is_unique
    for _, row in prov.iterrows():
        layout = json.loads(row["layout"])
        assert layout["seed"] == row["seed"] and layout["target"] == row["target"]
        assert layout["instruction"] == row["instruction"] and row["held"] == row["target"]
        assert row["regime"] == "small_jitter" and row["num_objects"] == 2 and row["policy"] == "scripted"
        assert json.loads(row["expert"])["name"] == "scripted" and row["object_set"] == "standin"
        for frame_index in (0, EPISODE_STEPS - 1):
            item = ds[int(row["episode_index"]) * EPISODE_STEPS + frame_index]
            assert item["task"] == row["instruction"]
            assert item["episode_index"].item() == row["episode_index"]
            for cam in ("hand_camera", "fixed_camera"):
                img = item[f"observation.images.{cam}"]
                assert img.shape == (IMAGE_SHAPE[2], *IMAGE_SHAPE[:2]) and img.dtype.is_floating_point
                assert 0.05 < img.mean() < 0.95 and img.std() > 0.05, f"{cam} looks blank"
            assert item["observation.state"].shape == (15,) and item["action"].shape == (7,)
            assert item["action"].abs().max() <= 1.0 + 1e-6
    tasks = ds.meta.episodes.to_pandas()["tasks"].map(lambda t: list(t))
    assert tasks.tolist() == [[i] for i in prov["instruction"]]


def test_recorded_seeds_replay_bit_for_bit(recorded, make_env):
    """Provenance is exact, and so is the physics: `record` rebuilds every scene, so a recorded seed replayed with
    the expert (state only, no cameras, another process) gives back every recorded state to the last bit, and the
    same success."""
    import torch

    from vla_ladder.policies import load_policy

    root, _ = recorded
    ds = _load(root)
    prov = read_provenance(root)
    assert prov["replayable"].all() and (prov["sim_backend"] == "physx_cpu").all()
    assert f"{EPISODES} of the {EPISODES} episodes were simulated on a scene rebuilt for them" in (
        root / "README.md").read_text()
    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=2)
    expert = load_policy("scripted")
    frames = ds.hf_dataset.with_format("numpy")
    for _, row in prov.iterrows():
        obs, _ = env.reset(seed=int(row["seed"]))
        expert.reset([int(row["seed"])])
        assert env.unwrapped.instructions == [row["instruction"]]
        first = int(row["episode_index"]) * EPISODE_STEPS
        recorded_states = frames[first:first + EPISODE_STEPS]["observation.state"]
        states = []
        for _ in range(EPISODE_STEPS):
            states.append(obs["extra"]["proprio"][0].numpy())
            obs, _, _, _, info = env.step(expert.act(obs, env.unwrapped.instructions).to(torch.float32))
        np.testing.assert_array_equal(np.stack(states), recorded_states)
        assert bool(info["success"][0])


def test_lerobot_policy_trains_on_the_recording(recorded):
    """One ACT training step through LeRobot's own dataloader and processors: the format is right."""
    import torch
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    root, _ = recorded
    meta = _load(root).meta
    cfg = ACTConfig(device="cpu", push_to_hub=False, pretrained_backbone_weights=None, dim_model=32, n_heads=2,
                    dim_feedforward=64, n_encoder_layers=1, n_decoder_layers=1, use_vae=False, chunk_size=4,
                    n_action_steps=4)
    policy = make_policy(cfg, ds_meta=meta)
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    ds = _load(root, delta_timestamps=resolve_delta_timestamps(cfg, meta))
    loader = torch.utils.data.DataLoader(ds, batch_size=4, shuffle=True, num_workers=0)
    batch = pre(next(iter(loader)))
    assert batch["action"].shape == (4, 4, 7)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-4)
    loss, _ = policy.forward(batch)
    loss.backward()
    optimizer.step()
    assert torch.isfinite(loss)


# ---------------------------------------------------------------------- protocol against a real server
@pytest.fixture(scope="module")
def server():
    """A token-protected server for two clients at most that builds its simulator only when an episode is first
    requested, and reuses its scene between episodes."""
    proc = subprocess.Popen(_cli("serve", *CONDITION, "--port", "0", "--token", TOKEN, "--lazy", "--max-clients", "2",
                                 "--exit-on-stdin-close", "--no-rebuild-scenes"),
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=ENV)
    line = proc.stdout.readline()
    assert line.startswith("listening on ws://127.0.0.1:"), line
    yield proc, line.split()[-1]
    proc.kill()
    proc.wait()


def _closed_by_server(url: str, *messages) -> tuple[int, str]:
    """Send messages, read until the server closes; returns its close code and reason."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    with connect(url, max_size=P.MAX_EPISODE_MESSAGE, compression=None) as ws:
        try:
            for m in messages:
                ws.send(m)
            while True:
                ws.recv(timeout=30)
        except ConnectionClosed as e:
            assert e.rcvd is not None, "the server dropped the connection without a close frame"
            return e.rcvd.code, e.rcvd.reason
    raise AssertionError("unreachable")


def _raw(header: dict, payload: bytes = b"") -> bytes:
    """A message built by hand, bypassing the checks of protocol.encode."""
    packed = msgpack.packb(header)
    return struct.pack("<I", len(packed)) + packed + payload


GOOD_HELLO = P.hello(TOKEN, P.MAX_EPISODE_MESSAGE)
BAD_CLIENTS = {
    "wrong protocol version": ([P.hello(TOKEN, P.MAX_EPISODE_MESSAGE, version=99)], P.CLOSE_VERSION, "version 99"),
    "wrong token": ([P.hello("guess", P.MAX_EPISODE_MESSAGE)], P.CLOSE_UNAUTHORISED, "unauthorised"),
    "no token": ([P.hello(None, P.MAX_EPISODE_MESSAGE)], P.CLOSE_UNAUTHORISED, "unauthorised"),
    "not msgpack": ([b"\x05\x00\x00\x00\xc1garbage"], P.CLOSE_MALFORMED, "msgpack"),
    "truncated": ([GOOD_HELLO[:9]], P.CLOSE_MALFORMED, "header length"),
    "text frame": (["hello"], P.CLOSE_MALFORMED, "text frames"),
    "object dtype": ([_raw({"type": "hello", "arrays": [["x", "object", [1]]]}, b"\x00" * 8)], P.CLOSE_MALFORMED,
                     "not allowed"),
    "shape whose product overflows int64": ([_raw({"type": "hello", "arrays": [["x", "uint8", [65536] * 4]]})],
                                            P.CLOSE_MALFORMED, "runs past the end"),
    # numpy's errors on these ended the connection without a reason, as if the client had gone.
    "bool in a shape": ([_raw({"type": "hello", "arrays": [["x", "uint8", [True]]]}, b"\x00")], P.CLOSE_MALFORMED,
                        "bad shape"),
    "empty array of huge sides": ([_raw({"type": "hello", "arrays": [["x", "uint8", [0] + [2**31 - 1] * 7]]})],
                                  P.CLOSE_MALFORMED, "not allowed"),
    "oversized message": ([b"\x00" * (P.MAX_CLIENT_MESSAGE + 1)], P.CLOSE_TOO_BIG, ""),
    "run before hello": ([P.run([1])], P.CLOSE_UNEXPECTED, "expected 'hello'"),
    "client max_size too small": ([P.hello(TOKEN, 1000)], P.CLOSE_LIMIT, "accepts 1000"),
    "malformed seeds": ([GOOD_HELLO, P.encode({"type": "run", "seeds": ["a"]})], P.CLOSE_MALFORMED, "integers"),
    # A numpy seed: the simulator refuses 2**32, which used to end the connection as the server's own failure.
    "seed beyond 2**32": ([GOOD_HELLO, P.encode({"type": "run", "seeds": [2**32]})], P.CLOSE_MALFORMED,
                          "[0, 4294967295]"),
    "too many outstanding": ([GOOD_HELLO, P.run(list(range(9)))], P.CLOSE_LIMIT, "outstanding"),
    "unknown message": ([GOOD_HELLO, P.encode({"type": "dance"})], P.CLOSE_UNEXPECTED, "'dance'"),
    "failed_frames not a bool": ([GOOD_HELLO, P.encode({"type": "run", "seeds": [1], "failed_frames": "no"})],
                                 P.CLOSE_MALFORMED, "'failed_frames' not bool"),
}


@pytest.mark.parametrize("case", list(BAD_CLIENTS))
def test_bad_clients_are_closed_with_a_reason(server, case):
    messages, code, reason = BAD_CLIENTS[case]
    got_code, got_reason = _closed_by_server(server[1], *messages)
    assert got_code == code and reason in got_reason, (got_code, got_reason)


def test_a_server_at_its_max_clients_refuses_more_until_one_leaves(server):
    """Two clients connected (handshake done), a third is refused before its handshake with HTTP 503, which the
    client takes for a busy server to retry, not a refusal for good; once one leaves, it gets in."""
    import asyncio

    from vla_ladder.recording.client import EpisodeClient, ServerError

    async def third_client(url: str) -> ServerError:
        first, second, third = (EpisodeClient(url, TOKEN) for _ in range(3))
        await first.connect()
        await second.connect()
        with pytest.raises(ServerError) as refused:
            await third.connect()
        await first.close()
        deadline = time.monotonic() + 30
        while True:  # the server counts a connection out once its close is done
            try:
                welcome = await third.connect()
                break
            except ServerError:
                assert time.monotonic() < deadline, "still refused after a client left"
                await asyncio.sleep(0.2)
        assert welcome["limits"]["max_outstanding"] >= 1
        await second.close()
        await third.close()
        return refused.value

    error = asyncio.run(third_client(server[1]))
    assert "refused the connection (HTTP 503: serving 2 clients already (its --max-clients)" in str(error), error
    assert not error.permanent


def test_malformed_episode_frames_are_rejected_by_the_client():
    frames = {"images.hand_camera": np.zeros((50, 256, 256, 3), np.uint8),
              "images.fixed_camera": np.zeros((50, 128, 128, 3), np.uint8),
              "state": np.zeros((50, 15), np.float32), "action": np.zeros((50, 7), np.float32)}
    metrics = {"success": True, "grasp_any": True, "reach": True, "lifted": False, "held": "apple", "reach_dist": 0.0}
    header = {"type": "episode", "seed": 1, "instruction": "grasp the apple", "target": "apple", "layout": {},
              "metrics": metrics, "expert": {"spec": "scripted"}, "condition": "small_jitter/canonical/2",
              "object_set": "standin", "num_frames": 50, "has_frames": True}
    with pytest.raises(P.ProtocolError, match="images.fixed_camera"):
        Episode.from_message(P.decode(P.encode(header, frames)), "test")
    # Every header field the writer uses is checked on arrival: a KeyError there lost the uncommitted batch, and a
    # success without frames was counted as a demo that never came (the recorder waited forever).
    for edit, words in (({"num_frames": "50"}, "num_frames"), ({"num_frames": 49}, "49 frames"),
                        ({"metrics": {k: v for k, v in metrics.items() if k != "grasp_any"}}, "grasp_any"),
                        ({"expert": {}}, "expert['spec']"), ({"target": None}, "'target'"),
                        ({"condition": "small_jitter/canonical/9"}, "num_objects"),
                        ({"has_frames": False}, "a successful episode sent without its frames"),
                        ({"layout": {"positions": b"\x00"}}, "layout is not JSON"),
                        ({"expert": {"spec": "scripted", "weights": b"\x00"}}, "expert is not JSON")):
        with pytest.raises(P.ProtocolError, match=re.escape(words)):
            Episode.from_message(P.decode(P.encode({**header, **edit}, {})), "test")
    failed = Episode.from_message(P.decode(P.encode({**header, "metrics": {**metrics, "success": False},
                                                     "has_frames": False})), "test")
    assert not failed.success and not failed.has_frames
    # A close frame carries at most 123 bytes: a reason cut by characters was refused ("control frame too long") and
    # the malformed episode taken for a lost connection.
    reason = P.ProtocolError("condition " + "é" * 100).close_reason
    assert len(reason.encode()) <= 123 and reason.startswith("condition é")


def test_record_refuses_a_server_that_serves_no_expert_or_does_not_say_what_it_serves(tmp_path, capsys):
    """A server's welcome names the expert the dataset records: a reference policy is refused as `record --policy`
    refuses it (it was recorded as the expert), and a welcome without it is one line, not a KeyError."""
    import functools

    from test_reconnect import LoopThread, _greeting_server

    limits = {"max_outstanding": 8, "max_seeds_per_request": 16}
    for serves, words in (({"policy": "random", "condition": "small_jitter/canonical/2", "num_envs": 1},
                           "serves 'random', which is not an expert; allowed: scripted, ppo:PATH"),
                          ({"condition": "small_jitter/canonical/2"}, "its welcome does not say what it serves")):
        with LoopThread(functools.partial(_greeting_server, serves=serves, limits=limits)) as greeter:
            assert main(["record", "--episodes", "1", "--out", str(tmp_path / "d"), "--server", greeter.url]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "d").exists()


def test_server_dropped_mid_episode_leaves_no_partial_episode(server, recorded, capsys):
    """After the bad clients, the server still serves `record`; killed while simulating the next episode, the
    recorder stops with an error and the dataset holds exactly the whole episodes it had committed."""
    proc, url = server
    root, _ = recorded
    before = read_provenance(root)
    # The local server's options given with --server must be what the server serves (they were ignored).
    for flag, value, served in (("--robot-mesh", "full", "lite"), ("--instructions", "paraphrase-train", "canonical")):
        assert main(["record", *CONDITION, "--episodes", "99", "--out", str(root), "--server", url, "--token", TOKEN,
                     flag, value]) == 2
        err = capsys.readouterr().err
        assert f"serves {flag[2:]} {served!r} but the command asks for {value!r}; drop {flag}" in err, err
    assert read_provenance(root).equals(before)

    def kill_server_mid_episode():
        _wait_for(lambda: _saved(root) >= EPISODES + 1, 900, "an episode from the server", proc)
        time.sleep(1)  # inside the next episode (each takes ~3 s to simulate and render)
        proc.send_signal(signal.SIGKILL)

    killer = threading.Thread(target=kill_server_mid_episode)
    killer.start()
    rc = main(["record", *CONDITION, "--episodes", str(EPISODES + 3), "--out", str(root), "--first-seed", str(SEED),
               "--commit-every", "1", "--server", url, "--token", TOKEN])
    killer.join()
    assert rc == 1 and "server closed the connection" in capsys.readouterr().err
    ds = _load(root)
    prov = read_provenance(root)
    n = ds.meta.total_episodes
    assert n >= EPISODES + 1 and len(ds) == EPISODE_STEPS * n and len(prov) == n
    assert prov.iloc[:len(before)].equals(before) and prov["seed"].is_unique and prov["success"].all()
    # Its episodes were simulated on a reused scene: the dataset says they do not promise a bit-exact replay.
    assert before["replayable"].all() and not prov["replayable"].iloc[len(before):].any()


def test_a_ctrl_c_at_the_terminal_is_the_recorders_alone_to_act_on(tmp_path):
    """Local servers run in a session of their own: a Ctrl-C sent to the recorder's process group reaches the
    recorder alone, which decides when they stop. A recorder that ignores SIGINT (`record ... &` in a script, or
    nohup) records on to the end; its servers used to die of that Ctrl-C and the recording stopped short."""
    root = tmp_path / "grasp"
    log = tmp_path / "record.log"
    cmd = _cli("record", *CONDITION, "--episodes", "8", "--out", str(root), "--workers", "2")
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, env=ENV, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
        try:
            _wait_for(lambda: "progress:" in log.read_text(), 900, "the first episode", proc)
            servers = _children(proc.pid)
            assert len(servers) == 2
            os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does to its foreground group
            assert proc.wait(timeout=900) == 0, log.read_text()
        finally:
            proc.kill()
    text = log.read_text()
    assert _saved(root) == 8 and "reconnecting" not in text and "connection lost" not in text, text
    _wait_for(lambda: not any(_alive(p) for p in servers), 30, "the servers to exit")


def test_a_recording_starts_far_from_the_evaluation_seeds_and_resumes_at_its_own(tmp_path):
    """record, eval and the grid all began at seed 0, and a seed is a scene: a model recorded and evaluated with
    the defaults was scored on its own demonstrations. A new recording starts at RECORD_FIRST_SEED; one resumed
    without --first-seed goes on from the seed it was recorded from (an older recording's 0)."""
    from vla_ladder.conditions import Condition
    from vla_ladder.files import write_json
    from vla_ladder.recording.record import RecordConfig
    from vla_ladder.recordings import FORMAT_VERSION, RECORD_FIRST_SEED, RECORDING_FILE, Recording

    assert RecordConfig(out=tmp_path / "new", episodes=10).first_seed == RECORD_FIRST_SEED == 1_000_000
    old = tmp_path / "old"
    state = {"format": FORMAT_VERSION, "config": Recording("scripted", Condition("small_jitter"), 0).to_dict(),
             "counters": {"saved": 0, "attempted": 0, "failed": 0, "commits": 0}, "next_seed": 0}
    write_json(old / RECORDING_FILE, state)
    assert RecordConfig(out=old, episodes=10).first_seed == 0
    assert RecordConfig(out=old, episodes=10, first_seed=5).first_seed == 5  # given: as given (and refused later)
