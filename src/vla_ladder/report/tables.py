"""The paper's four result tables (ladder, pairings, data scaling, object count) as Markdown and LaTeX.

Tables are built from per-condition summaries (`metrics.summarize`), so they work the same on fresh
evaluation runs and on summary.json files read back from disk. Markdown shows every rate with its 95%
Wilson interval; LaTeX keeps the paper's layout (percentages, booktabs, one multirow block per model).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from vla_ladder.conditions import LADDER
from vla_ladder.contract import METRICS

METRIC_NAMES = {"success": "Success", "grasp_any": "Grasp-any", "reach": "Reach"}
REGIME_NAMES = {name: r.title for name, r in LADDER.items()}
REGIME_SHORT = {name: r.short for name, r in LADDER.items()}
SPLIT_NAMES = {"canonical": "Canonical", "pairings_id": "Pairings (ID)", "pairings_ood": "Pairings (OOD)"}


@dataclass(frozen=True)
class Rate:
    """One metric of one condition: a rate and its 95% interval (fractions)."""

    value: float
    lo: float
    hi: float
    n: int

    @classmethod
    def of(cls, condition: dict, metric: str) -> "Rate":
        lo, hi = condition["ci95"][metric]
        return cls(condition[metric], lo, hi, condition["n"])

    def md(self) -> str:
        return f"{pct(self.value)} [{pct(self.lo)}, {pct(self.hi)}]"

    def tex(self) -> str:
        return f"${pct(self.value)}$"


@dataclass(frozen=True)
class Change:
    """A metric before -> after (data scaling)."""

    before: Rate
    after: Rate

    def md(self) -> str:
        return f"{self.before.md()} → {self.after.md()}"

    def tex(self) -> str:
        return f"${pct(self.before.value)}\\!\\rightarrow\\!{pct(self.after.value)}$"


@dataclass
class Table:
    """Rows grouped by model, with a Model column unless the table is of one unnamed model."""

    key: str
    caption: str
    row_title: str
    groups: dict[str, list[tuple[str, dict]]] = field(default_factory=dict)
    """model label -> [(row label, {metric: Rate | Change})]"""
    models: int = 1
    """how many models the results it was made from cover: a table that holds one's rows still names it"""

    def add(self, group: str, label: str, cells: dict) -> None:
        self.groups.setdefault(group, []).append((label, cells))

    @property
    def grouped(self) -> bool:
        return len(self.groups) > 1 or self.models > 1 or self.key in ("ladder", "data_scaling")

    def to_markdown(self) -> str:
        cols = (["Model"] if self.grouped else []) + [self.row_title] + [METRIC_NAMES[m] for m in METRICS]
        lines = [f"**{self.caption}**", "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for model, rows in self.groups.items():
            for i, (label, cells) in enumerate(rows):
                lead = ([model if i == 0 else ""] if self.grouped else []) + [label]
                lines.append("| " + " | ".join(lead + [cells[m].md() for m in METRICS]) + " |")
        lines += ["", "Rates in %, 95% Wilson intervals in brackets; n episodes per condition: "
                  + _n_note(self.groups) + "."]
        return "\n".join(lines) + "\n"

    def to_latex(self) -> str:
        n_lead = 2 if self.grouped else 1
        spec = "l" * n_lead + "c" * len(METRICS)
        head = (["Model"] if self.grouped else []) + [self.row_title] + [METRIC_NAMES[m] for m in METRICS]
        out = ["\\begin{table}[t]", "  \\centering", f"  \\caption{{{tex_escape(self.caption)}}}",
               f"  \\label{{tab:{self.key}}}", "  \\footnotesize", "  \\renewcommand{\\arraystretch}{1.25}",
               f"  \\begin{{tabular}}{{{spec}}}", "    \\toprule",
               "    " + " & ".join(map(tex_escape, head)) + " \\\\", "    \\midrule"]
        for g, (model, rows) in enumerate(self.groups.items()):
            if g:
                out.append("    \\midrule")
            for i, (label, cells) in enumerate(rows):
                lead = []
                if self.grouped:
                    lead = [f"\\multirow{{{len(rows)}}}{{*}}{{{tex_escape(model)}}}" if i == 0 else ""]
                lead.append(tex_escape(label))
                out.append("    " + " & ".join(lead + [cells[m].tex() for m in METRICS]) + " \\\\")
        out += ["    \\bottomrule", "  \\end{tabular}", "\\end{table}"]
        return "\n".join(out) + "\n"


def pct(x: float | None, signed: bool = False) -> str:
    """A rate in whole percent; "–" where it is undefined (NaN, or null as a result file holds it since it is strict
    JSON). Every report's tables use it. `signed`: a difference of two rates, in points with its sign ("+12", "-3")."""
    return "–" if x is None or x != x else f"{100 * x:+.0f}" if signed else f"{100 * x:.0f}"


_TEX = {"\\": "\\textbackslash{}", "_": "\\_", "%": "\\%", "&": "\\&", "#": "\\#", "$": "\\$", "{": "\\{",
        "}": "\\}", "~": "\\textasciitilde{}", "^": "\\textasciicircum{}", "→": "$\\rightarrow$", "–": "--"}


def tex_escape(s: str) -> str:
    return re.sub("|".join(map(re.escape, _TEX)), lambda m: _TEX[m.group()], s)


def _n_note(groups: dict) -> str:
    ns = sorted({n for rows in groups.values() for _, cells in rows for c in cells.values()
                 for n in ((c.n,) if isinstance(c, Rate) else (c.before.n, c.after.n))})
    return ", ".join(map(str, ns)) or "no complete rows"


def _cells(condition: dict) -> dict:
    return {m: Rate.of(condition, m) for m in METRICS}


def _find(conditions: dict, regime: str, split: str, num_objects: int) -> dict | None:
    return conditions.get(f"{regime}/{split}/{num_objects}")


def ladder_table(results: dict[str, dict], num_objects: int = 5) -> Table:
    """results: model label -> conditions (summary.json "conditions"); one row per regime present."""
    t = Table("ladder", "Performance along the spatial task ladder.", "Regime", models=len(results))
    for model, conds in results.items():
        for regime, name in REGIME_NAMES.items():
            c = _find(conds, regime, "canonical", num_objects)
            if c is not None:
                t.add(model, name, _cells(c))
    return t


def pairings_table(results: dict[str, dict], regime: str = "small_jitter", num_objects: int = 5) -> Table:
    # The paper's: small jitter, five objects.
    where = ", ".join(([] if regime == "small_jitter" else [REGIME_NAMES[regime].lower()])
                      + ([] if num_objects == 5 else [f"{num_objects} object{'s' * (num_objects > 1)}"]))
    where = where and f" ({where})"
    t = Table("pairings", f"Compositional generalization to held-out object-region pairings{where}.", "Split",
              models=len(results))
    for model, conds in results.items():
        for split in ("pairings_id", "pairings_ood"):
            c = _find(conds, regime, split, num_objects)
            if c is not None:
                t.add(model, SPLIT_NAMES[split], _cells(c))
    return t


def object_count_table(results: dict[str, dict], regime: str = "full_random") -> Table:
    t = Table("object_count", f"Object-count ablation under {REGIME_NAMES[regime].lower()} placement.",
              "# Objects", models=len(results))
    for model, conds in results.items():
        for k in range(1, 6):
            c = _find(conds, regime, "canonical", k)
            if c is not None:
                t.add(model, str(k), _cells(c))
    return t


def data_scaling_table(stages: list[dict], num_objects: int = 5) -> Table:
    """stages: [{"model", "regime", "sizes": (small, large), "before": conditions, "after": conditions}]."""
    sizes = "; ".join(f"{REGIME_SHORT[s['regime']]}: {s['sizes'][0]} → {s['sizes'][1]}"
                      for s in _unique_regimes(stages))
    t = Table("data_scaling", f"Response to data scaling under increasing spatial variability ({sizes}).",
              "Regime")
    for s in stages:
        a = _find(s["before"], s["regime"], "canonical", num_objects)
        b = _find(s["after"], s["regime"], "canonical", num_objects)
        if a is not None and b is not None:
            t.add(s["model"], REGIME_SHORT[s["regime"]], {m: Change(Rate.of(a, m), Rate.of(b, m)) for m in METRICS})
    return t


def _unique_regimes(stages: list[dict]) -> list[dict]:
    seen, out = set(), []
    for s in stages:
        if s["regime"] not in seen:
            seen.add(s["regime"])
            out.append(s)
    return out
