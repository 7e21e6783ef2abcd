"""`vla-ladder report RUN_DIR... --out report.html`: one self-contained HTML page of evaluation runs.

Everything is inlined (images and videos as data: URIs, no scripts, no fonts, no network), so the page
works opened from disk or mailed around. It holds: what each metric signature means, per-condition rates
with 95% Wilson intervals, the paper's tables and figures for whatever conditions the runs cover, the
confusion matrices, per-object rates, and for a sample of episodes of each outcome kind the rollout
video plus a frame strip every 300 ms (every 6th step at 20 Hz, as in the paper's appendix figures).
"""

from __future__ import annotations

import base64
import html
import itertools
import os
import tempfile
from collections import Counter
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated

import tyro

import numpy as np
import pandas as pd

from vla_ladder.conditions import JITTER_REGIMES, LADDER, REGIMES, Condition
from vla_ladder.contract import CONTROL_HZ, METRICS
from vla_ladder.evaluation.displacement import by_displacement
from vla_ladder.evaluation.metrics import OUTCOME_TEXT, OUTCOMES, outcomes
from vla_ladder.checks import check_output_file
from vla_ladder.evaluation.rundir import EPISODE_KEY, Run, load_runs
from vla_ladder.files import number, write_text
from vla_ladder.report import plots, tables
from vla_ladder.report.labels import short_labels
from vla_ladder.report import probes as probe_report
from vla_ladder.report.displacement import CAPTION as DISPLACEMENT_CAPTION
from vla_ladder.report.displacement import displacement_table

STRIP_EVERY = 6  # steps: 300 ms at 20 Hz
VIDEO_MAX_BYTES = 4_000_000  # larger videos are shown as frame strips only, to keep the page loadable

# (policy kind, the policies measured for it, success, grasp-any, reach, meaning). The measured figures come
# from data/reference_ladder.json (written by benchmarks/reference_ladder.py) and data/paper.json.
SIGNATURES = [
    ("Instruction-following expert (scripted, PPO)", ("scripted",), "high", "high", "high",
     "Reaches, grasps and holds the instructed object: the upper bound of the setting."),
    ("Nearest object (ignores the instruction)", ("nearest",), "≈ 1/#objects", "high", "≈ success",
     "Grasping works, object selection does not: grasp-any far above success, wrong-object grasps fill "
     "the confusion matrix's off-diagonal."),
    ("Layout prior (ignores perception)", ("layout-prior",),
     "high under small jitter, → 0 under full random / OOD pairings", "follows success", "follows success",
     "A location shortcut: it goes where the instructed object usually is. Success collapses as soon as "
     "objects leave their regions; on held-out pairings it grasps whatever sits in the target's usual "
     "region (wrong object) or nothing."),
    ("Random actions", ("random",), "≈ 0", "≈ 0", "≈ 0", "The floor: no motor skill at all."),
    ("Paper's VLA failure (e.g. SmolVLA, full random)", ("paper: SmolVLA",), "low", "above success", "low",
     "Confident reach-and-grasp motions to arbitrary places: the grasping primitive is learned, the "
     "binding of the motion to the instructed object is not."),
]


def reference_data(name: str) -> dict:
    """A data file shipped with the report: reference_ladder.json (measured) or paper.json (the paper's tables)."""
    import json
    from importlib import resources
    return json.loads(resources.files("vla_ladder.report").joinpath("data", name).read_text())


def _ladder_text(label: str, conditions: dict) -> str:
    """"label: success a, b, c, d; grasp-any ...; reach ..." along the ladder, in %."""
    parts = []
    for m, name in (("success", "success"), ("grasp_any", "grasp-any"), ("reach", "reach")):
        vals = [conditions.get(f"{r}/canonical/5", {}).get(m) for r in REGIMES]
        parts.append(name + " " + ", ".join("–" if v is None else f"{100 * v:.0f}" for v in vals))
    return f"{label}: " + "; ".join(parts)


