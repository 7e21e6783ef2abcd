"""Success against the named object's distance from its place in training (evaluation/displacement.py), on layouts
the sampler draws and outcomes drawn from a known curve. Simulator-free."""

import json

import numpy as np
import pandas as pd
import pytest

from vla_ladder.conditions import REGIMES, Condition
from vla_ladder.evaluation.displacement import DISPLACEMENT_BINS_CM, by_displacement, displacement, logistic_trend
from vla_ladder.stats import rates
from vla_ladder.task.layouts import REGION_CENTERS, sample_layout
from vla_ladder.task.objects import object_index

TRAINED = Condition("small_jitter", "canonical", 5)


def _ladder(outcome, seeds: int = 60, seed: int = 0) -> tuple[pd.DataFrame, np.ndarray]:
    """Episodes of every regime (as `eval --regimes all` plays them) whose outcomes come from outcome(d, rng), and
    their displacements from the canonical homes (object i's region i), computed here on their own."""
    rng = np.random.default_rng(seed)
    rows, ds = [], []
    for regime in REGIMES:
        for s in range(seeds):
            lay = sample_layout(Condition(regime, "canonical", 5), s).to_dict()
            d = float(np.linalg.norm(REGION_CENTERS[object_index(lay["target"])] - lay["positions"][lay["target"]]))
            ok = bool(outcome(d, rng))
            rows.append({"regime": regime, "split": "canonical", "num_objects": 5, "seed": s, "target": lay["target"],
                         "layout": json.dumps(lay), "success": ok, "grasp_any": True, "reach": ok,
                         "tcp_x": np.nan, "tcp_y": np.nan})
            ds.append(d)
    return pd.DataFrame(rows), np.array(ds)


def test_displacement_runs_from_the_jitter_regions_to_the_whole_table():
    small = [displacement(sample_layout(TRAINED, s).to_dict(), TRAINED) for s in range(100)]
    far = [displacement(sample_layout(Condition("full_random", "canonical", 5), s).to_dict(), TRAINED)
           for s in range(100)]
    assert max(small) <= np.hypot(0.02, 0.03) + 1e-9  # half small jitter's region extent
    assert max(far) > 0.2 and min(far) < max(small) * 3
    # In a pairing split the usual place is the nearest of the object's three training regions.
    pid = Condition("small_jitter", "pairings_id", 5)
    assert max(displacement(sample_layout(pid, s).to_dict(), pid) for s in range(100)) <= np.hypot(0.02, 0.03) + 1e-9
    with pytest.raises(ValueError, match="no regions"):
        displacement(sample_layout(TRAINED, 0).to_dict(), Condition("full_random", "canonical", 5))


def test_bins_hold_every_episode_with_its_wilson_interval_and_the_trend_recovers_a_known_slope():
    slope = -1.5  # log-odds per 10 cm
    episodes, d = _ladder(lambda d, rng: rng.random() < 1 / (1 + np.exp(-(2 + slope * d * 10))), seeds=150)
    curve = by_displacement(episodes, TRAINED)
    assert curve["trained_in"] == TRAINED.key and curve["n"] == len(episodes) == sum(b["n"] for b in curve["bins"])
    edges = np.asarray(DISPLACEMENT_BINS_CM) / 100
    for b in curve["bins"]:
        inside = (d >= b["from_cm"] / 100) & ((d < b["to_cm"] / 100) | (b["to_cm"] / 100 == edges[-1]))
        expected = rates(episodes[inside])
        assert b["n"] == expected["n"] and b["success"] == expected["success"]
        assert b["ci95"]["success"] == expected["ci95"]["success"]
        assert b["from_cm"] <= b["mean_cm"] <= b["to_cm"]
    trend = curve["trend"]["success"]
    lo, hi = trend["ci95"]
    assert lo < np.exp(slope) < hi and hi < 1 and trend["p_value"] < 1e-3
    assert curve["trend"]["grasp_any"]["odds_ratio_per_10cm"] is None  # every episode grasped: nothing to fit
    assert "every episode" in curve["trend"]["grasp_any"]["why"]


