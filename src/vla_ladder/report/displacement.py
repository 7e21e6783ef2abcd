"""The report's table of success against the named object's distance from its place in training
(evaluation/displacement.py): success per distance bin and the odds ratio per 10 cm, one row per policy (the
figure is plots.plot_displacement)."""

from __future__ import annotations

import html

from vla_ladder.report.tables import pct


def odds_text(trend: dict, interval: bool = True) -> str:
    """An odds ratio per 10 cm with its interval (without, when not `interval`); where outcomes separate at a
    distance, the one-sided bound the data give ("< 0.012"); "–" where nothing fits."""
    if trend["odds_ratio_per_10cm"] is None:
        if trend["ci95"] is None:
            return "–"
        lo, hi = trend["ci95"]
        return f"< {hi:.2g}" if hi is not None else f"> {lo:.2g}"
    lo, hi = trend["ci95"]
    return f"x{trend['odds_ratio_per_10cm']:.2g}" + (f" [{lo:.2g}, {hi:.2g}]" if interval else "")


def _share(rate: dict) -> str:
    """A Wilson rate as "value [lo, hi]" in %, "–" where it is unknown (a run without final TCP positions)."""
    if rate["value"] is None:
        return "–"
    return f"{pct(rate['value'])} <span class=ci>[{pct(rate['ci95'][0])}, {pct(rate['ci95'][1])}]</span>"


CAPTION = ("Success, grasp-anything and reach against the named object's distance from its place in training, each "
           "bin at its mean distance.")


def displacement_table(curves: dict[str, dict], trained_in: str) -> str:
    """One row per policy (label -> evaluation.displacement.by_displacement of its run): success per bin with its
    Wilson interval and n, the odds ratio per 10 cm (or why there is none), and a note on reading them."""
    bins = sorted({(b["from_cm"], b["to_cm"]) for c in curves.values() for b in c["bins"]})
    far_cm = next(iter(curves.values()))["far"]["from_cm"] if curves else 0
    head = "".join(f"<th>{lo:g}–{hi:g} cm</th>" for lo, hi in bins) + "".join(
        f"<th>≥ {far_cm:g} cm: {what}</th>" for what in ("reaches the object", "ends at its usual place"))
    rows = []
    for label, curve in curves.items():
        mine = {(b["from_cm"], b["to_cm"]): b for b in curve["bins"]}
        cells = [("–" if (b := mine.get(key)) is None else
                  f"{pct(b['success'])} <span class=ci>[{pct(b['ci95']['success'][0])}, "
                  f"{pct(b['ci95']['success'][1])}] n={b['n']}</span>") for key in bins]
        trend = curve["trend"]["success"]
        odds = odds_text(trend) + ("" if trend["odds_ratio_per_10cm"] is not None
                                   else f" <span class=ci>{html.escape(trend['why'])}</span>")
        far = [_share(curve["far"][k]) for k in ("reach", "ends_at_place")]
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in (html.escape(label), *cells, *far, odds)) + "</tr>")
    note = ("<p class=note>Success (%) of each run's episodes, binned by how far the named object stands from the "
            f"nearest place it stands in training ({html.escape(trained_in)}'s regions), pooled over the runs' "
            f"regimes: the curve between the ladder's rungs. Beyond {far_cm:g} cm the object and its usual place are "
            "more than two reach thresholds apart: the gripper ends at one or the other, or elsewhere. Odds ratio per "
            "10 cm: a logistic regression of success on the distance (profile-likelihood interval); about 1 for a "
            "policy that finds the object wherever it stands, far below 1 for one that goes where the object usually "
            "is; where success is all-or-nothing either side of a distance, no estimate but the bound the data allow "
            "(&lt; X: at most X).</p>")
    return f"<table><tr><th>policy</th>{head}<th>odds ratio / 10 cm [95% CI]</th></tr>{''.join(rows)}</table>{note}"
