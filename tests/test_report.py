"""Tables, plots, experiment configs and the self-contained HTML report (opened in headless Chromium)."""

import json
import shutil

import numpy as np
import pandas as pd
import pytest
from report_fixtures import chromium_page, make_run

from vla_ladder.cli import main
from vla_ladder.evaluation.metrics import OUTCOMES
from vla_ladder.evaluation.rundir import load_run
from vla_ladder.report import plots, tables
from vla_ladder.experiments.experiment import ExperimentConfig, PolicyEntry, available, plan
from vla_ladder.report.html import build_report

LADDER = [(r, "canonical", 5) for r in ("small_jitter", "medium_jitter", "large_jitter", "full_random")]
PAIRINGS = [("small_jitter", "pairings_id", 5), ("small_jitter", "pairings_ood", 5)]
COUNTS = [("full_random", "canonical", k) for k in (1, 2, 3, 4, 5)]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    a = make_run(root / "nearest", "nearest", LADDER + PAIRINGS, ["success", "wrong_object", "wrong_object",
                                                                    "wrong_object", "grasp_lost"], videos=5)
    # full_random with five objects is in both lists: a run holds each condition once.
    b = make_run(root / "prior", "layout-prior", LADDER + [c for c in COUNTS if c not in LADDER], list(OUTCOMES) * 2)
    return [load_run(a), load_run(b)]


def _results(runs):
    return {r.label: r.summary["conditions"] for r in runs}


def test_tables_follow_the_paper_layouts(runs):
    res = _results(runs)
    ladder = tables.ladder_table(res)
    md, tex = ladder.to_markdown(), ladder.to_latex()
    assert "| Model | Regime | Success | Grasp-any | Reach |" in md
    assert "| nearest | Small jitter | 20 [4, 62] | 100 [57, 100] | 20 [4, 62] |" in md
    assert "\\multirow{4}{*}{nearest} & Small jitter & $20$ & $100$ & $20$ \\\\" in tex
    assert "\\label{tab:ladder}" in tex and tex.count("\\midrule") == 2  # header rule + one between models

    # Of two policies only one played the pairings: its rows still name it (the Model column was dropped).
    pair = tables.pairings_table(res)
    assert "| Model | Split | Success | Grasp-any | Reach |" in pair.to_markdown()
    assert "\\multirow{2}{*}{nearest} & Pairings (ID) & " in pair.to_latex()
    alone = tables.pairings_table({"nearest": res["nearest"]})
    assert alone.to_markdown().splitlines()[2] == "| Split | Success | Grasp-any | Reach |"
    assert "Pairings (OOD) & $20$ & $100$ & $20$" in alone.to_latex()

    count = tables.object_count_table(res)
    assert [row for row, _ in count.groups["layout-prior"]] == ["1", "2", "3", "4", "5"]
    assert "\\# Objects" in count.to_latex()

    conds = res["layout-prior"]
    scaling = tables.data_scaling_table([{"model": "SmolVLA", "regime": "medium_jitter", "sizes": ("0.5k", "1k"),
                                          "before": res["nearest"], "after": conds}])
    assert "Med. jitter & $20\\!\\rightarrow\\!20$ & $100\\!\\rightarrow\\!60$" in scaling.to_latex()
    assert "0.5k → 1k" in scaling.to_markdown()
    # Labels such as lerobot:~/ckpt or a^2 stay LaTeX (~ and ^ were written raw: a space and a superscript).
    assert tables.tex_escape("lerobot:~/ckpt_a^2") == "lerobot:\\textasciitilde{}/ckpt\\_a\\textasciicircum{}2"


