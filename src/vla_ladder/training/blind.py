"""An instruction-blind copy of a recorded dataset: every episode's task is contract.BLIND_INSTRUCTION.

A policy trained on it (and evaluated with `lerobot:CKPT?instruction=<the same text>`) sees everything the
original policy sees but the instruction: the control that says what a learned policy scores by the layout
alone. Videos are hard links (nothing is re-encoded); the small Parquet files that carry task indices are
rewritten, and so are the task index's statistics (stats.json's, and each episode's in meta/episodes: they were the
original indices, one per instruction); LeRobot reads the copy as any other dataset. vla-ladder's provenance
(meta/vla_ladder_episodes: seed, layout, instruction) is kept: no training code reads it (`vla-ladder train` reads
the recording state's condition and contract only), and `vla-ladder check-dataset` checks the copy with it, and
checks that the copy shows no instruction and holds its source's frames and videos.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from vla_ladder import files
from vla_ladder.contract import BLIND_INSTRUCTION

STAMP = "meta/vla_ladder_blind.json"
FORMAT = 2
"""2: the task index's statistics are the copy's (a copy without a format, made before, is made again)"""


def blind_copy(src: str | os.PathLike, dst: str | os.PathLike) -> Path:
    """Make (or reuse) the instruction-blind copy of the dataset at `src` at `dst`."""
    src, dst = Path(src), Path(dst)
    info = json.loads((src / "meta" / "info.json").read_text())
    stamp = {"source": str(src.resolve()), "episodes": info["total_episodes"], "instruction": BLIND_INSTRUCTION,
             "format": FORMAT}
    if (dst / STAMP).is_file() and json.loads((dst / STAMP).read_text()) == stamp:
        return dst
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=files.temp_prefix(dst), dir=dst.parent))
    try:
        for dirpath, _, names in os.walk(src):
            rel = Path(dirpath).relative_to(src)
            (tmp / rel).mkdir(parents=True, exist_ok=True)
            for name in names:
                # Parquet files are rewritten below; everything else (videos, JSON) is shared.
                (shutil.copy2 if name.endswith((".parquet", ".json")) else os.link)(Path(dirpath) / name,
                                                                                      tmp / rel / name)
        pd.DataFrame({"task_index": [0]}, index=pd.Index([BLIND_INSTRUCTION], name="task")).to_parquet(
            tmp / "meta" / "tasks.parquet")
        for path in (tmp / "data").rglob("*.parquet"):
            df = pd.read_parquet(path)
            df["task_index"] = 0
            df.to_parquet(path, index=False)
        for path in (tmp / "meta" / "episodes").rglob("*.parquet"):
            df = pd.read_parquet(path)
            df["tasks"] = [[BLIND_INSTRUCTION]] * len(df)
            for col in df.columns:  # every frame's task index is 0 now; a count stays the count
                if col.startswith("stats/task_index/") and col != "stats/task_index/count":
                    df[col] = [np.zeros_like(v) for v in df[col]]
            df.to_parquet(path, index=False)
        stats_path = tmp / "meta" / "stats.json"
        if stats_path.is_file():
            stats = json.loads(stats_path.read_text())
            if "task_index" in stats:
                stats["task_index"] = {k: v if k == "count" else np.zeros_like(v).tolist()
                                       for k, v in stats["task_index"].items()}
                stats_path.write_text(json.dumps(stats, indent=4))
        card = tmp / "README.md"  # (a hard link to the source's card: replaced, not written through)
        if card.is_file():
            text = card.read_text()
            card.unlink()
            card.write_text(f"# Instruction-blind copy\n\nEvery frame's task here is \"{BLIND_INSTRUCTION}\": "
                            f"vla-ladder's instruction-blind copy of {src.resolve()}, for the blind twin (the policy "
                            "that sees everything but the instruction). The card below is the source's: the "
                            "instructions it lists are not in this copy's frames.\n\n" + text)
        info["total_tasks"] = 1
        (tmp / "meta" / "info.json").write_text(json.dumps(info, indent=4))
        (tmp / STAMP).write_text(json.dumps(stamp))
        if dst.exists():
            shutil.rmtree(dst)
        tmp.rename(dst)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dst
