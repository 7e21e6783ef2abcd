"""`vla-ladder diagnose`: one policy through the ladder and four probes beside the references, on the real
simulator (state-only reference policies, a few scenes)."""

from __future__ import annotations

import json

import pytest
from report_fixtures import chromium_page, table_row

from vla_ladder.cli import main
from vla_ladder.evaluation.rundir import load_run
from vla_ladder.experiments.diagnose import QUESTIONS

SMALL = ["--episodes", "3", "--probe-episodes", "3", "--workers", "1", "--videos", "1"]


def test_ladder_drop_pairs_the_regimes_episodes_by_seed(tmp_path):
    """Episode j plays the same seed in every regime: the drop's interval is the paired one (Newcombe's), and a
    policy whose own regime is the farthest gets no answer."""
    import numpy as np
    from report_fixtures import make_run

    from vla_ladder.evaluation.rundir import load_run
    from vla_ladder.experiments.diagnose import ladder_drop
    from vla_ladder.stats import paired_difference

    sj, fr = ("small_jitter", "canonical", 5), ("full_random", "canonical", 5)
    run = load_run(make_run(tmp_path / "r", "nearest", [sj, fr], ["success"] * 6 + ["nothing"] * 4))
    far = run.episodes["regime"] == "full_random"
    run.episodes.loc[far, "success"] = run.episodes.loc[far, "episode"] < 2  # 2 of the same 6 scenes still succeed
    drop = ladder_drop(run, "small_jitter/canonical/5")
    own = np.arange(10) < 6
    assert drop["value"] == pytest.approx(0.2 - 0.6) and drop["n"] == 10 and drop["to"] == "full_random/canonical/5"
    assert drop["ci95"] == pytest.approx(list(paired_difference(own, np.arange(10) < 2)))
    assert ladder_drop(run, "full_random/canonical/5") is None


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_a_one_object_policy_is_probed_with_the_object_counts_each_probe_can_play(tmp_path):
    """Trained with one object: its ladder and the probes that play one object (absent-object, paraphrase) stay in
    its condition; those that need a second object (the swaps, the switch, the removal) play two, as a study's do."""
    from vla_ladder.experiments.diagnose import DiagnoseConfig

    cfg = DiagnoseConfig(policy=("nearest",), out=tmp_path / "d", condition="medium_jitter/canonical/1",
                         references=())
    ((_, ladder, probes),) = cfg.plan()
    assert ladder.grid.num_objects == (1,) and ladder.grid.splits == ("canonical",)
    counts = {name: probe.grid.num_objects for name, probe in probes.items()}
    assert counts == {"instruction-swap": (2,), "position-swap": (2,), "absent-object": (1,),
                      "instruction-switch": (2,), "paraphrase": (1,), "appearance-swap": (2,),
                      "distractor-removal": (2,)}
    assert {probe.grid.regimes for probe in probes.values()} == {("medium_jitter",)}


def test_bad_input_is_refused_in_one_line_before_any_work(tmp_path, capsys):
    out = tmp_path / "d"
    cases = [(["--condition", "tiny/canonical/5"], "regime"),
             (["--references", "scripted", "oracle"], "allowed: scripted, nearest, layout-prior, random, committed)"),
             (["--references", "nearest", "nearest"], "distinct"),
             (["--episodes", "0"], "positive integer")]
    for extra, words in cases:
        assert main(["diagnose", "--policy", "layout-prior", "--out", str(out), *extra]) == 2
        assert words in _one_line(capsys)
    assert main(["diagnose", "--out", str(out)]) == 2 and "--policy SPEC is required" in _one_line(capsys)
    for argv, words in [(["--policy", "nearest", "nearest"], "--policy names a policy twice: nearest nearest"),
                        (["--policy", "nearest", "layout-prior", "--labels", "a"], "--labels must give 2 distinct"),
                        (["--policy", "nearest", "layout-prior", "--labels", "a", "a"], "got a a"),
                        (["--policy", "nearest", "layout-prior", "--labels", "a", "b/c"], "letters, digits"),
                        (["--policy", "nearest", "layout-prior", "--labels", "a", "references"], "distinct names"),
                        # one policy's directory is policy/: its label was accepted and ignored
                        (["--policy", "nearest", "--labels", "a"], "--labels names the directories of two or more")]:
        assert main(["diagnose", "--out", str(out), *argv]) == 2
        assert words in _one_line(capsys)
    assert main(["diagnose", "--policy", f"lerobot:{tmp_path}/missing", "--out", str(out)]) == 2
    _one_line(capsys)
    assert not out.exists()