def test_the_reports_paper_tables_follow_the_regimes_played(tmp_path):
    """Pairings evaluated under large jitter fill the pairings table from large jitter (it was fixed to small
    jitter and came out empty), and the object count falls back to the regime whose counts were played."""
    from vla_ladder.report.html import _paper_tables

    conds = [("large_jitter", "pairings_id", 5), ("large_jitter", "pairings_ood", 5)] + \
        [("medium_jitter", "canonical", k) for k in (1, 3)]
    run = load_run(make_run(tmp_path / "r", "nearest", conds, ["success", "nothing"]))
    found = {name: (table, kwargs) for name, table, kwargs in _paper_tables({run.label: run.summary["conditions"]})}
    assert set(found) == {"pairings", "object_count"}
    assert found["pairings"][1] == {"regime": "large_jitter", "num_objects": 5}
    assert len(found["pairings"][0].groups["nearest"]) == 2 and "(large jitter)" in found["pairings"][0].caption
    assert found["object_count"][1] == {"regime": "medium_jitter"}
    assert [row for row, _ in found["object_count"][0].groups["nearest"]] == ["1", "3"]
    # Pairings played with three objects (docs/evaluation.md's example) fill the table too (it came out empty).
    three = load_run(make_run(tmp_path / "r3", "nearest", [("small_jitter", "pairings_id", 3),
                                                            ("small_jitter", "pairings_ood", 3)], ["success"]))
    (_, table, kwargs), = _paper_tables({three.label: three.summary["conditions"]})
    assert kwargs == {"regime": "small_jitter", "num_objects": 3} and len(table.groups["nearest"]) == 2
    assert "(3 objects)" in table.caption


def test_runs_of_one_policy_keep_their_own_rows_and_curves(tmp_path):
    """Runs of one policy spec merge when they cover different conditions and keep rows of their own when they
    played the same one: three (diagnose's DIR/policy/ladder) were shown as two, the third's numbers replacing the
    second's; and `--trained-in` pools the episodes of a label's runs (it kept the last run's only)."""
    from vla_ladder.report.html import displacement_curves, results_by_label, run_labels

    cond = [("small_jitter", "canonical", 2)]
    same = [load_run(make_run(tmp_path / d / "ladder", "nearest", cond, kinds))
            for d, kinds in (("a", ["success"] * 2), ("b", ["nothing"] * 2), ("c", ["success", "nothing"]))]
    other = load_run(make_run(tmp_path / "d" / "ladder", "nearest", [("medium_jitter", "canonical", 2)],
                              ["success"] * 3))
    runs = [*same, other]
    labels = run_labels(runs)
    assert labels == ["nearest", "nearest (ladder)", "nearest (c/ladder)", "nearest"]
    results = results_by_label(runs)
    assert [results[label]["small_jitter/canonical/2"]["success"] for label in labels[:3]] == [1.0, 0.0, 0.5]
    assert set(results["nearest"]) == {"small_jitter/canonical/2", "medium_jitter/canonical/2"}
    curves = displacement_curves(runs, "small_jitter/canonical/2")
    assert list(curves) == labels[:3] and [curves[label]["n"] for label in labels[:3]] == [5, 2, 2]


def test_runs_of_one_policy_on_other_object_sets_are_kept_apart(tmp_path):
    """A policy's runs with the stand-in objects and with YCB's are two experiments: each keeps its rows under a
    label naming its object set (they were merged into one model's), and the run list says each run's set."""
    from vla_ladder.report.html import results_by_label, run_labels

    paths = [make_run(tmp_path / d, "nearest", [(regime, "canonical", 2)], kinds)
             for d, regime, kinds in (("standin", "small_jitter", ["success"]), ("ycb", "medium_jitter", ["nothing"]))]
    episodes = pd.read_parquet(paths[1] / "episodes.parquet")
    episodes.assign(object_set="ycb").to_parquet(paths[1] / "episodes.parquet", index=False)
    runs = [load_run(p) for p in paths]
    assert run_labels(runs) == ["nearest (standin)", "nearest (ycb)"]
    assert {label: list(conds) for label, conds in results_by_label(runs).items()} == {
        "nearest (standin)": ["small_jitter/canonical/2"], "nearest (ycb)": ["medium_jitter/canonical/2"]}
    page = build_report(runs, tmp_path / "r.html", placements=False).read_text()
    assert "1 episodes, object set standin</li>" in page and "1 episodes, object set ycb</li>" in page
    # One object set: the label is the policy's alone, as before.
    assert run_labels([runs[0], load_run(make_run(tmp_path / "more", "nearest", [("large_jitter", "canonical", 2)],
                                                  ["success"]))]) == ["nearest", "nearest"]


