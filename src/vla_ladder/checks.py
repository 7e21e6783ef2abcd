"""Checks every command makes on its input before any long work: seeds, output locations, ports, OS errors.

A bad value fails here in one line that names the flag or the path and what to do instead, so a typo is found
before a simulator starts or a model trains, not after. Seeds are checked on the command line itself, before
a config is built, so that every command says the same thing about the same mistake. Simulator-free.
"""

from __future__ import annotations

import dataclasses
import errno
import ipaddress
import os
import re
import socket
import tempfile
import typing
from pathlib import Path

SEED_SUFFIX = "seed"
"""A config field holds a seed when its name is `seed` or ends in `_seed` (first_seed, train_seed, rng_seed, ...:
seeds say which seed they are, docs/architecture.md), whatever the command."""
SEED_LIMIT = 2**32
"""Seeds are numpy RandomState seeds in the simulator (ManiSkill seeds each episode with one): 0 <= seed < 2**32."""


TORCH_DEVICE = re.compile(r"cpu|mps|cuda(:\d+)?")
"""The torch devices a policy or a training run may be put on (`--device`, `lerobot:...?device=`)."""


def check_torch_device(device: str, said: str, fix: str) -> str:
    """`device` (a TORCH_DEVICE) when this machine has it, else ValueError in one line that starts with `said` (how
    the command was told, "--device cuda:3" or "device=cuda:3") and, where no GPU is visible, ends with `fix`.
    LeRobot puts a model on a missing device's stand-in with a warning only, and torch fails on cuda:N past the
    GPUs only once the model is moved there, after the checkpoint or the data have loaded: every command that
    takes a device (train, eval and serve-policy of lerobot: checkpoints) checks it here, before that work."""
    import torch

    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"{said} needs a CUDA GPU and none is visible; {fix}")
        count, index = torch.cuda.device_count(), int(device.partition(":")[2] or 0)
        if index >= count:
            gpus = ", ".join(f"cuda:{i}" for i in range(count)) if count <= 2 else f"cuda:0 to cuda:{count - 1}"
            raise ValueError(f"{said}: this machine has {count} GPU{'s' if count > 1 else ''} ({gpus})")
    if device == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{said} needs Apple's Metal (MPS) and it is not available here; {fix}")
    return device


# ---------------------------------------------------------------------------------------------- counts
def ascii_digits(value: str) -> bool:
    """Whether `value` is one or more of the digits 0-9, the test before int() on a number typed or a folder's
    name: str.isdigit() alone also takes '٣' and '５', which int() reads as 3 and 5, and '²', which int() refuses
    in words that name no flag."""
    return value.isascii() and value.isdigit()


def check_count(value, name: str, least: int = 1):
    """`value` when it is an integer (numpy's too; a bool is not one) of at least `least`, else ValueError naming
    `name` (a flag or a config field)."""
    if isinstance(value, bool) or not hasattr(value, "__index__") or value < least:
        what = "a positive integer" if least == 1 else f"an integer >= {least}"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return value


def check_given(*flags: tuple[str, object, str]) -> None:
    """ValueError naming every flag of `flags` ((the flag and its metavar, its value, what the metavar is)) whose
    value is None or empty (a spec, a path, a tuple of specs): flags required on the command line whose fields a
    grid or a study fills in. All in one line (`eval` said --out alone, and only once given --out, --policy)."""
    missing = [(flag, says) for flag, value, says in flags if not value]
    if missing:
        verb = "is" if len(missing) == 1 else "are"
        raise ValueError(f"{' and '.join(f for f, _ in missing)} {verb} required ({'; '.join(s for _, s in missing)})")


# ---------------------------------------------------------------------------------------------- seeds
def check_seed(value, flag: str) -> int:
    """`value` as a seed, or ValueError naming `flag` and the allowed range."""
    if isinstance(value, bool) or not hasattr(value, "__index__"):
        raise ValueError(f"{flag} must be an integer seed (0 <= seed < 2**32), got {value!r}")
    if not 0 <= value < SEED_LIMIT:
        raise ValueError(f"{flag} must be >= 0 and < 2**32 (a numpy seed), got {value}")
    return int(value)


