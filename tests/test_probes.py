"""The grounding probes: their metrics on constructed plays, their commands, their report section, and their
calibration by the reference policies in the real simulator (CPU, state only)."""

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from report_fixtures import chromium_page, make_run, table_row

from vla_ladder.cli import main
from vla_ladder.conditions import Condition, ConditionGrid
from vla_ladder.evaluation import grounding
from vla_ladder.evaluation.rundir import load_run
from vla_ladder.evaluation.runner import EvalConfig, open_run_dir
from vla_ladder.experiments.probes import (PROBES, Probe, ProbeConfig, open_probe_dir, probe_results, rescore_probe,
                                         run_probe)
from vla_ladder.files import write_json
from vla_ladder.report import probes as probe_report
from vla_ladder.report.html import build_report
from vla_ladder.report.study import probe_rows
from vla_ladder.task.layouts import sample_layout
from vla_ladder.task.objects import OBJECT_NAMES


def plays(choose, regime="small_jitter", k=5, scenes=12) -> pd.DataFrame:
    """Instruction-swap plays of a made-up policy: choose(layout instructing rank r, rank, scene) -> held."""
    rows = []
    for j in range(scenes):
        base = sample_layout(Condition(regime, num_objects=k), j)
        for r in range(k):
            lay = base.instructed(r)
            held = choose(lay, r, j)
            rows.append(dict(regime=regime, split="canonical", num_objects=k, episode=j, seed=j, instruct=r,
                             target=lay.target, instruction=lay.instruction, held=held, success=held == lay.target,
                             grasp_any=held != "none", reach=held == lay.target, layout=json.dumps(lay.to_dict())))
    return pd.DataFrame(rows)


def metrics(df, key="small_jitter/canonical/5"):
    return grounding.instruction_swap(df, resamples=300)[key]


def test_instruction_swap_metrics_tell_grounded_from_blind_policies():
    grounded = metrics(plays(lambda lay, r, j: lay.target))
    assert grounded["scenes"] == 12 and grounded["plays"] == 60
    for m in ("instruction_sensitivity", "scene_accuracy", "grounded_accuracy", "nmi", "success"):
        assert grounded[m]["value"] == pytest.approx(1.0), m
    # Every grasp right: no variance between scenes to measure, so each scene counts as one trial (Wilson, 12 of
    # 12) rather than claiming [1.0, 1.0]; the same for success.
    for m in ("grounded_accuracy", "success"):
        assert grounded[m]["ci95"][0] == pytest.approx(0.757, abs=1e-3) and grounded[m]["ci95"][1] == 1.0, m
        assert grounded[m]["method"] == "wilson over scenes (every play alike)" and grounded[m]["n"] == 60
    assert grounded["instruction_sensitivity"]["ci95"][0] == pytest.approx(0.757, abs=1e-3)  # Wilson, 12 of 12
    counts = np.array(grounded["matrix"]["counts"])
    assert grounded["matrix"]["columns"][-1] == "none" and counts[:, :5].trace() == 60 and counts.sum() == 60

    blind = metrics(plays(lambda lay, r, j: sorted(lay.objects)[0]))  # one object per scene, whatever is said
    assert blind["instruction_sensitivity"]["value"] == 0 and blind["scene_accuracy"]["value"] == 0
    assert blind["nmi"]["value"] == pytest.approx(0.0, abs=1e-12) and blind["nmi"]["ci95"][1] < 1e-9
    # Shuffling what is held among a scene's plays changes nothing for it (p = 1), and everything for the grounded
    # policy, whose NMI no shuffle reaches.
    assert blind["nmi"]["permutation_p"] == 1.0 and blind["nmi"]["null_mean"] == pytest.approx(0.0, abs=1e-12)
    assert grounded["nmi"]["permutation_p"] == pytest.approx(1 / 301) and grounded["nmi"]["null_mean"] < 0.5
    assert blind["grounded_accuracy"]["value"] == pytest.approx(0.2)
    # With three of five objects on the table the held object is always "one of those present": the mutual
    # information conditions on the object set, so a blind policy still scores 0.
    three = metrics(plays(lambda lay, r, j: sorted(lay.objects)[0], k=3), "small_jitter/canonical/3")
    assert three["nmi"]["value"] == pytest.approx(0.0, abs=1e-12)
    pooled = grounding.normalised_mutual_information(
        pd.crosstab(plays(lambda lay, r, j: sorted(lay.objects)[0], k=3)["target"],
                    plays(lambda lay, r, j: sorted(lay.objects)[0], k=3)["held"]).to_numpy()[None])
    assert pooled > 0.05  # what conditioning removes

    nothing = metrics(plays(lambda lay, r, j: "none"))
    assert np.isnan(nothing["grounded_accuracy"]["value"]) and nothing["nmi"]["value"] == 0.0
    assert nothing["success"]["value"] == 0.0 and nothing["success"]["ci95"][1] == pytest.approx(0.243, abs=1e-3)

    half = metrics(plays(lambda lay, r, j: lay.target if j % 2 else lay.objects[-1] if r == 0 else lay.target))
    assert half["instruction_sensitivity"]["value"] == 1.0 and half["scene_accuracy"]["value"] == 0.5
    lo, hi = half["grounded_accuracy"]["ci95"]
    assert half["grounded_accuracy"]["value"] == pytest.approx(54 / 60) and lo < 54 / 60 < hi <= 1.0
    assert 0 < half["nmi"]["value"] < 1 and half["nmi"]["ci95"][0] <= half["nmi"]["value"] <= half["nmi"]["ci95"][1]