def _measured(labels: tuple[str, ...]) -> str:
    ref, paper = reference_data("reference_ladder.json"), reference_data("paper.json")
    out = []
    for label in labels:
        if label.startswith("paper: "):
            model = label.removeprefix("paper: ")
            out.append(_ladder_text(f"paper, {model}", paper["ladder"][model]))
        elif label in ref["results"]:
            out.append(_ladder_text(label, ref["results"][label]))
    return " | ".join(out)


def _data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def png_tag(path: Path) -> str:
    """A PNG file as an <img> that carries its picture (the page is one file)."""
    return f'<img class="plot" alt="{html.escape(path.stem)}" src="{_data_uri(path.read_bytes(), "image/png")}">'


def _jpeg(frame: np.ndarray) -> bytes:
    import imageio.v3 as iio
    return iio.imwrite("<bytes>", frame, extension=".jpg", quality=85)


def _read_frames(path: Path) -> np.ndarray:
    import imageio.v3 as iio
    return iio.imread(path, index=None)


def object_set(run: Run) -> str:
    """The object set(s) the run's episodes were played with (episodes' object_set column): "standin", "ycb"."""
    return "+".join(sorted(map(str, run.episodes["object_set"].unique()))) or "none"


def run_labels(runs: list[Run], labels: list[str] | None = None) -> list[str]:
    """The label each run is shown under (default: its policy spec, a checkpoint's path cut short by short_labels:
    the whole path made tables and legends unreadable and named the machine's folders). Runs of one label that
    played different object sets are told apart by it, "nearest (ycb)" and "nearest (standin)": their rates are of
    different objects, not one model's. Runs of one label that cover different conditions keep it, and their
    results merge; a run that evaluated a condition already shown under its label gets one of its own: the label
    with its directory's name, then with its parent's too, then numbered."""
    labels = labels or short_labels([r.label for r in runs])
    sets: dict[str, set] = {}
    for r, label in zip(runs, labels):
        sets.setdefault(label, set()).add(object_set(r))
    labels = [f"{label} ({object_set(r)})" if len(sets[label]) > 1 else label for r, label in zip(runs, labels)]
    shown: dict[str, set] = {}
    out = []
    for r, label in zip(runs, labels):
        conds = set(r.summary.get("conditions", {}))
        tries = itertools.chain([label, f"{label} ({r.path.name})", f"{label} ({r.path.parent.name}/{r.path.name})"],
                                (f"{label} ({r.path.name} {k})" for k in itertools.count(2)))
        label = next(t for t in tries if not shown.get(t, set()) & conds)
        shown.setdefault(label, set()).update(conds)
        out.append(label)
    return out


def results_by_label(runs: list[Run], labels: list[str] | None = None) -> dict[str, dict]:
    """label (run_labels) -> the merged conditions of its runs."""
    out: dict[str, dict] = {}
    for r, label in zip(runs, run_labels(runs, labels)):
        out.setdefault(label, {}).update(r.summary.get("conditions", {}))
    return out


def _rate_cell(cond: dict, m: str) -> str:
    lo, hi = map(number, cond["ci95"][m])  # (null: an undefined rate, as summary.json holds it)
    return f"{100 * number(cond[m]):.0f}<span class=ci> [{100 * lo:.0f}, {100 * hi:.0f}]</span>"


def _conditions_table(results: dict[str, dict]) -> str:
    head = "".join(f"<th>{tables.METRIC_NAMES[m]}</th>" for m in METRICS)
    kinds = "".join(f"<th>{k.replace('_', ' ')}</th>" for k in OUTCOMES)
    rows = []
    for label, conds in results.items():
        for key, c in conds.items():
            out = c.get("outcomes", {})
            rows.append(f"<tr><td>{html.escape(label)}</td><td>{html.escape(key)}</td><td>{c['n']}</td>"
                        + "".join(f"<td>{_rate_cell(c, m)}</td>" for m in METRICS)
                        + "".join(f"<td>{out.get(k, '')}</td>" for k in OUTCOMES) + "</tr>")
    return (f"<table><tr><th>policy</th><th>condition</th><th>n</th>{head}{kinds}</tr>{''.join(rows)}</table>"
            "<p class=note>Rates in %, 95% Wilson intervals in brackets. Outcome columns count episodes by "
            "how they ended (see the section above).</p>")


