"""The absent-object probe: instructing an object that is not on the table. Its counterfactual layouts, its
metrics on constructed plays, its commands, and its calibration by the reference policies in the real simulator
(CPU, state only)."""

import json

import numpy as np
import pandas as pd
import pytest
from report_fixtures import first_table_row

from vla_ladder.cli import main
from vla_ladder.conditions import Condition, ConditionGrid
from vla_ladder.evaluation import grounding
from vla_ladder.evaluation.rundir import load_run
from vla_ladder.experiments.probes import ProbeConfig, ProbeGrid, run_probe
from vla_ladder.report.html import build_report
from vla_ladder.stats import paired_difference
from vla_ladder.task.instructions import parse_instruction
from vla_ladder.task.layouts import REGION_CENTERS, TRAIN_REGIONS, layout_from_dict, sample_layout, usual_regions
from vla_ladder.task.objects import OBJECT_NAMES, object_index


# ---------------------------------------------------------------------- layouts
def test_instructing_an_absent_object_keeps_the_scene_and_needs_the_explicit_opt_in():
    for regime, seed in ((r, s) for r in ("small_jitter", "full_random") for s in range(10)):
        base = sample_layout(Condition(regime, num_objects=3), seed, appearance="swap")
        assert base.absent == tuple(n for n in OBJECT_NAMES if n not in base.objects) and len(base.absent) == 2
        for rank, name in enumerate(base.absent):
            lay = base.instructed_absent(rank)
            assert lay.to_dict() == base.instructed_absent(name).to_dict()
            assert lay.target == name and lay.target_index == object_index(name) and name not in lay.objects
            assert parse_instruction(lay.instruction).object == name
            assert lay.objects == base.objects and np.array_equal(lay.xy, base.xy)
            assert np.array_equal(lay.yaw, base.yaw) and lay.regions == base.regions
            assert lay.colour_swap == base.colour_swap
            d = lay.to_dict()
            assert d["target"] == name and d["absent_target"] is True and d["positions"] == base.to_dict()["positions"]
            assert layout_from_dict(d).to_dict() == d
            assert lay.instructed(0).target == base.target  # instructing a present object again clears it
        assert "absent_target" not in base.to_dict()
    lay = sample_layout(Condition("small_jitter", num_objects=3), 1)
    missing = lay.absent[0]
    with pytest.raises(ValueError, match=f"cannot instruct '{missing}': seed 1 .* holds only"):
        lay.instructed(missing)  # a name off the table given to a present-object instruct still fails
    with pytest.raises(ValueError, match=f"cannot instruct '{lay.objects[1]}' as absent: it is on the table"):
        lay.instructed_absent(lay.objects[1])
    with pytest.raises(ValueError, match="absent rank 2 is not an object missing .* allowed 0-1"):
        lay.instructed_absent(2)
    with pytest.raises(ValueError, match="unknown object 'banana'"):
        lay.instructed_absent("banana")
    with pytest.raises(ValueError, match="all five are present"):
        sample_layout(Condition("small_jitter"), 1).instructed_absent(0)


def test_usual_regions_are_the_training_layouts_regions():
    for i, name in enumerate(OBJECT_NAMES):
        for regime in ("small_jitter", "large_jitter"):
            assert usual_regions(name, Condition(regime)) == (i,)
            for split in ("pairings_id", "pairings_ood"):
                assert set(usual_regions(name, Condition(regime, split))) == TRAIN_REGIONS[i]
        assert usual_regions(name, Condition("full_random")) is None


# ---------------------------------------------------------------------- metrics on constructed plays
HOME = (-0.5, 0.0)  # where a policy that does nothing leaves the TCP: far from every region centre


