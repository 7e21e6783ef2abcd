"""A policy served by another process, over WebSockets: `--policy remote:ws://HOST:PORT[?n_action_steps=H]`.

Many VLAs run in a stack of their own (openpi's JAX models, a fork of LeRobot, another venv, a GPU box) that
cannot share a process with the simulator. vla-ladder evaluates them through openpi's policy-server protocol,
which such servers already speak (openpi's `scripts/serve_policy.py`, `openpi_client.WebsocketClientPolicy`):

- on connecting, the server sends one message: its metadata (a map, possibly empty);
- then, for every request, the client sends one observation (a map) and the server answers one map holding
  "actions", an action chunk (T, 7) (or one action, (7,)); the client runs its first `n_action_steps` actions
  (`?n_action_steps=H`, else the server's metadata "n_action_steps": openpi's servers say nothing, so H is then
  required) before it asks again;
- messages are msgpack, numpy arrays in openpi's msgpack-numpy layout ({"__ndarray__": True, "data", "dtype",
  "shape"}); a server that fails answers a text message (its error) and closes.

The observation of one episode holds both cameras under their LeRobot keys (contract.CAMERA_KEYS: uint8 HWC
256x256x3), the 15-d state under contract.STATE_KEY (float32), the instruction as "prompt", and two extra keys
that openpi's input transforms ignore: "vla_ladder/episode_seed" and "vla_ladder/chunk_index". vla-ladder's own
server (`vla-ladder serve-policy`, policies/serving.py) draws a flow-matching policy's noise from them, so a
remote episode plays exactly as the same checkpoint does in-process (`lerobot:`). A batch of envs
(`eval --num-envs N`) sends one request per env whose chunk has run out; to a server whose metadata says
"max_pipelined": K (vla-ladder's does) it sends up to K of them before reading the answers, which come in the order
asked; each request of such a window names its size under "vla_ladder/window", so that the server runs the window
in one forward pass. Other servers get one request at a time, as openpi's client sends them.

A server may say which task its policy was trained on: metadata "vla_ladder/contract", the
contract.policy_fingerprint() of its training data (vla-ladder's server sends the checkpoint's
vla_ladder_contract.json). The client refuses a policy trained under another contract (another control rate, a
camera's field of view, the meaning of a state entry) before any episode, as `lerobot:` refuses such a checkpoint;
a server that does not say is not checked.

A server that wants a key gets $VLA_LADDER_API_KEY as openpi's client sends its api_key. Nothing received is
unpickled: arrays are rebuilt with np.frombuffer, only for boolean, numeric and fixed-width string dtypes and
only when their bytes match their shape, every message is bounded (MAX_MESSAGE) and so are those received and not
yet read (two).
"""

from __future__ import annotations

import collections
import math
import os
import weakref
from typing import Any, Sequence

import msgpack
import numpy as np
import torch

from vla_ladder.checks import check_ws_url, refusal_body, ws_proxy
from vla_ladder.contract import ACTION_DIM, CAMERAS, POLICY_FIELDS, STATE_KEY, contract_changes
from vla_ladder.policies import Policy, instruction_text, parse_options, positive_int

PROMPT_KEY = "prompt"
SEED_KEY = "vla_ladder/episode_seed"
CHUNK_KEY = "vla_ladder/chunk_index"
WINDOW_KEY = "vla_ladder/window"  # the size of the pipelined window a request belongs to (module docstring)
CONTRACT_KEY = "vla_ladder/contract"  # metadata: the task contract the served policy was trained under
ACTIONS_KEY = "actions"
API_KEY_ENV = "VLA_LADDER_API_KEY"  # sent as openpi's client sends its api_key: `Authorization: Api-Key KEY`
# An observation is ~0.4 MB (two 256x256 RGB images); a chunk a few KB; metadata small. Both directions are
# bounded well above that and far below what a hostile peer could make us allocate.
MAX_MESSAGE = 4 * 1024 * 1024
MAX_CONTAINER = 4096  # entries of one msgpack list or map
# Lists and maps in one message. A request has a handful (the observation's map, an array's map and shape list); a
# 1-byte empty list becomes a ~60-byte Python object, so 16 MiB of them became 1.1 GiB before this bound.
MAX_CONTAINERS = 1024
CONNECT_TIMEOUT_S = 10.0
REPLY_TIMEOUT_S = 600.0  # the first chunk of a large model on a CPU can take minutes
_KINDS = frozenset("biufSU")  # bool, integers, floats, fixed-width strings: never objects, void or pointers