def _per_object_table(results: dict[str, dict]) -> str:
    from vla_ladder.task.objects import OBJECTS
    head = "".join(f"<th>{html.escape(o.phrase)}</th>" for o in OBJECTS)
    rows = []
    for label, conds in results.items():
        for key, c in conds.items():
            po = c.get("per_object", {})
            cells = "".join(
                f"<td>{_rate_cell(po[o.name], 'success')} <span class=ci>n={po[o.name]['n']}</span></td>"
                if o.name in po else "<td>–</td>" for o in OBJECTS)
            rows.append(f"<tr><td>{html.escape(label)}</td><td>{html.escape(key)}</td>{cells}</tr>")
    return (f"<table><tr><th>policy</th><th>condition</th>{head}</tr>{''.join(rows)}</table>"
            "<p class=note>Success rate (%) by instructed object.</p>")


def _paper_tables(results: dict[str, dict]) -> list[tuple[str, tables.Table, dict]]:
    """The paper's tables that the results can fill, with the keyword arguments of their figure: the ladder (two
    regimes or more), the pairings (in the first regime, in ladder order, that has them: the paper's is small
    jitter) and the object count (in full random, as in the paper, else the first regime with two counts)."""
    out = []
    keys = {k for conds in results.values() for k in conds}
    regimes = {k.split("/")[0] for k in keys if k.endswith("/canonical/5")}
    if len(regimes) >= 2:
        out.append(("ladder", tables.ladder_table(results), {}))
    paired = [r for r in REGIMES if any(k.startswith(f"{r}/pairings_") for k in keys)]
    if paired:
        # With the paper's five objects where the runs have them, else with the most they have (docs/evaluation.md's
        # example pairs three).
        counts = {int(k.split("/")[2]) for k in keys if k.startswith(f"{paired[0]}/pairings_")}
        kwargs = {"regime": paired[0], "num_objects": 5 if 5 in counts else max(counts)}
        out.append(("pairings", tables.pairings_table(results, **kwargs), kwargs))
    counted = [r for r in REGIMES if len({k for k in keys if k.startswith(f"{r}/canonical/")}) >= 2]
    if counted:
        regime = "full_random" if "full_random" in counted else counted[0]
        out.append(("object_count", tables.object_count_table(results, regime), {"regime": regime}))
    return out


def _md_table_html(t: tables.Table) -> str:
    """The paper-layout table rendered as HTML (same cells as the Markdown version)."""
    head = (["Model"] if t.grouped else []) + [t.row_title] + [tables.METRIC_NAMES[m] for m in METRICS]
    rows = []
    for model, group in t.groups.items():
        for i, (label, cells) in enumerate(group):
            lead = ([model if i == 0 else ""] if t.grouped else []) + [label]
            rows.append("<tr>" + "".join(f"<td>{html.escape(x)}</td>" for x in lead + [cells[m].md() for m in METRICS])
                        + "</tr>")
    return (f"<p><b>{html.escape(t.caption)}</b></p><table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head)
            + "</tr>" + "".join(rows) + "</table>"
            + f"<details><summary>LaTeX</summary><pre>{html.escape(t.to_latex())}</pre></details>")


def _figures(results: dict[str, dict], runs: list[Run], tmp: Path, placements: bool) -> list[tuple[str, str]]:
    figs = []
    for name, table, kwargs in _paper_tables(results):
        path = tmp / f"{name}.png"
        {"ladder": plots.plot_ladder, "pairings": plots.plot_pairings,
         "object_count": plots.plot_object_count}[name](results, path, **kwargs)
        figs.append((table.caption, png_tag(path)))
    for label, conds in results.items():
        panels = {key: c for key, c in conds.items() if "confusion" in c}
        if not panels:  # summaries from before the confusion matrices: nothing to draw
            continue
        path = tmp / f"confusion_{len(figs)}.png"
        plots.plot_confusion(panels, path)
        figs.append((f"Confusion matrices of {label}: instructed object x object held at the final step",
                     png_tag(path)))
    if placements:
        fig = _placement_figure(runs, tmp)
        if fig:
            figs.append(fig)
    return figs