def test_a_flat_policy_has_odds_near_one_and_a_step_has_none():
    flat = by_displacement(_ladder(lambda d, rng: rng.random() < 0.6, seeds=100)[0], TRAINED)["trend"]["success"]
    assert flat["ci95"][0] < 1 < flat["ci95"][1]
    step = by_displacement(_ladder(lambda d, rng: d < 0.05)[0], TRAINED)
    assert step["trend"]["success"]["odds_ratio_per_10cm"] is None
    assert "separates" in step["trend"]["success"]["why"]
    lo, hi = step["trend"]["success"]["ci95"]  # no estimate, but the data bound it: one-sided
    assert lo == 0 and 0 < hi < 1 and step["trend"]["success"]["p_value"] < 1e-6
    assert step["bins"][0]["success"] == 1.0 and step["bins"][-1]["success"] == 0.0


def test_the_trend_interval_is_the_profile_likelihood_one_not_walds():
    """At each end of the interval, the best fit with the slope held there (statsmodels' own Logit, the slope as an
    offset, the intercept refitted) loses chi2_1(0.95) / 2 of log-likelihood. On a steep, nearly separated curve (a
    policy that succeeds only near the usual place) that interval is not Wald's, and the p-value is the
    likelihood-ratio test's."""
    import statsmodels.api as sm
    from scipy.stats import chi2

    rng = np.random.default_rng(3)
    d = rng.uniform(0, 0.4, 150)
    y = rng.random(150) < 1 / (1 + np.exp(-(2 - 40 * d)))
    trend = logistic_trend(d, y)
    x = d * 100 / 10  # per 10 cm
    fit = sm.Logit(y.astype(float), sm.add_constant(x)).fit(disp=0)
    assert trend["odds_ratio_per_10cm"] == pytest.approx(np.exp(fit.params[1]))
    for end in np.log(trend["ci95"]):
        held = sm.Logit(y.astype(float), np.ones((len(y), 1)), offset=end * x).fit(disp=0)
        assert 2 * (fit.llf - held.llf) == pytest.approx(chi2.ppf(0.95, 1), abs=1e-4)
    wald = np.exp(fit.conf_int(0.05)[1])
    assert abs(np.log(trend["ci95"][1]) - np.log(wald[1])) > 0.1  # far from quadratic: not Wald's
    assert trend["p_value"] == pytest.approx(fit.llr_pvalue)


def test_nothing_to_measure_for_a_policy_trained_in_full_random_or_an_absent_target():
    episodes, _ = _ladder(lambda d, rng: True, seeds=3)
    assert by_displacement(episodes, "full_random/canonical/5") is None
    four = sample_layout(Condition("small_jitter", "canonical", 4), 0)
    absent = four.instructed_absent(four.absent[0])
    with pytest.raises(ValueError, match="not on the table"):
        by_displacement(pd.DataFrame([{"layout": json.dumps(absent.to_dict()), "success": True, "grasp_any": True,
                                       "reach": True}]), TRAINED)


def test_far_from_its_place_the_gripper_ends_at_the_object_or_at_the_place():
    """Beyond 10 cm the object and its usual place are apart: a gripper sent to the place is counted there, one
    sent to the object reaches it; a run without final TCP positions says nothing of the place."""
    episodes, d = _ladder(lambda d, rng: False, seeds=40)
    layouts = [json.loads(s) for s in episodes["layout"]]
    target_xy = np.array([lay["positions"][lay["target"]] for lay in layouts])
    place_xy = np.array([REGION_CENTERS[object_index(lay["target"])] for lay in layouts])
    far = d >= 0.10
    assert 10 < far.sum() < len(d)
    to_place = episodes.assign(tcp_x=place_xy[:, 0], tcp_y=place_xy[:, 1], reach=False)
    got = by_displacement(to_place, TRAINED)["far"]
    assert got["from_cm"] == 10 and got["n"] == far.sum()
    assert got["ends_at_place"]["value"] == 1.0 and got["reach"]["value"] == 0.0
    assert got["place_minus_object"]["value"] == 1.0 and got["place_minus_object"]["ci95"][0] > 0.8
    to_object = episodes.assign(tcp_x=target_xy[:, 0], tcp_y=target_xy[:, 1], reach=True)
    got = by_displacement(to_object, TRAINED)["far"]
    assert got["ends_at_place"]["value"] == 0.0 and got["reach"]["value"] == 1.0
    assert got["place_minus_object"]["value"] == -1.0 and got["place_minus_object"]["ci95"][1] < -0.8
    lo, hi = got["reach"]["ci95"]
    assert lo < 1.0 == hi  # Wilson: n far episodes, all reached
    unknown = by_displacement(episodes.assign(tcp_x=np.nan, tcp_y=np.nan), TRAINED)["far"]
    assert unknown["ends_at_place"] == {"value": None, "ci95": None} and unknown["reach"]["value"] == 0.0
    assert unknown["place_minus_object"] is None