_ALLOWED = "allowed: bool, integers, floats, fixed-width strings"


class BadMessage(ValueError):
    """A received message that is not one this protocol allows."""


def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in _KINDS:
            raise ValueError(f"cannot send an array of dtype {obj.dtype} ({_ALLOWED})")
        return {b"__ndarray__": True, b"data": np.ascontiguousarray(obj).tobytes(), b"dtype": obj.dtype.str,
                b"shape": list(obj.shape)}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot send a {type(obj).__name__}")


def _dtype(spec: Any) -> np.dtype:
    if not isinstance(spec, (str, bytes)):
        raise BadMessage(f"array dtype {spec!r} is not a dtype string")
    dtype = np.dtype(spec.decode() if isinstance(spec, bytes) else spec)
    if dtype.kind not in _KINDS or dtype.fields is not None or dtype.subdtype is not None:
        raise BadMessage(f"array dtype {dtype} is not allowed ({_ALLOWED})")
    return dtype


def _decode(obj: dict) -> Any:
    if b"__ndarray__" in obj:
        dtype = _dtype(obj.get(b"dtype"))
        shape, data = obj.get(b"shape"), obj.get(b"data")
        if not isinstance(shape, list) or not all(isinstance(n, int) and n >= 0 for n in shape):
            raise BadMessage(f"array shape {shape!r} is not a list of sizes")
        if not isinstance(data, bytes) or len(data) != math.prod(shape) * dtype.itemsize:
            raise BadMessage(f"array of shape {shape} and dtype {dtype} does not match its "
                             f"{len(data) if isinstance(data, bytes) else 'missing'} bytes")
        return np.frombuffer(data, dtype).reshape(shape)
    if b"__npgeneric__" in obj:
        return _dtype(obj.get(b"dtype")).type(obj.get(b"data"))
    return obj


def _no_ext(code: int, data: bytes) -> Any:
    raise BadMessage(f"msgpack extension type {code} is not allowed")


def pack(obj: Any) -> bytes:
    """One message: msgpack, numpy arrays in openpi's msgpack-numpy layout."""
    return msgpack.packb(obj, default=_encode, use_bin_type=True)


def unpack(data: bytes) -> Any:
    """The inverse of `pack`, for untrusted bytes: ValueError on anything but plain msgpack and numeric arrays."""
    if not isinstance(data, bytes):
        raise BadMessage(f"expected a binary message, got {type(data).__name__}")
    containers = 0

    def counted(hook):
        def count(obj):
            nonlocal containers
            containers += 1
            if containers > MAX_CONTAINERS:
                raise BadMessage(f"more than {MAX_CONTAINERS} lists and maps in one message")
            return hook(obj)
        return count

    try:
        # Container limits far above any observation, chunk or metadata (a handful of keys, shapes of 3 numbers),
        # so that a hostile message of tiny containers cannot become gigabytes of Python objects.
        return msgpack.unpackb(data, object_hook=counted(_decode), list_hook=counted(lambda x: x), ext_hook=_no_ext,
                               strict_map_key=False, max_array_len=MAX_CONTAINER, max_map_len=MAX_CONTAINER)
    except BadMessage:
        raise
    except Exception as e:  # msgpack's own errors (truncated data, extra bytes) and numpy's (a bad dtype string)
        raise BadMessage(f"not a msgpack message ({type(e).__name__}: {e})") from None


def check_url(url: str) -> str:
    return check_ws_url(url, "a remote policy")