def test_the_report_names_no_folder_of_the_machine_that_wrote_it(runs, tmp_path):
    """Run directories are shown relative to the report's folder (they were shown as given: absolute paths of the
    machine that made the page), in the run list and over each run's rollouts."""
    out = build_report(runs, tmp_path / "pages" / "report.html", samples=1, with_video=False, placements=False)
    page = out.read_text()
    shown = [f"../../{r.path.parent.name}/{r.path.name}" for r in runs]
    assert str(runs[0].path.parent) not in page and str(tmp_path) not in page
    for r, path in zip(runs, shown):
        assert (out.parent / path).resolve() == r.path.resolve()
        assert f"<code>{path}</code>" in page and f"<span class=ci>{path}</span></h3>" in page
    # A study writes STUDY/report.html over STUDY/eval/RUN: its runs are named as the study names them.
    study = tmp_path / "study"
    shutil.copytree(runs[0].path, study / "eval" / "run")
    page = build_report([load_run(study / "eval" / "run")], study / "report.html", samples=0,
                        placements=False).read_text()
    assert "<code>eval/run</code>" in page and "<span class=ci>eval/run</span></h3>" in page
    assert str(tmp_path) not in page


@pytest.mark.slow
def test_a_checkpoints_runs_are_labelled_by_its_training_run_and_step(tmp_path_factory, tmp_path):
    """A lerobot: run was labelled with its whole spec, an absolute path into the machine's folders, in every table,
    legend and heading; it is labelled by its training run's folder and step, with more folders where two
    experiments' runs share a name, and keeps its options. Labels given to the report win."""
    import lerobot_helpers as H
    from vla_ladder.report.html import run_labels

    trained = H.trained(tmp_path_factory, "act")  # a real `vla-ladder train` run: checkpoints/000002, last -> it
    for exp in ("expA", "expB"):
        shutil.copytree(trained, tmp_path / exp / "act", symlinks=True)
    specs = [f"lerobot:{tmp_path}/expA/act/checkpoints/last/pretrained_model",
             f"lerobot:{tmp_path}/expB/act/checkpoints/last/pretrained_model",
             f"lerobot:{tmp_path}/expB/act/checkpoints/last/pretrained_model?n_action_steps=2",
             f"lerobot:{tmp_path}/gone/act/checkpoints/last/pretrained_model"]
    cond = [("small_jitter", "canonical", 2)]
    runs = [load_run(make_run(tmp_path / f"eval{i}", spec, cond, ["success"])) for i, spec in enumerate(specs)]
    assert run_labels(runs) == ["lerobot:expA/act@step2", "lerobot:expB/act@step2",
                                "lerobot:expB/act@step2?n_action_steps=2", "lerobot:gone/act@last"]
    assert run_labels(runs[1:3]) == ["lerobot:act@step2", "lerobot:act@step2?n_action_steps=2"]
    # A training run's folder names its model too, and a ppo: checkpoint is cut to its file.
    trained_run = load_run(make_run(tmp_path / "evalrun", f"lerobot:{tmp_path}/expA/act", cond, ["success"]))
    ppo = load_run(make_run(tmp_path / "evalppo", f"ppo:{tmp_path}/ppo/final.pt", cond, ["success"]))
    assert run_labels([trained_run, ppo]) == ["lerobot:act@step2", "ppo:final.pt"]
    page = build_report(runs, tmp_path / "pages" / "r.html", samples=0, placements=False).read_text()
    assert str(tmp_path) not in page and "lerobot:expA/act@step2" in page
    page = build_report(runs, tmp_path / "pages" / "r.html", samples=0, placements=False,
                        labels=["a", "b", "c", "d"]).read_text()
    assert "<li>a: <code>../eval0</code>" in page and "act@step2" not in page


