"""Success against how far the named object stands from its place in training: the curve between the ladder's rungs.

The ladder measures four points (small, medium, large jitter, full random). An episode's displacement is the
distance from the instructed object to the nearest centre of the regions it stands in in the training condition's
layouts (layouts.usual_regions: region i for object i in the canonical split, its three training regions in the
pairing splits). Pooled over a ladder's regimes it runs from about 0 (small jitter) to 40 cm and more (full random),
so one run directory of `vla-ladder eval --regimes all` says where along the way a policy stops finding the object.

- bins: each metric's rate per displacement bin (DISPLACEMENT_BINS_CM), with Wilson intervals (stats.rates);
- far from the place (FAR_CM and more, where the object's centre and its usual place lie two reach thresholds apart;
  reach is measured to the object's box, so an object over 5 cm in radius could in principle let both hold at
  once, which no committed episode did): the share of episodes that reach the object and the share whose gripper
  ends at the object's usual place instead (within REACH_THRESHOLD of a usual region's centre, horizontally, as the
  absent-object probe measures it, but whether or not a distractor stands there: the probe counts empty places
  only), with Wilson intervals, and the second minus the first (Newcombe's paired interval: +1 always the
  place, -1 always the object): the location shortcut seen in ordinary episodes, no probe needed;
- the trend: a logistic regression of the metric on the displacement (statsmodels' Logit, profile-likelihood
  interval, likelihood-ratio p-value), as the odds ratio per 10 cm. A policy that goes to the named object wherever
  it stands is flat (about 1); one that goes to where the object usually stands falls off steeply. Where success is
  all-or-nothing on either side of some distance (a pure location shortcut: every near episode succeeds, no far one
  does) the slope is unbounded: no estimate is given, but the one-sided bound the data allow is (the odds ratio per
  10 cm is at most X), with the reason; the bins show where it falls.

A policy trained in full random has no usual place (no regions): there is nothing to measure then (None).
Simulator-free: it reads the episodes' recorded layouts.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd

from vla_ladder.conditions import Condition
from vla_ladder.contract import METRICS, REACH_THRESHOLD
from vla_ladder.stats import CONFIDENCE, paired_difference, rates, wilson
from vla_ladder.task.layouts import REGION_CENTERS, usual_regions
from vla_ladder.task.objects import OBJECT_NAMES

DISPLACEMENT_BINS_CM: tuple[float, ...] = (0, 2, 4, 7, 10, 15, 20, 30, 60)
"""Bin edges: small jitter's regions reach ~3.6 cm from their centres, medium ~7 cm, large ~10 cm; full random
reaches ~45 cm (the workspace is 35 x 50 cm). Fixed, so that curves of different policies line up."""
PER_CM = 10.0
"""The trend's unit of distance: the odds ratio per 10 cm."""
FAR_CM = 200 * REACH_THRESHOLD
"""From here on (10 cm) the object's centre and its usual place lie two reach thresholds apart: a gripper that ends at
the place has not reached the object unless the object's box comes within 5 cm of it (possible only for the mug and
the marker, whose footprints reach 5.9-6.1 cm; none of the committed far episodes)."""


def usual_places(layout: dict, trained: Condition) -> np.ndarray:
    """(k, 2) centres of the regions where the instructed object of a recorded layout (Layout.to_dict()) stands in
    `trained`'s layouts (which must have regions)."""
    regions = usual_regions(layout["target"], trained)
    if regions is None:
        raise ValueError(f"{trained.key} has no regions: no place is usual there")
    return REGION_CENTERS[list(regions)]


def displacement(layout: dict, trained: Condition) -> float:
    """Metres from the instructed object of a recorded layout to the nearest of its usual places in `trained`."""
    xy = np.asarray(layout["positions"][layout["target"]], dtype=float)
    return float(np.linalg.norm(usual_places(layout, trained) - xy, axis=1).min())


