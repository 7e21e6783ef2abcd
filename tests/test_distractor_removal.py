"""The distractor-removal probe: the same scenes with every distractor taken off the table. Its counterfactual
layouts, its metrics on constructed plays, its refusals, and its calibration by the reference policies in the real
simulator (CPU, state only)."""

import json

import numpy as np
import pandas as pd
import pytest
from report_fixtures import first_table_row

from vla_ladder.conditions import Condition
from vla_ladder.evaluation import grounding
from vla_ladder.evaluation.runner import EvalConfig
from vla_ladder.experiments.probes import ProbeConfig, ProbeGrid, run_probe
from vla_ladder.task.layouts import layout_from_dict, sample_layout


def test_alone_keeps_the_instructed_object_where_it_stood_and_names_what_left():
    for regime, split, k, seed in ((r, s, k, seed) for r, s in (("small_jitter", "canonical"),
                                                               ("large_jitter", "pairings_ood"),
                                                               ("full_random", "canonical"))
                                   for k in (2, 5) for seed in range(10)):
        base = sample_layout(Condition(regime, split, k), seed)
        for r in range(k):  # whichever object is instructed stays, the others leave
            scene = base.instructed(r)
            lay = scene.alone()
            assert lay.objects == (scene.target,) and lay.removed == scene.objects[1:]
            assert np.array_equal(lay.xy, scene.xy[:1]) and np.array_equal(lay.yaw, scene.yaw[:1])
            assert lay.instruction == scene.instruction and lay.condition == scene.condition
            d = lay.to_dict()
            assert d["removed"] == list(scene.objects[1:]) and list(d["positions"]) == [scene.target]
            assert layout_from_dict(d).to_dict() == d  # the seed gives it back (dataset checks, replays)
            assert lay.alone() is lay
    assert "removed" not in sample_layout(Condition("small_jitter"), 3).to_dict()
    # Under an appearance swap the instructed object keeps the colour it wore, whichever of the pair it is.
    swapped = [sample_layout(Condition("small_jitter", num_objects=4), seed, appearance="swap") for seed in range(20)]
    pair = next(lay for lay in swapped if lay.colour_swap is not None)
    assert pair.alone().colour_swap == pair.colour_swap
    partner = pair.instructed(pair.colour_swap[1])
    assert partner.alone().colour_swap == partner.colour_swap
    bystander = next((pair.instructed(o) for o in pair.objects if o not in pair.colour_swap), None)
    if bystander is not None:
        assert bystander.alone().colour_swap is None
    for lay in (pair.alone(), partner.alone()):
        assert layout_from_dict(lay.to_dict()).to_dict() == lay.to_dict()
    lay = sample_layout(Condition("small_jitter", num_objects=3), 4)
    with pytest.raises(ValueError, match="not on the table"):
        lay.instructed_absent(0).alone()
    with pytest.raises(ValueError, match="instruction switches to"):
        lay.switched(5).alone()


def test_alone_is_refused_with_what_it_cannot_go_with():
    for kw, match in ((dict(swap_positions=True), "alone takes the distractors off the table, which swap_positions"),
                      (dict(switch_at=5), "alone takes the distractors off the table, which swap_positions"),
                      (dict(instruct_absent=0, grid=ProbeGrid(num_objects=(3,))), "alone leaves the instructed "),
                      (dict(grid=ProbeGrid(num_objects=(1,))), "alone needs at least two objects")):
        with pytest.raises(ValueError, match=match):
            EvalConfig("nearest", alone=True, **kw)
    with pytest.raises(ValueError, match="distractor-removal needs at least two objects on the table; got "
                                         "--num-objects 1 \\(allowed: 2-5\\)"):
        ProbeConfig("distractor-removal", policy="nearest", grid=ProbeGrid(num_objects=(1,)))


