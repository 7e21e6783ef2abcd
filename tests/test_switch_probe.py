"""The instruction-switch probe: the instruction changes mid-episode, at control step K, from the instructed object A
to a distractor B. Its counterfactual layouts, its metrics on constructed plays, its commands, the env's switch
step by step, and its calibration by the reference policies in the real simulator (CPU, state only)."""

import json

import numpy as np
import pandas as pd
import pytest
from report_fixtures import first_table_row

from vla_ladder.conditions import Condition
from vla_ladder.evaluation import grounding
from vla_ladder.evaluation.rundir import load_run
from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
from vla_ladder.experiments.probes import SWITCH_STEPS, ProbeConfig, ProbeGrid, run_probe
from vla_ladder.report.study import probe_rows
from vla_ladder.task.instructions import instruction_text, parse_instruction
from vla_ladder.task.layouts import layout_from_dict, sample_layout
from vla_ladder.task.objects import object_index


# ---------------------------------------------------------------------- layouts
def test_switched_layout_keeps_the_scene_and_names_a_seed_chosen_distractor_from_its_step():
    partners = set()
    for regime, k, seed in ((r, k, s) for r in ("small_jitter", "full_random") for k in (2, 5) for s in range(30)):
        base = sample_layout(Condition(regime, num_objects=k), seed, instructions="paraphrase-heldout",
                             appearance="swap")
        lay = base.switched(7)
        step, new = lay.switch
        assert step == 7 and new in base.objects[1:] and new == base.switch_partner()
        assert lay.to_dict() == base.switched(7).to_dict()  # the seed decides B
        assert lay.switched(7).switch == lay.switch
        # The scene and the first instruction are the unswitched episode's.
        assert lay.objects == base.objects and np.array_equal(lay.xy, base.xy) and np.array_equal(lay.yaw, base.yaw)
        assert lay.colour_swap == base.colour_swap and lay.target == base.target
        assert lay.instruction == base.instruction and lay.final_target == new != base.target
        assert [lay.instruction_at(t) for t in (0, 6)] == [base.instruction] * 2
        assert parse_instruction(lay.instruction_at(7)).object == new
        assert lay.instruction_at(49) == lay.instruction_at(7)
        d = lay.to_dict()
        assert d["switch"] == {"step": 7, "target": new, "instruction": lay.instruction_at(7)}
        assert d["target"] == base.target and d["instruction"] == base.instruction
        assert {k: v for k, v in d.items() if k != "switch"} == base.to_dict()
        assert layout_from_dict(d).to_dict() == d
        partners.add((k, base.objects.index(new)))
    assert partners == {(2, 1), (5, 1), (5, 2), (5, 3), (5, 4)}  # every distractor rank is drawn
    assert "switch" not in sample_layout(Condition("small_jitter"), 3).to_dict()
    canonical = sample_layout(Condition("small_jitter"), 3).switched(5)
    assert canonical.instruction_at(5) == instruction_text(canonical.final_target, 3, "canonical")
    assert canonical.instruction_at(5).startswith("grasp the ")
    with pytest.raises(ValueError, match="it holds only .* allowed: 2-5 objects"):
        sample_layout(Condition("small_jitter", num_objects=1), 0).switched(5)
    with pytest.raises(ValueError, match="control step >= 1, got 0"):
        canonical.switched(0)
    with pytest.raises(ValueError, match="instruct names the first instruction of seed 3, which already switches"):
        canonical.instructed(1)
    with pytest.raises(ValueError, match="cannot switch the instruction in seed 1: the instructed object"):
        sample_layout(Condition("small_jitter", num_objects=3), 1).instructed_absent(0).switched(5)


# ---------------------------------------------------------------------- metrics on constructed plays
def switch_plays(policy, steps=(5, 25), regime="small_jitter", k=5, scenes=12):
    """The original plays and the switched plays per step of a made-up policy: policy(layout, step) -> held
    object name (step None: the original play). The TCP ends at the held object."""
    original, switched = [], {s: [] for s in steps}
    for j in range(scenes):
        base = sample_layout(Condition(regime, "canonical", k), j)
        for step, lay in [(None, base)] + [(s, base.switched(s)) for s in steps]:
            held = policy(lay, step)
            xy = lay.xy[lay.objects.index(held)] if held != "none" else (-0.5, 0.0)
            row = dict(regime=regime, split="canonical", num_objects=k, episode=j, seed=j, target=lay.final_target,
                       instruction=lay.instruction_at(50), held=held, success=held == lay.final_target,
                       grasp_any=held != "none", reach=held == lay.final_target, tcp_x=xy[0], tcp_y=xy[1],
                       layout=json.dumps(lay.to_dict()))
            (original if step is None else switched[step]).append(row)
    return pd.DataFrame(original), {s: pd.DataFrame(r) for s, r in switched.items()}