def by_displacement(episodes: pd.DataFrame, trained: Condition | str) -> dict | None:
    """The episodes' metrics against their displacement from the training condition's places: the bins (each with
    its displacement range, n and every metric's rate and Wilson interval, as stats.rates gives them) and, per
    metric, the logistic trend. None when `trained` has no regions (full random). Episodes whose named object is
    not on the table (the absent-object probe) have no displacement: ValueError."""
    trained = Condition.of(trained)
    if usual_regions(OBJECT_NAMES[0], trained) is None:
        return None
    layouts = [json.loads(s) for s in episodes["layout"]]
    if any(lay.get("absent_target") for lay in layouts):
        raise ValueError("episodes that name an object not on the table have no displacement")
    d = np.array([displacement(lay, trained) for lay in layouts])
    edges = np.asarray(DISPLACEMENT_BINS_CM) / 100
    which = np.clip(np.digitize(d, edges) - 1, 0, len(edges) - 2)  # beyond the last edge: the last bin
    bins = [{"from_cm": float(DISPLACEMENT_BINS_CM[b]), "to_cm": float(DISPLACEMENT_BINS_CM[b + 1]),
             "mean_cm": round(float(d[which == b].mean()) * 100, 2), **rates(episodes[which == b])}
            for b in range(len(edges) - 1) if (which == b).any()]
    return {"trained_in": trained.key, "n": int(len(d)), "bins_cm": list(DISPLACEMENT_BINS_CM),
            "displacement_cm": {"min": round(float(d.min()) * 100, 2) if len(d) else None,
                                "max": round(float(d.max()) * 100, 2) if len(d) else None},
            "bins": bins, "far": _far(episodes, layouts, d, trained),
            "trend": {m: logistic_trend(d, episodes[m].astype(bool).to_numpy()) for m in METRICS}}


def _far(episodes: pd.DataFrame, layouts: list[dict], d: np.ndarray, trained: Condition) -> dict:
    """The episodes FAR_CM or more from the named object's place: how many reach the object and how many end at its
    usual place instead ("ends_at_place" None where the run kept no final TCP position)."""
    far = d >= FAR_CM / 100
    tcp = episodes[["tcp_x", "tcp_y"]].to_numpy(dtype=float)[far]
    places = [usual_places(lay, trained) for lay, f in zip(layouts, far) if f]
    at_place = [bool(np.linalg.norm(c - xy, axis=1).min() <= REACH_THRESHOLD) for c, xy in zip(places, tcp)]
    n, known = int(far.sum()), bool(np.isfinite(tcp).all())
    reached = episodes["reach"].astype(bool).to_numpy()[far]
    lo, hi = paired_difference(reached, np.array(at_place, bool))
    # place - object: +1 always the place (the location shortcut), -1 always the object, 0 neither or both alike
    preference = ({"value": float(np.mean(at_place) - reached.mean()), "ci95": [lo, hi], "n": n,
                   "method": "newcombe paired score"} if n and known else None)
    return {"from_cm": FAR_CM, "n": n, **_share("reach", int(reached.sum()), n),
            **_share("ends_at_place", sum(at_place), n, known=known), "place_minus_object": preference}


def _share(name: str, k: int, n: int, known: bool = True) -> dict:
    lo, hi = wilson(k, n)
    return {name: {"value": k / n if n and known else None, "ci95": [lo, hi] if n and known else None}}


def logistic_trend(d: np.ndarray, y: np.ndarray, confidence: float = CONFIDENCE) -> dict:
    """Logit P(y) = a + b * d / 10 cm, by maximum likelihood: the odds ratio exp(b) per 10 cm with its
    profile-likelihood interval and likelihood-ratio p-value. "odds_ratio_per_10cm" is None, with "why", where no
    finite slope fits: every episode alike or at one distance (no interval either), or outcomes that separate at a
    distance, where the interval is one-sided ([0, bound] for success only nearer than some distance:
    `separation_bound`)."""
    import statsmodels.api as sm
    from statsmodels.tools.sm_exceptions import ConvergenceWarning, PerfectSeparationWarning

    out = {"odds_ratio_per_10cm": None, "ci95": None, "p_value": None, "n": int(len(y))}
    if len(y) < 3 or y.all() or not y.any():
        return {**out, "why": "too few episodes" if len(y) < 3 else
                f"{'every' if y.all() else 'no'} episode has this outcome: no trend to fit"}
    if np.ptp(d) < 1e-6:
        return {**out, "why": "every episode at the same displacement"}
    x, y = d * 100 / PER_CM, y.astype(float)
    if (separated := separation_bound(x, y, confidence)) is not None:
        return {**out, **separated}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            fit = sm.Logit(y, sm.add_constant(x)).fit(disp=0, maxiter=200)
        except np.linalg.LinAlgError as e:
            return {**out, "why": f"no fit ({e})"}
    if not fit.mle_retvals.get("converged", False) or any(
            issubclass(w.category, (PerfectSeparationWarning, ConvergenceWarning)) for w in caught):
        return {**out, "why": "no maximum-likelihood fit (the outcomes nearly separate at a distance); read the bins"}
    lo, hi = profile_interval(fit, x, y, confidence)
    return {**out, "odds_ratio_per_10cm": float(np.exp(fit.params[1])), "ci95": [float(np.exp(lo)), float(np.exp(hi))],
            "p_value": float(fit.llr_pvalue), "method": METHOD}


