"""The vla-ladder episode protocol (version 2): msgpack headers with raw numpy buffers over WebSockets.

Every message is one binary WebSocket message laid out as

    uint32 little-endian N | N bytes: msgpack map (the header) | payload: raw array buffers, back to back

The header always has "type"; a message carrying arrays lists them in header["arrays"] as
[name, dtype, shape] triples, in payload order, with dtypes from ALLOWED_DTYPES only. Nothing is ever
unpickled: headers are plain msgpack (no extension types) and arrays are rebuilt with np.frombuffer.
docs/recording.md is the full specification (message types, fields, close codes, limits).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

from vla_ladder.contract import CAMERAS, EPISODE_STEPS

PROTOCOL_VERSION = 2

# Close codes: 1000-1011 are the WebSocket standard ones, 4000-4999 are left to applications.
CLOSE_NORMAL = 1000
CLOSE_GOING_AWAY = 1001
CLOSE_TOO_BIG = 1009  # sent by `websockets` itself when a message exceeds max_size
CLOSE_INTERNAL = 1011
CLOSE_MALFORMED = 4000
CLOSE_VERSION = 4001
CLOSE_UNAUTHORISED = 4003
CLOSE_UNEXPECTED = 4004
CLOSE_LIMIT = 4005
CLOSE_HANDSHAKE_TIMEOUT = 4008

# Limits. Client messages are tiny (a hello, lists of seeds); an episode carries every frame of both cameras
# (~20 MB at 50 steps of 256x256 RGB), so the two directions get very different bounds. The episode bound
# follows the contract (three times the frames, at least 64 MiB): a larger camera or a longer episode raises it.
MAX_CLIENT_MESSAGE = 64 * 1024
MAX_EPISODE_MESSAGE = max(64 * 1024 * 1024,
                          3 * (EPISODE_STEPS + 1) * sum(math.prod(c.shape) for c in CAMERAS))
MAX_SEEDS_PER_REQUEST = 1024
MAX_HEADER = 1024 * 1024
HANDSHAKE_TIMEOUT_S = 10.0
SEED_RANGE = (0, 2**32 - 1)  # an episode seed seeds numpy (checks.SEED_LIMIT): the simulator refuses larger

ALLOWED_DTYPES = frozenset({"uint8", "float32", "int64", "bool"})
_LEN = struct.Struct("<I")


class ProtocolError(Exception):
    """A message that does not follow the protocol; `code` is the close code to answer it with."""

    def __init__(self, reason: str, code: int = CLOSE_MALFORMED):
        super().__init__(reason)
        self.reason, self.code = reason, code

    @property
    def close_reason(self) -> str:
        """The reason as a close frame may carry it: at most 123 UTF-8 bytes (a longer one is refused by websockets,
        "control frame too long", in place of the close)."""
        return self.reason.encode()[:123].decode(errors="ignore")


@dataclass
class Message:
    header: dict[str, Any]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def type(self) -> str:
        return self.header["type"]


def encode(header: dict[str, Any], arrays: dict[str, np.ndarray] | None = None) -> bytes:
    """Serialise one message. Arrays are sent C-contiguous in native little-endian byte order."""
    arrays = arrays or {}
    specs, buffers = [], []
    for name, a in arrays.items():
        a = np.ascontiguousarray(a)
        if a.dtype.name not in ALLOWED_DTYPES:
            raise ValueError(f"array {name!r} has dtype {a.dtype}; allowed: {sorted(ALLOWED_DTYPES)}")
        specs.append([name, a.dtype.name, list(a.shape)])
        a = a.astype(a.dtype.newbyteorder("<"), copy=False)
        buffers.append(a.reshape(-1).view(np.uint8).data if a.size else b"")
    packed = msgpack.packb({**header, "arrays": specs}, use_bin_type=True)
    return b"".join([_LEN.pack(len(packed)), packed, *buffers])


def decode(data: bytes | str) -> Message:
    """Parse and validate one message; raises ProtocolError with a human-readable reason."""
    if isinstance(data, str):
        raise ProtocolError("text frames are not part of the protocol; send binary messages")
    view = memoryview(data)
    if len(view) < _LEN.size:
        raise ProtocolError("message shorter than its 4-byte header length")
    (n,) = _LEN.unpack_from(view)
    if n > MAX_HEADER or _LEN.size + n > len(view):
        raise ProtocolError(f"header length {n} exceeds the message ({len(view)} bytes) or {MAX_HEADER}")
    try:
        header = msgpack.unpackb(view[_LEN.size:_LEN.size + n], raw=False, strict_map_key=True,
                                 ext_hook=_no_ext)
    except ProtocolError:
        raise
    except Exception as e:  # msgpack raises several unrelated exception types on garbage
        raise ProtocolError(f"header is not valid msgpack: {type(e).__name__}") from None
    if not isinstance(header, dict) or not isinstance(header.get("type"), str):
        raise ProtocolError("header must be a msgpack map with a string 'type'")
    specs = header.pop("arrays", [])
    arrays, offset = {}, _LEN.size + n
    if not isinstance(specs, list):
        raise ProtocolError("'arrays' must be a list of [name, dtype, shape]")
    for spec in specs:
        name, dtype, shape = _check_spec(spec)
        dt = np.dtype(dtype).newbyteorder("<")
        count = math.prod(shape)  # Python integers: an int64 product of [65536] * 4 wraps to 0
        if offset + count * dt.itemsize > len(view):
            raise ProtocolError(f"array {name!r} runs past the end of the message")
        try:  # numpy refuses some shapes the spec check lets through (an empty array of huge other sides)
            arrays[name] = np.frombuffer(view, dtype=dt, count=count, offset=offset).reshape(shape)
        except (ValueError, TypeError) as e:
            raise ProtocolError(f"array {name!r}: shape {list(shape)} not allowed ({e})") from None
        offset += count * dt.itemsize
    if offset != len(view):
        raise ProtocolError(f"{len(view) - offset} trailing bytes after the declared arrays")
    return Message(header, arrays)


def _no_ext(code, data):
    raise ProtocolError("msgpack extension types are not allowed")


def _check_spec(spec) -> tuple[str, str, tuple[int, ...]]:
    if not (isinstance(spec, list) and len(spec) == 3 and isinstance(spec[0], str) and isinstance(spec[1], str)
            and isinstance(spec[2], list)):
        raise ProtocolError("each array spec must be [name: str, dtype: str, shape: list[int]]")
    name, dtype, shape = spec
    if dtype not in ALLOWED_DTYPES:
        raise ProtocolError(f"array {name!r}: dtype {dtype!r} not allowed; allowed: {sorted(ALLOWED_DTYPES)}")
    if len(shape) > 8 or not all(type(d) is int and 0 <= d < 2**31 for d in shape):  # not bool, an int subclass
        raise ProtocolError(f"array {name!r}: bad shape {shape}")
    return name, dtype, tuple(shape)


# ---------------------------------------------------------------------- message builders and checks
def hello(token: str | None, max_message: int, client: str = "vla-ladder",
          version: int = PROTOCOL_VERSION) -> bytes:
    return encode({"type": "hello", "protocol": version, "token": token, "max_message": max_message,
                   "client": client})


def run(seeds: list[int], failed_frames: bool = False) -> bytes:
    return encode({"type": "run", "seeds": [int(s) for s in seeds], "failed_frames": bool(failed_frames)})


def require(header: dict, key: str, kind: type) -> Any:
    """header[key], which must exist and be a `kind` (a bool does not pass as an int)."""
    value = header.get(key)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ProtocolError(f"{header['type']!r} message: field {key!r} missing or not {kind.__name__}")
    return value


def check_seeds(seeds: Any) -> list[int]:
    if not isinstance(seeds, list) or not seeds or len(seeds) > MAX_SEEDS_PER_REQUEST:
        raise ProtocolError(f"'seeds' must be a list of 1..{MAX_SEEDS_PER_REQUEST} integers", CLOSE_LIMIT
                            if isinstance(seeds, list) and seeds else CLOSE_MALFORMED)
    lo, hi = SEED_RANGE
    if not all(isinstance(s, int) and not isinstance(s, bool) and lo <= s <= hi for s in seeds):
        raise ProtocolError(f"seeds must be integers in [{lo}, {hi}]")
    return seeds


def episode_message_size(num_frames: int, cameras: dict[str, tuple[int, ...]], state_dim: int,
                         action_dim: int) -> int:
    """Upper bound of an episode message's payload, to check against the client's max_message."""
    per_frame = sum(int(np.prod(s)) for s in cameras.values()) + 4 * (state_dim + action_dim)
    return num_frames * per_frame + MAX_HEADER // 16