def _placement_figure(runs: list[Run], tmp: Path) -> tuple[str, str] | None:
    try:
        from vla_ladder.report.placements import plot_placements
    except ImportError:
        return None
    # The split and object count the runs played (the most episodes, if several), in the regimes played with them.
    played = pd.concat([run.episodes[["regime", "split", "num_objects"]] for run in runs], ignore_index=True)
    counts = Counter(zip(played["split"], played["num_objects"]))
    if not counts:
        return None
    (split, k), = (key for key, _ in counts.most_common(1))
    k = int(k)
    present = set(played.loc[(played["split"] == split) & (played["num_objects"] == k), "regime"])
    regimes = [r for r in REGIMES if r in present]
    path = tmp / "placements.png"
    plot_placements(regimes, 200, 0, path, split=split, num_objects=k)
    what = f"{split.replace('_', ' ')} split, {k} object{'s' * (k > 1)}"
    if len(counts) > 1:
        what += f": the most played of the runs' {len(counts)} splits and object counts"
    return (f"Initial object positions per regime ({what}; 200 sampled layouts each)", png_tag(path))


def _episode_card(run: Run, row, with_video: bool) -> str:
    path = run.video_path(row["video"])
    head = (f"<div class=cap><b>{html.escape(row['instruction'])}</b> — held: {html.escape(row['held'])}; "
            + ", ".join(f"{tables.METRIC_NAMES[m].lower()} {int(row[m])}" for m in METRICS)
            + f" (d={row['reach_dist']:.3f} m); {html.escape(row['regime'])}/{html.escape(row['split'])}/"
            f"{row['num_objects']} seed {row['seed']}</div>")
    if path is None:  # filmed, but the file is not with the run: say so rather than that nothing was filmed
        note = "no video recorded" if not row["video"] else f"video {html.escape(row['video'])} not found in the run"
        return f"<div class=episode>{head}<p class=note>{note}</p></div>"
    frames = _read_frames(path)
    strip = "".join(
        f"<figure><img class=frame alt='t={t * 1000 // CONTROL_HZ} ms' "
        f"src='{_data_uri(_jpeg(frames[t]), 'image/jpeg')}'><figcaption>t = {t * 1000 // CONTROL_HZ} ms"
        f"</figcaption></figure>" for t in range(0, len(frames), STRIP_EVERY))
    video = ""
    data = path.read_bytes()
    if with_video and len(data) <= VIDEO_MAX_BYTES:
        video = (f"<video class=rollout controls muted loop preload=auto "
                 f"src='{_data_uri(data, 'video/mp4')}'></video>")
    return f"<div class=episode>{head}{video}<div class=strip>{strip}</div></div>"


def _shown(path: str | Path, base: Path) -> str:
    """A path as the report shows it: relative to the report's folder `base` (a study's runs: to the study), so
    that the page names no folder of the machine that wrote it and still points at the runs when copied with them."""
    return os.path.relpath(path, base)


def _rollouts(runs: list[Run], labels: list[str], samples: int, with_video: bool, base: Path) -> str:
    parts = []
    for run, label in zip(runs, labels):
        df = run.episodes.copy()
        df["outcome"] = outcomes(df)
        filmed = df[df["video"].astype(str) != ""]
        counts = ", ".join(f"{k.replace('_', ' ')} {int((df['outcome'] == k).sum())}" for k in OUTCOMES)
        parts.append(f"<h3>{html.escape(label)} <span class=ci>{html.escape(_shown(run.path, base))}</span></h3>"
                     f"<p class=note>{len(df)} episodes: {counts}; {len(filmed)} filmed.</p>")
        if filmed.empty:
            parts.append("<p class=note>This run recorded no videos (evaluate with --videos N to see rollouts "
                         "here).</p>")
            continue
        for kind in OUTCOMES:
            sample = filmed[filmed["outcome"] == kind].head(samples)
            if sample.empty:
                continue
            parts.append(f"<h4>{kind.replace('_', ' ')} <span class=ci>({OUTCOME_TEXT[kind]})</span></h4>")
            parts += [_episode_card(run, row, with_video) for _, row in sample.iterrows()]
    return "".join(parts)


