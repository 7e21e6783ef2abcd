"""Result files that are whole or absent: every writer goes through a temp file, flushed to disk, and os.replace.

Named `files` rather than `io` so that it never shadows the standard library module.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to `path`; it replaces `path` only if the block finishes, once its bytes are on
    disk: a file system may commit the rename before the data, so a host crash could otherwise leave an empty file
    under the name (a killed process cannot: what it wrote is in the page cache either way)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp makes the file private (0600); results are for everyone the umask allows.
        os.chmod(tmp, 0o666 & ~_umask())
        _fsync(tmp)
        os.replace(tmp, path)
        with contextlib.suppress(OSError):  # the rename itself; some file systems cannot sync a directory
            _fsync(path.parent, os.O_DIRECTORY)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _umask() -> int:
    """The process's umask, read without changing it: setting it to read it (os.umask) would, for that moment, give
    files that another thread creates (the recorder's writers, LeRobot's encoders) permissions for everyone."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1], 8) for line in f if line.startswith("Umask:"))
    except (OSError, StopIteration, ValueError):  # not Linux, or a kernel before 4.7
        umask = os.umask(0o022)
        os.umask(umask)
        return umask


def temp_prefix(path: Path) -> str:
    """A hidden temporary sibling's name start: `path`'s name, cut short so that the temporary name stays within
    the file system's 255 bytes however long the name it stands in for (tempfile adds 8 characters and a suffix)."""
    return f".{os.fsencode(path.name)[:100].decode(errors='ignore')}."


def sibling_name(path: str | os.PathLike, suffix: str) -> str:
    """The name of `path`'s hidden sibling that every process must find (`.NAME.lock`, a recorder's
    `.NAME.recording`): a name too long for the file system's 255 bytes with the dot and `suffix` is cut, and told
    apart from the other names it is cut from by a hash of the whole."""
    import hashlib

    name = os.fsencode(Path(path).name)
    if len(name) + 1 + len(suffix.encode()) <= 255:
        return os.fsdecode(b"." + name) + suffix
    return f".{name[:100].decode(errors='ignore')}~{hashlib.sha256(name).hexdigest()[:16]}{suffix}"