def test_nmi_null_is_what_an_instruction_blind_policy_scores():
    """A policy holding a random present object whatever is said: its plug-in NMI is above 0 (the estimator's
    bias), near the permutation null's mean, and the permutation p is not small; the reported value is
    bias-corrected, and its interval holds 0 (a percentile bootstrap's, [0.04, 0.19] here, did not)."""
    rng = np.random.default_rng(0)
    random = metrics(plays(lambda lay, r, j: lay.objects[rng.integers(len(lay.objects))], scenes=20))
    nmi = random["nmi"]
    assert 0.02 < nmi["plug_in"] < 0.2 and abs(nmi["plug_in"] - nmi["null_mean"]) < 0.05
    assert nmi["permutation_p"] > 0.05
    assert nmi["ci95"][0] == 0.0 <= nmi["value"] < nmi["plug_in"] - 0.02
    assert nmi["method"] == "jackknife over scenes, bias-corrected"
    # One scene: no jackknife, no interval, and the plain value is named so (it said "bias-corrected")
    one = metrics(plays(lambda lay, r, j: lay.target, scenes=1))["nmi"]
    assert one["method"].startswith("plug-in") and np.isnan(one["ci95"]).all() and one["value"] == one["plug_in"]


def test_nmi_interval_holds_the_true_value_where_a_bootstrap_did_not():
    """200 seeded draws of 20 scenes of five objects, each instruction followed with probability 1/2, else a present
    object or nothing held at random (true NMI 0.256): the interval holds it in 89% of draws (the percentile
    bootstrap it replaced: 25%, its plug-in value averaging 0.33)."""
    rng = np.random.default_rng(7)
    P = np.full((5, 6), 0.5 / 30)
    P[np.arange(5), np.arange(5)] += 0.1
    truth = float((P * np.log(P / (P.sum(1, keepdims=True) * P.sum(0, keepdims=True)))).sum() / np.log(5))
    assert truth == pytest.approx(0.256, abs=1e-3)
    hits, values = 0, []
    for _ in range(200):
        rows = []
        for e in range(20):
            objects = list(rng.permutation(OBJECT_NAMES))
            for r, t in enumerate(objects):
                held = t if rng.random() < 0.5 else (objects + ["none"])[rng.integers(6)]
                rows.append(dict(regime="small_jitter", split="canonical", num_objects=5, episode=e, seed=e, target=t,
                                 instruct=r, held=held, success=held == t, grasp_any=held != "none", reach=True))
        nmi = grounding.instruction_swap(pd.DataFrame(rows), resamples=20)["small_jitter/canonical/5"]["nmi"]
        hits += nmi["ci95"][0] <= truth <= nmi["ci95"][1]
        values.append(nmi["value"])
    assert hits / 200 >= 0.85 and abs(np.mean(values) - truth) < 0.03, (hits, np.mean(values))


def test_pooled_rate_counts_correlated_plays_by_their_design_effect():
    """Rates pooled over correlated plays of a scene: one play a scene is the Wilson interval of the plays; plays
    that a scene decides (all or none succeed) count as one trial a scene; plays independent of their scene come
    close to the plays' own Wilson interval."""
    from vla_ladder.stats import wilson

    one = grounding.pooled_rate(np.array([1, 0, 1, 1, 0, 1.0]), np.ones(6))
    assert one["ci95"] == pytest.approx(list(wilson(4, 6))) and one["n"] == 6
    decided = grounding.pooled_rate(np.array([5, 0, 5, 5, 0, 5.0] * 3), np.full(18, 5.0))
    assert decided["ci95"] == pytest.approx(list(wilson(12, 18)), abs=1e-9)
    rng = np.random.default_rng(0)
    num = rng.binomial(5, 0.5, 200).astype(float)
    spread = grounding.pooled_rate(num, np.full(200, 5.0))
    lo, hi = wilson(int(num.sum()), 1000)
    assert spread["ci95"] == pytest.approx([lo, hi], abs=0.01)
    assert grounding.pooled_rate(np.zeros(3), np.zeros(3))["n"] == 0
    # Plays in one scene only (a policy that grasps in one scene): one trial, never narrower than all of them alike.
    alone = grounding.pooled_rate(np.array([2.0, 0, 0]), np.array([5.0, 0, 0]))
    assert alone["ci95"] == pytest.approx(list(wilson(0.4, 1))) and alone["value"] == pytest.approx(0.4)
    every = grounding.pooled_rate(np.array([5.0]), np.array([5.0]))
    assert alone["ci95"][1] - alone["ci95"][0] > every["ci95"][1] - every["ci95"][0]


def test_incomplete_scenes_are_left_out():
    df = plays(lambda lay, r, j: lay.target)
    df = df[~((df["episode"] == 3) & (df["instruct"] == 4))]
    assert metrics(df)["scenes"] == 11