def absent_plays(policy, regime="small_jitter", k=3, scenes=10, split="canonical") -> tuple[pd.DataFrame,
                                                                                             pd.DataFrame]:
    """Present and absent plays of a made-up policy: policy(layout, scene) -> (held, tcp_xy)."""
    present, absent = [], []
    for j in range(scenes):
        base = sample_layout(Condition(regime, split, k), j)
        for rank, lay in [(None, base)] + [(r, base.instructed_absent(r)) for r in range(5 - k)]:
            held, tcp = policy(lay, j)
            row = dict(regime=regime, split=split, num_objects=k, episode=j, seed=j, target=lay.target,
                       instruction=lay.instruction, held=held, success=held == lay.target, grasp_any=held != "none",
                       reach=held == lay.target, tcp_x=tcp[0], tcp_y=tcp[1], layout=json.dumps(lay.to_dict()))
            (present if rank is None else absent).append(row if rank is None else {**row, "absent": rank})
    return pd.DataFrame(present), pd.DataFrame(absent)


def grounded(lay, j):
    return (lay.target, lay.xy[0]) if lay.target in lay.objects else ("none", HOME)


def shortcut(lay, j):
    usual = REGION_CENTERS[lay.target_index]
    return (lay.target if lay.target in lay.objects else "none", usual)


def empty_place(lay, j):  # a shortcut that finds the named object's usual place that nothing else fills
    if lay.target in lay.objects:
        return lay.target, lay.xy[0]
    free = [r for r in usual_regions(lay.target, lay.condition) if r not in lay.regions]
    return "none", REGION_CENTERS[free[0]] if free else HOME


def blind(lay, j):  # the same object whatever is said
    return sorted(lay.objects)[0], lay.xy[list(lay.objects).index(sorted(lay.objects)[0])]


def test_absent_metrics_tell_grounded_shortcut_and_blind_policies_apart():
    key = "small_jitter/canonical/3"
    g = grounding.absent_object(*absent_plays(grounded))[key]
    assert g["scenes"] == 10 and g["absent_plays"] == 20
    assert g["grasp_present"]["value"] == 1 and g["grasp_absent"]["value"] == 0 and g["grasp_change"]["value"] == -1
    assert g["shortcut_reach"]["value"] == 0 and g["usual_place_empty"]["value"] == 1  # canonical: always empty
    # Every absent play alike: the interval is Wilson's with each scene one trial, not [0, 0].
    assert g["grasp_absent"]["method"] == "wilson over scenes (every play alike)"
    assert g["grasp_absent"]["ci95"][1] == pytest.approx(0.278, abs=1e-3)
    assert g["usual_regions"]["mug"] == [3]
    # Two absent plays a scene: a share minus a 0/1, from the two rates' own intervals (Wilson, and Wilson over
    # scenes here, every play alike): nothing held absent, everything present, 10 scenes.
    assert g["grasp_change"]["method"].startswith("mover")
    assert g["grasp_change"]["ci95"] == pytest.approx([-1, -1 + (2 * 0.2775 ** 2) ** 0.5], abs=1e-3)
    # With four objects, one absent play a scene: the change is a paired binary difference (Newcombe's interval).
    four = grounding.absent_object(*absent_plays(grounded, k=4))["small_jitter/canonical/4"]
    assert four["grasp_change"]["value"] == -1 and four["grasp_change"]["method"] == "newcombe paired score"
    assert four["grasp_change"]["ci95"] == pytest.approx(list(paired_difference(np.ones(10, bool),
                                                                                 np.zeros(10, bool))))
    # The table shows McNemar's p beside a paired change (it showed none), and none beside a share change.
    from vla_ladder.report.probes import table_html
    assert f"p={four['grasp_change']['mcnemar_p']:.2g}" in table_html({"probe": "absent-object",
                                                                         "conditions": {"x": four}})
    assert "p=" not in table_html({"probe": "absent-object", "conditions": {"x": g}})
    s = grounding.absent_object(*absent_plays(shortcut))[key]
    assert s["shortcut_reach"]["value"] == 1 and s["grasp_absent"]["value"] == 0 and s["same_grasp"]["value"] == 0
    b = grounding.absent_object(*absent_plays(blind))[key]
    assert b["grasp_absent"]["value"] == b["grasp_present"]["value"] == 1 and b["grasp_change"]["value"] == 0
    assert b["grasp_change"]["ci95"] == pytest.approx([-0.2775, 0.2775], abs=1e-3)  # a width, not the point [0, 0]
    assert b["same_grasp"]["value"] == 1 and b["shortcut_reach"]["value"] == 0
    counts = np.array(b["matrix"]["counts"])
    assert counts.sum() == 20 and counts[:, -1].sum() == 0  # the named absent object x what was held instead
    named = {OBJECT_NAMES[i] for i in np.flatnonzero(counts.sum(1))}
    assert named <= set(OBJECT_NAMES) and len(named) >= 3
    # Pairing splits: the named object's three training regions often hold present objects. Going to one of those
    # is grasping what stands there, not a shortcut: only empty usual places count.
    key = "small_jitter/pairings_id/3"
    e = grounding.absent_object(*absent_plays(empty_place, split="pairings_id", scenes=30))[key]
    b = grounding.absent_object(*absent_plays(blind, split="pairings_id", scenes=30))[key]
    assert e["shortcut_reach"]["value"] == 1 and b["shortcut_reach"]["value"] == 0
    assert e["usual_place_empty"]["value"] == b["usual_place_empty"]["value"] == 0.9  # 54 of 60 plays have one
    assert e["shortcut_reach"]["n"] == 54 and e["usual_regions"]["apple"] == [0, 1, 2]
    key = "small_jitter/canonical/3"
    # Full random has no usual place: shortcut reach is undefined, not 0.
    f = grounding.absent_object(*absent_plays(shortcut, "full_random"))["full_random/canonical/3"]
    assert f["shortcut_reach"] is None and f["usual_regions"] is None and f["grasp_absent"]["value"] == 0
    # A scene missing one of its absent plays is left out; so is one missing its present play.
    present, absent = absent_plays(grounded)
    absent = absent[~((absent["episode"] == 3) & (absent["absent"] == 1))]
    assert grounding.absent_object(present[present["episode"] != 5], absent)[key]["scenes"] == 8
    # Runs from before tcp_x/tcp_y were kept read as NaN: shortcut reach is then unknown, not 0.
    present, absent = absent_plays(shortcut)
    old = grounding.absent_object(present, absent.assign(tcp_x=np.nan))[key]
    assert old["shortcut_reach"] is None and old["grasp_absent"]["value"] == 0