def is_seed_field(name: str) -> bool:
    return name == SEED_SUFFIX or name.endswith(f"_{SEED_SUFFIX}")


def seed_flags(cls: type) -> dict[str, str]:
    """Every seed flag of the config dataclass `cls`, nested configs included (`--train.train-seed`), spelled
    with hyphens as tyro prints them."""
    flags: dict[str, str] = {}
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        hint = hints.get(f.name)
        inner = typing.get_args(hint)[0] if typing.get_origin(hint) is typing.Annotated else hint
        if is_seed_field(f.name):
            flags[f"--{f.name.replace('_', '-')}"] = f.name
        elif isinstance(inner, type) and dataclasses.is_dataclass(inner):
            flattened = any(getattr(m, "name", None) == "" for m in getattr(hint, "__metadata__", ()))
            prefix = "" if flattened else f"{f.name.replace('_', '-')}."
            flags.update({f"--{prefix}{flag[2:]}": name for flag, name in seed_flags(inner).items()})
    return flags


def check_seed_args(cls: type, argv: list[str]) -> None:
    """ValueError for the first seed flag in `argv` whose value is an integer outside the seed range (tyro itself
    rejects values that are not integers). Stops at `--`: what follows belongs to another program."""
    flags = seed_flags(cls)
    for i, arg in enumerate(argv):
        if arg == "--":
            return
        name, eq, value = arg.partition("=")
        flag = name.replace("_", "-")
        if not flag.startswith("--") or flag not in flags:
            continue
        if not eq:
            value = argv[i + 1] if i + 1 < len(argv) else ""
        try:
            number = int(value)
        except ValueError:
            continue
        check_seed(number, flag)


# ---------------------------------------------------------------------------------------- output paths
def check_output_dir(path: str | os.PathLike, flag: str) -> Path:
    """`path` can be a directory this process writes into: it is one, or can be made under a writable directory.
    ValueError naming `flag`, the path and the fix otherwise."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {str(path)!r} is a file, not a directory; give a directory (or remove the file)")
    if not path.resolve().name:
        raise ValueError(f"{flag} {str(path)!r} is the file system's root; give a directory for the results")
    _check_writable_under(path if path.is_dir() else path.parent, flag, path)
    return path


def check_output_file(path: str | os.PathLike, flag: str) -> Path:
    """`path` can be written as a file: it is not a directory, and its directory is (or can be made) writable."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{flag} {str(path)!r} is a directory; give the path of the file to write in it, e.g. "
                         f"{str(path / 'out')!r}")
    _check_writable_under(path.parent, flag, path)
    return path


def _check_writable_under(directory: Path, flag: str, target: Path) -> None:
    existing = directory.absolute()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{flag} {str(target)!r}: {str(existing)!r} is a file where a directory is needed; "
                         "remove it or choose another path")
    if not os.access(existing, os.W_OK | os.X_OK):
        why = "is on a read-only file system" if _read_only(existing) else "is not writable by this user"
        raise ValueError(f"{flag} {str(target)!r}: {str(existing)!r} {why}; choose a location you can write to")
    try:  # root passes os.access everywhere, /proc included: write a file there to know
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as e:
        raise ValueError(f"{flag} {str(target)!r}: cannot write in {str(existing)!r} ({e.strerror}); choose a "
                         "location you can write to") from None