def _fsync(path: str | os.PathLike, flags: int = 0) -> None:
    fd = os.open(path, os.O_RDONLY | flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary directory next to `path`, renamed to `path` only if the block finishes: a directory built
    there is whole or absent. Where another process built `path` first (from the same inputs), theirs is kept."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(path), dir=path.parent))
    try:
        yield tmp
        try:
            tmp.rename(path)
        except OSError:
            if not path.is_dir():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def remove_dir(path: str | os.PathLike) -> None:
    """Delete directory `path` in a way a kill cannot leave half done under its name: renamed aside to a hidden
    sibling first (one step), then deleted. A half-deleted run directory would be refused as not a run of ours."""
    path = Path(path).resolve()  # ("." has no name: its aside would be made inside it)
    if Path.cwd().resolve().is_relative_to(path):
        raise ValueError(f"{path} holds the current directory, which it cannot remove; run the command from "
                         "elsewhere, or give another --out")
    aside = Path(tempfile.mkdtemp(prefix=temp_prefix(path) + "removing.", dir=path.parent))
    path.rename(aside / path.name)
    shutil.rmtree(aside)


def lock_path(directory: str | os.PathLike) -> Path:
    """The lock file of an output directory: beside it, so that nothing a run removes or lists inside takes it."""
    directory = Path(directory).resolve()  # (one lock whichever path or link names the directory)
    return directory.parent / sibling_name(directory, ".lock")


@contextmanager
def writing(directory: str | os.PathLike, what: str) -> Iterator[None]:
    """Hold `directory`'s lock (lock_path) while the block runs; ValueError at once when another process holds it.
    A study, training run or evaluation started again while the first still runs (in another terminal, or after
    the first only seemed to have died) would otherwise write the same files, or remove a run that had not saved
    its first checkpoint yet. The kernel releases the lock when its holder dies, kill -9 included.

    The holder removes the lock file before it lets go, so none is left beside the output (a refused --out
    included); a process that locked a file already removed tries again with the path's new one."""
    import fcntl

    path = lock_path(directory)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        with open(path, "a+") as f:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise ValueError(f"another {what} is writing {directory} (it holds {path}); let it finish or stop "
                                 "it, then run this again") from None
            try:
                held = os.stat(path).st_ino == os.fstat(f.fileno()).st_ino
            except FileNotFoundError:
                held = False
            if not held:  # its holder removed it between our open and our lock: lock the path's file instead
                continue
            try:
                yield
            finally:
                path.unlink(missing_ok=True)  # (while locked: nobody else holds this file)
            return


@contextmanager
def own_tempdir() -> Iterator[Path]:
    """Point `tempfile`'s default directory at a fresh one for the block, and remove it with whatever was left.

    For library calls that leave files behind: LeRobot's `PreTrainedConfig.from_pretrained` writes the config
    it parses to a `NamedTemporaryFile(delete=False)` and never removes it, one file in /tmp per policy load,
    thousands over a study. The setting is process-wide, so use it around loading, not around threaded work.
    """
    previous = tempfile.tempdir
    with tempfile.TemporaryDirectory(prefix="vla-ladder-") as own:
        tempfile.tempdir = own
        try:
            yield Path(own)
        finally:
            tempfile.tempdir = previous


def claim_dir(out: Path, previous: dict | None, request: dict, overwrite: bool, kind: str, dir_kind: str) -> None:
    """Make directory `out` ready for `request` (what decides a command's results): resumed when `previous`, what
    it was last asked (None: nothing saved), is the same; another request refused in one line unless `overwrite`,
    which starts afresh. Files of something else are refused even with `overwrite`: it replaces only a directory
    of its own kind, never a folder of someone's files. `kind` names the request in the error ("probe"),
    `dir_kind` the directory ("a probe directory")."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {str(out)!r} is a file; give a directory")
    if out.is_dir() and any(out.iterdir()) and previous != request:
        if previous is None:
            raise ValueError(f"{out} holds files that are not {dir_kind} (--overwrite replaces only {dir_kind}); "
                             "pick a new or empty --out")
        if not overwrite:
            # Name what differs: a default that changed (a regime added to "all") reads like the same command.
            differ = sorted(k for k in {*previous, *request} if previous.get(k) != request.get(k))
            raise ValueError(f"{out} holds another {kind} request (it differs in {', '.join(differ)}: "
                             f"{'; '.join(f'{k} was {previous.get(k)!r}' for k in differ)[:300]}); rerun the "
                             "command that made it to resume it, pick a new --out, or pass --overwrite")
        remove_dir(out)


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """`data` as strict JSON at `path` (atomically): an undefined number (NaN, a rate over no scenes; an infinity)
    is written as null, which every JSON parser reads, where Python's json would write NaN, which JSON.parse, jq and
    most other languages' parsers refuse. A reader that computes with such a value reads null as NaN
    (`number`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(dumps(data, indent=2) + "\n")
    return Path(path)


def dumps(data: Any, **kwargs) -> str:
    """`data` as strict JSON text: non-finite numbers as null (`finite`), numpy values and paths as plain ones
    (`json_default`). What every JSON that vla-ladder writes for others to read goes through; a non-finite number
    that `finite` did not reach fails here (allow_nan=False) rather than write a file strict parsers refuse."""
    return json.dumps(finite(data), default=json_default, allow_nan=False, **kwargs)


def finite(data: Any) -> Any:
    """`data` with every non-finite float (NaN, +-inf; numpy's and those inside numpy arrays too) replaced by None,
    numpy scalars and arrays as Python values, tuples as lists: what strict JSON can hold."""
    import numpy as np

    def walk(o):
        if isinstance(o, float):  # (numpy's float64 is one)
            return float(o) if math.isfinite(o) else None
        if isinstance(o, dict):
            return {k: walk(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [walk(v) for v in o]
        if isinstance(o, np.ndarray):
            return walk(o.tolist())
        if isinstance(o, np.generic):  # float32, int64, bool_ ...
            return walk(o.item())
        return o

    return walk(data)


def number(x: Any) -> Any:
    """A number as a result file holds it, for a reader that computes or formats with it: NaN for null, which
    write_json writes for an undefined number (files written before it hold NaN itself, which json reads as NaN)."""
    return float("nan") if x is None else x


def write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_parquet(path: str | os.PathLike, frame) -> Path:
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, index=False)
    return Path(path)


def json_default(o):
    """json.dumps' `default` for what results hold besides plain types: numpy scalars and arrays, paths."""
    import numpy as np
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def plain(data):
    """`data` as write_json stores it and json.load gives it back (tuples as lists, paths as strings, numpy values
    as Python ones, non-finite numbers as None): what a config compares equal to once saved."""
    return json.loads(dumps(data))


def first_difference(a, b, where: str = "") -> str:
    """The path of the first field where two JSON values differ ("policies[1].train_seed"), "" where they are equal:
    what a refusal to resume names."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            found = first_difference(a.get(key), b.get(key), f"{where}.{key}" if where else key)
            if found:
                return found
        return ""
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        found = (first_difference(x, y, f"{where}[{i}]") for i, (x, y) in enumerate(zip(a, b)))
        return next((f for f in found if f), "")
    return "" if a == b else (where or "the whole")


def _checkout_version() -> str | None:
    """The version in the checkout's pyproject.toml, for a run from src/ on the path without installing (the GPU
    kit does that), so its results still say which vla-ladder made them."""
    import tomllib
    pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
    if not pyproject.is_file():
        return None
    return tomllib.loads(pyproject.read_text()).get("project", {}).get("version")


def cpu_model() -> str | None:
    """The CPU's model name and widest vector extension (Linux), e.g. "Intel(R) Xeon(R) Processor, avx512f", or
    None. Physics replays bit for bit on one machine, but another host (or another SAPIEN build) may differ in the
    last bits of a step, which can flip a marginal grasp: results say where they were measured."""
    try:
        with open("/proc/cpuinfo") as f:
            info = dict(line.split(":", 1) for line in f.read().split("\n\n")[0].splitlines() if ":" in line)
    except OSError:
        return None
    info = {k.strip(): v.strip() for k, v in info.items()}
    flags = set(info.get("flags", "").split())
    isa = next((f for f in ("avx512f", "avx2", "avx", "sse4_2") if f in flags), None)
    return ", ".join(x for x in (info.get("model name"), isa) if x) or None


def provenance(object_set: str | None = None) -> dict:
    """Versions, CPU and asset set to stamp into every result file."""
    from importlib.metadata import PackageNotFoundError, version
    out = {}
    for pkg in ("vla-ladder", "mani-skill", "sapien", "lerobot", "torch", "numpy"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = _checkout_version() if pkg == "vla-ladder" else None
    out["cpu"] = cpu_model()
    if object_set is not None:
        out["object_set"] = object_set
    return out