def connect(url: str, timeout_s: float = CONNECT_TIMEOUT_S):
    """(connection, metadata) of the policy server at `url`; ValueError, in one line, when none answers there."""
    from websockets.exceptions import InvalidStatus, WebSocketException
    from websockets.sync.client import connect as ws_connect

    check_url(url)
    key = os.environ.get(API_KEY_ENV)
    headers = {"Authorization": f"Api-Key {key}"} if key else None
    try:
        # Entered as a context manager, and closed by whoever holds it (websockets >= 17.1 warns otherwise).
        # max_queue: frames received and not yet read before reading pauses; websockets' default (16) let a server
        # fill 16 x MAX_MESSAGE here. A window's answers (a few KB each) wait in TCP's buffers until read.
        ws = ws_connect(url, open_timeout=timeout_s, max_size=MAX_MESSAGE, max_queue=2, compression=None,
                        additional_headers=headers, proxy=ws_proxy(url)).__enter__()
    except InvalidStatus as e:
        if e.response.status_code == 401:
            raise ValueError(f"the policy server at {url} refused the connection: it needs its --api-key in "
                             f"${API_KEY_ENV}") from None
        if e.response.status_code == 503:  # vla-ladder's serve-policy at its --max-clients
            raise ValueError(f"the policy server at {url} is busy: {refusal_body(e) or 'HTTP 503'}") from None
        raise ValueError(f"{url} refused the WebSocket connection (HTTP {e.response.status_code}); is it a policy "
                         "server?") from None
    except (OSError, TimeoutError, WebSocketException) as e:
        raise ValueError(f"no policy server answers at {url} ({e}); start one there (vla-ladder serve-policy "
                         f"--policy lerobot:CHECKPOINT, or openpi's serve_policy.py) or fix the URL") from None
    try:
        metadata = unpack(ws.recv(timeout=timeout_s))
    except (ValueError, TimeoutError, WebSocketException) as e:
        ws.close()
        raise ValueError(f"{url} is not a policy server: its first message is not its metadata ({e})") from None
    if not isinstance(metadata, dict):
        ws.close()
        raise ValueError(f"{url} is not a policy server: its metadata is a {type(metadata).__name__}, not a map")
    return ws, metadata


QUERY_KEYS = {"n_action_steps": positive_int, "instruction": instruction_text}


def parse_arg(arg: str) -> tuple[str, dict]:
    """"ws://host:8000?n_action_steps=4" -> ("ws://host:8000", {"n_action_steps": 4})."""
    url, options = parse_options("remote", arg, QUERY_KEYS)
    return check_url(url), options