def test_a_condition_without_one_complete_scene_scores_nothing_instead_of_failing():
    """The confusion table of no plays (pandas' crosstab of empty categoricals repeated its columns) made every
    metric of the probe fail where each scene of a condition lacked a variant."""
    df = plays(lambda lay, r, j: lay.target, k=2, scenes=3)
    res = metrics(df[df["instruct"] == 0], "small_jitter/canonical/2")
    assert res["scenes"] == 0 and np.isnan(res["instruction_sensitivity"]["value"])
    assert np.array(res["matrix"]["counts"]).shape == (5, 6) and not np.array(res["matrix"]["counts"]).any()
    ordinary = df[df["instruct"] == 0].assign(absent=np.nan, tcp_x=0.0, tcp_y=0.0)
    absent = ordinary.assign(absent=0, target="mug")  # 2 objects: three absent ones a scene, one played
    res = grounding.absent_object(ordinary, absent)["small_jitter/canonical/2"]
    assert res["scenes"] == 0 and np.isnan(res["grasp_absent"]["value"])


def test_a_paired_change_over_no_scenes_has_no_p_value():
    """A condition none of whose scenes both variants played: its change, interval and McNemar p are all undefined.
    The p was 1 (no discordant pairs), shown "p=1" beside "– [–, –]" as if the scenes had played alike; scenes
    that did play alike still get 1."""
    a = pd.concat([plays(lambda lay, r, j: lay.target), plays(lambda lay, r, j: "none", regime="medium_jitter",
                                                               scenes=3)])
    a = a[a["instruct"] == 0].drop(columns="instruct")
    res = grounding.paired(a, a[a["regime"] == "small_jitter"])
    empty = res["medium_jitter/canonical/5"]
    assert empty["n"] == 0 and empty["left_out"] == 3
    for change in empty["difference"].values():
        assert change["n"] == 0 and np.isnan(change["value"]) and np.isnan(change["ci95"]).all()
        assert np.isnan(change["mcnemar_p"])
    alike = res["small_jitter/canonical/5"]["difference"]["success"]
    assert alike["n"] == 12 and alike["value"] == 0 and alike["mcnemar_p"] == 1.0


def test_instruction_swap_plays_of_other_scenes_are_refused():
    """Its plays pair on the episode index, as every paired probe's do: variants of other seeds (directories of
    two requests put together) were scored as scenes, 3 of them 'sensitive'; every other probe refused them."""
    df = plays(lambda lay, r, j: lay.target)
    shifted = df.assign(seed=df["seed"] + 100 * (df["instruct"] == 1))
    with pytest.raises(ValueError, match="played different seeds on 12 of 12 scenes"):
        metrics(shifted)
    twice = df.assign(target=np.where(df["instruct"] == 1, df["target"].where(df["instruct"] == 0).ffill(),
                                      df["target"]))
    with pytest.raises(ValueError, match="instructed an object twice in a scene"):
        metrics(twice.sort_values(["episode", "instruct"]))


def test_paired_and_appearance_metrics():
    a = plays(lambda lay, r, j: lay.target)
    a = a[a["instruct"] == 0].drop(columns="instruct")
    b = a.assign(success=[j >= 4 for j in a["episode"]], held=[t if j >= 4 else "none" for t, j in
                                                                zip(a["target"], a["episode"])])
    diff = grounding.paired(a, b)["small_jitter/canonical/5"]["difference"]["success"]
    assert diff["value"] == pytest.approx(-4 / 12) and diff["ci95"][1] < 0
    assert diff["mcnemar_p"] == pytest.approx(0.125)  # 4 discordant pairs, all one way
    rows = []
    for j in range(12):
        lay = sample_layout(Condition("small_jitter"), j, appearance="swap")
        partner = lay.colour_swap[1] if lay.colour_swap else None
        held = partner if partner and j % 2 else lay.target
        rows.append(dict(regime="small_jitter", split="canonical", num_objects=5, episode=j, seed=j,
                         target=lay.target, held=held, layout=json.dumps(lay.to_dict())))
    swapped = pd.DataFrame(rows)
    plain = [json.dumps(sample_layout(Condition("small_jitter"), j).to_dict()) for j in range(12)]
    original = swapped.assign(held=swapped["target"], layout=plain)
    c = grounding.appearance_swap(original, swapped)["small_jitter/canonical/5"]
    n = c["swapped"]
    followed = sum(1 for r in rows if r["held"] != r["target"])
    assert 0 < n < 12 and c["follows_colour"]["value"] == pytest.approx(followed / n)
    assert c["original"]["instructed"]["value"] == 1.0
    assert c["follows_shape"]["value"] == pytest.approx(1 - followed / n)
    assert c["transitions"]["counts"][0][:2] == [n - followed, followed] and c["shape_change"]["value"] < 0
    assert c["colour_change"]["value"] == pytest.approx(followed / n)  # (no swap: never the partner)
    with pytest.raises(ValueError, match="played different seeds on 12 of 12 scenes"):  # not the same scenes: no pairs
        grounding.appearance_swap(original.assign(seed=original["seed"] + 100), swapped)