# ---------------------------------------------------------------------- commands
def test_absent_object_configs_and_refusals(tmp_path, refused):
    cfg = ProbeConfig("absent-object", policy="nearest", out=tmp_path / "p")
    assert cfg.grid.num_objects == (3,)  # its own default; every other probe keeps five
    assert ProbeConfig("instruction-swap", policy="nearest", out=tmp_path / "q").grid.num_objects == (5,)
    variants = cfg.variants()
    assert list(variants) == ["present", "absent-0", "absent-1"]
    assert variants["present"].jobs()[0].options == ()  # exactly an ordinary evaluation
    assert variants["absent-1"].jobs()[0].options == (("instruct_absent", 1),)
    mixed = ProbeConfig("absent-object", policy="nearest", out=tmp_path / "p",
                        grid=ConditionGrid(("small_jitter",), ("canonical",), (2, 4))).variants()
    assert [c.num_objects for c in mixed["absent-0"].conditions] == [2, 4]
    assert [c.num_objects for c in mixed["absent-2"].conditions] == [2] and "absent-3" not in mixed
    cases = [
        (["probe", "absent-object", "--policy", "nearest", "--out", str(tmp_path / "p"), "--num-objects", "5"],
         "absent-object needs an object off the table; got --num-objects 5 (allowed: 1-4)"),
        (["probe", "absent-object", "--policy", "nearest", "--out", str(tmp_path / "p"), "--num-objects", "2", "5"],
         "absent-object needs an object off the table"),
        (["eval", "--policy", "nearest", "--out", str(tmp_path / "e"), "--instruct-absent", "0"],
         "instruct_absent must be an absent-object rank none: 5 objects leave none off the table"),
        (["eval", "--policy", "nearest", "--out", str(tmp_path / "e"), "--num-objects", "3", "--instruct-absent", "2"],
         "instruct_absent must be an absent-object rank from 0 to 1"),
        (["eval", "--policy", "nearest", "--out", str(tmp_path / "e"), "--num-objects", "3", "--instruct", "1",
          "--instruct-absent", "0"], "instruct 1 and instruct_absent 0 each name the instructed object"),
    ]
    refused(cases, tmp_path / "p", tmp_path / "e")
    # A study probes each model in its training condition; five objects leave nothing to name, so five-object data
    # are probed with four (cpu-mini's datasets all have five).
    from vla_ladder.experiments.study import Study, StudyCommand

    study = Study(StudyCommand("cpu-mini", out=tmp_path / "s"))
    study.cfg.evaluation.probes = ["instruction-swap", "absent-object"]
    units = {u.id: u.config["grid"] for u in study.probe_units(study.best({}))}
    assert units["probe-SmolVLA-scratch-sj-absent-object"] == {
        "regimes": ["small_jitter"], "splits": ["canonical"], "num_objects": [4]}
    assert units["probe-SmolVLA-scratch-sj-instruction-swap"]["num_objects"] == [5]
    assert ProbeConfig("absent-object", policy="nearest", out=tmp_path / "u",
                       grid=units["probe-SmolVLA-scratch-pid-absent-object"]).variants()["absent-0"].conditions