def test_switch_metrics_tell_rereading_committing_and_ignoring_policies_apart():
    key = "small_jitter/canonical/5"

    def rereads(lay, step):  # re-reads its instruction, and has grasped by step 15
        return lay.final_target if step is None or step < 15 else lay.target

    top = grounding.instruction_switch(*switch_plays(rereads))[key]
    assert top["scenes"] == 12 and top["switch_steps"] == [5, 25]
    r = top["by_step"]
    assert list(r) == ["5", "25"] and r["5"]["scenes"] == 12 and r["5"]["switch_step"] == 5
    # The switched play's headline rates also sit at the condition's top, as every probe's flat metrics do.
    assert top["follows_new_at_5"] == r["5"]["follows_new_switched"] and top["stays_old_at_25"]["value"] == 1
    rows = probe_rows({"model": {"probe": "instruction-switch", "conditions": {key: top}}})
    assert [row[3] for row in rows] == ["follows new at 5", "stays old at 5", "follows new at 25", "stays old at 25"]
    assert r["5"]["follows_new_original"]["value"] == 0 and r["5"]["follows_new_switched"]["value"] == 1
    assert r["5"]["stays_old_original"]["value"] == 1 and r["5"]["stays_old_switched"]["value"] == 0
    assert r["5"]["follows_new_change"]["value"] == 1
    assert r["5"]["follows_new_change"]["mcnemar_p"] == pytest.approx(2 * 0.5 ** 12)
    assert r["5"]["reaches_new_switched"]["value"] == 1 and r["5"]["reaches_old_switched"]["value"] == 0
    assert r["5"]["transitions"]["rows"] == list(grounding.SWITCH_OUTCOMES)
    assert r["5"]["transitions"]["counts"][1] == [12, 0, 0, 0]  # old in the original -> new when switched early
    assert r["25"]["follows_new_switched"]["value"] == 0 and r["25"]["stays_old_change"]["value"] == 0
    assert r["25"]["transitions"]["counts"][1] == [0, 12, 0, 0]
    assert sum(r["5"]["pairs"].values()) == 12
    c = grounding.instruction_switch(*switch_plays(lambda lay, step: lay.target))[key]["by_step"]  # commits
    assert all(c[s]["stays_old_switched"]["value"] == 1 and c[s]["follows_new_switched"]["value"] == 0 for s in c)
    # Ignores the instruction: the same grasp in both plays, whatever either names.
    b = grounding.instruction_switch(*switch_plays(lambda lay, step: sorted(lay.objects)[0]))[key]["by_step"]
    for s in b.values():
        assert s["follows_new_change"]["value"] == 0 and s["stays_old_change"]["value"] == 0
        assert s["follows_new_original"] == s["follows_new_switched"]
        counts = np.array(s["transitions"]["counts"])
        assert counts.trace() == counts.sum() == 12
    original, switched = switch_plays(rereads)
    with pytest.raises(ValueError, match="different seeds"):
        grounding.instruction_switch(original, {5: switched[5].assign(seed=switched[5]["seed"] + 1)})
    with pytest.raises(ValueError, match="do not all switch at step 25"):
        grounding.instruction_switch(original, {25: switched[5]})


