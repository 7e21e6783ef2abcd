"""The page and the lines of `vla-ladder diagnose` (experiments/diagnose.py): its five answers beside the
reference policies' answers, with the reference each is nearest."""

from __future__ import annotations

import html


def _pct(x: float | None, signed: bool = False) -> str:
    return "–" if x is None or x != x else (f"{100 * x:+.0f}" if signed else f"{100 * x:.0f}")


def _answer(q: dict) -> tuple[str, str] | None:
    """The policy's answer to question `q` and its interval, in % (the ladder's drop in signed points)."""
    v, signed = q["policy"], q["id"] == "holds_up"
    if v is None:
        return None
    return _pct(v["value"], signed), f"[{_pct(v['ci95'][0], signed)}, {_pct(v['ci95'][1], signed)}]"


def answer_lines(data: dict) -> list[str]:
    """One line per question: the answer, the measure, the references' answers and the nearest."""
    lines = []
    for q in data["questions"]:
        value = " ".join(_answer(q) or ("n/a",))
        refs = ", ".join(f"{r} {_pct(x, q['id'] == 'holds_up')}" for r, x in q["references"].items())
        like = f"; resembles {q['resembles']}" if q["resembles"] else ""
        lines.append(f"{q['question']} {value} ({q['measure']}){'; ' + refs if refs else ''}{like}")
    return lines


def diagnosis_html(data: dict) -> str:
    """The diagnosis table, the first section of the report."""
    refs = data["references"]
    head = "".join(f"<th>{html.escape(h)}</th>" for h in ("question", "measure", "this policy [95% CI]",
                                                          *refs, "resembles"))
    rows = []
    for q in data["questions"]:
        answer = _answer(q)
        value = "n/a" if answer is None else f"{answer[0]} <span class=ci>{answer[1]}</span>"
        cells = [html.escape(q["question"]), html.escape(q["measure"]), value,
                 *(_pct(q["references"][r], q["id"] == "holds_up") for r in refs), html.escape(q["resembles"] or "–")]
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    note = ("<p class=note>Rates in %, on the same seeded scenes for every policy. The references: "
            "<b>scripted</b> reads its target every step (grounded by construction), <b>committed</b> is that expert "
            "reading its target once, at the first step, <b>layout-prior</b> goes where "
            "the named object stands in training (the location shortcut), <b>nearest</b> grasps whatever is nearest "
            "and ignores the words. <i>Resembles</i>: the reference whose answer is nearest this policy's; read it "
            "with the interval, and the probes' sections below for what lies behind each number.</p>")
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>{note}"
