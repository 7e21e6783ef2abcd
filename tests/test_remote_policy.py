"""`--policy remote:URL` and `vla-ladder serve-policy`: openpi's policy-server protocol over a real loopback WebSocket,
a real LeRobot checkpoint served by a real `vla-ladder serve-policy` process, episodes in the real simulator."""

import contextlib
import json
import os
import pickle
import re
import subprocess
import sys
import time
import urllib.error
import urllib.request

import msgpack
import numpy as np
import pandas as pd
import pytest

import lerobot_helpers as H
from vla_ladder.cli import main
from vla_ladder.contract import CAMERAS, CONTROL_HZ, STATE_KEY, policy_fingerprint
from vla_ladder.policies.remote import (CHUNK_KEY, CONTRACT_KEY, MAX_MESSAGE, PROMPT_KEY, SEED_KEY, WINDOW_KEY, pack,
                                        parse_arg, unpack)
from vla_ladder.policies.serving import check_servable, read_request

KEY = "k3y"
EVAL = ["--regimes", "small_jitter", "--num-objects", "2", "--episodes", "2", "--first-seed", "7", "--workers", "1"]


# ---------------------------------------------------------------------- the wire format
def _openpi_array(a: np.ndarray) -> dict:
    """An array as openpi's msgpack_numpy packs it, written out by hand."""
    return {b"__ndarray__": True, b"data": a.tobytes(), b"dtype": a.dtype.str, b"shape": list(a.shape)}


def test_messages_read_openpi_layout_and_refuse_anything_but_plain_arrays():
    chunk = np.arange(14, dtype=np.float32).reshape(2, 7)
    openpi = msgpack.packb({"actions": _openpi_array(chunk), "n": 3}, use_bin_type=True)
    got = unpack(openpi)
    assert got["n"] == 3 and got["actions"].dtype == np.float32
    np.testing.assert_array_equal(got["actions"], chunk)
    obs = {"img": np.zeros((4, 4, 3), np.uint8), "s": np.ones(15, np.float32), "t": "grasp the mug",
           "k": np.int64(5), "b": np.array([True, False]), "words": np.array(["a", "bc"])}
    back = unpack(pack(obs))
    for k, v in obs.items():
        if isinstance(v, np.ndarray):
            assert back[k].dtype == v.dtype and np.array_equal(back[k], v)
        else:
            assert back[k] == v and type(back[k]) is type(v)

    def bad(message: dict) -> bytes:
        return msgpack.packb(message, use_bin_type=True)

    with pytest.raises(ValueError, match="dtype object is not allowed"):
        unpack(bad({b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "|O", b"shape": [1]}))
    with pytest.raises(ValueError, match="dtype .*V8.* is not allowed"):
        unpack(bad({b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "|V8", b"shape": [1]}))
    with pytest.raises(ValueError, match="does not match its 8 bytes"):
        unpack(bad({b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "<f4", b"shape": [1000, 1000]}))
    with pytest.raises(ValueError, match="extension type 3 is not allowed"):
        unpack(msgpack.packb(msgpack.ExtType(3, b"x")))
    with pytest.raises(ValueError, match="not a msgpack message"):
        unpack(pack({"a": 1})[:-1])
    with pytest.raises(ValueError, match="not a msgpack message"):
        unpack(msgpack.packb([[]] * 5000))  # more entries than any message has
    # Many small containers, each within the entries' bound: 4 MiB of empty lists would be 280 MiB of Python objects.
    with pytest.raises(ValueError, match="more than 1024 lists and maps in one message"):
        unpack(msgpack.packb([[[]] * 4000] * 1000))
    with pytest.raises(ValueError, match="more than 1024 lists and maps in one message"):
        unpack(msgpack.packb({"junk": [{}] * 2000, "state": [0.0] * 15}))
    with pytest.raises(ValueError, match="expected a binary message"):
        unpack("text")
    with pytest.raises(ValueError, match="cannot send an array of dtype object"):
        pack({"a": np.array([object()])})