@pytest.mark.slow
def test_a_probe_of_a_checkpoint_is_titled_and_labelled_by_its_training_run(tmp_path_factory, tmp_path):
    """A probe's report labelled its variants `SPEC [variant]` with the checkpoint's whole spec, an absolute path into
    the machine's folders, in its title, tables and legends: it uses the report's short label of the spec."""
    import lerobot_helpers as H
    from vla_ladder.experiments.probes import ProbeConfig, ProbeGrid, run_probe

    trained = H.trained(tmp_path_factory, "act")
    spec = f"lerobot:{trained}/checkpoints/last/pretrained_model"
    run_probe(ProbeConfig("position-swap", policy=spec, out=tmp_path / "probe", grid=ProbeGrid(("small_jitter",)),
                          episodes=1, workers=1), progress=False)
    page = (tmp_path / "probe" / "report.html").read_text()
    assert str(trained) not in page, "the report names the checkpoint's folder"
    assert f"lerobot:{trained.name}@step2 [original]" in page and f"lerobot:{trained.name}@step2 [swapped]" in page


def test_no_committed_report_names_a_folder_of_the_machine_that_wrote_it():
    """The committed studies' pages named their runs by the /tmp folders they were evaluated in (written before
    build_report named them relative to the page); they name the run directories committed beside them. Inlined
    pictures and videos (data: URIs) are left out of the search: base64 may spell anything."""
    import re
    from pathlib import Path

    data_uri = re.compile(r"data:[\w/+.-]+;base64,[A-Za-z0-9+/=]+")
    absolute = re.compile(r"(?<![\w.~/-])/(?:[\w.+-]+/)+[\w.+-]*")  # /a/b, also in lerobot:/a/b; not eval/a, ../a
    results = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
    pages = sorted(results.rglob("*.html"))
    assert len(pages) >= 5
    found = {str(p.relative_to(results)): sorted(set(absolute.findall(data_uri.sub("", p.read_text()))))
             for p in pages}
    assert {page: paths for page, paths in found.items() if paths} == {}
    for page in pages:  # what they name instead is there
        for run in re.findall(r"<code>(eval/[^<]+)</code>", page.read_text()):
            assert (page.parent / run / "episodes.parquet").is_file(), (page, run)


def test_the_placement_figure_draws_the_split_and_object_count_played(tmp_path, monkeypatch):
    """The figure was always of the canonical split with five objects whatever the runs played; it draws the most
    played split and count, in the regimes played with them, and its caption says which."""
    from vla_ladder.report import placements
    from vla_ladder.report.html import _placement_figure

    drawn = []
    real = placements.plot_placements
    monkeypatch.setattr(placements, "plot_placements", lambda *a, **kw: drawn.append((a, kw)) or real(*a, **kw))
    three = [(r, "pairings_ood", 3) for r in ("small_jitter", "large_jitter")]
    run = load_run(make_run(tmp_path / "a", "nearest", three + [("full_random", "canonical", 5)], ["success"] * 2))
    caption, img = _placement_figure([run], tmp_path)
    assert drawn[-1][0][0] == ["small_jitter", "large_jitter"]
    assert drawn[-1][1] == {"split": "pairings_ood", "num_objects": 3} and "<img" in img
    assert caption == ("Initial object positions per regime (pairings ood split, 3 objects: the most played of the "
                       "runs' 2 splits and object counts; 200 sampled layouts each)")
    one = load_run(make_run(tmp_path / "b", "nearest", [("medium_jitter", "canonical", 1)], ["success"]))
    caption, _ = _placement_figure([one], tmp_path)
    assert drawn[-1][0][0] == ["medium_jitter"] and drawn[-1][1] == {"split": "canonical", "num_objects": 1}
    assert caption == "Initial object positions per regime (canonical split, 1 object; 200 sampled layouts each)"


