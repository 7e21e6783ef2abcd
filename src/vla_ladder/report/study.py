"""A study's tables and figures: the train x eval regime matrix, the paper's layouts with the reference
policies and the paper's own numbers beside the learned ones, and learning curves.

Every function takes the study's cells (summary.json "cells": one dict per policy x train condition x eval
condition, with n, rates and 95% Wilson intervals) and returns text or writes a PNG; nothing here runs.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Sequence

from vla_ladder.conditions import REGIMES, Condition
from vla_ladder.contract import METRICS
from vla_ladder.files import atomic_path, number
from vla_ladder.report.probes import VIEWS
from vla_ladder.report.tables import METRIC_NAMES, REGIME_NAMES, SPLIT_NAMES, pct, tex_escape


def _cell(c: dict) -> str:
    return " / ".join(pct(c[m]) for m in METRICS)


def _row_label(cell: dict) -> tuple[str, str]:
    train = cell.get("train_condition")
    return cell["policy"], ("—" if train is None else f"{cell.get('train_dataset', '')} ({train})")


def matrix(cells: list[dict]) -> tuple[list[tuple[str, int]], list[str], list[tuple[str, str, dict]]]:
    """Columns (regime, object count) in ladder order, their titles, and rows (policy, trained on,
    {column: cell}) of the canonical cells."""
    rows: dict[tuple[str, str], dict] = {}
    cols = set()
    for c in cells:
        cond = Condition.parse(c["eval_condition"])
        if cond.split != "canonical":
            continue
        rows.setdefault(_row_label(c), {})[(cond.regime, cond.num_objects)] = c
        cols.add((cond.regime, cond.num_objects))
    counts = sorted({k for _, k in cols})
    order = [(r, k) for k in counts for r in REGIMES if (r, k) in cols]
    titles = [REGIME_NAMES[r] + (f", {k} objects" if len(counts) > 1 else "") for r, k in order]
    return order, titles, [(p, t, row) for (p, t), row in rows.items()]


def matrix_markdown(cells: list[dict]) -> str:
    regimes, titles, rows = matrix(cells)
    head = ["Policy", "Trained on", *titles]
    lines = ["**Train regime x eval regime: success / grasp-any / reach (%).**", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for policy, train, row in rows:
        lines.append("| " + " | ".join([policy, train, *(_cell(row[r]) if r in row else "–" for r in regimes)])
                     + " |")
    ns = sorted({c["n"] for _, _, row in rows for c in row.values()})
    lines += ["", f"n episodes per cell: {', '.join(map(str, ns))}; every cell's 95% Wilson intervals are in "
              "summary.json and the per-condition table."]
    return "\n".join(lines) + "\n"


def matrix_latex(cells: list[dict]) -> str:
    regimes, titles, rows = matrix(cells)
    head = ["Policy", "Trained on", *titles]
    out = ["\\begin{table}[t]", "  \\centering",
           "  \\caption{Train regime $\\times$ eval regime: success / grasp-any / reach (\\%).}",
           "  \\label{tab:study_matrix}", "  \\footnotesize", f"  \\begin{{tabular}}{{ll{'c' * len(regimes)}}}",
           "    \\toprule", "    " + " & ".join(map(tex_escape, head)) + " \\\\", "    \\midrule"]
    for policy, train, row in rows:
        out.append("    " + " & ".join([tex_escape(policy), tex_escape(train),
                                        *(_cell(row[r]) if r in row else "--" for r in regimes)]) + " \\\\")
    out += ["    \\bottomrule", "  \\end{tabular}", "\\end{table}"]
    return "\n".join(out) + "\n"


def _rate(c: dict, m: str) -> str:
    lo, hi = c["ci95"][m]
    return f"{pct(c[m])} [{pct(lo)}, {pct(hi)}]"


def paper_comparison_markdown(cells: list[dict], paper: dict) -> str:
    """The paper's Tables 2 and 3 layout: each learned model on its own training condition (and pairings ID/OOD),
    the reference policies on the same cells, and the paper's SmolVLA and pi0.5 numbers."""
    lines = ["**Learned policies on their training condition, beside the reference policies and the paper.**", "",
             "| Policy | Trained on | Evaluated on | n | " + " | ".join(METRIC_NAMES[m] for m in METRICS) + " |",
             "|---|---|---|---|---|---|---|"]
    own = [c for c in cells if c.get("train_condition") is not None and _same_cell(c)]
    refs = [c for c in cells if c.get("train_condition") is None]
    for c in own:
        lines.append(f"| {c['policy']} | {c['train_dataset']} ({c['train_condition']}) | {c['eval_condition']} | "
                     f"{c['n']} | " + " | ".join(_rate(c, m) for m in METRICS) + " |")
    learned_keys = {c["eval_condition"] for c in own}
    for c in refs:
        if c["eval_condition"] in learned_keys:
            lines.append(f"| {c['policy']} (reference) | — | {c['eval_condition']} | {c['n']} | "
                         + " | ".join(_rate(c, m) for m in METRICS) + " |")
    for table in ("ladder", "pairings"):
        for model, conds in paper.get(table, {}).items():
            for key, c in conds.items():
                if key in learned_keys:
                    lines.append(f"| paper: {model} | {key.split('/')[0]} | {key} | {c['n']} | "
                                 + " | ".join(pct(c[m]) for m in METRICS) + " |")
    lines += ["", "Rates in %, 95% Wilson intervals in brackets (the paper reports rates of 100 episodes without "
              "intervals). Pairing-trained models are evaluated on the held-out pairings (OOD) as well."]
    return "\n".join(lines) + "\n"