def _read_only(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


# ----------------------------------------------------------------------------------------------- ports
def is_loopback(host: str) -> bool:
    """Whether `host` is this machine only (what a service may listen on without a secret)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def ws_proxy(url: str) -> None | bool:
    """websockets' `proxy` argument for a client of `url`: None (connect directly) for a loopback host, else True
    (websockets' default: the environment's proxy, unless no_proxy names the host). websockets sends even
    ws://127.0.0.1 through $https_proxy / $http_proxy when no_proxy does not name it, so on a machine with a proxy
    (a cluster's login node) no client reached the servers vla-ladder starts on this machine."""
    return None if is_loopback(_ws_host(url)) else True


def refuse_past_max_clients(connection, max_clients: int, log):
    """For a websockets server's `process_request`: HTTP 503 naming the limit when `max_clients` connections are
    open already (each one's queued work and messages are in the server's memory), else None (go on)."""
    import http

    if len(connection.server.connections) < max_clients:
        return None
    log.warning("refused %s: serving %d clients already", connection.remote_address, max_clients)
    return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, f"serving {max_clients} clients already (its "
                              "--max-clients); try again once one has left\n")


def refusal_body(error) -> str:
    """What a server said with its refusal of a WebSocket handshake (websockets' InvalidStatus), cut short: the
    reason refuse_past_max_clients gives, or "" (a server may say nothing)."""
    return error.response.body.decode(errors="replace").strip()[:200]


def check_port_free(host: str, port: int, flag: str = "--port") -> None:
    """ValueError when `host`:`port` cannot be listened on (in use, or not an address of this machine). Binds the
    way asyncio's server does (SO_REUSEADDR), so a port in TIME_WAIT is free. Port 0 (any free port) always is, but
    its host is checked all the same."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise ValueError(f"--host {host!r} is not an address of this machine ({e.strerror}); use 127.0.0.1 or "
                         "one of its own addresses") from None
    for family, kind, proto, _, address in infos:
        with socket.socket(family, kind, proto) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind(address)
            except OSError as e:
                fix = FIXES.get(e.errno, f"choose another {flag}")
                raise ValueError(f"cannot listen on {host}:{port} ({e.strerror}); {fix}") from None


# ------------------------------------------------------------------------------------------- OS errors
# errno -> what to do about it, for the one line a command ends with.
FIXES = {
    errno.EROFS: "write somewhere else (another --out)",
    errno.EACCES: "write somewhere you may (another --out), or change the permissions",
    errno.EPERM: "write somewhere you may (another --out), or change the permissions",
    errno.ENOSPC: "free some space on that disk, or write somewhere else (another --out)",
    errno.EDQUOT: "free some space on that disk, or write somewhere else (another --out)",
    errno.ENOENT: "check the path",
    errno.ENOTDIR: "a file is where a directory is needed: remove or rename it, or choose another path",
    errno.EISDIR: "a directory is where a file is needed: give a file path",
    errno.EEXIST: "a file is where a directory is needed: remove or rename it, or choose another path",
    errno.ENOTEMPTY: "choose a new path",
    errno.EADDRINUSE: "pick another --port (0 picks a free one) or stop what listens there",
    errno.EADDRNOTAVAIL: "use 127.0.0.1 or one of this machine's own addresses (--host)",
    errno.ECONNREFUSED: "start the server first, or check the address",
    errno.EMFILE: "raise the limit (ulimit -n) or run fewer workers",
    errno.ENOMEM: "run fewer workers or smaller batches",
}


def os_error_message(e: OSError, resource: str | None = None) -> str:
    """One line for an OSError: the path (or `resource`) it concerns, what went wrong and what to do."""
    where = resource or " -> ".join(str(p) for p in (e.filename, e.filename2) if p is not None)
    what = e.strerror or str(e) or type(e).__name__
    fix = FIXES.get(e.errno)
    text = f"{where}: {what}" if where else what
    return f"{text}; {fix}" if fix else text


# ---------------------------------------------------------------------------------------------- URLs
def check_ws_url(url: str, what: str) -> str:
    """`url` when it is a WebSocket URL with a host (and a port in 0..65535 if it names one), else ValueError saying
    that `what` (a flag, or "a remote policy") is one; websockets' own errors name neither."""
    from urllib.parse import urlsplit

    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018  (raises on a port outside 0..65535 or one that is not a number)
    except ValueError as e:  # an unclosed IPv6 bracket, a port out of range
        raise ValueError(f"{what} is a WebSocket URL, ws://HOST:PORT or wss://HOST:PORT; got {url!r} ({e})") from None
    if parts.scheme not in ("ws", "wss") or not parts.hostname:
        raise ValueError(f"{what} is a WebSocket URL, ws://HOST:PORT or wss://HOST:PORT; got {url!r}")
    return url


def ws_endpoint(url: str) -> tuple[frozenset[str], int, str]:
    """What a checked WebSocket URL reaches, spelling aside: its host's addresses, its port (80 for ws, 443 for wss
    where it names none) and its path without a trailing slash. Two URLs whose hosts share an address, with the same
    port and path, reach one server (`ws://localhost:P`, `ws://127.0.0.1:P/`). An IP literal is its own address and
    a loopback name is resolved (a local lookup); any other name stays a lower-case name, never looked up here, so
    two names of one remote machine are not caught."""
    from urllib.parse import urlsplit

    parts, host = urlsplit(url), _ws_host(url)
    if is_loopback(host) and not _ip(host):
        try:
            addresses = {_ip(info[4][0]) for info in socket.getaddrinfo(host, None)} - {None}
        except OSError:  # no resolver: what localhost is everywhere
            addresses = set()
        names = frozenset(addresses or {"127.0.0.1", "::1"})
    else:
        names = frozenset({host})
    return names, parts.port or (443 if parts.scheme == "wss" else 80), parts.path.rstrip("/")


def _ws_host(url: str) -> str:
    """The host a WebSocket URL names, spelt one way for ws_proxy and ws_endpoint alike: without user info or the
    brackets of an IPv6 literal, in lower case, without a trailing dot ("localhost." is localhost), an IP literal as
    ipaddress writes it and an IPv4-mapped IPv6 one as IPv4 (`[::ffff:127.0.0.1]` is 127.0.0.1: ws_endpoint took it
    for that, while ws_proxy sent it through the environment's proxy); "" when it names none."""
    from urllib.parse import urlsplit

    host = (urlsplit(url).hostname or "").rstrip(".")
    return _ip(host) or host


def _ip(host: str) -> str | None:
    """`host`'s address written one way (an IPv4-mapped IPv6 address as IPv4), None when it is not an IP literal."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return None
    return str(getattr(ip, "ipv4_mapped", None) or ip)


def check_distinct_ws_urls(urls: typing.Sequence[str], flag: str) -> None:
    """ValueError naming both spellings when two of `urls` (each checked by check_ws_url) reach one server
    (`ws_endpoint`)."""
    seen: list[tuple[str, tuple]] = []
    for url in urls:
        names, port, path = ws_endpoint(url)
        for other, (other_names, other_port, other_path) in seen:
            if port == other_port and path == other_path and names & other_names:
                said = f"{flag} {url} is given twice" if url == other else \
                    f"{flag} {other} and {url} are one server"
                raise ValueError(f"{said}; name each server once (a server with more envs serves more: its "
                                 "--num-envs)")
        seen.append((url, (names, port, path)))


RAY_ADDRESS = re.compile(r"auto|(ray://)?[^\s:/]+:\d{1,5}")
"""What ray.init(address=...) takes: auto (the local cluster), or HOST:PORT, or ray://HOST:PORT (Ray Client)."""


def check_ray_address(address: str | None) -> str | None:
    """`address` when it is one Ray can take (None: no cluster), else ValueError naming the forms: said before the
    command writes anything (Ray's own "Invalid address format" came after the grid saved its settings)."""
    if address is not None and not RAY_ADDRESS.fullmatch(address):
        raise ValueError(f"--ray-address must be auto, HOST:PORT or ray://HOST:PORT, got {address!r}")
    return address