def test_data_scaling_keeps_each_dataset_size_in_results_json(tmp_path):
    """Data scaling evaluates one model per dataset size on the same conditions: results.json keeps both sizes
    (it once kept the larger only, the two sharing the model's label), as table.md does."""
    from vla_ladder.experiments.experiment import build_outputs

    cond = [("medium_jitter", "canonical", 5)]
    small = load_run(make_run(tmp_path / "runs" / "small", "nearest", cond, ["success"] + ["wrong_object"] * 3))
    large = load_run(make_run(tmp_path / "runs" / "large", "nearest", cond, ["success"] * 3 + ["wrong_object"]))
    cfg = ExperimentConfig.load("data_scaling")
    entries = [PolicyEntry("nearest", "SmolVLA", "medium_jitter", size) for size in cfg.sizes["medium_jitter"]]
    summary = build_outputs(cfg, list(zip(entries, [small, large])), tmp_path)
    results = json.loads((tmp_path / "results.json").read_text())["results"]
    assert results == summary["results"]
    assert {k: v["medium_jitter/canonical/5"]["success"] for k, v in results.items()} == \
        {f"SmolVLA@{cfg.sizes['medium_jitter'][0]}": 0.25, f"SmolVLA@{cfg.sizes['medium_jitter'][1]}": 0.75}
    assert "25 [5, 70] → 75 [30, 95]" in (tmp_path / "table.md").read_text()


def test_plots_write_pngs(runs, tmp_path):
    res = _results(runs)
    paths = [plots.plot_ladder(res, tmp_path / "ladder.png"), plots.plot_pairings(res, tmp_path / "pair.png"),
             plots.plot_object_count(res, tmp_path / "count.png"),
             plots.plot_confusion(res["nearest"], tmp_path / "cm.png"),
             plots.plot_data_scaling([{"model": "m", "regime": "full_random", "sizes": ("10k", "100k"),
                                       "before": res["nearest"], "after": res["layout-prior"]}], tmp_path / "ds.png")]
    from vla_ladder.report.study import plot_curves
    ci = {m: [0.1, 0.6] for m in ("success", "grasp_any", "reach")}
    points = [{"step": s, "success": 0.2, "grasp_any": 0.3, "reach": 0.4, "ci95": ci} for s in (200_000, 400_000)]
    paths.append(plot_curves({"a": points, "b": points}, tmp_path / "curves.png", xlabel="env steps"))
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000
    # Summaries without confusion matrices: refused in one line (a ZeroDivisionError), and the report skips them.
    with pytest.raises(ValueError, match="no condition with a confusion matrix"):
        plots.plot_confusion({}, tmp_path / "none.png")
    from vla_ladder.report.html import _figures
    bare = {label: {k: {x: v for x, v in c.items() if x != "confusion"} for k, c in conds.items()}
            for label, conds in res.items()}
    captions = [caption for caption, _ in _figures(bare, runs, tmp_path, placements=False)]
    assert captions and not any("Confusion" in c for c in captions)


def test_study_probe_table_names_the_model_and_explains_its_probes():
    """A study keys each probe by its directory, "<model>-<probe>"; the table's model column is the model alone,
    and the page explains the probes it shows, not others."""
    from vla_ladder.report.study import probe_rows, probes_html
    m = {"value": 0.55, "ci95": [0.34, 0.74], "n": 20}
    probes = {"SmolVLA-scratch-sj-position-swap": {"probe": "position-swap",
                                                   "conditions": {"small_jitter/canonical/5": {"follows_object": m,
                                                                                               "no_swap": 0}}},
              "SmolVLA-scratch-sj-absent-object": {"probe": "absent-object",
                                                   "conditions": {"small_jitter/canonical/4": {"grasp_absent": m}}}}
    rows = probe_rows(probes)
    assert rows == [["SmolVLA-scratch-sj", "position-swap", "small_jitter/canonical/5", "follows object",
                     "55 [34, 74]", "20"],
                    ["SmolVLA-scratch-sj", "absent-object", "small_jitter/canonical/4", "grasp absent",
                     "55 [34, 74]", "20"]]
    page = probes_html(probes)
    assert "<b>position-swap</b>" in page and "<b>absent-object</b>" in page
    assert "<b>instruction-swap</b>" not in page