@pytest.mark.slow
def test_a_policy_diagnosed_beside_itself_resembles_itself(tmp_path, capsys):
    """layout-prior is deterministic: played as the policy and as a reference on the same seeds, it answers every
    question exactly as its reference twin, so "resembles" names it on all five; the expert answers otherwise where
    the shortcut shows (it follows the moved object, it does not go to an empty place)."""
    out = tmp_path / "diag"
    argv = ["diagnose", "--policy", "layout-prior", "--out", str(out), "--references", "scripted", "layout-prior",
            *SMALL]
    assert main(argv) == 0
    data = json.loads((out / "diagnosis.json").read_text())
    rows = {q["id"]: q for q in data["questions"]}
    assert [q["id"] for q in data["questions"]] == [k for k, _, _ in QUESTIONS]
    for q in rows.values():
        assert q["policy"]["value"] == pytest.approx(q["references"]["layout-prior"]), q
        if q["id"] == "reworded":  # wording cannot move a state-reading reference
            assert q["references"] == {"scripted": 0.0, "layout-prior": 0.0}, q
        if len(set(q["references"].values())) == 1:  # no reference is nearer than another: none is named
            assert q["resembles"] is None, q
            continue
        assert "layout-prior" in q["resembles"].split(" / "), q
        lo, hi = q["policy"]["ci95"]
        assert lo <= q["policy"]["value"] <= hi
    assert rows["follows_object"]["references"]["scripted"] == 1.0 and rows["follows_object"]["policy"]["value"] == 0
    assert rows["empty_place"]["policy"]["value"] == 1.0 and rows["empty_place"]["references"]["scripted"] == 0
    assert rows["holds_up"]["policy"]["value"] < 0 and rows["holds_up"]["policy"]["to"] == "full_random/canonical/5"
    # The ladder's episodes against the named object's distance from its training place: the twin's curve is the
    # policy's, every ladder episode in one bin.
    disp = data["displacement"]
    assert disp["trained_in"] == "small_jitter/canonical/5" and set(disp["references"]) == {"scripted", "layout-prior"}
    assert disp["policies"]["layout-prior"] == disp["references"]["layout-prior"]
    ladder = load_run(out / "policy" / "ladder").episodes
    assert sum(b["n"] for b in disp["policies"]["layout-prior"]["bins"]) == len(ladder)
    printed = capsys.readouterr().out
    assert "Does it keep reading the instruction?" in printed and "resembles layout-prior" in printed
    assert "Where does it stop finding the object? success" in printed
    # The policy's filmed scenes, and no reference's.
    assert list((out / "policy" / "ladder" / "videos").glob("*.mp4"))
    assert not (out / "references" / "scripted" / "ladder" / "videos").exists()

    # The page: the diagnosis first, the ladder of all three, the policy's probe sections.
    with chromium_page(out / "report.html") as (page, failed):
        row = table_row(page, "this policy")
        text = page.inner_text("body")
    assert not failed
    assert row["question"] == "Does it hold up as the objects move?" and "layout-prior" in row["resembles"]
    assert text.index("Diagnosis") < text.index("Where it stops finding the object") < text.index("Grounding probes")
    for probe in ("instruction-swap: layout-prior", "position-swap: layout-prior", "absent-object: layout-prior",
                  "instruction-switch: layout-prior", "paraphrase: layout-prior", "appearance-swap: layout-prior",
                  "distractor-removal: layout-prior"):
        assert probe in text

    # The same command resumes (nothing is played again); another request is refused in one line.
    videos = sorted(out.glob("policy/**/*.mp4"))  # a replayed episode would write its video again
    before = [v.stat().st_mtime_ns for v in videos]
    assert main(argv) == 0
    assert [v.stat().st_mtime_ns for v in videos] == before and len(videos) >= 5
    assert json.loads((out / "diagnosis.json").read_text())["questions"] == data["questions"]
    capsys.readouterr()
    assert main([*argv[:-len(SMALL)], *SMALL[:-2], "--videos", "0", "--first-seed", "5"]) == 2
    assert "holds another diagnosis request" in _one_line(capsys)