def _signatures() -> str:
    rows = "".join("<tr>" + "".join(f"<td>{html.escape(x)}</td>" for x in (kind, *cells, _measured(labels)))
                   + "</tr>" for kind, labels, *cells in SIGNATURES)
    ref = reference_data("reference_ladder.json")["experiment"]
    kinds = "".join(f"<li><b>{k.replace('_', ' ')}</b>: {html.escape(v)}</li>" for k, v in OUTCOME_TEXT.items())
    return (
        "<p><b>Success</b>: the instructed object is grasped at the final step. <b>Grasp-any</b>: some object "
        "was grasped at some step (the grasping primitive works). <b>Reach</b>: the gripper ends within 5 cm of "
        "the instructed object (the policy at least went to the right object).</p>"
        "<table><tr><th>policy kind</th><th>success</th><th>grasp-any</th><th>reach</th><th>what it means</th>"
        f"<th>measured along the ladder ({' → '.join(r.title.lower() for r in LADDER.values())}, %)</th>"
        f"</tr>{rows}</table><p class=note>Reference policies measured with {ref['episodes']} episodes per regime, "
        f"seeds {ref['first_seed']}-{ref['first_seed'] + ref['episodes'] - 1}, five objects (docs/diagnostics.md); "
        "the last row is the paper's Table 2.</p>"
        "<p>Reading a result: <i>grasp-any ≫ success</i> means the policy can grasp but picks the wrong object "
        "(look at the confusion matrix: which object instead?); <i>reach ≫ grasp-any</i> means it goes to the "
        "right object and fumbles the grasp; <i>success high under small jitter but not on OOD pairings</i> "
        "means it learned where objects usually are, not what they are. Two rates whose intervals overlap "
        "may still differ: use <code>vla-ladder compare RUN_A RUN_B</code> (paired test on the same seeds).</p>"
        f"<p>Each episode ends in one of these outcomes:</p><ul>{kinds}</ul>")


def _paired_plays(variants: list[Run], samples: int, with_video: bool) -> str:
    """The first `samples` scenes filmed in every variant of a probe, each shown once per variant, one above the
    other: the frame strips line up in time, so what the probe changed between the plays shows."""
    if len(variants) < 2 or samples == 0:  # nothing to set side by side, or no scene asked for
        return ""
    indexed = [r.episodes.set_index(list(EPISODE_KEY)) for r in variants]
    filmed = set.intersection(*(set(e.index[e["video"].astype(str) != ""]) for e in indexed))
    if not filmed:
        return ("<p class=note>No scene was filmed in every variant (run the probe with --videos N to see the same "
                "scenes played side by side here).</p>")
    scenes = sorted(filmed)[:samples]
    parts = [f"<h4>The same scenes in each variant <span class=ci>(first {len(scenes)} filmed)</span></h4>"]
    for key in scenes:
        parts.append(f"<p class=note><b>{html.escape('/'.join(map(str, key[:3])))}, scene {key[3]}</b></p>")
        for run, episodes in zip(variants, indexed):
            card = _episode_card(run, {**episodes.loc[key].to_dict(), **dict(zip(EPISODE_KEY, key))}, with_video)
            parts.append(card.replace("<div class=cap>", f"<div class=cap>{html.escape(run.path.name)}: ", 1))
    return "".join(parts)