def test_probe_and_eval_configs_reject_bad_input_before_any_work(tmp_path, refused):
    cases = [
        (["probe", "bogus", "--policy", "nearest", "--out", str(tmp_path / "p")],
         "unknown probe 'bogus'; allowed: instruction-swap, paraphrase, appearance-swap"),
        (["probe", "appearance-swap", "--policy", "nearest", "--out", str(tmp_path / "p"), "--num-objects", "1"],
         "appearance-swap needs at least two objects on the table"),
        (["probe", "instruction-swap", "--policy", "teleport", "--out", str(tmp_path / "p")], "unknown policy"),
        (["probe", "instruction-swap", "--out", str(tmp_path / "p")], "--policy SPEC is required"),
        (["eval", "--policy", "nearest", "--out", str(tmp_path / "e"), "--num-objects", "3", "--instruct", "3"],
         "instruct must be a present-object rank from 0 to 2"),
        (["eval", "--policy", "nearest", "--out", str(tmp_path / "e"), "--instructions", "poetic"],
         "unknown instruction set 'poetic'; allowed: canonical, paraphrase-train, paraphrase-heldout"),
        (["eval", "--policy", "nearest", "--out", str(tmp_path / "e"), "--appearance", "neon"],
         "unknown appearance 'neon'; allowed: original, swap"),
        (["probe", "position-swap", "--policy", "scripted", "--out", str(tmp_path / "p"), "--object-set", "ycb"],
         "object_set='ycb' but ManiSkill's YCB models are incomplete"),  # (none here; before any directory is made)
    ]
    refused(cases, tmp_path / "p", tmp_path / "e")


def test_probe_variants_share_seeds_and_a_probe_dir_refuses_another_request(tmp_path):
    cfg = ProbeConfig("instruction-swap", policy="nearest", out=tmp_path / "p",
                      grid=ConditionGrid(("small_jitter",), ("canonical",), (2, 4)), episodes=3)
    variants = cfg.variants()
    assert list(variants) == ["instruct-0", "instruct-1", "instruct-2", "instruct-3"]
    assert [c.num_objects for c in variants["instruct-2"].conditions] == [4]
    assert variants["instruct-1"].jobs()[0].options == (("instruct", 1),)
    assert {j.seed for j in variants["instruct-3"].jobs()} == {0, 1, 2}
    para = ProbeConfig("paraphrase", policy="nearest", out=tmp_path / "q").variants()
    assert [c.num_objects for c in para["paraphrase-heldout"].conditions] == [5, 1, 5, 1]  # distractor-free control
    assert para["paraphrase-train"].jobs()[0].options == (("instructions", "paraphrase-train"),)
    open_probe_dir(cfg)
    open_probe_dir(cfg)  # the same request resumes
    other = ProbeConfig("instruction-swap", policy="scripted", out=tmp_path / "p")
    with pytest.raises(ValueError, match="holds another probe request.*--overwrite") as e:
        open_probe_dir(other)
    assert "it differs in " in str(e.value) and "policy was 'nearest'" in str(e.value)  # what to change


def test_a_probe_is_one_entry_in_probes_and_one_view_in_the_report(tmp_path, monkeypatch):
    assert list(PROBES) == list(probe_report.VIEWS)  # every probe can be shown, in the same order
    assert PROBES["absent-object"].fit(5) == 4 and PROBES["instruction-swap"].fit(1) == 2  # nearest playable count
    assert PROBES["paraphrase"].fit(3) == 3
    # A newcomer's probe: the same scenes in the canonical and a held-out wording, scored by how many scenes each
    # variant succeeds in. Registering it is all the CLI, the request, the rescoring and the report need.
    seen = {}

    def results(runs, resamples):
        seen["resamples"] = resamples
        return {"small_jitter/canonical/2": {name: int(r.episodes["success"].sum()) for name, r in runs.items()}}

    monkeypatch.setitem(PROBES, "wording-pair", Probe(
        lambda cfg: {"plain": dict(grid=cfg.grid), "heldout": dict(grid=cfg.grid, instructions="paraphrase-heldout")},
        results, objects=(2, 3), needs="two or three objects", default_objects=2, options=("switch_steps",)))
    monkeypatch.setitem(probe_report.VIEWS, "wording-pair", probe_report.ProbeView(
        "Canonical against held-out wording.", lambda conds: (["condition", "plain", "held out"], [
            [k, str(c["plain"]), str(c["heldout"])] for k, c in conds.items()]),
        lambda key, c: [f"{key}: {c['plain']} -> {c['heldout']}"], lambda data, path: path))
    cfg = ProbeConfig("wording-pair", policy="nearest", out=tmp_path / "p", episodes=3)
    assert cfg.grid.num_objects == (2,) and list(cfg.variants()) == ["plain", "heldout"]
    assert cfg.variants()["heldout"].jobs()[0].options == (("instructions", "paraphrase-heldout"),)
    assert "switch_steps" in cfg.request()  # its own option is part of its request, and of no other probe's
    assert "switch_steps" not in ProbeConfig("position-swap", policy="nearest").request()
    with pytest.raises(ValueError, match=r"wording-pair needs two or three objects; got --num-objects 4 "
                                         r"\(allowed: 2-3\)"):
        ProbeConfig("wording-pair", policy="nearest", grid=ConditionGrid(num_objects=(4,)))
    with pytest.raises(ValueError, match="unknown probe 'nope'; allowed: .*wording-pair"):
        ProbeConfig("nope")
    for name, kinds in (("plain", ["success", "success", "wrong_object"]), ("heldout", ["success"] * 3)):
        make_run(tmp_path / "p" / name, "nearest", [("small_jitter", "canonical", 2)], kinds)
    write_json(tmp_path / "p" / "probe.json", {"probe": "wording-pair", "policy": {"spec": "nearest"},
                                               "variants": {"plain": "plain", "heldout": "heldout"},
                                               "config": {"resamples": 321}, "conditions": {}})
    data = rescore_probe(tmp_path / "p")
    assert data["conditions"] == {"small_jitter/canonical/2": {"plain": 2, "heldout": 3}} and seen["resamples"] == 321
    assert probe_report.summary_lines(data) == ["small_jitter/canonical/2: 2 -> 3"]
    assert "<td>small_jitter/canonical/2</td><td>2</td><td>3</td>" in probe_report.table_html(data)
    assert "Canonical against held-out wording." in probe_report.section(data, [], "here")
    monkeypatch.delitem(probe_report.VIEWS, "wording-pair")
    with pytest.raises(ValueError, match="the report does not know the probe 'wording-pair'; allowed: "):
        probe_report.table_html(data)