# ---------------------------------------------------------------------- commands
def test_switch_configs_and_refusals(tmp_path, refused):
    cfg = ProbeConfig("instruction-switch", policy="nearest", out=tmp_path / "p")
    assert cfg.grid.num_objects == (5,) and cfg.switch_steps == SWITCH_STEPS == (5, 25)
    variants = cfg.variants()
    assert list(variants) == ["original", "switch-5", "switch-25"]
    assert variants["original"].jobs()[0].options == ()  # exactly an ordinary evaluation
    assert variants["switch-25"].jobs()[0].options == (("switch_at", 25),)
    assert "switch_steps" in cfg.request()
    assert "switch_steps" not in ProbeConfig("position-swap", policy="nearest").request()  # old dirs still resume
    # The same steps in another order are the same variants, so the same request (a rerun was refused).
    assert ProbeConfig("instruction-switch", policy="nearest", switch_steps=(25, 5)).request() == cfg.request()
    p, e = str(tmp_path / "p"), str(tmp_path / "e")
    cases = [
        (["probe", "instruction-switch", "--policy", "nearest", "--out", p, "--num-objects", "1"],
         "instruction-switch needs at least two objects on the table; got --num-objects 1 (allowed: 2-5)"),
        (["probe", "instruction-switch", "--policy", "nearest", "--out", p, "--switch-steps", "0", "25"],
         "--switch-steps must be distinct control steps from 1 to 49 (the episode has 50), got 0 25"),
        (["probe", "instruction-switch", "--policy", "nearest", "--out", p, "--switch-steps", "50"],
         "--switch-steps must be distinct control steps from 1 to 49"),
        (["probe", "instruction-switch", "--policy", "nearest", "--out", p, "--switch-steps", "5", "5"],
         "--switch-steps must be distinct control steps"),
        # Another probe's option was accepted and ignored.
        (["probe", "instruction-swap", "--policy", "nearest", "--out", p, "--switch-steps", "5"],
         "--switch-steps is instruction-switch's option; instruction-swap has none"),
        (["probe", "position-swap", "--policy", "nearest", "--out", p, "--resamples", "500"],
         "--resamples is instruction-swap's option; position-swap has none"),
        (["eval", "--policy", "nearest", "--out", e, "--switch-at", "50"],
         "switch_at must be a control step from 1 to 49 (the episode has 50), got 50"),
        (["eval", "--policy", "nearest", "--out", e, "--switch-at", "0"], "switch_at must be a control step"),
        (["eval", "--policy", "nearest", "--out", e, "--num-objects", "1", "--switch-at", "5"],
         "switch_at needs at least two objects on the table; got --num-objects 1 (allowed: 2-5)"),
        (["eval", "--policy", "nearest", "--out", e, "--num-objects", "3", "--switch-at", "5", "--instruct-absent",
          "0"], "switch_at switches from the instructed object to another present one and instruct_absent names"),
    ]
    refused(cases, tmp_path / "p", tmp_path / "e")


# ---------------------------------------------------------------------- the real simulator
@pytest.mark.slow
def test_the_env_switches_target_and_instruction_exactly_at_its_step(make_env):
    import torch

    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=5)
    u = env.unwrapped
    base = sample_layout(Condition("small_jitter"), 4)
    new = base.switched(6).final_target
    a, b = object_index(base.target), object_index(new)
    trace = {}
    for name, options in (("original", {}), ("switched", {"switch_at": 6}), ("list", {"switch_at": [6]}),
                          ("none", {"switch_at": [None]})):
        obs, _ = env.reset(seed=4, options=options)
        rows = [(0, u.instructions[0], int(u.target_idx[0]), int(obs["extra"]["target_onehot"][0].argmax()))]
        poses = [obs["extra"]["obj_pose"].clone()]
        for t in range(1, 9):
            obs, _, _, _, info = env.step(torch.zeros(1, 7))
            rows.append((t, u.instructions[0], int(u.target_idx[0]), int(obs["extra"]["target_onehot"][0].argmax())))
            poses.append(obs["extra"]["obj_pose"].clone())
        trace[name] = rows, poses
        if name in ("switched", "list"):
            assert u.layouts[0].switch == (6, new) and u.layouts[0].target == base.target
    for t, text, target, onehot in trace["switched"][0]:
        want = (base.instruction, a) if t < 6 else (base.switched(6).instruction_at(6), b)
        assert (text, target, onehot) == (*want, want[1]), t  # not before step 6, from it on
    assert trace["list"][0] == trace["switched"][0]
    assert trace["none"][0] == trace["original"][0] and {r[2] for r in trace["original"][0]} == {a}
    # Nothing in the scene changes: the same states, step by step.
    assert all(torch.equal(x, y) for x, y in zip(trace["original"][1], trace["switched"][1]))
    # A reset without the option starts unswitched again.
    env.reset(seed=4)
    env.step(torch.zeros(1, 7))
    assert u.instructions == [base.instruction] and u._switch_step.tolist() == [0]
    for bad, message in ((50, "switch_at must be a control step from 1 to 49"), (True, "switch_at must be"),
                         ([5, 6], "got 2 switch_at values for 1 envs")):
        with pytest.raises(ValueError, match=message):
            env.reset(seed=4, options={"switch_at": bad})
    with pytest.raises(ValueError, match="switch_at switches from the instructed object"):
        env.reset(seed=4, options={"switch_at": 5, "instruct_absent": 0})