def _same_cell(c: dict) -> bool:
    """The cell is on the model's training condition, or the OOD pairing counterpart of it."""
    t, e = Condition.parse(c["train_condition"]), Condition.parse(c["eval_condition"])
    return (t.regime, t.num_objects) == (e.regime, e.num_objects) and \
        (t.split == e.split or (t.split, e.split) == ("pairings_id", "pairings_ood"))


def matrix_html(cells: list[dict]) -> str:
    regimes, titles, rows = matrix(cells)
    head = "".join(f"<th>{html.escape(t)}</th>" for t in titles)
    body = "".join(
        f"<tr><td>{html.escape(p)}</td><td>{html.escape(t)}</td>"
        + "".join(f"<td>{_cell(row[r])}<span class=ci> n={row[r]['n']}</span></td>" if r in row else "<td>–</td>"
                  for r in regimes) + "</tr>" for p, t, row in rows)
    return (f"<table><tr><th>policy</th><th>trained on</th>{head}</tr>{body}</table>"
            "<p class=note>success / grasp-any / reach in %, canonical split; the diagonal is each "
            "model's training regime. Intervals: summary.json and the per-condition table below.</p>")


def pairings_html(cells: list[dict]) -> str:
    rows = [c for c in cells if Condition.parse(c["eval_condition"]).split != "canonical"]
    if not rows:
        return ""
    body = "".join(
        f"<tr><td>{html.escape(c['policy'])}</td><td>{html.escape(str(c.get('train_condition') or '—'))}</td>"
        f"<td>{SPLIT_NAMES[Condition.parse(c['eval_condition']).split]}</td><td>{c['n']}</td>"
        + "".join(f"<td>{_rate(c, m)}</td>" for m in METRICS) + "</tr>" for c in rows)
    head = "".join(f"<th>{METRIC_NAMES[m]}</th>" for m in METRICS)
    return f"<table><tr><th>policy</th><th>trained on</th><th>split</th><th>n</th>{head}</tr>{body}</table>"


REPLICATE_COLUMNS = ("replicates", "trained on", "eval condition", "n", "success per replicate (%)",
                     "range (points)", "episodes alike, pair by pair")


def replicate_rows(cells: list[dict]) -> list[list[str]]:
    """One row per replicate_cells cell: the rates side by side, their spread, and how many episodes each pair of
    models agrees on (a rate can hold while the episodes it is made of change with the training run)."""
    rows = []
    for c in cells:
        rates = [100 * c["success_count"][n] / c["n"] for n in c["replicates"]]
        rows.append([", ".join(c["replicates"]), c["train_dataset"], c["eval_condition"], str(c["n"]),
                     " / ".join(f"{r:.0f}" for r in rates), f"{max(rates) - min(rates):.0f}",
                     ", ".join(f"{k} of {c['n']}" for k in c["episodes_alike"].values())])
    return rows


def replicates_markdown(cells: list[dict]) -> str:
    pairs = ", ".join(dict.fromkeys(p for c in cells for p in c["episodes_alike"]))
    return "\n".join(_markdown_table(REPLICATE_COLUMNS, replicate_rows(cells))) + f"\n\nPairs, in order: {pairs}.\n"


def replicates_html(cells: list[dict]) -> str:
    return _html_table(REPLICATE_COLUMNS, replicate_rows(cells))


def _markdown_table(head: Sequence[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head), *("| " + " | ".join(r) + " |" for r in rows)]


def _html_table(head: Sequence[str], rows: list[list[str]]) -> str:
    return ("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{html.escape(x)}</td>" for x in r) + "</tr>" for r in rows) + "</table>")