def test_requests_are_checked_before_inference():
    good = {c.key: np.zeros(c.shape, np.uint8) for c in CAMERAS}
    good.update({STATE_KEY: np.zeros(15, np.float32), PROMPT_KEY: "grasp the mug", SEED_KEY: 3, CHUNK_KEY: 0})
    obs, prompt, seed, chunk = read_request(good)
    assert obs["sensor_data"][CAMERAS[0].name]["rgb"].shape == (1, *CAMERAS[0].shape)
    assert obs["extra"]["proprio"].shape == (1, 15) and (prompt, seed, chunk) == ("grasp the mug", 3, 0)
    cam = CAMERAS[0].key
    for change, message in [({cam: np.zeros((224, 224, 3), np.uint8)}, f"{cam} must be a uint8 array of shape"),
                            ({cam: np.zeros(CAMERAS[0].shape, np.float32)}, "got float32"),
                            ({STATE_KEY: np.zeros(8, np.float32)}, r"must be a float array of shape \(15,\)"),
                            ({PROMPT_KEY: ""}, "must be the instruction"),
                            ({PROMPT_KEY: "x" * 1001}, "1-1000 characters"),
                            ({SEED_KEY: -1}, "come together, as integers in 0..4294967295"),
                            ({SEED_KEY: 2**32}, "come together, as integers in 0..4294967295"),
                            ({CHUNK_KEY: 2**32}, "come together, as integers in 0..4294967295"),
                            ({CHUNK_KEY: None}, "come together")]:
        with pytest.raises(ValueError, match=message):
            read_request({**good, **change})
    with pytest.raises(ValueError, match="a request is a map"):
        read_request([1, 2])
    with pytest.raises(ValueError, match="allowed types: smolvla, pi0, pi05, act"):
        check_servable("diffusion")
    with pytest.raises(ValueError, match="an act checkpoint with temporal_ensemble_coeff"):
        check_servable("act", 0.01)
    check_servable("act")