def probe(tmp_path, policy, scenes, **kw) -> dict:
    cfg = ProbeConfig("instruction-switch", policy=policy, out=tmp_path / policy, grid=ProbeGrid(("small_jitter",)),
                      episodes=scenes, workers=1, object_set="standin", **kw)
    return run_probe(cfg, progress=False)


@pytest.mark.slow
def test_switch_calibration_rereading_layout_prior_and_blind_nearest(tmp_path):
    key = "small_jitter/canonical/5"
    prior = probe(tmp_path, "layout-prior", 6, report=True)["conditions"][key]["by_step"]
    # layout-prior reads its instruction at every step: early, it goes to the new object's place and grasps it;
    # late, it has grasped the old one and keeps it (its controller never lets go).
    assert prior["5"]["stays_old_original"]["value"] >= 0.8 and prior["5"]["follows_new_original"]["value"] == 0
    assert prior["5"]["follows_new_switched"]["value"] >= 0.5 and prior["5"]["stays_old_switched"]["value"] == 0
    assert prior["5"]["reaches_new_switched"]["value"] >= 0.8
    assert prior["25"]["stays_old_switched"]["value"] == prior["25"]["stays_old_original"]["value"]
    assert prior["25"]["follows_new_switched"]["value"] == 0
    # nearest never reads the instruction: the same grasp in both plays, at every step.
    blind = probe(tmp_path, "nearest", 6, report=False)["conditions"][key]["by_step"]
    for s in blind.values():
        counts = np.array(s["transitions"]["counts"])
        assert counts.trace() == counts.sum() == 6 and s["follows_new_change"]["value"] == 0
    # The original variant is exactly `vla-ladder eval`; the switched one says what it switched.
    plain = tmp_path / "plain"
    run_evaluation(EvalConfig(policy="layout-prior", out=plain, grid=ProbeGrid(("small_jitter",), num_objects=(5,)),
                              episodes=6, workers=1, object_set="standin"), progress=False)
    cols = ["seed", "target", "instruction", "held", "success", "tcp_x", "tcp_y", "layout"]
    ours = load_run(tmp_path / "layout-prior" / "original").episodes.sort_values("episode")[cols]
    assert ours.reset_index(drop=True).equals(load_run(plain).episodes.sort_values("episode")[cols].reset_index(
        drop=True))
    switched = load_run(tmp_path / "layout-prior" / "switch-5").episodes
    for _, row in switched.iterrows():
        lay = json.loads(row["layout"])
        assert lay["switch"]["step"] == 5 and row["target"] == lay["switch"]["target"] != lay["target"]
        assert row["instruction"] == lay["switch"]["instruction"] and row["success"] == (row["held"] == row["target"])
    root = tmp_path / "layout-prior"
    assert (root / "instruction-switch.png").stat().st_size > 5000
    widths, cells = first_table_row(root / "report.html", "follows new")
    assert len(widths) >= 2 and min(widths) > 300
    assert cells["condition"] == key and cells["switch at"] == "step 5 (0.25 s)", cells
    assert cells["follows new: original → switched"].startswith("0"), cells
    page = (root / "report.html").read_text()
    assert "instruction-switch: layout-prior" in page and "held: original \\ switched" in page


@pytest.mark.slow
def test_the_committed_expert_is_the_expert_until_the_instruction_switches(tmp_path):
    """`committed` reads its target once: with no switch it plays exactly as `scripted` (same final distances to
    the bit); switched at step 5, where the expert follows the new object, it keeps the first one."""
    expert = probe(tmp_path, "scripted", 4, report=False, switch_steps=(5,))
    once = probe(tmp_path, "committed", 4, report=False, switch_steps=(5,))
    cols = ["seed", "held", "success", "reach_dist", "tcp_x", "tcp_y"]
    plain = [load_run(tmp_path / p / "original").episodes.sort_values("episode")[cols].reset_index(drop=True)
             for p in ("scripted", "committed")]
    assert plain[0].equals(plain[1])
    key = "small_jitter/canonical/5"
    a, b = expert["conditions"][key]["by_step"]["5"], once["conditions"][key]["by_step"]["5"]
    assert a["follows_new_switched"]["value"] >= 0.75 and a["stays_old_switched"]["value"] == 0
    assert b["follows_new_switched"]["value"] == 0
    assert b["stays_old_switched"]["value"] == b["stays_old_original"]["value"] == 1.0
    assert b["reaches_old_switched"]["value"] == 1.0