def _probe_sections(runs: list[Run], tmp: Path, base: Path, samples: int = 2, with_video: bool = True) -> str:
    """A section per grounding probe whose variants are among the runs (`vla-ladder probe` writes its variants as
    run directories next to probe.json, so `vla-ladder report PROBE_DIR/*/` shows the probe); its folder is shown
    relative to the report's, `base`."""
    parts = []
    for i, path in enumerate(probe_report.probe_dirs([r.path for r in runs])):
        data = probe_report.load_probe(path)
        figures = [png_tag(p) for p in probe_report.plot_probe(data, tmp / f"probe_{i}.png")]
        variants = [r for r in runs if r.path.resolve().parent == path]
        # (the folder as the runs name it, not resolved: a resolved path names the machine's folders)
        where = _shown(os.path.dirname(os.path.abspath(variants[0].path)), base)
        parts.append(probe_report.section(data, figures, where) + _paired_plays(variants, samples, with_video))
    return "<h2>Grounding probes</h2>" + "".join(parts) if parts else ""


CSS = """
body{font-family:sans-serif;margin:1.5em auto;max-width:1200px;color:#222}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}
td,th{border:1px solid #ccc;padding:3px 7px;text-align:left}
th{background:#f2f2f2}.ci{color:#777;font-size:.85em}.note{color:#555;font-size:.9em}
img.plot{max-width:100%;display:block;margin:.5em 0}
.episode{border:1px solid #ddd;margin:.6em 0;padding:.4em}.cap{font-size:.9em;margin-bottom:.3em}
.strip{display:flex;flex-wrap:wrap;gap:4px}.strip figure{margin:0;text-align:center;font-size:.75em}
img.frame{height:96px;display:block}video.rollout{height:256px;display:block;margin-bottom:.3em}
pre{background:#f7f7f7;padding:.5em;overflow-x:auto}
"""