def test_bad_remote_specs_fail_in_one_line_before_work(tmp_path, capsys):
    out = tmp_path / "run"
    for spec, message in [("remote:ws://127.0.0.1:1", "no policy server answers at ws://127.0.0.1:1"),
                          ("remote:http://127.0.0.1:8000", "a remote policy is a WebSocket URL"),
                          ("remote:ws://127.0.0.1:1?horizon=3", "unknown option 'horizon' .*allowed: n_action_steps"),
                          ("remote:ws://127.0.0.1:1?n_action_steps=0", "expected an integer >= 1"),
                          # (the server refuses a prompt this long: it failed at the first request, in the run)
                          ("remote:ws://127.0.0.1:1?instruction=" + "grasp" * 201,
                           "an instruction has at most 1000 characters, got 1005"),
                          ("remote:ws://127.0.0.1:99999", "a remote policy is a WebSocket URL"),
                          ("remote:ws://[::1", "a remote policy is a WebSocket URL"),
                          ("remote:", "policy 'remote' needs a server: remote:URL")]:
        assert main(["eval", "--policy", spec, *EVAL, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and re.search(message, err), err
        assert not out.exists()
    assert main(["probe", "instruction-swap", "--policy", "remote:ws://127.0.0.1:1", "--episodes", "2",
                 "--out", str(out)]) == 2
    assert "no policy server answers" in capsys.readouterr().err and not out.exists()
    for argv, message in [(["--policy", "scripted"], "serve-policy serves LeRobot checkpoints"),
                          (["--policy", "lerobot:/nonexistent"], "no LeRobot checkpoint at '/nonexistent'"),
                          ([], "--policy lerobot:CHECKPOINT is required"),
                          (["--policy", "lerobot:/nonexistent", "--host", "0.0.0.0"], "needs --api-key"),
                          (["--policy", "lerobot:/nonexistent", "--port", "70000"], "port must be in 0..65535"),
                          (["--policy", "lerobot:/nonexistent", "--max-clients", "0"],
                           "--max-clients must be a positive integer, got 0")]:
        assert main(["serve-policy", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and message in err, err
    assert parse_arg("ws://h:1?n_action_steps=3&instruction=grasp the object") == (
        "ws://h:1", {"n_action_steps": 3, "instruction": "grasp the object"})


@contextlib.contextmanager
def metadata_server(metadata: dict):
    """The URL of a WebSocket server on loopback that sends `metadata` (read when each client connects, so a test may
    change it between connections) and nothing else."""
    import threading

    from websockets.sync.server import serve

    def server_side(ws):
        ws.send(pack(metadata))
        for _ in ws:
            pass

    with serve(server_side, "127.0.0.1", 0) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        yield f"ws://127.0.0.1:{server.socket.getsockname()[1]}"
        server.shutdown()


def test_a_server_that_does_not_name_a_horizon_needs_one(tmp_path, capsys):
    """openpi's servers send empty metadata: the horizon must then be given, not defaulted to the whole chunk."""
    from vla_ladder.policies.remote import check_server

    with metadata_server({}) as url:
        assert main(["eval", "--policy", f"remote:{url}", *EVAL, "--out", str(tmp_path / "run")]) == 2
        err = capsys.readouterr().err
        assert "does not say how many actions of a chunk to run" in err and f"remote:{url}?n_action_steps=H" in err
        assert not (tmp_path / "run").exists()
        check_server(f"{url}?n_action_steps=5")


def test_a_horizon_past_the_served_chunk_is_refused(tmp_path, capsys):
    """n_action_steps=1000 on a 16-step chunk ran the whole chunk while the run directory said 1000."""
    from vla_ladder.policies.remote import check_server

    with metadata_server({"server": "vla-ladder", "policy": {"chunk_size": 16}, "n_action_steps": 8}) as url:
        assert main(["eval", "--policy", f"remote:{url}?n_action_steps=17", *EVAL, "--out", str(tmp_path / "run")]) == 2
        err = capsys.readouterr().err.strip()
        assert f"n_action_steps must be from 1 to the chunk size of the policy served at {url} (16), got 17" in err
        assert len(err.splitlines()) == 1 and not (tmp_path / "run").exists()
        check_server(f"{url}?n_action_steps=16")


def test_a_loopback_policy_server_is_reached_directly_where_the_environment_names_a_proxy(monkeypatch):
    """websockets sends every connection through $https_proxy / $http_proxy unless no_proxy names the host: with a
    proxy set (a cluster's login node), `remote:ws://127.0.0.1:P` could not reach serve-policy on the same machine.
    A remote host still goes through the proxy (the environment's choice)."""
    from vla_ladder.checks import ws_proxy
    from vla_ladder.policies.remote import check_server

    for name in ("https_proxy", "http_proxy", "HTTPS_PROXY", "HTTP_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.setenv(name, "http://127.0.0.1:9")  # (the discard port: nothing listens there)
    for name in ("no_proxy", "NO_PROXY"):
        monkeypatch.delenv(name, raising=False)
    with metadata_server({"server": "vla-ladder", "n_action_steps": 2}) as url:
        check_server(url)
        check_server(url.replace("127.0.0.1", "localhost"))
    assert ws_proxy("ws://gpu-node.example:8000") is True and ws_proxy("ws://[::1]:8000") is None


def test_more_workers_than_the_server_takes_are_refused_before_the_run(tmp_path, capsys):
    """Each worker holds a connection: past the server's --max-clients the extra workers failed once playing."""
    with metadata_server({"server": "vla-ladder", "n_action_steps": 2, "max_clients": 1}) as url:
        assert main(["eval", "--policy", f"remote:{url}", *EVAL[:-2], "--workers", "2",
                     "--out", str(tmp_path / "run")]) == 2
        err = capsys.readouterr().err.strip()
        assert (f"--workers 2 would open 2 connections to the policy server at {url}, which serves at most 1 (its "
                "--max-clients); use --workers 1 or fewer, or --num-envs N") in err
        assert len(err.splitlines()) == 1 and not (tmp_path / "run").exists()


def test_a_policy_served_under_another_task_contract_is_refused(tmp_path, capsys):
    """A server that names the contract its policy was trained under is checked before any episode, as a lerobot:
    checkpoint is: another control rate is named and refused; the same contract, or none said, passes."""
    from vla_ladder.policies.remote import check_server

    said = {}
    with metadata_server(said) as server_url:
        url = f"{server_url}?n_action_steps=2"
        said[CONTRACT_KEY] = {**policy_fingerprint(), "control_hz": 10}
        assert main(["eval", "--policy", f"remote:{url}", *EVAL, "--out", str(tmp_path / "run")]) == 2
        err = capsys.readouterr().err
        assert f"was trained under another task contract (control_hz was 10, now {CONTROL_HZ})" in err
        assert len(err.strip().splitlines()) == 1 and not (tmp_path / "run").exists()
        said[CONTRACT_KEY] = "GraspObject-v1"
        with pytest.raises(ValueError, match="sent 'vla_ladder/contract' as a str; expected a map"):
            check_server(url)
        # The episode length only scores episodes differently: not a contract a policy is refused for.
        said[CONTRACT_KEY] = {**policy_fingerprint(), "episode_steps": 1}
        check_server(url)
        del said[CONTRACT_KEY]
        check_server(url)


@pytest.mark.parametrize("answer, says", [
    # openpi-style servers answer a failure as text; an empty one crashed the client with an IndexError.
    (" \n", r"the policy server at ws://.* failed: \(no message\)$"),
    # A NaN action passed the shape checks, stayed NaN through the clamp and reached the simulator (serve-policy
    # itself answers NaN to a state that is not finite).
    (pack({"actions": np.full((4, 7), np.nan, np.float32)}), r"answered actions that are not finite")])
def test_a_bad_answer_is_one_clear_error(answer, says):
    import threading

    from websockets.sync.server import serve

    from vla_ladder.policies.remote import RemotePolicy

    def server_side(ws):
        ws.send(pack({}))
        for _ in ws:
            ws.send(answer)

    with serve(server_side, "127.0.0.1", 0) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        policy = RemotePolicy(f"ws://127.0.0.1:{server.socket.getsockname()[1]}", n_action_steps=2)
        policy.send({PROMPT_KEY: "grasp the apple"})
        with pytest.raises(RuntimeError, match=says):
            policy.receive()
        server.shutdown()


def test_a_server_cannot_make_the_client_buffer_more_than_a_few_messages():
    """A server that sends faster than the client reads stalls after a few messages (websockets' default queue let
    one fill 16 x MAX_MESSAGE, 64 MiB, in the client), and every message still arrives once read."""
    import threading

    from websockets.sync.server import serve

    from vla_ladder.policies.remote import connect

    blob, sent = b"x" * (MAX_MESSAGE - 1024), []

    def server_side(ws):
        ws.send(pack({}))
        for i in range(24):
            ws.send(pack({"actions": blob, "i": i}))  # blocks once the client stops reading
            sent.append(i)

    with serve(server_side, "127.0.0.1", 0, max_size=None) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        ws, _ = connect(f"ws://127.0.0.1:{server.socket.getsockname()[1]}")
        with ws:
            seen = -1
            while seen != len(sent):  # until the server stalls (or is done)
                seen = len(sent)
                time.sleep(0.5)
            assert seen <= 8, f"the server got {seen} messages of 4 MiB into a client that read none"
            assert [unpack(ws.recv(timeout=30))["i"] for _ in range(24)] == list(range(24))
        server.shutdown()


def test_every_option_may_be_given_as_a_keyword(monkeypatch):
    """load_policy("remote:URL", **kwargs) takes the spec's options as keywords; instruction= was dropped unsaid."""
    from vla_ladder.policies import load_policy, remote

    made = {}
    monkeypatch.setattr(remote, "RemotePolicy", lambda url, **options: made.update(options, url=url))
    load_policy("remote:ws://127.0.0.1:9?n_action_steps=3", instruction="grasp the thing", device="cpu")
    assert made == {"url": "ws://127.0.0.1:9", "n_action_steps": 3, "instruction": "grasp the thing"}
    load_policy("remote:ws://127.0.0.1:9?n_action_steps=3", n_action_steps=5)
    assert made["n_action_steps"] == 5


@pytest.mark.parametrize("depth", [None, 2])
def test_a_batch_of_envs_pipelines_its_requests_only_to_servers_that_say_so(depth):
    """With --num-envs N, `remote:` sends up to the server's "max_pipelined" requests before it reads an answer, and
    gives each env the answer to its own request; to a server that does not say, one request at a time."""
    import threading

    import torch
    from websockets.sync.server import serve

    from vla_ladder.policies.remote import RemotePolicy

    arrived_together = []

    def server_side(ws):
        ws.send(pack({} if depth is None else {"max_pipelined": depth}))
        while True:
            try:
                first = [unpack(ws.recv())]
            except Exception:
                return
            try:  # a second request before the first is answered: the client pipelines
                first.append(unpack(ws.recv(timeout=1)))
            except TimeoutError:
                pass
            arrived_together.append([r.get(WINDOW_KEY) for r in first])
            for request in first:
                ws.send(pack({"actions": np.full((3, 7), request[SEED_KEY] / 100, np.float32)}))

    with serve(server_side, "127.0.0.1", 0) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        policy = RemotePolicy(f"ws://127.0.0.1:{server.socket.getsockname()[1]}", n_action_steps=1)
        n = 3
        obs = {"sensor_data": {c.name: {"rgb": torch.zeros((n, *c.shape), dtype=torch.uint8)} for c in CAMERAS},
               "extra": {"proprio": torch.zeros(n, 15)}}
        policy.reset([10, 20, 30])
        action = policy.act(obs, ["grasp the mug"] * n)
        server.shutdown()
    np.testing.assert_allclose(action[:, 0].numpy(), [0.1, 0.2, 0.3])  # each env its own chunk, in order
    assert policy.pipelined == (depth or 1)
    assert arrived_together == ([[None]] * 3 if depth is None else [[2, 2], [None]])  # each names its window


# ---------------------------------------------------------------------- a served checkpoint
@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A tiny SmolVLA trained here, served by `vla-ladder serve-policy` (horizon 2, an api key, 5 clients at most) on
    a free port."""
    run = H.trained(tmp_path_factory, "smolvla")
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "VLA_LADDER_API_KEY": KEY}
    proc = subprocess.Popen([sys.executable, "-m", "vla_ladder.cli", "serve-policy", "--policy",
                             f"lerobot:{run}?n_action_steps=2", "--port", "0", "--max-clients", "5"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    try:  # the server goes away even when it never says where it listens
        lines = [proc.stdout.readline()]  # after what LeRobot prints while it loads the model
        while lines[-1] and not lines[-1].startswith("listening on "):
            lines.append(proc.stdout.readline())
        line = lines[-1]
        assert line.startswith("listening on ws://127.0.0.1:"), lines
        yield run, line.split()[-1]
    finally:
        proc.kill()
        proc.wait()


@pytest.mark.slow
def test_a_served_checkpoint_plays_what_it_plays_in_process(served, tmp_path, monkeypatch, capsys):
    """Episode for episode, the remote policy ends where the in-process `lerobot:` one does (to the bit: the same
    flow-matching noise, drawn from each episode's seed and chunk index), at the server's horizon by default."""
    run, url = served
    assert main(["eval", "--policy", f"remote:{url}", *EVAL, "--out", str(tmp_path / "nokey")]) == 2
    assert "needs its --api-key in $VLA_LADDER_API_KEY" in capsys.readouterr().err
    monkeypatch.setenv("VLA_LADDER_API_KEY", KEY)
    runs = {"remote": [f"remote:{url}"], "local": [f"lerobot:{run}?n_action_steps=2"],
            "remote4": [f"remote:{url}?n_action_steps=4"], "batched": [f"remote:{url}", "--num-envs", "2"],
            "local_batched": [f"lerobot:{run}?n_action_steps=2", "--num-envs", "2"]}
    for name, (spec, *more) in runs.items():
        assert main(["eval", "--policy", spec, *EVAL, *more, "--out", str(tmp_path / name)]) == 0
    remote, local, remote4, batched, local_batched = (
        pd.read_parquet(tmp_path / n / "episodes.parquet").drop(columns="policy").sort_values("episode")
        .reset_index(drop=True) for n in runs)
    pd.testing.assert_frame_equal(remote, local, check_exact=True)
    # Two envs at once: their two requests are one window, one forward pass of two rows, as in-process.
    pd.testing.assert_frame_equal(batched, local_batched, check_exact=True)
    # ... and the same episodes as one env at a time, up to float rounding (batched matmuls round differently).
    assert (batched[["success", "grasp_any", "reach"]] == local[["success", "grasp_any", "reach"]]).all().all()
    np.testing.assert_allclose(batched[["tcp_x", "tcp_y"]], local[["tcp_x", "tcp_y"]], atol=1e-4, rtol=0)
    assert not np.array_equal(remote4[["tcp_x", "tcp_y"]].to_numpy(), local[["tcp_x", "tcp_y"]].to_numpy())
    # The server names its weights (sha256), so the run directory keeps them as the in-process run does.
    saved = [json.loads((tmp_path / n / "config.json").read_text())["policy_weights"] for n in ("remote", "local")]
    assert saved[0]["sha256"] == saved[1]["sha256"] and saved[0]["server"] == url


@pytest.mark.slow
def test_the_server_answers_bad_requests_in_one_message_and_keeps_serving(served):
    from websockets.exceptions import ConnectionClosed, InvalidStatus
    from websockets.sync.client import connect

    _, url = served
    headers = {"Authorization": f"Api-Key {KEY}"}
    with urllib.request.urlopen(url.replace("ws://", "http://") + "/healthz", timeout=10) as r:  # openpi's check
        assert r.status == 200
    with pytest.raises(InvalidStatus, match="401"):
        connect(url, additional_headers={"Authorization": "Api-Key wrong"}, open_timeout=10)
    good = {c.key: np.zeros(c.shape, np.uint8) for c in CAMERAS}
    good.update({STATE_KEY: np.zeros(15, np.float32), PROMPT_KEY: "grasp the mug"})

    def closes(*messages) -> tuple[str | None, int]:
        text = None
        with connect(url, additional_headers=headers, max_size=2 * MAX_MESSAGE, compression=None) as ws:
            metadata = unpack(ws.recv(timeout=30))
            assert metadata["server"] == "vla-ladder" and metadata["n_action_steps"] == 2
            assert metadata[CONTRACT_KEY] == policy_fingerprint()  # the checkpoint's, which the client checks
            try:
                for m in messages:
                    ws.send(m)
                while True:
                    reply = ws.recv(timeout=60)
                    if isinstance(reply, str):
                        text = reply
            except ConnectionClosed as e:
                return text, e.rcvd.code
        raise AssertionError("the server did not close")

    text, code = closes(pack({**good, STATE_KEY: np.zeros(3, np.float32)}))
    assert code == 1008 and text.startswith(f"bad request: {STATE_KEY} must be a float array"), text
    text, code = closes(pickle.dumps({"a": 1}))  # never unpickled: not msgpack, refused
    assert code == 1008 and text.startswith("bad request: not a msgpack message"), text
    assert closes(b"\0" * (MAX_MESSAGE + 1))[1] == 1009  # too big: closed by websockets before it is read
    # Inside an open window (two requests announced, one sent), a bad request or an episode marker hung the
    # connection: its first answer waited for the window, and nothing came back, not even a close.
    opened = pack({**good, SEED_KEY: 1, CHUNK_KEY: 0, WINDOW_KEY: 2})
    text, code = closes(opened, pack({"bogus": 1}))
    assert code == 1008 and text.startswith("bad request:"), text
    text, code = closes(opened, pack({"__ctrl__": "episode_start"}))
    assert code == 1008 and "an episode marker inside an open window of requests" in text, text
    with connect(url, additional_headers=headers, compression=None) as ws:  # still serving
        unpack(ws.recv(timeout=30))
        ws.send(pack({"__ctrl__": "episode_start"}))  # openpi's episode markers are acknowledged
        assert unpack(ws.recv(timeout=30)) == {"__ack__": "episode_start"}
        ws.send(pack({**good, SEED_KEY: 1, CHUNK_KEY: 0}))
        chunk = unpack(ws.recv(timeout=120))["actions"]
        assert chunk.dtype == np.float32 and chunk.shape == (4, 7)  # the whole chunk; the client runs 2
        ws.send(pack({**good, SEED_KEY: 1, CHUNK_KEY: 0}))
        np.testing.assert_array_equal(unpack(ws.recv(timeout=120))["actions"], chunk)  # same episode, same noise
    with pytest.raises(urllib.error.HTTPError):
        urllib.request.urlopen(url.replace("ws://", "http://") + "/other", timeout=10)


@pytest.mark.slow
def test_a_server_at_its_max_clients_refuses_more_until_one_leaves(served, monkeypatch):
    """Five clients connected, a sixth is refused before its handshake (HTTP 503), which `remote:` reports in one
    line naming the limit; a wrong key is still told so first; once a client leaves, the next one gets in."""
    import time

    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    from vla_ladder.policies.remote import connect as remote_connect

    _, url = served
    monkeypatch.setenv("VLA_LADDER_API_KEY", KEY)
    first, metadata = remote_connect(url)
    assert metadata["max_clients"] == 5  # what eval checks its --workers against
    clients = [first] + [remote_connect(url)[0] for _ in range(4)]  # each has read the metadata its handler sends
    try:
        with pytest.raises(ValueError) as busy:
            remote_connect(url)
        assert str(busy.value) == (f"the policy server at {url} is busy: serving 5 clients already (its "
                                   "--max-clients); try again once one has left")
        with pytest.raises(InvalidStatus, match="401"):
            connect(url, additional_headers={"Authorization": "Api-Key wrong"}, open_timeout=10)
        clients.pop().close()
        deadline = time.monotonic() + 30
        while True:  # the server counts a connection out once its close is done
            try:
                clients.append(remote_connect(url)[0])
                break
            except ValueError:
                assert time.monotonic() < deadline, "still refused after a client left"
                time.sleep(0.2)
    finally:
        for ws in clients:
            ws.close()


# ---------------------------------------------------------------------- openpi's own client
def test_openpi_codec_and_ours_read_each_other():
    from openpi_client import msgpack_numpy

    obs = {"img": np.arange(12, dtype=np.uint8).reshape(2, 2, 3), "s": np.ones(15, np.float32), "p": "grasp",
           "k": np.int64(4), "nested": {"a": [np.zeros(2, np.float64)]}}
    for there_and_back in (unpack(msgpack_numpy.packb(obs)), msgpack_numpy.unpackb(pack(obs))):
        assert there_and_back["p"] == "grasp" and there_and_back["k"] == 4
        for key in ("img", "s"):
            assert there_and_back[key].dtype == obs[key].dtype and np.array_equal(there_and_back[key], obs[key])
        assert np.array_equal(there_and_back["nested"]["a"][0], np.zeros(2))


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:connect\\(\\) must be used as a context manager:DeprecationWarning")  # openpi's
def test_openpis_client_is_served(served):
    """openpi's WebsocketClientPolicy (openpi-client from PyPI), as an openpi user's robot code calls it, gets the
    chunk vla-ladder's own client gets for the same observation, seed and chunk index."""
    from openpi_client.websocket_client_policy import WebsocketClientPolicy
    from websockets.sync.client import connect

    _, url = served
    obs = {c.key: np.random.default_rng(i).integers(0, 256, c.shape, dtype=np.uint8) for i, c in enumerate(CAMERAS)}
    obs.update({STATE_KEY: np.linspace(-1, 1, 15, dtype=np.float32), PROMPT_KEY: "grasp the apple",
                SEED_KEY: 5, CHUNK_KEY: 1})
    client = WebsocketClientPolicy(host=url, api_key=KEY)
    assert client.get_server_metadata()["n_action_steps"] == 2
    theirs = client.infer(obs)
    assert set(theirs) == {"actions", "server_timing"} and theirs["actions"].shape == (4, 7)
    with connect(url, additional_headers={"Authorization": f"Api-Key {KEY}"}, compression=None) as ws:
        unpack(ws.recv(timeout=30))
        ws.send(pack(obs))
        np.testing.assert_array_equal(unpack(ws.recv(timeout=120))["actions"], theirs["actions"])
    del obs[SEED_KEY], obs[CHUNK_KEY]  # what any openpi client sends: noise from the server's own generator
    assert client.infer(obs)["actions"].shape == (4, 7)


def _request(seed: int) -> dict:
    """An observation of its own for each seed, naming that seed's first chunk."""
    obs = {c.key: np.random.default_rng(seed * 10 + i).integers(0, 256, c.shape, dtype=np.uint8)
           for i, c in enumerate(CAMERAS)}
    obs.update({STATE_KEY: np.full(15, seed / 10, np.float32), PROMPT_KEY: "grasp the mug", SEED_KEY: seed,
                CHUNK_KEY: 0})
    return obs


@pytest.mark.slow
def test_requests_that_arrive_together_share_a_forward_pass(served):
    """Four clients asking at once are answered by batched forward passes (dynamic batching), and each gets the
    chunk it gets alone, up to float rounding."""
    import threading

    from websockets.sync.client import connect

    _, url = served
    headers = {"Authorization": f"Api-Key {KEY}"}
    with connect(url, additional_headers=headers, compression=None) as ws:
        unpack(ws.recv(timeout=30))
        alone = {}
        for seed in range(4):
            ws.send(pack(_request(seed)))
            answer = unpack(ws.recv(timeout=120))
            assert answer["server_timing"]["batch"] == 1
            alone[seed] = answer["actions"]

    barrier, answers, lock = threading.Barrier(4), [], threading.Lock()

    def client(seed: int) -> None:
        with connect(url, additional_headers=headers, compression=None) as ws:
            unpack(ws.recv(timeout=30))
            for _ in range(5):
                barrier.wait(timeout=60)
                ws.send(pack(_request(seed)))
                answer = unpack(ws.recv(timeout=120))
                with lock:
                    answers.append((seed, answer))

    threads = [threading.Thread(target=client, args=(seed,)) for seed in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert len(answers) == 20
    assert max(a["server_timing"]["batch"] for _, a in answers) > 1
    for seed, answer in answers:
        np.testing.assert_allclose(answer["actions"], alone[seed], atol=1e-5, rtol=0)


@pytest.mark.slow
def test_one_connection_may_pipeline_requests_and_gets_answers_in_order(served):
    """Up to max_pipelined requests sent before any answer is read (what `remote:` does with --num-envs N) share
    forward passes and come back in the order asked, each the chunk it gets alone up to float rounding."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    from vla_ladder.policies.remote import pipeline_depth

    _, url = served
    with connect(url, additional_headers={"Authorization": f"Api-Key {KEY}"}, compression=None) as ws:
        metadata = unpack(ws.recv(timeout=30))
        assert pipeline_depth(metadata) == metadata["max_pipelined"] == 16  # serve-policy's --max-batch
        alone = []
        for seed in range(4):
            ws.send(pack(_request(seed)))
            alone.append(unpack(ws.recv(timeout=120))["actions"])
        for seed in range(4):
            ws.send(pack(_request(seed)))
        ws.send(pack({"__ctrl__": "episode_end"}))  # answered in its turn too
        answers = [unpack(ws.recv(timeout=120)) for _ in range(5)]
        for seed in range(4):  # a window of 4: one forward pass, however the requests arrive
            ws.send(pack({**_request(seed), WINDOW_KEY: 4}))
        answers += [unpack(ws.recv(timeout=120)) for _ in range(4)]
    assert answers[4] == {"__ack__": "episode_end"}
    assert max(a["server_timing"]["batch"] for a in answers[:4]) > 1
    assert [a["server_timing"]["batch"] for a in answers[5:]] == [4] * 4
    for answer, chunk in zip(answers[:4] + answers[5:], alone * 2):
        np.testing.assert_allclose(answer["actions"], chunk, atol=1e-5, rtol=0)
    assert not np.allclose(alone[0], alone[1])  # the order is visible: seeds give different chunks
    with connect(url, additional_headers={"Authorization": f"Api-Key {KEY}"}, compression=None) as ws:
        unpack(ws.recv(timeout=30))
        ws.send(pack(_request(0)))
        ws.send(pack({**_request(1), PROMPT_KEY: ""}))  # bad: refused after the answer to what came before it
        np.testing.assert_allclose(unpack(ws.recv(timeout=120))["actions"], alone[0], atol=1e-5, rtol=0)
        assert ws.recv(timeout=30).startswith(f"bad request: {PROMPT_KEY!r} must be the instruction")
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=30)
        assert closed.value.rcvd.code == 1008
    with connect(url, additional_headers={"Authorization": f"Api-Key {KEY}"}, compression=None) as ws:
        unpack(ws.recv(timeout=30))
        ws.send(pack({**_request(0), WINDOW_KEY: 17}))  # larger than max_pipelined
        assert ws.recv(timeout=30).startswith(f"bad request: {WINDOW_KEY!r} must be an integer in 1..16")
    assert pipeline_depth({}) == pipeline_depth({"max_pipelined": True}) == 1  # openpi's servers: one at a time


# A serve-policy whose forward pass raises for a batch holding the prompt "fail" (no request the server takes makes
# the tiny SmolVLA raise) and sleeps 2 s for one holding "slow" (so that requests sent meanwhile share the next pass).
FAILING_SERVER = """
import sys, time
from vla_ladder.policies import serving

class FailingServer(serving.PolicyServer):
    def chunks(self, requests):
        prompts = [r[1] for r in requests]
        if "slow" in prompts:
            time.sleep(2)
        if "fail" in prompts:
            raise RuntimeError("this policy cannot take that request")
        return super().chunks(requests)

serving.PolicyServer = FailingServer
sys.exit(serving.run(serving.ServePolicyConfig(policy=sys.argv[1], port=0)))
"""


@pytest.mark.slow
def test_a_request_that_fails_a_shared_forward_pass_fails_alone(tmp_path_factory, tmp_path):
    """A forward pass shared by three clients fails on one client's request: that client gets the error, the others
    their chunks, to the bit what they get alone (each group run again on its own: a lone request, a window of two).
    Before, every connection of the batch got the error and was closed."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    run = H.trained(tmp_path_factory, "smolvla")
    env = {k: v for k, v in os.environ.items() if k != "VLA_LADDER_API_KEY"} | {"PYTHONUNBUFFERED": "1"}
    log = tmp_path / "server.log"
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-c", FAILING_SERVER, f"lerobot:{run}?n_action_steps=2"],
                                stdout=subprocess.PIPE, stderr=err, text=True, env=env)
    try:
        line = proc.stdout.readline()
        while line and not line.startswith("listening on "):
            line = proc.stdout.readline()
        url = line.split()[-1]
        with contextlib.ExitStack() as stack:  # (the connections close before the server is killed)
            clients = {name: stack.enter_context(connect(url, compression=None))
                       for name in ("slow", "one", "bad", "window")}
            for ws in clients.values():
                unpack(ws.recv(timeout=30))
            one, window = clients["one"], clients["window"]
            one.send(pack(_request(0)))
            alone = [unpack(one.recv(timeout=120))["actions"]]
            for seed in (2, 3):
                window.send(pack({**_request(seed), WINDOW_KEY: 2}))
            alone += [unpack(window.recv(timeout=120))["actions"] for _ in range(2)]

            clients["slow"].send(pack({**_request(5), PROMPT_KEY: "slow"}))
            time.sleep(0.5)  # its pass has begun: what follows waits for the next one, together
            one.send(pack(_request(0)))
            clients["bad"].send(pack({**_request(1), PROMPT_KEY: "fail"}))
            for seed in (2, 3):
                window.send(pack({**_request(seed), WINDOW_KEY: 2}))
            assert unpack(clients["slow"].recv(timeout=120))["actions"].shape == alone[0].shape
            answers = [unpack(one.recv(timeout=120))] + [unpack(window.recv(timeout=120)) for _ in range(2)]
            assert [a["server_timing"]["batch"] for a in answers] == [1, 2, 2]
            for answer, chunk in zip(answers, alone):
                np.testing.assert_array_equal(answer["actions"], chunk)
            assert clients["bad"].recv(timeout=120) == \
                "inference failed: RuntimeError: this policy cannot take that request"
            with pytest.raises(ConnectionClosed) as closed:
                clients["bad"].recv(timeout=30)
            assert closed.value.rcvd.code == 1011
            one.send(pack(_request(0)))  # the others' connections go on
            np.testing.assert_array_equal(unpack(one.recv(timeout=120))["actions"], alone[0])
    finally:
        proc.kill()
        proc.wait()
    # They did share the pass that failed (else the test proves nothing).
    assert "inference failed for a batch of 4 from 3 groups" in log.read_text(), log.read_text()[-2000:]
