"""A finished study's results: summary.json (every cell), the tables, the learning curves and report.html."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from vla_ladder import files
from vla_ladder.checks import ascii_digits
from vla_ladder.contract import METRICS
from vla_ladder.evaluation.displacement import by_displacement
from vla_ladder.evaluation.rundir import load_run
from vla_ladder.experiments.probes import rescore_probe

REPORT_MAX_BYTES = 5_000_000


def cells_of(run_dir: Path, policy: str, train=None) -> list[dict]:
    """One cell per condition of an evaluation run: n, counts, rates and 95% Wilson intervals."""
    summary = json.loads((run_dir / "summary.json").read_text())
    out = []
    for key, c in summary["conditions"].items():
        cell = {"policy": policy, "train_dataset": train and train[0], "train_condition": train and train[1],
                "eval_condition": key, "n": c["n"], **{f"{m}_count": round(c[m] * c["n"]) for m in METRICS},
                **{m: c[m] for m in METRICS}, "ci95": c["ci95"], "run": str(run_dir)}
        out.append(cell)
    return out


def curve_points(study, chosen: dict) -> dict[str, list[dict]]:
    ev = study.cfg.evaluation
    curves = {}
    if not ev.curve_episodes:
        return curves
    for p, d, _ in study.models():
        model = chosen[(p.name, d.name)]["model"]
        points = []
        for run_dir in sorted((study.root / "curves").glob(f"{model}-*")):
            head, _, step = run_dir.name.rpartition("-")
            if head != model or not ascii_digits(step):  # another model's, whose name starts with this one's and '-'
                continue
            step = int(step)
            c = next(iter(json.loads((run_dir / "summary.json").read_text())["conditions"].values()))
            points.append({"step": step, "n": c["n"], **{m: c[m] for m in METRICS}, "ci95": c["ci95"]})
        curves[f"{p.name} on {d.name}"] = sorted(points, key=lambda x: x["step"])
    return curves


def displacement_curves(runs: dict[str, tuple]) -> dict[str, dict]:
    """dataset name -> {"trained_in", "runs": label -> evaluation.displacement.by_displacement}: the models trained
    on each dataset recorded where objects have usual places (not full random), and every reference run that
    played the same episodes, against the named object's distance from its place in that dataset's condition.
    `runs`: label -> (Run, the dataset's (name, condition key) or None for a reference)."""
    out = {}
    for name, cond in dict.fromkeys(train for _, train in runs.values() if train is not None):
        mine = {label: run for label, (run, train) in runs.items() if train == (name, cond)}
        played = {run.played for run in mine.values()}
        with_refs = {**mine, **{label: run for label, (run, train) in runs.items()
                                if train is None and run.played in played}}
        curves = {label: by_displacement(run.episodes, cond) for label, run in with_refs.items()}
        if all(c is not None for c in curves.values()):
            out[name] = {"trained_in": cond, "runs": curves}
    return out


def replicate_groups(policies: list[dict]) -> dict[str, list[str]]:
    """Training replicates among a study's policies (study.json's): those that differ only in name and train_seed,
    as {first name: every name} for each group of two or more (docs/study.md, "Training replicates")."""
    groups: dict[str, list[str]] = {}
    for p in policies:
        recipe = json.dumps({k: v for k, v in p.items() if k not in ("name", "train_seed")}, sort_keys=True)
        groups.setdefault(recipe, []).append(p["name"])
    return {names[0]: names for names in groups.values() if len(names) > 1}


def replicate_cells(groups: dict[str, list[str]], runs: dict[str, tuple]) -> list[dict]:
    """For each group of replicates, dataset they all trained on and evaluation condition: each replicate's
    successes, and for each pair of them the episodes whose success agrees (same seeds, so outcomes pair up).
    `runs`: study_runs' labels, "NAME (DATASET)" -> (Run, train)."""
    key = ["regime", "split", "num_objects", "seed"]
    cells = []
    for names in groups.values():
        datasets = dict.fromkeys(train[0] for label, (_, train) in runs.items()
                                 if train is not None and label == f"{names[0]} ({train[0]})")
        for d in datasets:
            episodes = {n: runs[f"{n} ({d})"][0].episodes for n in names if f"{n} ({d})" in runs}
            members = list(episodes)
            if len(members) < 2:
                continue
            outcome = None  # one success column per replicate, rows paired by condition and seed
            for n, e in episodes.items():
                e = e[key + ["success"]].rename(columns={"success": n})
                outcome = e if outcome is None else outcome.merge(e, on=key)
            for (regime, split, k), g in outcome.groupby(["regime", "split", "num_objects"], sort=False):
                cells.append({
                    "replicates": members, "train_dataset": d, "eval_condition": f"{regime}/{split}/{k}",
                    "n": len(g), "success_count": {n: int(g[n].sum()) for n in members},
                    "episodes_alike": {f"{a} | {b}": int((g[a] == g[b]).sum())
                                       for i, a in enumerate(members) for b in members[i + 1:]}})
    return cells


def write_results(study, chosen: dict, results: dict) -> Path:
    """Gather a finished study's cells, selection and learning curves, then write_report."""
    root, cfg = study.root, study.cfg
    cells = []
    for p, d, _ in study.models():
        cells += cells_of(root / "eval" / f"{p.name}-{d.name}", p.name, (d.name, d.condition))
    for ref in cfg.evaluation.reference_policies:
        for run_dir in sorted((root / "eval").glob(f"reference-{ref}-*")):
            cells += cells_of(run_dir, ref)
    for cell in cells:  # relative to the study's folder, so that its summary holds wherever it is copied
        cell["run"] = os.path.relpath(cell["run"], root)
    summary = {"study": cfg.name, "description": cfg.description, "cells": cells,
               "selection": {f"{p}/{d}": v for (p, d), v in chosen.items()}, "curves": curve_points(study, chosen),
               "units": results}
    return write_report(root, summary)


def study_runs(root: Path, cells: list[dict]) -> dict[str, tuple]:
    """label -> (Run, its training (dataset name, condition key) or None for a reference), in the cells' order:
    "SmolVLA (sj)" for a model, "layout-prior #0" for a reference's run eval/reference-layout-prior-0."""
    runs, seen = {}, set()
    for cell in cells:  # one cell per condition; a run holds several
        run_dir = cell["run"]
        if run_dir in seen:
            continue
        seen.add(run_dir)
        if cell["train_dataset"] is None:
            label, train = f"{cell['policy']} #{run_dir.rsplit('-', 1)[1]}", None
        else:
            label, train = f"{cell['policy']} ({cell['train_dataset']})", (cell["train_dataset"],
                                                                            cell["train_condition"])
        runs[label] = (load_run(root / run_dir), train)
    return runs


def write_report(root: Path, summary: dict) -> Path:
    """From a study's summary (cells, selection, curves, units) and the evaluation and probe directories under
    `root`: rescore the probes and the displacement curves, then write summary.json, tables/ and report.html.
    `vla-ladder study --report-only` calls it on a finished study's summary.json: a study copied without its
    datasets and models gets this version's metrics and report."""
    from vla_ladder.report import study as present
    from vla_ladder.report.html import build_report, displacement_section, reference_data

    cells, curves = summary["cells"], summary["curves"]
    runs = study_runs(root, cells)
    displacement = displacement_curves(runs)
    # Probe metrics are recomputed from the plays (cheap), so a re-run with newer metrics refreshes them.
    probes = {}
    for uid in summary["units"]:
        if uid.startswith("probe-"):
            data = rescore_probe(root / "probes" / uid.removeprefix("probe-"))
            probes[uid.removeprefix("probe-")] = {"probe": data["probe"], "conditions": data["conditions"]}
    groups = replicate_groups(json.loads((root / "study.json").read_text())["policies"])
    replicates = {"groups": groups, "cells": replicate_cells(groups, runs)}
    summary = {**summary, "probes": probes, "displacement": displacement, "replicates": replicates,
               "units": {**summary["units"], **{f"probe-{name}": r for name, r in probes.items()}},
               "provenance": files.provenance()}
    files.write_json(root / "summary.json", summary)
    paper = reference_data("paper.json")
    tables = root / "tables"
    files.write_text(tables / "matrix.md", present.matrix_markdown(cells))
    files.write_text(tables / "matrix.tex", present.matrix_latex(cells))
    files.write_text(tables / "paper_comparison.md", present.paper_comparison_markdown(cells, paper))
    sections = [("Study: train regime x eval regime", present.matrix_html(cells))]
    if probes:
        files.write_text(tables / "probes.md", present.probes_markdown(probes))
        sections.append(("Study: grounding probes", present.probes_html(probes)))
    else:  # (a table an earlier report wrote would stand beside results that no longer hold it)
        (tables / "probes.md").unlink(missing_ok=True)
    if replicates["cells"]:
        files.write_text(tables / "replicates.md", present.replicates_markdown(replicates["cells"]))
        sections.append(("Study: training replicates (the same recipe, other training seeds)",
                         present.replicates_html(replicates["cells"])))
    else:
        (tables / "replicates.md").unlink(missing_ok=True)
    pairings = present.pairings_html(cells)
    if pairings:
        sections.append(("Study: held-out object-region pairings", pairings))
    for name, disp in displacement.items():
        with tempfile.TemporaryDirectory() as tmp:
            sections.append((f"Study: where the models trained on {name} stop finding the object",
                             displacement_section(disp["runs"], disp["trained_in"], Path(tmp))))
    if curves:
        png = present.plot_curves(curves, root / "curves.png")
        import base64
        sections.append(("Study: learning curves (validation episodes of the training condition)",
                         f"<img class=plot alt=curves src='data:image/png;base64,"
                         f"{base64.b64encode(png.read_bytes()).decode()}'>"))
    report, title = root / "report.html", f"vla-ladder study: {summary['study']}"
    labels = list(runs)
    run_list = [run for run, _ in runs.values()]
    build_report(run_list, report, title=title, labels=labels, sections=sections)
    if report.stat().st_size > REPORT_MAX_BYTES:  # a page that mails and commits: frame strips only
        build_report(run_list, report, title=title, labels=labels, sections=sections, with_video=False)
    print((tables / "matrix.md").read_text())
    return report
