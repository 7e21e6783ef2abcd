"""Decomposed metrics of a set of evaluated episodes (success, grasp-anything, reach)."""

from __future__ import annotations

import pandas as pd

METRICS = ("success", "grasp_any", "reach")
CONDITION_KEYS = ("regime", "split", "num_objects")


def rates(df: pd.DataFrame) -> dict:
    """n and the rate of each metric over the episodes in df."""
    n = int(len(df))
    return {"n": n, **{m: (float(df[m].mean()) if n else float("nan")) for m in METRICS}}


def summarize(episodes: pd.DataFrame) -> dict:
    """Per-condition figures, keyed "regime/split/num_objects"."""
    out = {}
    for key, df in episodes.groupby(list(CONDITION_KEYS), sort=False):
        out["/".join(str(k) for k in key)] = {**dict(zip(CONDITION_KEYS, key)), **rates(df)}
    return out
