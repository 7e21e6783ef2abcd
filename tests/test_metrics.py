"""Statistics of evaluation runs: Wilson intervals, confusion counts, outcome kinds, `vla-ladder compare`."""

import json

import numpy as np
import pandas as pd
import pytest
from report_fixtures import make_run

from vla_ladder.cli import main
from vla_ladder.evaluation.compare import compare_runs, format_table, mcnemar_exact, two_proportion_z
from vla_ladder.evaluation.metrics import confusion, outcomes, summarize
from vla_ladder.stats import detectable_difference, mcnemar_power, paired_difference, rates, wilson
from vla_ladder.evaluation.rundir import load_run

SJ = ("small_jitter", "canonical", 5)
FR = ("full_random", "canonical", 5)


def test_wilson_interval_known_values():
    # Reference values: Wilson score interval, z = 1.95996 (e.g. R's prop.test(correct=FALSE)).
    assert wilson(0, 10) == pytest.approx((0.0, 0.27753), abs=1e-5)
    assert wilson(37, 100) == pytest.approx((0.28182, 0.46779), abs=1e-5)
    assert wilson(90, 100) == pytest.approx((0.82563, 0.94477), abs=1e-5)
    assert wilson(10, 10)[1] == pytest.approx(1.0)
    lo, hi = wilson(0, 0)
    assert lo != lo and hi != hi  # nan without episodes


def test_paired_and_unpaired_tests_known_values():
    # McNemar exact: 1 vs 9 discordant pairs -> 2 * P(Bin(10, 1/2) <= 1) = 22/1024.
    assert mcnemar_exact(1, 9) == pytest.approx(22 / 1024)
    assert mcnemar_exact(9, 1) == pytest.approx(22 / 1024)
    assert mcnemar_exact(0, 0) == 1.0
    # Pooled two-proportion z-test, 37/100 vs 41/100: z = -0.04 / sqrt(.39 * .61 * .02).
    z, p = two_proportion_z(37, 100, 41, 100)
    assert z == pytest.approx(-0.57989, abs=1e-4)
    assert p == pytest.approx(0.56199, abs=1e-4)
    assert two_proportion_z(0, 10, 0, 10) == (0.0, 1.0)


def _pairs(both: int, only_y: int, only_x: int, neither: int) -> tuple[np.ndarray, np.ndarray]:
    x = np.array([1] * both + [0] * only_y + [1] * only_x + [0] * neither, bool)
    y = np.array([1] * both + [1] * only_y + [0] * only_x + [0] * neither, bool)
    return x, y


def test_paired_difference_is_newcombes_interval():
    # Fagerland, Lydersen & Laake, Statistical Analysis of Contingency Tables (2017), chapter 8: Cavo et al. (2012),
    # 59 / 6 / 16 / 80 pairs: Newcombe's square-and-add interval -0.0621 (-0.1186 to -0.0046); Bentur et al.
    # (2009), 1 / 1 / 7 / 12: -0.2857 (-0.5069 to -0.0256).
    assert paired_difference(*_pairs(59, 6, 16, 80)) == pytest.approx((-0.1186, -0.0046), abs=1e-4)
    assert paired_difference(*_pairs(1, 1, 7, 12)) == pytest.approx((-0.5069, -0.0256), abs=1e-4)
    # No scene changes: a width from the rates' Wilson intervals, never the point [0, 0] a bootstrap gives.
    lo, hi = paired_difference(np.zeros(50, bool), np.zeros(50, bool))
    assert lo == pytest.approx(-wilson(0, 50)[1]) and hi == pytest.approx(wilson(0, 50)[1])
    assert paired_difference(np.ones(20, bool), np.zeros(20, bool)) == pytest.approx((-1.0, -0.7721), abs=1e-4)
    lo, hi = paired_difference(np.zeros(0, bool), np.zeros(0, bool))
    assert lo != lo and hi != hi