def test_run_directories_from_before_the_presentation_fields_still_resume(tmp_path):
    cfg = EvalConfig("nearest", out=tmp_path / "run", episodes=2)
    saved = {k: v for k, v in json.loads(json.dumps(cfg.request())).items()
             if k not in ("instructions", "appearance", "instruct", "instruct_absent")}
    write_json(tmp_path / "run" / "config.json", saved)
    assert open_run_dir(cfg) == []
    with pytest.raises(ValueError, match="another evaluation request"):
        open_run_dir(EvalConfig("nearest", out=tmp_path / "run", episodes=2, instructions="paraphrase-heldout"))


def make_probe(root: Path, videos: int = 0) -> Path:
    """A probe directory of constructed instruction-swap variants (report_fixtures' run directories); the first
    `videos` scenes of each variant filmed."""
    kinds = {0: ["success", "success", "wrong_object"], 1: ["wrong_object", "success", "grasp_lost"]}
    for r, k in kinds.items():
        run = make_run(root / f"instruct-{r}", "nearest", [("small_jitter", "canonical", 2)], k, videos=videos)
        episodes = pd.read_parquet(run / "episodes.parquet")  # instruct-r names the scene's rank-r object
        lays = [sample_layout(Condition("small_jitter", "canonical", 2), s).instructed(r) for s in episodes["seed"]]
        episodes["target"], episodes["instruction"] = [x.target for x in lays], [x.instruction for x in lays]
        episodes.to_parquet(run / "episodes.parquet", index=False)
    df = pd.concat([load_run(root / f"instruct-{r}").episodes.assign(instruct=r) for r in kinds])
    write_json(root / "probe.json", {"probe": "instruction-swap", "policy": {"spec": "nearest"}, "complete": True,
                                     "conditions": grounding.instruction_swap(df, 300)})
    return root


def test_the_report_shows_a_probe_found_next_to_its_variant_runs(tmp_path):
    probe = make_probe(tmp_path / "probe")
    runs = [load_run(probe / "instruct-0"), load_run(probe / "instruct-1")]
    assert probe_report.probe_dirs([r.path for r in runs]) == [probe.resolve()]
    page = build_report(runs, tmp_path / "r.html", placements=False).read_text()
    assert "Grounding probes" in page and "instruction sensitivity" in page and "Counts" in page
    assert 'alt="probe_0"' in page and 'alt="probe_0_matrix"' in page
    assert "No scene was filmed in every variant" in page  # made without videos
    # The probe's folder is shown relative to the page (it was resolved: the machine's absolute path).
    assert "<span class=ci>probe</span></h3>" in page and str(tmp_path) not in page
    plain = build_report([load_run(make_run(tmp_path / "plain", "nearest", [("small_jitter", "canonical", 2)],
                                            ["success"]))], tmp_path / "p.html", placements=False).read_text()
    assert "Grounding probes" not in plain
    # Filmed variants and --samples 0: no scene shown, and no note that none was filmed.
    filmed = make_probe(tmp_path / "filmed", videos=1)
    runs = [load_run(filmed / "instruct-0"), load_run(filmed / "instruct-1")]
    page = build_report(runs, tmp_path / "f.html", placements=False, samples=0).read_text()
    assert "Grounding probes" in page and "No scene was filmed" not in page and "The same scenes" not in page
    page = build_report(runs, tmp_path / "f.html", placements=False, samples=1).read_text()
    assert "No scene was filmed" not in page and "(first 1 filmed)" in page


# ---------------------------------------------------------------------- the real simulator
def probe(tmp_path, name, policy, regimes, scenes, **kw) -> dict:
    cfg = ProbeConfig(name, policy=policy, out=tmp_path / f"{name}-{policy}", grid=ConditionGrid(tuple(regimes)),
                      episodes=scenes, workers=1, report=False,
                      **({"resamples": 500} if name == "instruction-swap" else {}), **kw)  # (its own option)
    return run_probe(cfg, progress=False)