def test_study_probe_table_shows_the_nmi_as_a_share_with_its_p_and_every_wording():
    """The NMI was printed x100 under "Rates in %" without its permutation p, and the paraphrase probe, whose
    conditions hold one entry per wording, had no row at all."""
    from vla_ladder.report.study import PROBE_TABLE_NOTE, probe_rows, probes_markdown
    nmi = {"value": 0.05, "ci95": [0.0, 0.21], "n": 60, "plug_in": 0.11, "null_mean": 0.09, "permutation_p": 0.31}
    wording = {"n": 20, "success": 0.4, "grasp_any": 0.9, "reach": 1.0,
               "ci95": {"success": [0.22, 0.61], "grasp_any": [0.7, 0.97], "reach": [0.84, 1.0]}}
    change = {"value": -0.2, "ci95": [-0.41, 0.03], "n": 20, "mcnemar_p": 0.125}
    probes = {"m-instruction-swap": {"probe": "instruction-swap", "conditions": {"c": {"nmi": nmi}}},
              "m-paraphrase": {"probe": "paraphrase", "conditions": {"c": {
                  "canonical": {**wording, "success": 0.6, "ci95": {**wording["ci95"], "success": [0.39, 0.78]}},
                  "paraphrase-heldout": {**wording, "vs_canonical": {"success": change}}}}}}
    assert [r[3:] for r in probe_rows(probes)] == [
        ["nmi", "0.05 [0.00, 0.21] (p=0.31)", "60"],
        ["success, canonical", "60 [39, 78]", "20"],
        ["success, paraphrase-heldout", "40 [22, 61]", "20"],
        ["Δ success vs canonical, paraphrase-heldout", "-20 [-41, 3], p=0.12", "20"]]
    assert probes_markdown(probes).rstrip().endswith(PROBE_TABLE_NOTE)


def test_experiment_configs_and_policy_entries():
    assert set(available()) >= {"ladder", "pairings", "data_scaling", "object_count"}
    assert [c.regime for c in ExperimentConfig.load("ladder").conditions] == \
        ["small_jitter", "medium_jitter", "large_jitter", "full_random"]
    assert [c.num_objects for c in ExperimentConfig.load("object_count").conditions] == [1, 2, 3, 4, 5]
    e = PolicyEntry.parse("label=SmolVLA,regime=medium_jitter,size=0.5k,spec=lerobot:/tmp/ckpt")
    assert (e.label, e.regime, e.size, e.spec) == ("SmolVLA", "medium_jitter", "0.5k", "lerobot:/tmp/ckpt")
    ds = ExperimentConfig.load("data_scaling")
    assert [c.regime for c in plan(ds, [e])[0][1]] == ["medium_jitter"]
    with pytest.raises(ValueError, match="size="):
        plan(ds, [PolicyEntry.parse("label=a,regime=medium_jitter,size=5k,spec=nearest")])
    with pytest.raises(ValueError, match="unknown policy"):
        PolicyEntry.parse("teleport")
    with pytest.raises(ValueError, match="unknown experiment.*ladder"):
        ExperimentConfig.load("ladderr")
    with pytest.raises(ValueError, match="data_scaling only"):
        plan(ExperimentConfig.load("ladder"), [e])


