"""How OpenMP's wait policy and the calling thread change a LeRobot policy's CPU chunk latency.

`vla-ladder` starts with OMP_WAIT_POLICY=PASSIVE unless it is set (cli.py): OpenMP workers then sleep between
parallel regions instead of spinning, which is kind to a machine whose cores are busy with simulation processes
and costly on one whose cores are free (every small matmul wakes a sleeping worker). `serve-policy` runs its
forward passes on the main thread for a related reason: torch's OpenMP pool belongs to the thread that made it,
and a second thread's pool makes libgomp's workers outnumber the cores, so they stop spinning anyway.

For each wait policy (PASSIVE, ACTIVE, unset: libgomp spins a while, then sleeps), each thread (the main one, or
another thread of the same process), and each number of busy-looping processes beside it (--hogs), a fresh
process loads CHECKPOINT with torch's default thread count and times one chunk of one observation.

    .venv/bin/python benchmarks/openmp_wait.py CHECKPOINT [--repeats 20] [--hogs 0 1 2] [--out FILE]

Writes benchmarks/results/openmp_wait_cpu.json.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

from vla_ladder import files
from vla_ladder.machine import cores

RESULTS = Path(__file__).parent / "results"
CHILD = "VLA_LADDER_OPENMP_WAIT_CHILD"  # set in the measuring process: "main" or "other" (the thread that infers)
POLICIES = ("PASSIVE", "ACTIVE", None)


@dataclass
class Args:
    checkpoint: tyro.conf.Positional[str]
    """a LeRobot checkpoint (its chunk is what is timed)"""
    repeats: int = 20
    """chunks timed in each setting (after two untimed)"""
    hogs: tuple[int, ...] = (0, 1, 2)
    """busy-looping processes running beside the measurement (0: an idle machine)"""
    out: Path = RESULTS / "openmp_wait_cpu.json"
    """result file"""

    def __post_init__(self):
        # checked before the first child loads the model: no timed chunk would leave an empty median after the load
        if self.repeats < 1:
            raise ValueError(f"--repeats must be >= 1, got {self.repeats}")


def child(checkpoint: str, repeats: int, thread: str) -> None:
    """In the measuring process: the median chunk in ms, printed as JSON."""
    import torch

    sys.path.insert(0, str(Path(__file__).parent))
    from remote_overhead import observation

    from vla_ladder.policies import load_policy
    from vla_ladder.policies.serving import read_request

    # on the CPU even where a GPU is visible (a spec without a device picks cuda then): this times CPU inference
    policy = load_policy(f"lerobot:{checkpoint}?device=cpu")
    batch, prompt, _, _ = read_request(observation())
    times: list[float] = []

    def measure() -> None:
        for _ in range(repeats + 2):
            t0 = time.perf_counter()
            policy.predict_chunk(batch, [prompt])
            times.append(time.perf_counter() - t0)

    if thread == "main":
        measure()
    else:
        worker = threading.Thread(target=measure)
        worker.start()
        worker.join()
    print(json.dumps({"chunk_ms": round(statistics.median(times[2:]) * 1000, 2), "torch_threads":
                      torch.get_num_threads()}))


def main(args: Args) -> dict:
    load_before = os.getloadavg()[0]
    rows = []
    for hogs in args.hogs:
        for policy in POLICIES:
            for thread in ("main", "other"):
                env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
                env.update({CHILD: thread, **({"OMP_WAIT_POLICY": policy} if policy else {})})
                busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(hogs)]
                try:
                    done = subprocess.run([sys.executable, __file__, args.checkpoint, "--repeats", str(args.repeats)],
                                          env=env, capture_output=True, text=True, check=True)
                finally:
                    for p in busy:
                        p.kill()
                        p.wait()
                row = {"hogs": hogs, "omp_wait_policy": policy or "unset", "thread": thread,
                       **json.loads(done.stdout.strip().splitlines()[-1])}
                rows.append(row)
                print(row, flush=True)
    import torch

    # the GPU is not used (the child infers on the CPU) but says which machine this was
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    result = {"benchmark": "openmp_wait", "checkpoint": args.checkpoint, "repeats": args.repeats, "rows": rows,
              "machine": {"cores": cores(), "gpu": gpu, "load_average_1min": [load_before, os.getloadavg()[0]]},
              "provenance": files.provenance(),
              "note": "median ms of one chunk (batch 1) on the CPU with torch's default threads; hogs = busy-looping "
                      "processes beside it; thread = the thread that infers (other: a second thread of the process)"}
    files.write_json(args.out, result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    cli = tyro.cli(Args)
    if os.environ.get(CHILD):
        child(cli.checkpoint, cli.repeats, os.environ[CHILD])
    else:
        main(cli)