class RemotePolicy(Policy):
    """A policy behind a policy server (module docstring): one connection, per-env chunks run open-loop."""

    obs_mode = "rgb"

    def __init__(self, url: str, n_action_steps: int | None = None, instruction: str | None = None):
        """`n_action_steps`: actions of each chunk run before the next request (default: the server's metadata
        "n_action_steps"; a server that does not say needs it given). `instruction` replaces every episode's (a
        blind policy's contract.BLIND_INSTRUCTION)."""
        self._ws, self.server = connect(url)  # checks the URL first
        self.url = url
        weakref.finalize(self, self._ws.close)
        check_contract(url, self.server)
        self.n_action_steps = horizon(self.url, n_action_steps, self.server)
        self.pipelined = pipeline_depth(self.server)
        self.instruction = instruction
        self.name = "remote"
        self._seeds: list[int | None] = []
        self._chunks: list[int] = []
        self._queues: list[collections.deque] = []

    def _grow(self, n: int) -> None:
        while len(self._queues) < n:
            self._seeds.append(None)
            self._chunks.append(0)
            self._queues.append(collections.deque())

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> None:
        ids = list(range(len(seeds))) if env_ids is None else [int(i) for i in env_ids]
        self._grow(max(ids, default=-1) + 1)
        for i, seed in zip(ids, seeds):
            self._seeds[i], self._chunks[i] = int(seed), 0
            self._queues[i].clear()

    def observation(self, obs: Any, i: int, instruction: str) -> dict:
        """The request for env i: what the module docstring lists."""
        out: dict[str, Any] = {cam.key: np.asarray(obs["sensor_data"][cam.name]["rgb"][i].cpu(), np.uint8)
                               for cam in CAMERAS}
        out[STATE_KEY] = np.asarray(obs["extra"]["proprio"][i].cpu(), np.float32)
        out[PROMPT_KEY] = self.instruction or str(instruction)
        if self._seeds[i] is not None:
            out[SEED_KEY], out[CHUNK_KEY] = self._seeds[i], self._chunks[i]
        return out

    def send(self, observation: dict) -> None:
        """Ask for one chunk; `receive` reads the answers in the order asked."""
        from websockets.exceptions import ConnectionClosed

        try:
            self._ws.send(pack(observation))
        except ConnectionClosed as e:
            raise RuntimeError(f"the policy server at {self.url} closed the connection ({e})") from None

    def receive(self) -> np.ndarray:
        """The next answer: the chunk (T, 7) the server sent, checked."""
        from websockets.exceptions import ConnectionClosed

        try:
            reply = self._ws.recv(timeout=REPLY_TIMEOUT_S)
        except ConnectionClosed as e:
            raise RuntimeError(f"the policy server at {self.url} closed the connection ({e})") from None
        except TimeoutError:
            raise RuntimeError(f"the policy server at {self.url} sent no action in {REPLY_TIMEOUT_S:.0f} s") from None
        if isinstance(reply, str):  # openpi's servers (and ours) answer their error as text, then close
            last = (reply.strip().splitlines() or ["(no message)"])[-1]
            raise RuntimeError(f"the policy server at {self.url} failed: {last[:500]}")
        answer = unpack(reply)
        actions = answer.get(ACTIONS_KEY) if isinstance(answer, dict) else None
        if not isinstance(actions, np.ndarray) or actions.dtype.kind != "f" or actions.ndim not in (1, 2) \
                or actions.shape[-1] != ACTION_DIM or actions.size == 0:
            got = actions.shape if isinstance(actions, np.ndarray) else type(actions).__name__
            raise RuntimeError(f"the policy server at {self.url} answered {got} under {ACTIONS_KEY!r}; expected a "
                               f"float array of shape (T, {ACTION_DIM}) or ({ACTION_DIM},)")
        if not np.isfinite(actions).all():  # (clamped, a NaN stays NaN and reaches the simulator)
            raise RuntimeError(f"the policy server at {self.url} answered actions that are not finite (NaN or inf)")
        return actions.reshape(-1, ACTION_DIM)

    @torch.no_grad()
    def act(self, obs: Any, instructions: Sequence[str]) -> torch.Tensor:
        proprio = torch.as_tensor(obs["extra"]["proprio"])
        n = proprio.shape[0]
        self._grow(n)
        empty = [i for i in range(n) if not self._queues[i]]
        for start in range(0, len(empty), self.pipelined):  # windows the server takes in one go (module docstring)
            window = empty[start:start + self.pipelined]
            for i in window:
                request = self.observation(obs, i, instructions[i])
                if len(window) > 1:
                    request[WINDOW_KEY] = len(window)
                self.send(request)
            for i in window:
                chunk = self.receive()
                self._chunks[i] += 1
                self._queues[i].extend(torch.from_numpy(chunk[:self.n_action_steps].astype(np.float32)))
        action = torch.stack([self._queues[i].popleft() for i in range(n)])
        return action.to(proprio.device).clamp(-1, 1)

    def describe(self) -> dict:
        return {"name": self.name, "url": self.url, "n_action_steps": self.n_action_steps,
                "instruction": self.instruction, "pipelined": self.pipelined, "server": _jsonable(self.server)}