@pytest.mark.slow
def test_two_policies_side_by_side_beside_one_set_of_references(tmp_path, capsys):
    """Two policies on the same scenes: each answers in its own column, in its own directory, and resembles its own
    reference twin (both are deterministic); the references play once."""
    out = tmp_path / "diag"
    argv = ["diagnose", "--policy", "layout-prior", "nearest", "--labels", "shortcut", "blind", "--out", str(out),
            "--references", "layout-prior", "nearest", "--episodes", "2", "--probe-episodes", "2", "--workers", "1",
            "--videos", "0"]
    assert main(argv) == 0
    data = json.loads((out / "diagnosis.json").read_text())
    assert data["policies"] == {"shortcut": "layout-prior", "blind": "nearest"}
    assert sorted(p.name for p in (out / "policies").iterdir()) == ["blind", "shortcut"]
    assert not (out / "policy").exists()
    for q in data["questions"]:
        assert set(q["answers"]) == {"shortcut", "blind"} and "policy" not in q
        for label, twin in (("shortcut", "layout-prior"), ("blind", "nearest")):
            assert q["answers"][label]["answer"]["value"] == pytest.approx(q["references"][twin]), q
            if len(set(q["references"].values())) > 1:  # else none is named (test above)
                assert twin in q["answers"][label]["resembles"].split(" / "), q
    follows = next(q for q in data["questions"] if q["id"] == "empty_place")["answers"]
    assert follows["shortcut"]["answer"]["value"] == 1.0 and follows["blind"]["answer"]["value"] == 0.0
    # Alone with its target, the nearest object is the target: the blind policy can only gain; the shortcut, in its
    # own small-jitter condition, neither gains nor loses.
    distracted = next(q for q in data["questions"] if q["id"] == "distracted")["answers"]
    assert distracted["shortcut"]["answer"]["value"] == 0.0 and distracted["blind"]["answer"]["value"] >= 0
    printed = capsys.readouterr().out
    assert "[shortcut] Does it read the instruction?" in printed and "[blind] Does it read" in printed
    with chromium_page(out / "report.html") as (page, failed):
        row = table_row(page, "shortcut [95% CI]")
        text = page.inner_text("body")
    assert not failed
    assert row["question"] == "Does it hold up as the objects move?" and "resembles layout-prior" in row[
        "shortcut [95% CI]"] and "blind [95% CI]" in row
    assert "instruction-swap: layout-prior" in text and "instruction-swap: nearest" in text


def test_an_answer_or_reference_without_plays_resembles_nothing_by_it():
    """A NaN answer (no plays, say a probe none of whose scenes was complete) named no reference as "" where the
    others say None; a NaN reference is left out of the comparison."""
    from vla_ladder.experiments.diagnose import _resembles

    nan = float("nan")
    assert _resembles({"value": nan}, {"nearest": 0.1, "layout-prior": 0.5}) is None
    assert _resembles({"value": 0.2}, {"nearest": nan, "layout-prior": 0.5, "scripted": 0.1}) == "scripted"


def test_every_difference_is_shown_in_signed_points():
    """by_colour is the change the swap makes (swapped minus as the scene is), like the other differences: its answer
    and the references' were shown unsigned ("10 [-5, 25]"), as if the swapped share it once was."""
    from vla_ladder.experiments.diagnose import QUESTIONS
    from vla_ladder.report.diagnosis import answer_lines, diagnosis_html

    differences = [key for key, _, measure in QUESTIONS if "minus" in measure]
    assert "by_colour" in differences
    for key in differences:
        q = {"id": key, "question": "Q?", "measure": "m", "references": {"scripted": 0.0, "nearest": 0.05},
             "answers": {"p": {"answer": {"value": 0.1, "ci95": [-0.05, 0.25]}, "resembles": None}}}
        data = {"questions": [q], "references": ["scripted", "nearest"]}
        assert answer_lines(data) == ["Q? +10 [-5, +25] (m); scripted +0, nearest +5"], key
        assert "+10 <span class=ci>[-5, +25]</span>" in diagnosis_html(data), key