def removal_plays(choose, regime="small_jitter", k=5, scenes=12) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Both plays of a made-up policy: choose(layout) -> held, on each scene as it is and alone."""
    rows = {"original": [], "alone": []}
    for j in range(scenes):
        base = sample_layout(Condition(regime, num_objects=k), j)
        for name, lay in (("original", base), ("alone", base.alone())):
            held = choose(lay)
            rows[name].append(dict(regime=regime, split="canonical", num_objects=k, episode=j, seed=j,
                                   target=lay.target, held=held, success=held == lay.target,
                                   grasp_any=held != "none", reach=held == lay.target,
                                   layout=json.dumps(lay.to_dict())))
    return pd.DataFrame(rows["original"]), pd.DataFrame(rows["alone"])


def test_removal_metrics_split_the_failures_by_what_the_policy_does_alone():
    key = "small_jitter/canonical/5"
    # Picks the first object by name: right only when that is the target; alone, the target is all there is.
    by_name = grounding.distractor_removal(*removal_plays(lambda lay: sorted(lay.objects)[0]))[key]
    wrong = by_name["held_original"]["distractor"]["value"]
    assert by_name["success_alone"]["value"] == 1 and by_name["failures_alone_too"]["value"] == 0
    assert by_name["distractor_failures"]["value"] == pytest.approx(1 - by_name["success_original"]["value"]) == wrong
    change = by_name["success_change"]
    assert change["value"] == pytest.approx(wrong) and change["ci95"][0] > 0 and change["mcnemar_p"] < 0.05
    # Never grasps: it fails alone too, and the distractors explain none of it.
    clumsy = grounding.distractor_removal(*removal_plays(lambda lay: "none"))[key]
    assert clumsy["failures_alone_too"]["value"] == 1 and clumsy["distractor_failures"]["value"] == 0
    assert clumsy["held_original"]["none"]["value"] == 1 and clumsy["grasp_any_alone"]["value"] == 0
    assert clumsy["success_change"]["value"] == 0 and clumsy["success_change"]["ci95"][1] > 0  # a width, not [0, 0]
    # A coin flip on every play: the distractors change nothing, yet scenes flip both ways. The failures as it is
    # split exactly into those that succeed alone and those that fail alone too; Δ nets the flips, near 0.
    rng = np.random.default_rng(0)
    coin = grounding.distractor_removal(*removal_plays(lambda lay: lay.target if rng.random() < 0.5 else "none",
                                                       scenes=60))[key]
    parts = sum(coin[m]["value"] for m in ("success_original", "distractor_failures", "failures_alone_too"))
    assert parts == pytest.approx(1) and coin["distractor_failures"]["value"] > 0.1
    assert coin["success_change"]["ci95"][0] < 0 < coin["success_change"]["ci95"][1]
    original, alone = removal_plays(lambda lay: lay.target)
    with pytest.raises(ValueError, match="different seeds"):
        grounding.distractor_removal(original, alone.assign(seed=alone["seed"] + 1))


@pytest.mark.slow
def test_removal_calibration_nearest_layout_prior_and_scripted(tmp_path):
    def probe(policy, regimes, scenes=6, report=False):
        cfg = ProbeConfig("distractor-removal", policy=policy, out=tmp_path / policy, grid=ProbeGrid(regimes),
                          episodes=scenes, workers=1, report=report)
        return run_probe(cfg, progress=False)["conditions"]

    # The nearest object is the target only by chance among five; alone it is always the target.
    nearest = probe("nearest", ("small_jitter",), report=True)["small_jitter/canonical/5"]
    assert nearest["success_alone"]["value"] == 1 and nearest["distractor_failures"]["value"] >= 0.5
    # The location shortcut under full random goes to the target's usual region, empty with or without others.
    prior = probe("layout-prior", ("full_random",))["full_random/canonical/5"]
    assert prior["failures_alone_too"]["value"] >= 0.8 and prior["distractor_failures"]["value"] <= 0.2
    scripted = probe("scripted", ("small_jitter",))["small_jitter/canonical/5"]
    assert scripted["success_original"]["value"] == scripted["success_alone"]["value"] == 1
    root = tmp_path / "nearest"
    alone = pd.read_parquet(root / "alone" / "episodes.parquet")
    assert all(len(json.loads(lay)["positions"]) == 1 and len(json.loads(lay)["removed"]) == 4
               for lay in alone["layout"])
    assert (root / "distractor-removal.png").stat().st_size > 5000
    widths, cells = first_table_row(root / "report.html", "fails as it is, succeeds alone")
    assert len(widths) >= 2 and min(widths) > 300
    assert cells["condition"] == "small_jitter/canonical/5" and cells["fails alone too"].startswith("0"), cells