@pytest.mark.slow
def test_instruction_swap_calibration_scripted_nearest_layout_prior(tmp_path):
    scripted = probe(tmp_path, "instruction-swap", "scripted", ["full_random"], 3)["conditions"]
    c = scripted["full_random/canonical/5"]
    for m in ("instruction_sensitivity", "scene_accuracy", "grounded_accuracy", "nmi", "success"):
        assert c[m]["value"] >= 0.9, (m, c[m])
    nearest = probe(tmp_path, "instruction-swap", "nearest", ["full_random"], 3)
    c = nearest["conditions"]["full_random/canonical/5"]
    assert c["instruction_sensitivity"]["value"] == 0 and c["nmi"]["value"] == pytest.approx(0, abs=1e-9)
    assert c["grounded_accuracy"]["value"] == pytest.approx(0.2)
    prior = probe(tmp_path, "instruction-swap", "layout-prior", ["small_jitter", "full_random"], 4)["conditions"]
    small, full = prior["small_jitter/canonical/5"], prior["full_random/canonical/5"]
    assert small["instruction_sensitivity"]["value"] >= 0.75 and small["grounded_accuracy"]["value"] >= 0.8
    assert small["nmi"]["value"] >= 0.6
    assert full["success"]["value"] <= small["success"]["value"] - 0.5
    assert full["nmi"]["value"] < small["nmi"]["value"] and full["scene_accuracy"]["value"] == 0
    # The variants are run directories: instruct-0 is exactly `vla-ladder eval` on the same seeds.
    root = tmp_path / "instruction-swap-nearest"
    assert json.loads((root / "probe.json").read_text())["variants"]["instruct-4"] == "instruct-4"
    assert main(["compare", str(root / "instruct-0"), str(root / "instruct-1")]) == 0
    assert (root / "instruction-swap.png").stat().st_size > 5000
    # Rescoring recomputes the metrics from the plays alone (what a re-run study's report does): stale metrics in
    # probe.json are replaced by the same ones run_probe wrote.
    stale = json.loads((root / "probe.json").read_text())
    write_json(root / "probe.json", {**stale, "conditions": {}})
    assert rescore_probe(root)["conditions"] == nearest["conditions"]
    assert json.loads((root / "probe.json").read_text())["conditions"] == nearest["conditions"]


@pytest.mark.slow
def test_paraphrase_and_appearance_probes_in_the_simulator(tmp_path):
    data = probe(tmp_path, "paraphrase", "layout-prior", ["small_jitter"], 2)
    runs = {v: load_run(tmp_path / "paraphrase-layout-prior" / v) for v in data["variants"]}
    texts = {v: set(r.episodes["instruction"]) for v, r in runs.items()}
    assert all(t.startswith("grasp the ") for t in texts["canonical"]) and not texts["canonical"] & \
        texts["paraphrase-heldout"]
    for key in ("small_jitter/canonical/5", "small_jitter/canonical/1"):  # the layout prior reads every wording
        c = data["conditions"][key]
        assert c["paraphrase-heldout"]["success"] == c["canonical"]["success"] >= 0.5
        assert c["paraphrase-heldout"]["vs_canonical"]["success"]["value"] == 0
    app = probe(tmp_path, "appearance-swap", "scripted", ["small_jitter"], 2)
    c = app["conditions"]["small_jitter/canonical/5"]
    assert c["swapped"] >= 1 and c["follows_shape"]["value"] == 1.0 and c["follows_colour"]["value"] == 0.0
    swap_layouts = load_run(tmp_path / "appearance-swap-scripted" / "swap").episodes["layout"]
    assert any("colour_swap" in json.loads(lay) for lay in swap_layouts)


@pytest.mark.slow
def test_probe_report_renders_in_chromium(tmp_path):
    probe = make_probe(tmp_path / "probe", videos=2)
    out = build_report([load_run(probe / "instruct-0"), load_run(probe / "instruct-1")], tmp_path / "r.html",
                       placements=False)
    moved = shutil.copy(out, tmp_path / "elsewhere.html")
    with chromium_page(moved) as (page, failed):
        images = dict(page.evaluate("[...document.images].map(i => [i.alt, i.naturalWidth])"))
        text = page.inner_text("body")
        cells = list(table_row(page, "instruction sensitivity").values())
        # The paired plays: between the probe's heading and the next section, each filmed scene once per variant.
        page.wait_for_function("[...document.querySelectorAll('video')].every(v => v.readyState >= 2 || v.error)",
                               timeout=30000)
        paired = page.evaluate("""() => { const h = [...document.querySelectorAll('h4')].find(h =>
            h.innerText.startsWith('The same scenes')); const out = []; let e = h.nextElementSibling;
            while (e && e.tagName !== 'H2' && e.tagName !== 'H3') { if (e.classList.contains('episode'))
            out.push([e.querySelector('.cap').innerText, e.querySelector('video').readyState]);
            e = e.nextElementSibling; } return out; }""")
    assert not failed
    assert [cap.split(":")[0] for cap, _ in paired] == ["instruct-0", "instruct-1"] * 2
    assert all(state >= 2 for _, state in paired)
    # Scene 0 is "success" under instruct-0 and "wrong_object" under instruct-1: the captions say so.
    assert "success 1" in paired[0][0] and "success 0" in paired[1][0]
    assert images["probe_0"] > 300 and images["probe_0_matrix"] > 300
    assert "Grounding probes" in text and "instruction-swap: nearest" in text
    assert cells[:2] == ["small_jitter/canonical/2", "3"]