def plot_curves(curves: dict[str, list[dict]], path: str | Path, xlabel: str = "training step",
                ylabel: str = "% of validation episodes") -> Path:
    """curves: model -> [{step, success, grasp_any, reach, ci95}] on validation episodes; one panel per model."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import EngFormatter

    n = max(len(curves), 1)
    fig, axes = plt.subplots(1, n, figsize=(4 * n, 3.2), squeeze=False)
    for ax, (model, points) in zip(axes[0], curves.items()):
        steps = [p["step"] for p in points]
        for m in METRICS:
            ax.plot(steps, [100 * number(p[m]) for p in points], marker="o", label=METRIC_NAMES[m])
            ax.fill_between(steps, [100 * number(p["ci95"][m][0]) for p in points],
                            [100 * number(p["ci95"][m][1]) for p in points], alpha=0.15)
        ax.set_title(model, fontsize=9)
        ax.set_xlabel(xlabel)
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))  # 200k, not 200000 running into its neighbours
        ax.set_ylim(-2, 102)
    axes[0][0].set_ylabel(ylabel)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return Path(path)


def _metric(m: dict) -> str:
    lo, hi = m["ci95"]
    return f"{pct(m['value'])} [{pct(lo)}, {pct(hi)}]"


def _probe_value(metric: str, m: dict) -> str:
    """A probe metric's cell: % with its interval, and the p of its test where it has one; the NMI is a share of
    the instruction's entropy, not a rate, and stays one (0.25), with its permutation p."""
    if metric != "nmi":
        return _metric(m) + (f", p={number(m['mcnemar_p']):.2g}" if "mcnemar_p" in m else "")
    lo, hi = map(number, m["ci95"])
    cell = f"{number(m['value']):.2f} [{lo:.2f}, {hi:.2f}]"
    if "permutation_p" not in m:
        return cell
    # Probes from before 2026-11-27 hold the plug-in value (biased up): the shuffles' mean is what to compare it with.
    shuffled = "" if "plug_in" in m else f"shuffled {number(m['null_mean']):.2f}, "
    return f"{cell} ({shuffled}p={number(m['permutation_p']):.2g})"


def probe_rows(probes: dict[str, dict]) -> list[list[str]]:
    """probes: the probe's directory name (model label, "-", probe) -> probe.json data (or a unit's {probe,
    conditions}); one row per metric at a condition's top, and for the paraphrase probe, whose conditions hold one
    entry of rates per wording, each wording's success and its paired change from the canonical wording."""
    rows = []
    for name, data in probes.items():
        model = name.removesuffix(f"-{data['probe']}")
        for cond, metrics in data["conditions"].items():
            def row(metric: str, m: dict, label: str | None = None) -> None:
                rows.append([model, data["probe"], cond, label or metric.replace("_", " "), _probe_value(metric, m),
                             str(m.get("n", ""))])

            if metrics.get("left_out"):  # (scenes some variant lacks: grounding.common_scenes)
                rows.append([model, data["probe"], cond, "scenes left out (played in some variants only)",
                             str(metrics["left_out"]), ""])
            for metric, m in metrics.items():
                if isinstance(m, dict) and "value" in m and "ci95" in m:
                    row(metric, m)
                elif isinstance(m, dict) and isinstance(m.get("ci95"), dict):  # a wording's rates (stats.rates)
                    row("success", {"value": m["success"], "ci95": m["ci95"]["success"], "n": m["n"]},
                        f"success, {metric}")
                    if "vs_canonical" in m:
                        row("success", m["vs_canonical"]["success"], f"Δ success vs canonical, {metric}")
    return rows


PROBE_TABLE_NOTE = ("Rates and their changes in %, with 95% intervals and, for a paired change, McNemar's exact p; "
                    "the NMI is a share (0 to 1) with its permutation p. n counts scenes for rates over scenes and "
                    "paired changes, plays for rates pooled over a scene's plays and for the NMI.")


def probes_markdown(probes: dict[str, dict]) -> str:
    head = ["Model", "Probe", "Condition", "Metric", "Value [95% CI]", "n"]
    lines = ["**Grounding probes of the learned policies (docs/probes.md says how to read them).**", "",
             *_markdown_table(head, probe_rows(probes))]
    return "\n".join(lines) + "\n\n" + PROBE_TABLE_NOTE + "\n"


def probes_html(probes: dict[str, dict]) -> str:
    head = ["model", "probe", "condition", "metric", "value [95% CI]", "n"]
    kinds = [k for k in VIEWS if any(d["probe"] == k for d in probes.values())]
    notes = "".join(f"<p class=note><b>{k}</b>. {VIEWS[k].explain}</p>" for k in kinds)
    return _html_table(head, probe_rows(probes)) + f"<p class=note>{PROBE_TABLE_NOTE}</p>{notes}"