def build_report(runs: list[Run], out: str | Path, title: str = "vla-ladder evaluation report", samples: int = 2,
                 with_video: bool = True, placements: bool = True, labels: list[str] | None = None,
                 sections: list[tuple[str, str]] | None = None, probe_runs: list[Run] | None = None,
                 displacement: tuple[str, dict[str, dict]] | None = None) -> Path:
    """Write the HTML page for `runs` to `out` and return its path; `labels` name the runs' policies
    (default: their policy specs); `sections` ((title, HTML) pairs, e.g. a study's tables) come first;
    `probe_runs`, variants of grounding probes, appear in their probes' sections only (not in the tables,
    figures and rollouts of `runs`); `displacement`, (the condition the policies were trained in, label -> its
    run's evaluation.displacement.by_displacement), adds their success against the named object's distance from
    its place there (displacement_section)."""
    if labels is not None and len(labels) != len(runs):
        raise ValueError(f"got {len(labels)} labels for {len(runs)} runs")
    labels = run_labels(runs, labels)
    results = results_by_label(runs, labels)
    base = Path(out).parent
    prov = runs[0].summary.get("provenance", {})
    with tempfile.TemporaryDirectory() as tmp:
        figs = _figures(results, runs, Path(tmp), placements)
        body = [
            f"<h1>{html.escape(title)}</h1>",
            f"<p class=note>Generated {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC from "
            f"{len(runs)} run(s); versions: {html.escape(', '.join(f'{k} {v}' for k, v in prov.items()))}</p>",
            "<ul>" + "".join(f"<li>{html.escape(label)}: <code>{html.escape(_shown(r.path, base))}</code>, "
                             f"{len(r.episodes)} episodes, object set {html.escape(object_set(r))}</li>"
                             for r, label in zip(runs, labels)) + "</ul>",
            *[part for heading, fragment in sections or () for part in (f"<h2>{html.escape(heading)}</h2>", fragment)],
            "<h2>Reading the metrics</h2>", _signatures(),
            "<h2>Results per condition</h2>", _conditions_table(results),
        ]
        paper = _paper_tables(results)
        if paper:
            body.append("<h2>The paper's tables</h2>")
            body += [_md_table_html(t) for _, t, _ in paper]
        body.append("<h2>Figures</h2>")
        body += [f"<figure>{img}<figcaption class=note>{html.escape(cap)}</figcaption></figure>" for cap, img in figs]
        if displacement is not None:
            trained_in, curves = displacement
            body += ["<h2>Where it stops finding the object</h2>", displacement_section(curves, trained_in, Path(tmp))]
        body.append(_probe_sections([*runs, *(probe_runs or ())], Path(tmp), base, samples, with_video))
        body += ["<h2>Success by instructed object</h2>", _per_object_table(results),
                 "<h2>Rollouts</h2>", f"<p class=note>Up to {samples} recorded episodes of each outcome per run; "
                 f"frames every {STRIP_EVERY * 1000 // CONTROL_HZ} ms.</p>",
                 _rollouts(runs, labels, samples, with_video, base)]
    page = ("<!DOCTYPE html><html lang=en><head><meta charset=utf-8>"
            f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>{''.join(body)}</body></html>")
    return write_text(out, page)


def displacement_section(curves: dict[str, dict], trained_in: str, tmp: Path) -> str:
    """The table of each policy's success against the named object's distance from its place in `trained_in`
    (label -> evaluation.displacement.by_displacement) and the figure of its three metrics, drawn in `tmp`."""
    figure = png_tag(plots.plot_displacement(curves, tmp / "displacement.png"))
    return (f"{displacement_table(curves, trained_in)}<figure>{figure}"
            f"<figcaption class=note>{html.escape(DISPLACEMENT_CAPTION)}</figcaption></figure>")


def displacement_curves(runs: list[Run], trained_in: str) -> dict[str, dict]:
    """label (run_labels) -> evaluation.displacement.by_displacement of the episodes of its runs, pooled as the
    tables pool their conditions."""
    grouped: dict[str, list[Run]] = {}
    for r, label in zip(runs, run_labels(runs)):
        grouped.setdefault(label, []).append(r)
    curves = {}
    for label, group in grouped.items():
        try:
            curves[label] = by_displacement(pd.concat([r.episodes for r in group], ignore_index=True), trained_in)
        except ValueError as e:  # an absent-object variant: its named object is not on the table
            raise ValueError(f"{', '.join(str(r.path) for r in group)}: {e}; --trained-in reads ladder runs") from None
    return curves


@dataclass
class ReportConfig:
    """Write one self-contained HTML page of evaluation runs (`vla-ladder report RUN_DIR... --out report.html`)."""

    runs: Annotated[tuple[Path, ...], tyro.conf.Positional, tyro.conf.arg(metavar="RUN...",
                                                                           help_behavior_hint="(required)")]
    """run directories from `vla-ladder eval --out`, one or more"""
    out: Path
    """HTML file to write"""
    title: str = "vla-ladder evaluation report"
    """page title"""
    samples: int = 2
    """recorded episodes shown per outcome kind and run"""
    video: bool = True
    """embed rollout videos (--no-video: frame strips only, a smaller page)"""
    placements: bool = True
    """include the placement figure"""
    trained_in: str | None = None
    """the condition the runs' policies were trained in (regime/split/objects, a jitter regime): adds their success
    against the named object's distance from its place there, the curve between the ladder's rungs"""

    def __post_init__(self):
        if self.samples < 0:
            raise ValueError(f"--samples must be >= 0, got {self.samples}")
        if self.trained_in is not None:
            cond = Condition.parse(self.trained_in)
            if REGIMES[cond.regime] is None:
                raise ValueError(f"--trained-in {self.trained_in}: a policy trained in {cond.regime} has no usual "
                                 f"place to measure from; allowed: a jitter regime ({', '.join(JITTER_REGIMES)})")
            self.trained_in = cond.key
        if not self.runs:
            raise ValueError("give at least one run directory")
        if len({p.resolve() for p in map(Path, self.runs)}) != len(self.runs):  # it was shown twice
            raise ValueError(f"a run directory is given twice: {' '.join(map(str, self.runs))}")
        check_output_file(self.out, "--out")


def run(cfg: ReportConfig) -> int:
    runs = load_runs(cfg.runs)
    displacement = None if cfg.trained_in is None else (cfg.trained_in, displacement_curves(runs, cfg.trained_in))
    out = build_report(runs, cfg.out, cfg.title, cfg.samples, cfg.video, cfg.placements, displacement=displacement)
    print(out.resolve())
    return 0
