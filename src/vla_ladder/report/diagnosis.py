"""The page and the lines of `vla-ladder diagnose` (experiments/diagnose.py): its answers, for one policy or
several side by side, beside the reference policies' answers, with the reference each is nearest."""

from __future__ import annotations

import html

from vla_ladder.report.displacement import odds_text
from vla_ladder.report.tables import pct

DIFFERENCES = ("holds_up", "reworded", "by_colour", "distracted", "goes_to_place")
"""Questions answered by a difference of two rates: shown in signed points (by_colour too since it became the change
the swap makes: unsigned, "10" read as the swapped share it was before)."""


def _answer(q: dict, answer: dict | None) -> tuple[str, str] | None:
    """A policy's answer to question `q` and its interval, in % (the ladder's drop in signed points)."""
    signed = q["id"] in DIFFERENCES
    if answer is None:
        return None
    return pct(answer["value"], signed), f"[{pct(answer['ci95'][0], signed)}, {pct(answer['ci95'][1], signed)}]"


def _policies(q: dict) -> dict[str, dict]:
    """label -> {"answer", "resembles"}; a diagnosis written before several policies were possible has one."""
    return q.get("answers") or {"policy": {"answer": q["policy"], "resembles": q["resembles"]}}


def answer_lines(data: dict) -> list[str]:
    """One line per question (and policy): the answer, the measure, the references' answers and the nearest; then
    where it stops finding the object (displacement_lines)."""
    lines = []
    for q in data["questions"]:
        refs = ", ".join(f"{r} {pct(x, q['id'] in DIFFERENCES)}" for r, x in q["references"].items())
        several = len(_policies(q)) > 1
        for label, a in _policies(q).items():
            value = " ".join(_answer(q, a["answer"]) or ("n/a",))
            like = f"; resembles {a['resembles']}" if a["resembles"] else ""
            who = f"[{label}] " if several else ""
            lines.append(f"{who}{q['question']} {value} ({q['measure']}){'; ' + refs if refs else ''}{like}")
    return lines + displacement_lines(data)


def diagnosis_html(data: dict) -> str:
    """The diagnosis table, the first section of the report: one policy's answer and the reference it resembles in
    two columns, or one column per policy (each answer with what it resembles under it)."""
    refs = data["references"]
    labels = list(_policies(data["questions"][0])) if data["questions"] else []
    several = len(labels) > 1
    policy_heads = [f"{label} [95% CI]" for label in labels] if several else ["this policy [95% CI]"]
    head = "".join(f"<th>{html.escape(h)}</th>" for h in ("question", "measure", *policy_heads, *refs,
                                                          *(() if several else ("resembles",))))
    rows = []
    for q in data["questions"]:
        cells = [html.escape(q["question"]), html.escape(q["measure"])]
        for a in _policies(q).values():
            answer = _answer(q, a["answer"])
            value = "n/a" if answer is None else f"{answer[0]} <span class=ci>{answer[1]}</span>"
            if several:
                value += f"<br><span class=ci>resembles {html.escape(a['resembles'] or '–')}</span>"
            cells.append(value)
        cells += [pct(q["references"][r], q["id"] in DIFFERENCES) for r in refs]
        if not several:
            cells.append(html.escape(next(iter(_policies(q).values()))["resembles"] or "–"))
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    note = ("<p class=note>Rates in %, on the same seeded scenes for every policy. The references: "
            "<b>scripted</b> reads its target every step (grounded by construction), <b>committed</b> is that expert "
            "reading its target once, at the first step, <b>layout-prior</b> goes where "
            "the named object stands in training (the location shortcut), <b>nearest</b> grasps whatever is nearest "
            "and ignores the words. <i>Resembles</i>: the reference whose answer is nearest this policy's; read it "
            "with the interval, and the probes' sections below for what lies behind each number."
            + (" Two policies' answers are on the same scenes: <code>vla-ladder compare</code> on their run "
               "directories tests a difference pair by pair." if several else "") + "</p>")
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>{note}"


def displacement_lines(data: dict) -> list[str]:
    """One line per policy: its success nearest and farthest from the named object's place in training, and the
    odds ratio per 10 cm beside the references'."""
    disp = data.get("displacement")
    if not disp:
        return []
    several = len(disp["policies"]) > 1
    refs = ", ".join(f"{r} {odds_text(c['trend']['success'])}" for r, c in disp["references"].items())
    lines = []
    for label, curve in disp["policies"].items():
        near, far = curve["bins"][0], curve["bins"][-1]
        who = f"[{label}] " if several else ""
        beyond = curve["far"]
        at_place = ("" if beyond["ends_at_place"]["value"] is None else
                    f", ends at its usual place in {pct(beyond['ends_at_place']['value'])}%")
        lines.append(f"{who}Where does it stop finding the object? success {pct(near['success'])}% at "
                     f"{near['from_cm']:g}-{near['to_cm']:g} cm from the named object's place in training, "
                     f"{pct(far['success'])}% at {far['from_cm']:g}-{far['to_cm']:g} cm; beyond "
                     f"{beyond['from_cm']:g} cm (n={beyond['n']}) it reaches the object in "
                     f"{pct(beyond['reach']['value'])}%{at_place}; odds {odds_text(curve['trend']['success'])} "
                     f"per 10 cm{'; ' + refs if refs else ''}")
    return lines
