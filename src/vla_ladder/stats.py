"""Rates with 95% Wilson score intervals (statsmodels): the one statistic every stage reports.

A policy evaluated on 100 episodes per condition cannot be told apart from one 8 points better without an
interval, so no rate is ever written without one.
"""

from __future__ import annotations

import pandas as pd
from statsmodels.stats.proportion import proportion_confint

from vla_ladder.contract import METRICS

CONFIDENCE = 0.95


def wilson(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of k successes in n trials (nan, nan for n = 0)."""
    if n == 0:
        return float("nan"), float("nan")
    lo, hi = proportion_confint(int(k), int(n), alpha=1 - confidence, method="wilson")
    return float(lo), float(hi)


def rates(df: pd.DataFrame, metrics=METRICS) -> dict:
    """n, the rate of each metric over the episodes in df, and its Wilson interval under "ci95"."""
    n = int(len(df))
    out: dict = {"n": n}
    ci = {}
    for m in metrics:
        k = int(df[m].astype(bool).sum()) if n else 0
        out[m] = k / n if n else float("nan")
        ci[m] = list(wilson(k, n))
    out["ci95"] = ci
    return out