def test_paired_difference_covers_its_level():
    """Simulated pairs of correlated outcomes on 30 scenes: the interval holds the true difference in about 95% of
    draws (a percentile bootstrap over scenes held it in 61% at 10 scenes and 87% at 20, by the same kind of
    simulation)."""
    rng = np.random.default_rng(1)
    cover, trials = 0, 2000
    for _ in range(trials):
        u = rng.random(30)
        x, y = u < 0.4, (u < 0.55) ^ (rng.random(30) < 0.1)  # correlated, true difference 0.55*0.9+0.45*0.1-0.4
        lo, hi = paired_difference(x, y)
        cover += lo <= 0.14 <= hi
    assert 0.92 < cover / trials < 0.985


def test_a_share_of_several_plays_minus_a_paired_rate_covers_its_level():
    """The absent object's grasp change with two absent plays a scene (grounding.share_change): scenes whose
    latent difficulty drives both the present play and the absent ones; the interval holds the true difference in
    about 95% of draws at 12 scenes (the bootstrap over scenes it replaced held it in 87-95% at 10)."""
    from vla_ladder.evaluation.grounding import pooled_rate, share_change, wilson_rate

    rng = np.random.default_rng(2)
    cover, trials, n = 0, 1500, 12
    for _ in range(trials):
        u = rng.random(n)
        present = rng.random(n) < 0.35 + 0.5 * u  # mean 0.6
        absent = rng.random((n, 2)) < (0.05 + 0.3 * u)[:, None]  # mean 0.2
        first = wilson_rate(int(present.sum()), n)
        second = pooled_rate(absent.sum(1).astype(float), np.full(n, 2.0))
        lo, hi = share_change(first, second, present.astype(float), absent.mean(1))["ci95"]
        cover += lo <= -0.4 <= hi
    assert 0.92 < cover / trials < 0.985


def test_rates_refuse_missing_outcomes():
    df = pd.DataFrame({"success": [np.nan, 0, 1, np.nan], "grasp_any": [1, 1, 1, 1], "reach": [0, 0, 1, 1]})
    with pytest.raises(ValueError, match="2 episode.*no success outcome"):
        rates(df)


def _ep(target, held, success, grasp_any, reach):
    return {"regime": "small_jitter", "split": "canonical", "num_objects": 5, "target": target, "held": held,
            "success": success, "grasp_any": grasp_any, "reach": reach}


def test_confusion_outcomes_and_per_object_rates_on_constructed_episodes():
    df = pd.DataFrame([
        _ep("apple", "apple", True, True, True),
        _ep("apple", "mug", False, True, False),
        _ep("apple", "mug", False, True, True),
        _ep("mug", "none", False, True, False),  # grasped something, dropped it
        _ep("mug", "none", False, False, True),
        _ep("large_marker", "none", False, False, False),
    ])
    cm = confusion(df)
    assert list(cm.columns)[-1] == "none" and cm.shape == (5, 6)
    assert cm.loc["apple", "apple"] == 1 and cm.loc["apple", "mug"] == 2
    assert cm.loc["mug", "none"] == 2 and cm.loc["large_marker", "none"] == 1
    assert int(cm.values.sum()) == len(df)
    assert list(outcomes(df)) == ["success", "wrong_object", "wrong_object", "grasp_lost", "reached_no_grasp",
                                  "nothing"]

    cond = summarize(df)["small_jitter/canonical/5"]
    assert cond["n"] == 6 and cond["success"] == pytest.approx(1 / 6) and cond["grasp_any"] == pytest.approx(4 / 6)
    assert cond["ci95"]["success"] == pytest.approx(list(wilson(1, 6)))
    assert cond["per_object"]["apple"]["success"] == pytest.approx(1 / 3)
    assert cond["per_object"]["apple"]["n"] == 3 and "orange" not in cond["per_object"]
    assert cond["outcomes"] == {"success": 1, "wrong_object": 2, "grasp_lost": 1, "reached_no_grasp": 1,
                                "nothing": 1}
    assert cond["confusion"]["counts"][0][:4] == [1, 0, 0, 2]
    json.dumps(cond)  # summaries go straight into summary.json


