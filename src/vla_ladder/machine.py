"""What this machine offers: CPU cores and memory for worker processes, and a cache directory for built files."""

from __future__ import annotations

import os
from pathlib import Path

WORKER_MEMORY_BYTES = 2 * 2**30
"""Memory one simulation worker needs with two rendered cameras and a small policy (~1.1 GB peak measured for
a tiny SmolVLA): automatic worker counts keep this much free per worker."""


def cores() -> int:
    """CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def auto_workers(requested: int = 0) -> int:
    """`requested`, or (0) one per CPU core, capped by the memory available for WORKER_MEMORY_BYTES each."""
    if requested > 0:
        return requested
    try:
        available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):
        return cores()
    return max(1, min(cores(), available // WORKER_MEMORY_BYTES))


def check_workers(workers: int, flag: str = "--workers") -> int:
    """`workers` when it is 0 (one per core) or what this machine's memory holds at WORKER_MEMORY_BYTES each, else
    ValueError: each worker is a process with a simulator and a copy of the policy, and a thousand of them were
    started as asked."""
    if workers < 0:
        raise ValueError(f"{flag} must be >= 0 (0: one per core), got {workers}")
    try:
        most = max(cores(), os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // WORKER_MEMORY_BYTES)
    except (ValueError, OSError):
        return workers
    if workers > most:
        raise ValueError(f"{flag} must be at most {most} here (each worker takes about "
                         f"{WORKER_MEMORY_BYTES // 2**30} GiB; 0: one per core), got {workers}")
    return workers


def cache_root() -> Path:
    """Where files built once per machine live (the lite robot, FFmpeg links): $VLA_LADDER_CACHE, else
    ~/.cache/vla-ladder. An empty $VLA_LADDER_CACHE (a variable set to an unset one's value) counts as unset: as a
    path it would be the current directory."""
    return Path(os.environ.get("VLA_LADDER_CACHE") or Path.home() / ".cache" / "vla-ladder")


def limit_threads(threads: int) -> None:
    """In a worker process, before its renderer starts: `threads` threads for lavapipe and for torch, so that N
    worker processes use N cores instead of all fighting over all of them."""
    os.environ.setdefault("LP_NUM_THREADS", str(threads))  # lavapipe: read when Vulkan starts
    import torch

    torch.set_num_threads(threads)


def auto_writers(servers: int, requested: int = 0) -> int:
    """`requested`, or (0) one dataset writer per two simulation servers: on 2 idle cores a writer takes 0.24 s a
    demo (0.40 CPU s) and a server rendering on the CPU 1.2 s (benchmarks/results/record_speed_cpu.json), so one
    writer keeps up with several servers; on the 16-core GPU machine a writer cost 0.88 CPU s a demo and a server,
    rendering on the GPU, 0.7-0.85 s (H200, 2026-11-27; docs/benchmarks.md), about one writer per server, so one per
    two servers is the margin for both. (The rule was set when a writer cost 0.9 and 3.3 CPU s, before the writer's
    image statistics and encoder settings were made cheaper.)"""
    return requested if requested > 0 else max(1, servers // 2)


def exit_with_parent() -> None:
    """In a spawned worker (a process pool's, a vector env's): end, with SIGTERM, when the process that started it
    dies, even by kill -9, instead of idling on with its memory. A no-op in a process that multiprocessing did not
    start (a vector env builds one env in its caller too). Linux sends it when the thread that started the worker
    ends: start workers from a thread that lives as long as they should."""
    import multiprocessing
    import signal

    if multiprocessing.parent_process() is not None:
        signal_on_parent_death(signal.SIGTERM)


def signal_on_parent_death(sig: int) -> None:
    """Linux: have the kernel send `sig` to this process when its parent dies (prctl PR_SET_PDEATHSIG), so that a
    child does not outlive a parent killed with kill -9. Elsewhere a no-op: the child may outlive it."""
    import ctypes

    PR_SET_PDEATHSIG = 1
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, sig)
    except (OSError, AttributeError):
        pass