# ---------------------------------------------------------------------- the real simulator
@pytest.mark.slow
def test_the_env_instructs_an_absent_object_in_the_same_scene(make_env):
    import torch

    from vla_ladder.policies import load_policy

    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=3, reward_mode="normalized_dense")
    u, expert = env.unwrapped, load_policy("scripted")
    lay = sample_layout(Condition("small_jitter", num_objects=3), 4)
    starts = []
    for options in ({}, {"instruct_absent": 0}, {"instruct_absent": lay.absent[1]}, {"instruct_absent": [1]}):
        obs, _ = env.reset(seed=4, options=options)
        starts.append(torch.cat([obs["extra"]["obj_pose"], obs["agent"]["qpos"], obs["extra"]["obj_present"]], 1))
        assert u.layouts[0].objects == lay.objects
        expert.reset([4])
        for _ in range(50):  # the expert reads the parked target from privileged state: nothing breaks
            obs, reward, _, _, info = env.step(expert.act(obs, u.instructions))
            assert torch.isfinite(reward).all()
        if options:
            named = u.layouts[0].target
            assert named in lay.absent and parse_instruction(u.instructions[0]).object == named
            assert int(obs["extra"]["target_onehot"][0].argmax()) == object_index(named)
            assert not info["success"][0] and not info["reach"][0] and not info["lifted"][0]
        else:
            assert info["success"][0] and OBJECT_NAMES[int(info["held"][0])] == lay.target
        assert info["tcp_xy"].shape == (1, 2)
    assert all(torch.equal(starts[0], s) for s in starts[1:])  # the same scene, to the bit
    with pytest.raises(ValueError, match=f"cannot instruct '{lay.absent[0]}'"):
        env.reset(seed=4, options={"instruct": lay.absent[0]})  # no opt-in: a name off the table still fails
    with pytest.raises(ValueError, match="instruct .* and instruct_absent .* give one per env"):
        env.reset(seed=4, options={"instruct": 1, "instruct_absent": 0})
    with pytest.raises(ValueError, match="as absent: it is on the table"):
        env.reset(seed=4, options={"instruct_absent": lay.objects[2]})


def probe(tmp_path, policy, regimes, scenes, **kw) -> dict:
    cfg = ProbeConfig("absent-object", policy=policy, out=tmp_path / policy, grid=ProbeGrid(tuple(regimes)),
                      episodes=scenes, workers=1, **kw)
    return run_probe(cfg, progress=False)