def test_compare_pairs_episodes_and_tests_each_metric(tmp_path, capsys):
    a = make_run(tmp_path / "a", "nearest", [SJ, FR], ["success"] * 3 + ["nothing"] * 7)
    b = make_run(tmp_path / "b", "scripted", [SJ, FR], ["success"] * 10)
    result = compare_runs(load_run(a), load_run(b))
    row = next(r for r in result["rows"] if r["condition"] == "small_jitter/canonical/5" and r["metric"] == "success")
    assert (row["n"], row["only_a"], row["only_b"]) == (10, 0, 7)
    assert row["rate_a"] == pytest.approx(0.3) and row["diff"] == pytest.approx(0.7)
    assert row["mcnemar_p"] == pytest.approx(2 / 2**7)
    assert row["ci95_diff"] == pytest.approx(list(paired_difference(*_pairs(3, 7, 0, 0))))
    assert row["ci95_diff"][0] > 0 and row["z"] > 0  # B better: the interval and z both say B - A > 0
    assert len(result["rows"]) == 2 * 3

    # Pooled success 65% over 10 scenes: only a difference of ~0.6 or more is found 80% of the time.
    assert row["detectable_diff"] == pytest.approx(detectable_difference(0.65, 10), abs=1e-9)
    assert 0.5 < row["detectable_diff"] < 0.75

    assert main(["compare", str(a), str(b), "--json", str(tmp_path / "cmp.json")]) == 0
    out = capsys.readouterr().out
    assert "McNemar" in out and "full_random/canonical/5" in out and "MDD" in out
    assert json.loads((tmp_path / "cmp.json").read_text())["rows"][0]["metric"] == "success"


def test_detectable_difference_is_what_mcnemar_finds_80_percent_of_the_time():
    """Simulated pairs of independent runs at the two rates detectable_difference returns: McNemar's exact test
    (compare's own) rejects in ~80% of them, and in far fewer at half that difference."""
    rng = np.random.default_rng(0)

    def rejections(p1: float, p2: float, n: int, trials: int = 1500) -> float:
        a, b = rng.random((trials, n)) < p1, rng.random((trials, n)) < p2
        only_a, only_b = (a & ~b).sum(1), (~a & b).sum(1)
        return float(np.mean([mcnemar_exact(int(x), int(y)) < 0.05 for x, y in zip(only_a, only_b)]))

    d = detectable_difference(0.5, 100)
    assert 0.19 < d < 0.22  # the textbook ~20 points at 50% with 100 scenes
    assert abs(rejections(0.5 - d / 2, 0.5 + d / 2, 100) - 0.8) < 0.04
    assert rejections(0.5 - d / 4, 0.5 + d / 4, 100) < 0.4
    assert mcnemar_power(0.5 - d / 2, 0.5 + d / 2, 100) == pytest.approx(0.8, abs=0.01)
    # At 0%: the other run must reach ~8%, 6 of 6+ discordant scenes being the fewest McNemar can call.
    low = detectable_difference(0.0, 100)
    assert 0.06 < low < 0.1 and abs(rejections(0.0, low, 100) - 0.8) < 0.04
    assert detectable_difference(0.5, 400) < d / 1.8  # four times the scenes, about half the difference
    assert np.isnan(detectable_difference(0.5, 5))  # 5 scenes cannot reach p < 0.05 (2 / 2**5 = 0.0625)
    with pytest.raises(ValueError, match="n >= 1"):
        detectable_difference(0.5, 0)