def test_a_study_draws_each_datasets_curve_with_the_references_that_played_its_episodes():
    """study_results.displacement_curves: a model trained on sj is drawn beside the references that played the
    same episodes (in any order), not beside one that played other seeds; a full-random model has no curve."""
    from pathlib import Path

    from vla_ladder.evaluation.rundir import Run
    from vla_ladder.experiments.study_results import displacement_curves

    def run(episodes: pd.DataFrame) -> Run:
        return Run(Path("run"), episodes, {})

    model, _ = _ladder(lambda d, rng: d < 0.03 or rng.random() < 0.1, seeds=20)
    same, _ = _ladder(lambda d, rng: rng.random() < 0.5, seeds=20, seed=1)
    other, _ = _ladder(lambda d, rng: True, seeds=21)
    curves = displacement_curves({
        "model (sj)": (run(model), ("sj", TRAINED.key)), "nearest": (run(same.iloc[::-1]), None),
        "other seeds": (run(other), None), "model (fr)": (run(model), ("fr", "full_random/canonical/5"))})
    assert list(curves) == ["sj"] and curves["sj"]["trained_in"] == TRAINED.key
    assert list(curves["sj"]["runs"]) == ["model (sj)", "nearest"]
    assert curves["sj"]["runs"]["nearest"] == by_displacement(same.iloc[::-1], TRAINED)  # its own episodes


def test_separated_outcomes_get_the_one_sided_profile_bound():
    """Every success nearer than every failure: no finite slope, and the log-likelihood rises towards 0 as the slope
    falls; the bound is the slope whose best fit (statsmodels' Logit, the slope as an offset) loses chi2_1(0.95) / 2
    of that. A wider gap between the last success and the first failure bounds it less tightly (a gentler slope fits
    it as well); the mirror image gets a bound from below."""
    import statsmodels.api as sm
    from scipy.stats import chi2

    from vla_ladder.report.displacement import odds_text

    d = np.linspace(0, 0.3, 61)
    y = d < 0.08
    trend = logistic_trend(d, y)
    assert trend["odds_ratio_per_10cm"] is None and trend["ci95"][0] == 0
    assert "every success within 7.5 cm, every failure beyond 8.0 cm" in trend["why"]
    bound = np.log(trend["ci95"][1])
    held = sm.Logit(y.astype(float), np.ones((len(y), 1)), offset=bound * d * 10).fit(disp=0)
    assert -2 * held.llf == pytest.approx(chi2.ppf(0.95, 1), abs=1e-4)
    assert odds_text(trend) == f"< {trend['ci95'][1]:.2g}"
    wider = logistic_trend(d[(d < 0.04) | (d > 0.12)], y[(d < 0.04) | (d > 0.12)])
    assert trend["ci95"][1] < wider["ci95"][1] < 1
    mirror = logistic_trend(d, ~y)
    assert mirror["ci95"][1] is None and mirror["ci95"][0] == pytest.approx(1 / trend["ci95"][1], rel=1e-6)
    assert odds_text(mirror).startswith("> ")
    one_off = logistic_trend(d, (d < 0.08) ^ (d == d[3]))  # one near failure: no longer separated, an estimate
    assert one_off["odds_ratio_per_10cm"] is not None and one_off["ci95"][1] < 1
