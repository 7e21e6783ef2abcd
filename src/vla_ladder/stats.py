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


def wilson(k: float, n: float, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of k successes in n trials (nan, nan for n = 0); n may be an effective number of
    trials, not a whole one (grounding.pooled_rate's)."""
    if n == 0:
        return float("nan"), float("nan")
    lo, hi = proportion_confint(k, n, alpha=1 - confidence, method="wilson")
    # At k = 0 statsmodels' lower bound comes out a rounding error above 0 (5.6e-17 for n = 3): keep the rate inside.
    return min(float(lo), k / n), max(float(hi), k / n)


def paired_difference(x: np.ndarray, y: np.ndarray, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Interval of mean(y) - mean(x) for paired binary outcomes (x[i], y[i] the same scene twice): Newcombe's hybrid
    score interval for paired data (Statistics in Medicine 1998, method 10), which combines the two rates' Wilson
    intervals through their correlation. Unlike a bootstrap over scenes it keeps its width when no scene changes (0 of
    50 changed, all failing both times: [-7, 7] points, not [0, 0]). Like McNemar's asymptotic test it can exclude 0
    where the exact test, conservative on few changes, does not (4 of 10 scenes lose a success, none gains one:
    [-69, -4] points, exact p = 0.125). nan, nan for no scenes."""
    x, y = np.asarray(x, bool), np.asarray(y, bool)
    n = len(x)
    if n == 0:
        return float("nan"), float("nan")
    both, only_y, only_x, neither = (int(v.sum()) for v in (x & y, y & ~x, x & ~y, ~x & ~y))
    py, px = (both + only_y) / n, (both + only_x) / n
    ly, uy = wilson(both + only_y, n, confidence)
    lx, ux = wilson(both + only_x, n, confidence)
    margins = (both + only_y) * (only_x + neither) * (both + only_x) * (only_y + neither)
    # The correlation of the two rates, with Newcombe's continuity correction of a positive one.
    a = both * neither - only_y * only_x
    psi = 0.0 if margins == 0 or 0 <= a <= n / 2 else (a - n / 2 if a > 0 else a) / math.sqrt(margins)
    return difference_interval((px, lx, ux), (py, ly, uy), psi)


def difference_interval(x: tuple[float, float, float], y: tuple[float, float, float],
                        correlation: float) -> tuple[float, float]:
    """Interval of y - x from each rate's own (value, lo, hi) and the correlation of the two estimates: the MOVER
    construction (Zou and Donner, Statistical Methods in Medical Research 2008), which recovers the variance of
    each rate near its limits from its own interval. Newcombe's paired interval (paired_difference) is this with
    Wilson intervals and a continuity-corrected phi; the absent object's grasp change uses it with a rate pooled
    over each scene's plays (grounding.absent_object). Clipped to [-1, 1]."""
    (px, lx, ux), (py, ly, uy) = x, y
    diff = py - px
    lo = diff - math.sqrt(max((py - ly) ** 2 + (ux - px) ** 2 - 2 * correlation * (py - ly) * (ux - px), 0.0))
    hi = diff + math.sqrt(max((px - lx) ** 2 + (uy - py) ** 2 - 2 * correlation * (px - lx) * (uy - py), 0.0))
    return max(lo, -1.0), min(hi, 1.0)


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
        if df[m].isna().any():  # (astype(bool) would count a missing outcome as a success)
            raise ValueError(f"{int(df[m].isna().sum())} episode(s) have no {m} outcome (NaN); rates need every one")
        k = int(df[m].astype(bool).sum()) if n else 0
        out[m] = k / n if n else float("nan")
        ci[m] = list(wilson(k, n))
    out["ci95"] = ci
    return out