def test_compare_rejects_mismatched_runs_and_non_run_dirs(tmp_path, capsys):
    a = make_run(tmp_path / "a", "nearest", [SJ], ["success"] * 4)
    shifted = make_run(tmp_path / "s", "nearest", [SJ], ["success"] * 4, seed=100)
    other = make_run(tmp_path / "o", "nearest", [FR], ["success"] * 4)
    shorter = make_run(tmp_path / "h", "nearest", [SJ], ["success"] * 3)
    with pytest.raises(ValueError, match="different seeds"):
        compare_runs(load_run(a), load_run(shifted))
    with pytest.raises(ValueError, match="different conditions.*full_random"):
        compare_runs(load_run(a), load_run(other))
    with pytest.raises(ValueError, match="different episodes"):
        compare_runs(load_run(a), load_run(shorter))
    # A ladder run against one of small jitter only: refused, or with --conditions-in-both the shared condition.
    ladder = make_run(tmp_path / "l", "scripted", [FR, SJ], ["success", "miss", "success", "success"])
    with pytest.raises(ValueError, match="only in .*: \\['full_random/canonical/5'\\]; .*--conditions-in-both"):
        compare_runs(load_run(ladder), load_run(a))
    with pytest.raises(ValueError, match="they share none"):
        compare_runs(load_run(a), load_run(other), in_both=True)
    assert main(["compare", str(ladder), str(a), "--conditions-in-both"]) == 0
    out = capsys.readouterr().out
    assert "small_jitter/canonical/5" in out.split("left out")[0] and "full_random/canonical/5     success" not in out
    assert "left out, played by one run only: A full_random/canonical/5; B none" in out
    result = compare_runs(load_run(ladder), load_run(a), in_both=True)
    assert {r["condition"] for r in result["rows"]} == {"small_jitter/canonical/5"}
    assert result["rows"][0]["rate_a"] == 0.75 and result["rows"][0]["only_a"] == 0
    assert result["other_target"] == 0 and "named another object" not in format_table(result)

    (tmp_path / "empty").mkdir()
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "summary.json").write_text("{}")
    assert main(["compare", str(a), str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err
    assert "not a run directory" in err and "episodes.parquet" in err and "summary.json" in err
    (tmp_path / "empty" / "config.json").write_text((a / "config.json").read_text())  # killed before its first save
    assert main(["compare", str(a), str(tmp_path / "empty")]) == 2
    assert "holds no episode yet (its evaluation stopped before the first was saved); rerun the command" in \
        capsys.readouterr().err
    assert main(["compare", str(tmp_path / "half"), str(a)]) == 2
    err = capsys.readouterr().err
    assert "missing episodes.parquet" in err and "missing episodes.parquet, summary.json" not in err
    assert main(["compare", str(a), str(shifted)]) == 2
    assert "different seeds" in capsys.readouterr().err

    # The same seeds with other objects on the table were paired as the same scenes; with another object named
    # (a probe's variant, --instruct 1) they are the same scenes, paired, and the table says so. And --json into a
    # run directory replaced its summary.json, after which the run no longer loaded.
    from vla_ladder.files import write_parquet
    for column, value in (("target", "orange"), ("object_set", "ycb")):
        changed = make_run(tmp_path / f"c-{column}", "nearest", [SJ], ["success"] * 4)
        df = pd.read_parquet(changed / "episodes.parquet")
        df.loc[1, column] = value if df.loc[1, column] != value else "mug"
        write_parquet(changed / "episodes.parquet", df)
        if column == "object_set":
            with pytest.raises(ValueError, match="1 of 4 episodes with different object sets \\(e.g. "
                                                 "small_jitter/canonical/5 episode 1"):
                compare_runs(load_run(a), load_run(changed))
        else:
            result = compare_runs(load_run(a), load_run(changed))
            assert result["other_target"] == 1 and "named another object than A in 1 of" in format_table(result)
    for inside in (a / "summary.json", a / "cmp.json"):
        assert main(["compare", str(a), str(ladder), "--conditions-in-both", "--json", str(inside)]) == 2
        assert "is inside the run directory" in capsys.readouterr().err
    assert load_run(a) and not (a / "cmp.json").exists()