def _jsonable(metadata: dict) -> Any:
    """The server's metadata as run files can hold it (arrays and bytes named, not written out)."""
    def plain(o):
        if isinstance(o, dict):
            return {str(k): plain(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [plain(v) for v in o]
        return o if isinstance(o, (str, int, float, bool, type(None))) else f"<{type(o).__name__}>"
    return plain(metadata)


def horizon(url: str, n_action_steps: int | None, metadata: dict) -> int:
    """The actions of each chunk to run: the spec's ?n_action_steps, else the server's metadata "n_action_steps".
    Never a silent default: an openpi server says nothing, and running its whole chunk (pi0's 50 steps are a whole
    episode) open-loop is rarely what anyone means."""
    if n_action_steps is not None:
        # vla-ladder's server says its chunk size (metadata "policy"): more steps than a chunk holds would run the
        # whole chunk while the run directory says otherwise. An openpi server does not say.
        policy = metadata.get("policy")
        chunk = policy.get("chunk_size") if isinstance(policy, dict) else None
        if isinstance(chunk, int) and not isinstance(chunk, bool) and chunk > 0 and int(n_action_steps) > chunk:
            raise ValueError(f"n_action_steps must be from 1 to the chunk size of the policy served at {url} "
                             f"({chunk}), got {n_action_steps}")
        return int(n_action_steps)
    served = metadata.get("n_action_steps")
    if isinstance(served, int) and not isinstance(served, bool) and served > 0:
        return served
    raise ValueError(f"the policy server at {url} does not say how many actions of a chunk to run (its metadata has "
                     f"no n_action_steps); give one: remote:{url}?n_action_steps=H (openpi's examples run 5)")


def check_contract(url: str, metadata: dict) -> None:
    """ValueError when the server says its policy was trained under another task contract than this one plays
    (metadata CONTRACT_KEY; see the module docstring): every shape may fit while the rate, a camera's view or the
    meaning of a state entry differ. A server that does not say is not checked."""
    saved = metadata.get(CONTRACT_KEY)
    if saved is None:
        return
    if not isinstance(saved, dict):
        raise ValueError(f"the policy server at {url} sent {CONTRACT_KEY!r} as a {type(saved).__name__}; expected a "
                         "map, contract.policy_fingerprint() of the policy's training data")
    if changed := contract_changes(saved, POLICY_FIELDS):
        raise ValueError(f"the policy served at {url} was trained under another task contract ({'; '.join(changed)}):"
                         " its numbers here would be those of a task it never saw; evaluate it with the vla-ladder "
                         "version it was trained with")


def pipeline_depth(metadata: dict) -> int:
    """Requests one connection may have in flight: the server's metadata "max_pipelined", else 1 (an openpi server
    would answer more in order too, but one at a time; asking one at a time is what its own client does)."""
    depth = metadata.get("max_pipelined")
    return depth if isinstance(depth, int) and not isinstance(depth, bool) and depth > 0 else 1


def check_server(arg: str, connections: int = 1) -> None:
    """The spec's options parse, a policy server answers at its URL, its policy was trained under this task
    contract (where it says), the horizon is known and the server takes `connections` clients at once (where it
    says: vla-ladder's metadata "max_clients"): checked before any long work."""
    url, options = parse_arg(arg)
    ws, metadata = connect(url)
    ws.close()
    check_contract(url, metadata)
    horizon(url, options.get("n_action_steps"), metadata)
    most = metadata.get("max_clients")
    if isinstance(most, int) and not isinstance(most, bool) and connections > most:
        # Each worker process holds a connection of its own; the ones past the limit would fail in the worker.
        raise ValueError(f"--workers {connections} would open {connections} connections to the policy server at {url}, "
                         f"which serves at most {most} (its --max-clients); use --workers {most} or fewer, or "
                         "--num-envs N (one connection for N envs)")


def make_policy(arg: str | None, **kwargs) -> RemotePolicy:
    """Factory for `load_policy("remote:ws://HOST:PORT[?n_action_steps=H&instruction=TEXT]")`."""
    if not arg:
        raise ValueError("policy 'remote' needs a server: remote:ws://HOST:PORT[?n_action_steps=H]")
    url, options = parse_arg(arg)
    # Every option the spec may give may be given as a keyword too, as for lerobot: (instruction= was dropped unsaid)
    options.update({k: v for k, v in kwargs.items() if k in QUERY_KEYS and v is not None})
    if "n_action_steps" in options:
        options["n_action_steps"] = int(options["n_action_steps"])
    return RemotePolicy(url, **options)