def test_paired_variants_count_the_scenes_one_lacks_and_refuse_other_seeds():
    """An inner join dropped the scenes one variant lacked and reported the rest as the whole probe; they are left
    out and counted now, as every probe does (grounding.common_scenes). Another seed on the same episode is not a
    scene left out: it is refused."""
    df = plays(lambda lay, r, j: lay.target)
    short = grounding.paired(df, df[df["episode"] > 0])["small_jitter/canonical/5"]
    assert short["left_out"] == 1 and short["n"] == 11 * 25  # (5 plays a scene here: 5 x 5 pairs each)
    assert grounding.paired(df, df)["small_jitter/canonical/5"]["n"] == len(df) * 5
    with pytest.raises(ValueError, match=r"the variants played different seeds on 1 of 12 scenes \(e.g. "
                                         r"small_jitter/canonical/5 episode 3\); a probe compares the same scenes"):
        grounding.paired(df, df.assign(seed=df["seed"] + 100 * (df["episode"] == 3)))
    with pytest.raises(ValueError, match="the variants played different object sets"):  # resumed on another machine
        grounding.paired(df.assign(object_set="standin"), df.assign(object_set="ycb"))


def test_probes_pooling_several_variants_refuse_plays_of_both_object_sets():
    """The two-play probes refused variants played with different object sets (same_scenes); the instruction swap
    and the absent object, which pool more variants, compared stand-in plays with YCB ones without a word (a resume
    on another machine with object_set auto plays the remaining variants with the other set)."""
    from test_absent_probe import absent_plays, grounded

    df = plays(lambda lay, r, j: lay.target)
    assert metrics(df.assign(object_set="ycb"))["scenes"] == 12
    with pytest.raises(ValueError, match="the variants played different object sets"):
        metrics(df.assign(object_set=np.where(df["instruct"] < 2, "standin", "ycb")))
    present, absent = absent_plays(grounded)
    assert grounding.absent_object(present.assign(object_set="ycb"), absent.assign(object_set="ycb"))
    with pytest.raises(ValueError, match="the variants played different object sets"):
        grounding.absent_object(present.assign(object_set="standin"), absent.assign(object_set="ycb"))


def _nan_everywhere(data):
    """`data` with every float undefined (NaN), as a probe of conditions without scenes writes them."""
    if isinstance(data, dict):
        return {k: _nan_everywhere(v) for k, v in data.items()}
    if isinstance(data, list):
        return [_nan_everywhere(v) for v in data]
    return float("nan") if isinstance(data, float) else data


def test_a_probe_with_undefined_metrics_writes_strict_json_and_reports_them_as_before(tmp_path):
    """probe.json held bare NaN tokens for the rates of a condition without one complete scene, which JSON.parse,
    jq and most languages' parsers refuse: it holds null now, and the report, the terminal's lines, the study's
    table and diagnose read it as they read NaN ("–" in the tables, "nan" in the lines)."""
    from test_files import strict_json

    from vla_ladder.experiments.diagnose import _rate
    from vla_ladder.report import study as study_report

    df = plays(lambda lay, r, j: lay.target, k=2, scenes=3)
    swap = grounding.instruction_swap(df[df["instruct"] == 0], resamples=300)  # no scene has both plays
    ordinary = df[df["instruct"] == 0].assign(absent=np.nan, tcp_x=0.0, tcp_y=0.0)
    absent = grounding.absent_object(ordinary, ordinary.assign(absent=0, target="mug"))
    a = plays(lambda lay, r, j: lay.target)
    a = a[a["instruct"] == 0].drop(columns="instruct")
    rows = []
    for j in range(12):
        lay = sample_layout(Condition("small_jitter"), j, appearance="swap")
        rows.append(dict(regime="small_jitter", split="canonical", num_objects=5, episode=j, seed=j,
                         target=lay.target, held=lay.target, layout=json.dumps(lay.to_dict())))
    swapped = pd.DataFrame(rows)
    original = swapped.assign(layout=[json.dumps(sample_layout(Condition("small_jitter"), j).to_dict())
                                      for j in range(12)])
    appearance = _nan_everywhere(grounding.appearance_swap(original, swapped))
    cases = {"instruction-swap": swap, "absent-object": absent, "appearance-swap": appearance,
             "nan-swap": _nan_everywhere(grounding.instruction_swap(df, resamples=300))}
    for name, conditions in cases.items():
        probe = "instruction-swap" if name == "nan-swap" else name
        data = {"probe": probe, "policy": {"spec": "nearest"}, "complete": True, "conditions": conditions}
        path = tmp_path / name
        write_json(path / "probe.json", data)
        text = (path / "probe.json").read_text()
        assert "NaN" not in text and "null" in text
        strict_json(text)
        loaded = probe_report.load_probe(path)
        assert probe_report.table_html(loaded) == probe_report.table_html(data)
        assert "–" in probe_report.table_html(loaded)
        assert probe_report.summary_lines(loaded) == probe_report.summary_lines(data)
        assert any("nan" in line for line in probe_report.summary_lines(loaded))
        assert probe_report.section(loaded, [], "here") == probe_report.section(data, [], "here")
        assert all(p.is_file() for p in probe_report.plot_probe(loaded, tmp_path / f"{name}.png"))
        shown = {f"m-{probe}": loaded}
        assert study_report.probes_markdown(shown) == study_report.probes_markdown({f"m-{probe}": data})
    key = "small_jitter/canonical/2"
    entry = probe_report.load_probe(tmp_path / "instruction-swap")["conditions"][key]["instruction_sensitivity"]
    assert entry["value"] is None and np.isnan(_rate(entry)["value"]) and np.isnan(_rate(entry)["ci95"]).all()
    assert probe_report.load_probe(tmp_path / "absent-object")["conditions"][key]["grasp_absent"]["value"] is None


