"""Rates with 95% Wilson score intervals (statsmodels): the one statistic every stage reports.

A policy evaluated on 100 episodes per condition cannot be told apart from one 8 points better without an
interval, so no rate is ever written without one.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
from statsmodels.stats.proportion import proportion_confint

from vla_ladder.contract import METRICS

CONFIDENCE = 0.95


def wilson(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of k successes in n trials (nan, nan for n = 0)."""
    if n == 0:
        return float("nan"), float("nan")
    lo, hi = proportion_confint(int(k), int(n), alpha=1 - confidence, method="wilson")
    # At k = 0 statsmodels' lower bound comes out a rounding error above 0 (5.6e-17 for n = 3): keep the rate inside.
    return min(float(lo), k / n), max(float(hi), k / n)


def mcnemar_power(p1: float, p2: float, n: int, alpha: float = 0.05) -> float:
    """The exact probability that McNemar's exact test (two-sided, at `alpha`; what `vla-ladder compare` stars)
    finds a difference between two runs of the same `n` scenes whose outcomes are independent draws at rates p1
    and p2, as a policy's own sampling makes them (README: 44 of 100 episodes changed outcome on a replay). A sum
    over the counts of the two kinds of discordant pairs, within 10 standard deviations of their means."""
    from scipy.special import gammaln, xlogy
    from scipy.stats import binom

    qa, qb = p1 * (1 - p2), p2 * (1 - p1)  # P(only A succeeds), P(only B succeeds) in one scene

    def support(q: float) -> np.ndarray:
        half = 10 * math.sqrt(n * q * (1 - q)) + 1
        return np.arange(max(0, math.floor(n * q - half)), min(n, math.ceil(n * q + half)) + 1)

    i, j = np.meshgrid(support(qa), support(qb), indexing="ij")
    rest = n - i - j
    ok = rest >= 0
    i, j, rest = i[ok], j[ok], rest[ok]
    # xlogy(0, 0) = 0: a kind of pair that cannot occur (q = 0) weighs 0 unless counted.
    log_pmf = (gammaln(n + 1) - gammaln(i + 1) - gammaln(j + 1) - gammaln(rest + 1)
               + xlogy(i, qa) + xlogy(j, qb) + xlogy(rest, 1 - qa - qb))
    p_value = np.minimum(1.0, 2 * binom.cdf(np.minimum(i, j), i + j, 0.5))
    return float(np.exp(log_pmf)[p_value < alpha].sum())


def detectable_difference(rate: float, n: int, alpha: float = 0.05, power: float = 0.8) -> float:
    """The smallest difference between two true rates around `rate` (centred on it, shifted to stay in [0, 1])
    that McNemar's exact test on `n` paired scenes finds with probability `power` when the scenes' outcomes are
    independent draws: a comparison that is not significant says little more than that the difference is
    probably below this. For policies whose outcomes a scene decides (the scripted expert, the reference
    policies) pairing finds smaller differences; for one that samples its actions this is what it can see."""
    if n < 1 or not 0 <= rate <= 1 or not 0 < power < 1:
        raise ValueError(f"need n >= 1, a rate in [0, 1] and a power in (0, 1), got n={n}, rate={rate}, "
                         f"power={power}")

    def rates_apart(d: float) -> tuple[float, float]:
        lo = min(max(rate - d / 2, 0.0), 1.0 - d)
        return lo, lo + d

    if mcnemar_power(*rates_apart(1.0), n, alpha) < power:
        return float("nan")  # not even 0 against 1 is found that often (n too small)
    lo, hi = 0.0, 1.0
    while hi - lo > 1e-4:  # power grows with the difference: bisect
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if mcnemar_power(*rates_apart(mid), n, alpha) >= power else (mid, hi)
    return hi


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
