"""physx_cuda's PhysX GPU library: found, fetchable, or a one-line error before any simulator starts.

SAPIEN (3.0.x) does not ship the closed-source `libPhysXGpu_64.so`: `sapien.physx.enable_gpu()` downloads it
from a GitHub release into ~/.sapien/physx/<physx version>/ the first time a physx_cuda scene is made. On a
machine that cannot reach GitHub (clusters, this project's GPU machines) that download fails deep inside env
creation, or waits on a connection. `check_physx_gpu` looks first, so a command that asks for physx_cuda says
where the file must go instead.
"""

from __future__ import annotations

import platform
import urllib.error
import urllib.request
from pathlib import Path

# The simulator backends vla-ladder runs: one env per process on the CPU, or many at once on a CUDA GPU.
SIM_BACKENDS = ("physx_cpu", "physx_cuda")
RELEASES = "https://github.com/sapien-sim/physx-precompiled/releases/download"


def check_sim_backend(sim_backend: str, flag: str = "--sim-backend", allowed: tuple[str, ...] = SIM_BACKENDS) -> None:
    """ValueError naming the backends for one vla-ladder does not run (eval, train-expert, the LeRobot env)."""
    if sim_backend not in allowed:
        raise ValueError(f"{flag}: unknown sim_backend {sim_backend!r}; allowed: {', '.join(allowed)}")


def library() -> tuple[Path, str]:
    """Where SAPIEN looks for the PhysX GPU library, and the URL of the archive it downloads it from."""
    from sapien.physx import version

    parent = Path.home() / ".sapien" / "physx" / version()
    archive = "linux-aarch64-so.zip" if platform.machine() in ("aarch64", "arm64") else "linux-so.zip"
    return parent / "libPhysXGpu_64.so", f"{RELEASES}/{version()}/{archive}"


def check_physx_gpu(timeout_s: float = 5.0, url: str | None = None) -> Path:
    """The library's path when it is on disk or SAPIEN can download it; ValueError naming the path otherwise.

    `url` overrides where the download is tried (tests)."""
    path, release = library()
    if path.is_file():
        return path
    url = url or release
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method="HEAD"), timeout=timeout_s):
            return path  # reachable: SAPIEN downloads it on first use
    except (urllib.error.URLError, OSError) as e:
        reason = f"HTTP {e.code} {e.reason}" if isinstance(e, urllib.error.HTTPError) else getattr(e, "reason", e)
        raise ValueError(f"physx_cuda needs SAPIEN's PhysX GPU library {path}, which SAPIEN downloads from {url} "
                         f"on first use, and it cannot be fetched from here ({reason}); download it on "
                         f"a machine with network and unzip it into {path.parent}, or use physx_cpu with "
                         "--workers N") from None


def check_physx_cuda(no_gpu: str) -> Path:
    """What physx_cuda needs before any simulator: a CUDA GPU (ValueError(no_gpu), the caller's advice, without
    one), then the PhysX GPU library (`check_physx_gpu`)."""
    import torch

    if not torch.cuda.is_available():
        raise ValueError(no_gpu)
    return check_physx_gpu()