METHOD = "logistic regression (statsmodels Logit), profile-likelihood interval, likelihood-ratio p-value"


def profile_log_likelihood(x: np.ndarray, y: np.ndarray, a_start: float = 0.0):
    """b -> the log-likelihood of the best fit with the slope held at b (the intercept refitted). For a fixed slope
    the intercept's likelihood is concave in one variable, so a scalar search finds it; statsmodels' IRLS diverges
    from its own start when the offsets b * x are large, as they are far along a steep slope."""
    from scipy import optimize

    def log_likelihood(a: float, b: float) -> float:
        eta = a + b * x
        return float(np.sum(y * eta - np.logaddexp(0.0, eta)))  # log(1 + e^eta) without overflow

    def best(b: float) -> float:
        return -float(optimize.minimize_scalar(lambda a: -log_likelihood(a, b), bracket=(a_start - 1, a_start + 1)).fun)
    return best


def _crossing(above_floor, inside: float, step: float) -> float:
    """Where above_floor (> 0 at `inside`, falling without bound away from it in the direction of `step`) crosses 0."""
    from scipy import optimize

    far = inside + step
    for _ in range(60):
        if above_floor(far) < 0:
            break
        far = inside + 2 * (far - inside)
    return optimize.brentq(above_floor, min(inside, far), max(inside, far), xtol=1e-10)


def profile_interval(fit, x: np.ndarray, y: np.ndarray, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The slope's profile-likelihood interval: the slopes b whose best fit (the intercept refitted with b fixed)
    loses at most chi2_1(confidence) / 2 of log-likelihood. Near separation, where a policy succeeds only close to
    the usual place, the likelihood is far from quadratic and Wald's interval (estimate +- 1.96 SE) is too wide on
    one side and too narrow on the other; the profile interval is what R's confint(glm) gives."""
    from scipy import stats

    floor = fit.llf - stats.chi2.ppf(confidence, 1) / 2
    (a_hat, b_hat), step = (float(v) for v in fit.params), max(float(fit.bse[1]), 1e-3)
    profile = profile_log_likelihood(x, y, a_hat)
    return (_crossing(lambda b: profile(b) - floor, b_hat, -step),
            _crossing(lambda b: profile(b) - floor, b_hat, step))


def separation_bound(x: np.ndarray, y: np.ndarray, confidence: float = CONFIDENCE) -> dict | None:
    """None unless the outcomes separate completely at a distance (every success nearer than every failure, or
    farther): the pure location shortcut. Then no finite slope fits (the likelihood rises towards 1, log-likelihood
    0, as the slope grows without bound), but the data still bound it on the other side: the slopes whose best fit
    loses at most chi2_1(confidence) / 2 of that supremum. The odds ratio per 10 cm is then at most (at least)
    exp(bound); the p-value is the likelihood-ratio test's against no trend (supremum 0)."""
    from scipy import stats

    if x[y == 1].max() < x[y == 0].min():
        sign = -1.0  # success only nearer: the slope runs to minus infinity
    elif x[y == 1].min() > x[y == 0].max():
        sign = 1.0
    else:
        return None
    floor = -stats.chi2.ppf(confidence, 1) / 2
    profile = profile_log_likelihood(x, y)
    inside = sign
    for _ in range(200):  # steep enough to be within the bound (the profile rises towards 0 that way)
        if profile(inside) >= floor:
            break
        inside *= 2
    bound = float(np.exp(_crossing(lambda b: profile(b) - floor, inside, -inside)))
    k, n = y.sum(), len(y)
    null = k * np.log(k / n) + (n - k) * np.log1p(-k / n)
    near, far = sorted((x[y == 1].max(), x[y == 0].min()) if sign < 0 else (x[y == 0].max(), x[y == 1].min()))
    first, then = ("success", "failure") if sign < 0 else ("failure", "success")
    return {"ci95": [0.0, bound] if sign < 0 else [bound, None],  # the open end: no finite limit
            "p_value": float(stats.chi2.sf(-2 * null, 1)), "method": METHOD,
            "why": f"the outcome separates at a distance (every {first} within {near * PER_CM:.1f} cm, every "
                   f"{then} beyond {far * PER_CM:.1f} cm): the slope is unbounded; the odds ratio per 10 cm is "
                   f"{'at most' if sign < 0 else 'at least'} {bound:.2g} ({100 * confidence:.0f}%, profile "
                   "likelihood)"}