# ---------------------------------------------------------------------- variants that played different scenes
CUT_SHORT = {  # probe -> its --num-objects: the fewest variants that probe plays (two each), three scenes
    "instruction-swap": 2, "absent-object": 4, "position-swap": 5}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CUT_SHORT))
def test_every_probe_pairs_the_scenes_every_variant_played_and_counts_the_rest(tmp_path, name):
    """A variant cut short holds fewer scenes than the others. The two-play probes refused to score such variants
    ("the variants played different scenes: 1 in one only") while the instruction swap and the absent object left
    the scenes out without a word; every probe now pairs the scenes every variant played, in one place
    (grounding.common_scenes), and says how many it left out, in probe.json, the terminal's lines and the report's
    table. Another seed on the same episode is no scene left out: an error. The plays are real (scripted expert)."""
    cfg = ProbeConfig(name, policy="scripted", out=tmp_path / name, episodes=3, workers=1, report=False,
                      grid=ConditionGrid(("small_jitter",), ("canonical",), (CUT_SHORT[name],)),
                      **({"resamples": 100} if name == "instruction-swap" else {}))
    whole = run_probe(cfg, progress=False)
    key = f"small_jitter/canonical/{CUT_SHORT[name]}"
    assert whole["conditions"][key]["scenes"] == 3 and whole["conditions"][key]["left_out"] == 0
    runs = {v: load_run(tmp_path / name / rel) for v, rel in whole["variants"].items()}
    assert len(runs) == 2

    def cut(run, keep):
        return type(run)(run.path, run.episodes[run.episodes["episode"] < keep], run.summary, run.config)

    last = list(runs)[-1]  # the variant played last: the one an interruption cuts short
    short = probe_results(name, {**runs, last: cut(runs[last], 2)}, 100)
    assert short[key]["scenes"] == 2 and short[key]["left_out"] == 1
    # Exactly the metrics of the two scenes both variants played, nothing of the third.
    both = probe_results(name, {v: cut(r, 2) for v, r in runs.items()}, 100)
    assert both[key]["left_out"] == 0 and {**short[key], "left_out": 0} == both[key]
    data = {**whole, "conditions": short}
    lines = probe_report.summary_lines(data)
    assert lines[-1] == f"{key}: 1 scene left out, {probe_report.LEFT_OUT}"
    assert f"<b>Scenes left out</b>, {probe_report.LEFT_OUT}: {key}: 1.</p>" in probe_report.table_html(data)
    assert [key, "scenes left out (played in some variants only)", "1"] in [r[2:5] for r in probe_rows({"m": data})]
    assert "left out" not in " ".join(probe_report.summary_lines(whole)) + probe_report.table_html(whole)
    # The first variant cut short instead: the same.
    first = list(runs)[0]
    assert probe_results(name, {**runs, first: cut(runs[first], 2)}, 100) == short
    # Another seed on scene 1 of one variant: not the same scenes, refused.
    other = runs[last].episodes.assign(seed=lambda e: e["seed"] + 1000 * (e["episode"] == 1))
    with pytest.raises(ValueError, match=rf"the variants played different seeds on 1 of 3 scenes \(e.g. {key} "
                                         r"episode 1\); a probe compares the same scenes"):
        probe_results(name, {**runs, last: type(runs[last])(runs[last].path, other, {}, {})}, 100)


@pytest.mark.slow
def test_an_interrupted_probe_is_refused_by_rescoring_and_finished_by_its_command(tmp_path):
    """An interrupted probe has no probe.json yet: rescoring it (a study's report) failed with a FileNotFoundError
    traceback; it names the command now, and that command resumes the cut-short variant and finishes the probe
    with the same metrics as an uninterrupted one."""
    cfg = ProbeConfig("position-swap", policy="scripted", out=tmp_path / "p", episodes=3, workers=1, report=False,
                      grid=ConditionGrid(("small_jitter",), ("canonical",), (5,)))
    whole = run_probe(cfg, progress=False)
    (tmp_path / "p" / "probe.json").unlink()
    swapped = tmp_path / "p" / "swapped"  # cut short after two scenes, as a Ctrl-C leaves it
    episodes = pd.read_parquet(swapped / "episodes.parquet")
    write_json(swapped / "summary.json", {**json.loads((swapped / "summary.json").read_text()), "complete": False})
    episodes[episodes["episode"] < 2].to_parquet(swapped / "episodes.parquet", index=False)
    with pytest.raises(ValueError, match=r"p holds no probe.json: its probe has not finished \(interrupted\?\); "
                                         "rerun the same `vla-ladder probe` command, which resumes it"):
        rescore_probe(tmp_path / "p")
    again = run_probe(cfg, progress=False)
    assert again["complete"] and again["conditions"] == whole["conditions"]
    assert len(load_run(swapped).episodes) == 3 and rescore_probe(tmp_path / "p")["conditions"] == whole["conditions"]