@pytest.mark.slow
def test_absent_object_calibration_layout_prior_and_nearest(tmp_path):
    prior = probe(tmp_path, "layout-prior", ["small_jitter", "full_random"], 6, report=True)["conditions"]
    small, full = prior["small_jitter/canonical/3"], prior["full_random/canonical/3"]
    # The location shortcut goes where the named object usually stands: an empty place, so it grasps nothing.
    assert small["shortcut_reach"]["value"] >= 0.9 and small["grasp_absent"]["value"] <= 0.1
    assert small["grasp_present"]["value"] >= 0.6 and small["grasp_change"]["value"] <= -0.5
    assert full["shortcut_reach"] is None and full["usual_regions"] is None
    nearest = probe(tmp_path, "nearest", ["small_jitter"], 6, report=False)["conditions"]["small_jitter/canonical/3"]
    # Blind to the instruction: it grasps as often absent as present, and the very same object.
    assert nearest["grasp_absent"]["value"] == nearest["grasp_present"]["value"] >= 0.8
    assert nearest["grasp_change"]["value"] == 0 and nearest["same_grasp"]["value"] == nearest["grasp_absent"]["value"]
    assert nearest["shortcut_reach"]["value"] == 0
    # The scene is identical in every variant: same objects at the same poses, only the named object differs.
    root = tmp_path / "layout-prior"
    runs = {v: load_run(root / v).episodes for v in ("present", "absent-0", "absent-1")}
    for j in range(6):
        lays = {v: json.loads(df[(df["regime"] == "small_jitter") & (df["episode"] == j)]["layout"].iloc[0])
                for v, df in runs.items()}
        for v in ("absent-0", "absent-1"):
            assert lays[v]["positions"] == lays["present"]["positions"] and lays[v]["yaw"] == lays["present"]["yaw"]
            assert lays[v]["absent_target"] and lays[v]["target"] not in lays[v]["positions"]
        assert lays["absent-0"]["target"] != lays["absent-1"]["target"]
    present = runs["present"]
    assert np.isfinite(present[["tcp_x", "tcp_y"]].to_numpy()).all()  # the final TCP, recorded per episode
    assert main(["compare", str(root / "present"), str(root / "absent-0")]) == 0
    page = (root / "report.html").read_text()
    assert "absent-object: layout-prior" in page and "shortcut reach" in page and "named (absent)" in page
    assert (root / "absent-object.png").stat().st_size > 5000 and (root / "absent-object_matrix.png").is_file()
    assert build_report([load_run(root / "present")], tmp_path / "r.html", placements=False).read_text().count(
        "Grounding probes") == 1
    # The probe's own page, in a real browser: its figures decode, and its table shows the shortcut.
    widths, cells = first_table_row(root / "report.html", "shortcut reach")
    assert len(widths) >= 2 and min(widths) > 300
    assert cells["condition"] == "small_jitter/canonical/3", cells
    assert next(v for k, v in cells.items() if k.startswith("shortcut reach")).startswith("100"), cells


def test_the_table_says_why_shortcut_reach_is_undefined():
    """Shortcut reach is None under full random (no usual place) and for a run that kept no TCP; the table said "no
    usual place" for both, also beside a small-jitter condition's usual places."""
    from vla_ladder.report.probes import table_html

    present, absent = absent_plays(shortcut)
    old = grounding.absent_object(present, absent.assign(tcp_x=np.nan))["small_jitter/canonical/3"]
    table = table_html({"probe": "absent-object", "conditions": {"x": old}})
    assert table.count("n/a (no TCP recorded)") == 2 and "no usual place" not in table
    f = grounding.absent_object(*absent_plays(shortcut, "full_random"))["full_random/canonical/3"]
    table = table_html({"probe": "absent-object", "conditions": {"x": f}})
    assert table.count("n/a (no usual place)") == 2 and "TCP" not in table
