"""torchcodec where the system has no FFmpeg: LeRobot's fast video decoder, run on the FFmpeg that PyAV bundles.

LeRobot decodes training videos with torchcodec when it loads and falls back to PyAV otherwise, which is 3.1x
slower a frame of a 400-demo dataset's 20000-frame AV1 file (1.94 ms against 0.63 ms on the 2-core machine,
benchmarks/results/video_codec.json: torchcodec keeps each file's decoder open, PyAV opens the file for every
sample). torchcodec ships no FFmpeg: it loads the system's shared libraries (FFmpeg 4 to 8), which clusters and
this project's GPU machines often lack, and there the H100's study trainings waited on PyAV for half of every step
(docs/gpu.md). PyAV's wheels carry FFmpeg under renamed files (auditwheel);
`ffmpeg_links` links them under the names torchcodec asks for, and a process started with those links and PyAV's
library directory first on LD_LIBRARY_PATH loads torchcodec on them. The dynamic loader reads LD_LIBRARY_PATH
once, when a process starts, so `restart_with_torchcodec` starts the command again with it, once.
"""

from __future__ import annotations

import importlib
import os
import shutil
import sys
import tempfile
from pathlib import Path

from vla_ladder.machine import cache_root

RESTARTED = "VLA_LADDER_TORCHCODEC_ON_PYAV"
"""Set in a command restarted with PyAV's FFmpeg: it never restarts twice."""


def torchcodec_loads() -> bool:
    """Whether torchcodec imports here (it loads its FFmpeg libraries on import)."""
    try:
        importlib.import_module("torchcodec")
        return True
    except (ImportError, OSError, RuntimeError):
        return False


def pyav_libraries() -> Path | None:
    """The directory of the shared libraries a PyAV wheel bundles (FFmpeg's among them), or None (a PyAV built
    against the system's FFmpeg, or none)."""
    try:
        import av
    except ImportError:
        return None
    libs = Path(av.__file__).resolve().parent.parent / "av.libs"
    return libs if libs.is_dir() else None


def ffmpeg_links(libs: Path, root: Path) -> Path:
    """A directory under `root` where each FFmpeg library of PyAV's `libs` is linked as lib<name>.so.<major>, the
    names torchcodec's builds ask for. Built once per PyAV version, atomically (concurrent builders: one wins)."""
    import av

    out = root / f"ffmpeg-of-pyav-{av.__version__}"
    if out.is_dir():
        return out
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=".ffmpeg-"))
    for name, (major, *_) in av.library_versions.items():
        found = sorted(libs.glob(f"{name}-*.so.{major}*"))
        if not found:
            shutil.rmtree(tmp)
            raise FileNotFoundError(f"PyAV reports {name} {major} but {libs} holds no {name}-*.so.{major}*")
        (tmp / f"{name}.so.{major}").symlink_to(found[0])
    try:
        tmp.rename(out)
    except OSError:  # another process built it meanwhile
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def torchcodec_env(root: Path) -> dict[str, str] | None:
    """This process's environment with PyAV's FFmpeg first on LD_LIBRARY_PATH (None without a bundled FFmpeg)."""
    libs = pyav_libraries()
    if libs is None:
        return None
    paths = [str(ffmpeg_links(libs, root)), str(libs), os.environ.get("LD_LIBRARY_PATH", "")]
    return {**os.environ, "LD_LIBRARY_PATH": os.pathsep.join(p for p in paths if p), RESTARTED: "1"}


def restart_with_torchcodec(argv: list[str]) -> None:
    """Where torchcodec does not load but PyAV bundles FFmpeg, run `vla-ladder ARGV` again in this process's place
    with that FFmpeg on LD_LIBRARY_PATH (the training, and every unit a study or grid spawns, then decodes with
    torchcodec); otherwise return and go on."""
    if os.environ.get(RESTARTED) or torchcodec_loads():
        return
    try:
        env = torchcodec_env(cache_root())
    except OSError as e:  # a cache that cannot be written, a PyAV laid out otherwise: a speed-up missed, no more
        print(f"vla-ladder: torchcodec finds no FFmpeg libraries here and PyAV's could not be linked ({e}); LeRobot "
              "decodes with PyAV", file=sys.stderr, flush=True)
        return
    if env is None:
        return
    print("vla-ladder: torchcodec finds no FFmpeg libraries here; restarting with PyAV's own FFmpeg on "
          f"LD_LIBRARY_PATH, for LeRobot's faster video decoding ({env['LD_LIBRARY_PATH'].split(os.pathsep)[0]})",
          file=sys.stderr, flush=True)
    sys.stdout.flush()
    os.execve(sys.executable, [sys.executable, "-m", "vla_ladder.cli", *argv], env)