@pytest.mark.slow
def test_report_is_self_contained_and_renders_in_chromium(runs, tmp_path):
    out = build_report(runs, tmp_path / "report.html", samples=1)
    page_html = out.read_text()
    assert "http://" not in page_html and "https://" not in page_html and "<script" not in page_html
    # Move it away from the run dirs: nothing may be loaded from disk either.
    moved = shutil.copy(out, tmp_path / "elsewhere.html")
    with chromium_page(moved) as (page, failed):
        images = page.evaluate("[...document.images].map(i => [i.alt, i.naturalWidth])")
        # Videos: wait until every one has decoded its first frame (or failed).
        page.wait_for_function("[...document.querySelectorAll('video')].every(v => v.readyState >= 2 || v.error)",
                               timeout=30000)
        videos = page.evaluate("[...document.querySelectorAll('video')].map(v => [v.readyState, !!v.error, "
                               "v.videoWidth])")
        text = page.inner_text("body")
        shot = page.screenshot(full_page=False)
    assert not failed
    plots_ = [i for i in images if not i[0].startswith("t=")]
    frames = [i for i in images if i[0].startswith("t=")]
    assert len(plots_) >= 5 and all(w > 100 for _, w in plots_), plots_  # ladder, pairings, counts, 2 confusions
    assert len(frames) >= 9 and all(w > 0 for _, w in frames)
    assert ["t=0 ms", "t=300 ms"] == [a for a, _ in frames[:2]]
    assert videos and all(state >= 2 and not err and w > 0 for state, err, w in videos), videos
    for needle in ("Reading the metrics", "Performance along the spatial task ladder", "wrong object",
                   "Pairings (OOD)"):
        assert needle in text
    import imageio.v3 as iio
    pixels = iio.imread(shot)
    assert pixels.std() > 20 and len(np.unique(pixels.reshape(-1, pixels.shape[-1]), axis=0)) > 50


def test_report_command_and_bad_input(runs, tmp_path, capsys):
    out = tmp_path / "r.html"
    assert main(["report", str(runs[1].path), "--out", str(out), "--no-placements"]) == 0
    assert "no video" in out.read_text().lower() or "recorded no videos" in out.read_text()
    assert main(["report", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert "not a run directory" in capsys.readouterr().err
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "episodes.parquet").write_bytes(b"")
    assert main(["report", str(bad), "--out", str(out)]) == 2
    assert "missing summary.json" in capsys.readouterr().err
    json.loads((runs[0].path / "summary.json").read_text())
    # A run copied without its videos: its filmed episodes say which file is missing, not that none was filmed.
    copy = tmp_path / "copied"
    shutil.copytree(runs[0].path, copy, ignore=shutil.ignore_patterns("videos"))
    assert main(["report", str(copy), "--out", str(out), "--no-placements"]) == 0
    page = out.read_text()
    missing = runs[0].episodes["video"].loc[lambda v: v != ""].iloc[0]
    assert f"video {missing} not found in the run" in page and "no video recorded" not in page


def test_report_trained_in_adds_success_against_the_named_objects_distance(runs, tmp_path, capsys):
    """`--trained-in COND`: the runs' success per distance bin from the named object's place in COND's layouts,
    its odds ratio per 10 cm, and the figure; refused in one line for a condition without usual places."""
    out = tmp_path / "d.html"
    assert main(["report", str(runs[0].path), str(runs[1].path), "--out", str(out), "--no-placements",
                 "--no-video", "--trained-in", "small_jitter/canonical/5"]) == 0
    with chromium_page(out) as (page, failed):
        images = dict(page.evaluate("[...document.images].map(i => [i.alt, i.naturalWidth])"))
        text = page.inner_text("body")
    assert not failed and images["displacement"] > 100
    assert "Where it stops finding the object" in text and "odds ratio / 10 cm" in text
    assert "small_jitter/canonical/5's regions" in text and "0–2 cm" in text
    capsys.readouterr()
    for bad, words in (("full_random/canonical/5", "has no usual place to measure from; allowed: a jitter regime"),
                       ("nowhere/canonical/5", "nowhere")):
        assert main(["report", str(runs[0].path), "--out", str(tmp_path / "x.html"), "--trained-in", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "x.html").exists()
    # An absent-object variant names an object that is not on the table: nothing to measure from, said in one line.
    absent = tmp_path / "absent"
    shutil.copytree(runs[0].path, absent)
    episodes = pd.read_parquet(absent / "episodes.parquet")
    episodes["layout"] = [json.dumps({**json.loads(lay), "absent_target": True}) for lay in episodes["layout"]]
    episodes.to_parquet(absent / "episodes.parquet")
    assert main(["report", str(absent), "--out", str(tmp_path / "x.html"), "--trained-in",
                 "small_jitter/canonical/5"]) == 2
    assert f"{absent}: episodes that name an object not on the table" in capsys.readouterr().err
