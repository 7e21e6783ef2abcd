"""What this machine offers to worker processes: CPU cores and memory."""

from __future__ import annotations

import os

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
