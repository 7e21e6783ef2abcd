"""The grounding probes (`vla-ladder probe`) in the report: one table and one figure per probe, from probe.json.

A probe directory holds probe.json (experiments/probes.py) and its variants' run directories; the report finds
a probe next to any run it is given (a run directory whose parent holds probe.json) or is handed the probe
directories directly. Every value is shown with its 95% interval: Wilson for proportions over scenes, Wilson on
the effective number of plays where plays of one scene are pooled (grounded accuracy, the absent plays of a
scene), the bias-corrected jackknife over scenes for the mutual information (beside its permutation p);
Newcombe's paired interval and McNemar's exact p with every paired change.
"""

from __future__ import annotations

import html
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vla_ladder.contract import CONTROL_HZ, EPISODE_STEPS
from vla_ladder.files import number
from vla_ladder.report.labels import short_labels
from vla_ladder.report.plots import _plt, _save, plot_confusion
from vla_ladder.report.tables import pct

PROBE_FILE = "probe.json"
SWAP_METRICS = {"instruction_sensitivity": "instruction sensitivity", "scene_accuracy": "scene accuracy",
                "grounded_accuracy": "grounded accuracy", "nmi": "NMI", "success": "success"}
COLOUR_OUTCOMES = ("instructed", "partner", "other", "none")
COLOUR_NAMES = {"instructed": "instructed object (shape)", "partner": "colour partner (colour)",
                "other": "another object", "none": "nothing"}
PLACE_NAMES = {"instructed": "instructed object (follows the object)",
               "partner": "swap partner (follows the place)", "other": "another object", "none": "nothing"}
SWITCH_NAMES = {"new": "switched-to object B (follows the new instruction)",
                "old": "first-named object A (stays with the old one)", "other": "another object", "none": "nothing"}
WORDINGS = ("canonical", "paraphrase-train", "paraphrase-heldout")
REMOVAL_SERIES = {"success_original": "success, as it is", "success_alone": "success, distractors removed",
                  "distractor_failures": "fails as it is, succeeds alone", "failures_alone_too": "fails alone too"}
ABSENT_SERIES = {"grasp_present": "grasp, own target named", "grasp_absent": "grasp, absent object named",
                 "shortcut_reach": "ends at an empty usual place of the absent object",
                 "same_grasp": "grasps what it grasps when its own target is named"}
EXPLAIN = {
    "instruction-swap": "Each scene is played once per present object, instructing each in turn; only the "
    "instruction changes. <b>Instruction sensitivity</b>: share of scenes whose held object is not the same under "
    "all instructions. <b>Scene accuracy</b>: share of scenes where the instructed object is held under every "
    "instruction. <b>Grounded accuracy</b>: P(held = instructed | something held). <b>NMI</b>: I(instructed; "
    "held | objects present) / H(instructed | objects present), 0 when the held object does not depend on the "
    "instruction, 1 when it determines it. The value is the jackknife's bias-corrected estimate over scenes (the "
    "plug-in one is above 0 even then) with its interval, and p is the permutation test's: the share of "
    "shuffles of the held objects among each scene's plays whose NMI is at least as high. With fewer than five "
    "objects, or when most plays hold nothing, the interval is too narrow at a few dozen scenes "
    "(docs/probes.md): read p. A location shortcut is sensitive everywhere (it goes to a different usual place "
    "for each instruction), but only where objects sit in their usual regions does it hold the named one: under "
    "full random its grounded accuracy falls to chance and its NMI near 0 (p large). A policy that ignores "
    "the instruction is never sensitive.",
    "paraphrase": "The same scenes with the canonical wording, training paraphrases and held-out paraphrases "
    "(task/paraphrases.json); one-object conditions are the distractor-free control: a drop there is the wording "
    "upsetting the motion, not object selection. Δ is the paired difference to the canonical wording (Newcombe's "
    "paired interval) with McNemar's exact p.",
    "appearance-swap": "The same scenes with the instructed object and one distractor exchanging colours "
    "(task/appearance.py). Shares of what is held, without the swap → with it: the instructed object (follows "
    "shape and words) or its colour partner, which now wears the instructed object's usual colour (follows "
    "colour). Scenes whose instructed object has no swap partner are left out.",
    "absent-object": "The same scenes (fewer than five objects) instructing each object that is <i>not</i> on the "
    "table, next to the ordinary play naming the scene's own target. <b>Grasp</b>: some object is held at the final "
    "step (present → absent; Δ is the paired change). <b>Shortcut reach</b>: among absent plays whose named object "
    "has an empty usual place, the gripper ends within 5 cm (horizontally) of the centre of one; its usual places "
    "are the regions where it stands in this condition's training layouts (its canonical region; its three "
    "training regions for the pairing splits; undefined under full random), empty when no present object stands "
    "there (always, in the canonical split). <b>Same grasp</b>: the absent play holds the object the present play "
    "holds. A policy that grounds the words in what it sees grasps nothing; one that maps them to a place goes "
    "there (high shortcut reach); one that ignores them grasps as often, and the same object, as when its own "
    "target is named.",
    "position-swap": "The same scenes with the instructed object and one distractor (its partner, chosen from the "
    "seed) exchanging places, each keeping its yaw; the other objects, colours, robot start and instruction are "
    "unchanged (task/layouts.py Layout.positions_swapped). Shares of what is held, original → swapped: the "
    "instructed object (<b>follows the object</b>) or the partner, which in the swapped play stands where the "
    "instructed object stood (<b>follows the place</b>; in the original play holding it is an ordinary wrong "
    "grasp). Δ is the paired change (Newcombe's paired interval) with McNemar's exact p. A grounded policy follows the "
    "object in both plays; a location shortcut's follows-object drops and its follows-place rises; a policy that "
    "ignores the instruction grasps by its own rule. <b>Gripper ends at the object / place</b>: the TCP ends "
    "within 5 cm (horizontally) of the instructed object's / the partner's footprint, nearer it than the other, "
    "whatever is held (a place-follower whose grasp does not fit the partner's shape still goes there). Scenes "
    "where no distractor fitted collision-free played unswapped and are left out.",
    "instruction-switch": "The same scenes played as they are (original) and with the instruction switching "
    "mid-episode: it names the scene's target A until control step K and, from K on, a distractor B chosen from "
    "the seed, which success is then judged against (task/layouts.py Layout.switched; 50 steps at 20 Hz, so K = 5 "
    "is 0.25 s). Shares of what is held at the end, original → switched: B (<b>follows new</b>: the policy kept "
    "reading its instruction) or A (<b>stays with old</b>: it committed to its first reading); in the original play "
    "holding B is an ordinary wrong grasp. Δ is the paired change (Newcombe's paired interval) with McNemar's "
    "exact p. "
    "<b>Gripper ends at B / A</b>: the TCP ends within 5 cm (horizontally) of that object's footprint, nearer it "
    "than the other, whatever is held. A policy that re-reads its instruction follows the new one when K is early "
    "and, having grasped, stays with the old one when K is late; one that commits from its first frames stays with "
    "the old one at every K; one that ignores the instruction plays the same in both plays.",
    "distractor-removal": "The same scenes played as they are and with every distractor taken off the table, the "
    "instructed object alone where it stood, with the same wording, colours and robot start (task/layouts.py "
    "Layout.alone). <b>Success</b> in each play and its paired change <b>Δ success</b> (Newcombe's paired interval, "
    "McNemar's exact p): what the other objects cost. The failures as it is, split: <b>fails as it is, succeeds "
    "alone</b> (the other objects drew it off, or, for a policy whose outcomes vary from play to play, chance: Δ "
    "nets these against the opposite flips) and <b>fails alone too</b> (with nothing to choose between: reaching, "
    "grasping, or a place where the object is not). <b>Held, as it is</b>: the instructed object, a distractor, or "
    "nothing. A grounded policy with sound control fails neither way; one that picks objects by something other than "
    "the instruction (the nearest, its usual object) gains alone; a location shortcut under full random fails alone "
    "too, its usual place being empty.",
}


def load_probe(path: str | Path) -> dict:
    """probe.json of a probe directory; ValueError when it is not one."""
    path = Path(path)
    file = path / PROBE_FILE
    if not file.is_file():
        raise ValueError(f"{path} is not a probe directory: no {PROBE_FILE} (written by `vla-ladder probe`)")
    return json.loads(file.read_text())


def probe_dirs(run_paths) -> list[Path]:
    """The probes that runs belong to: the parents of run directories that hold probe.json, in run order."""
    return list(dict.fromkeys(Path(p).resolve().parent for p in run_paths
                              if (Path(p).resolve().parent / PROBE_FILE).is_file()))


def _undefined(x) -> bool:
    """NaN, or null: how probe.json stores an undefined number (a rate over no scenes) since it is strict JSON."""
    return x is None or x != x


def _num(x, spec: str) -> str:
    """`x` formatted by `spec`, "nan" where it is undefined (NaN or null) as it always showed."""
    return format(number(x), spec)



def _cell(entry: dict, scale: str = "pct") -> str:
    """"value [lo, hi]" of a {value, ci95} entry, in % or (scale="unit") with two decimals."""
    fmt = pct if scale == "pct" else (lambda x: "–" if _undefined(x) else f"{x:.2f}")
    lo, hi = entry["ci95"]
    return f"{fmt(entry['value'])}<span class=ci> [{fmt(lo)}, {fmt(hi)}]</span>"


def _nmi(entry: dict) -> str:
    """The NMI cell: its value and interval, then the permutation p. Probes from before 2026-11-27 give the plug-in
    value with a percentile bootstrap interval (both biased up): the mean of the shuffles is shown beside them, the
    value to compare with; older still, nothing more."""
    cell = _cell(entry, "unit")
    if "null_mean" not in entry:
        return cell
    shuffled = "" if "plug_in" in entry else f"shuffled {_num(entry['null_mean'], '.2f')}, "
    return cell + f"<span class=ci> ({shuffled}p={_num(entry['permutation_p'], '.2g')})</span>"


def _rate(cond: dict, metric: str) -> str:
    return _cell({"value": cond[metric], "ci95": cond["ci95"][metric]})


def _signed(entry: dict, note: str = "") -> str:
    """"+value [lo, hi]" of a difference, in points, with an optional note inside the interval's span."""
    lo, hi = entry["ci95"]
    sign = lambda x: "–" if _undefined(x) else f"{100 * x:+.0f}"  # noqa: E731
    return f"{sign(entry['value'])}<span class=ci> [{sign(lo)}, {sign(hi)}]{note}</span>"


def _delta(entry: dict) -> str:
    """A paired change with McNemar's p where it has one (a share change over several plays a scene has none)."""
    return _signed(entry, f", p={_num(entry['mcnemar_p'], '.2g')}" if "mcnemar_p" in entry else "")


def _table(head: list[str], rows: list[list[str]]) -> str:
    return ("<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows) + "</table>")


def _two_play_cells(c: dict, follows: tuple[str, ...], second: tuple[str, str], ends: tuple[str, ...]) -> list[str]:
    """The cells of a probe playing each scene twice (evaluation/grounding.py _two_plays): each `follows` metric
    original → second play and its Δ, the other/none shares, where the gripper ends; `second` is the second play's
    share key and metric suffix."""
    shares, suffix = second
    cells = []
    for m in follows:
        cells += [f"{_cell(c[f'{m}_original'])} → {_cell(c[f'{m}_{suffix}'])}", _delta(c[f"{m}_change"])]
    cells += [f"{_cell(c['original'][o])} → {_cell(c[shares][o])}" for o in ("other", "none")]
    return cells + ["n/a (no TCP recorded)" if c[f"{m}_original"] is None else
                    f"{_cell(c[f'{m}_original'])} → {_cell(c[f'{m}_{suffix}'])}" for m in ends]


def _swap_table(conds: dict) -> tuple[list[str], list[list[str]]]:
    head = ["condition", "scenes", *SWAP_METRICS.values()]
    return head, [[html.escape(k), str(c["scenes"])] + [_nmi(c[m]) if m == "nmi" else _cell(c[m]) for m in SWAP_METRICS]
                  for k, c in conds.items()]


def _paraphrase_table(conds: dict) -> tuple[list[str], list[list[str]]]:
    head = ["condition", "wording", "n", "success", "grasp-any", "reach", "wrong object", "Δ success vs canonical",
            "success by novelty"]
    rows = []
    for key, variants in conds.items():
        for wording in [w for w in WORDINGS if w in variants]:
            c = variants[wording]
            novelty = ", ".join(f"{k} {pct(v['value'])} (n={v['n']})" for k, v in c.get("by_novelty", {}).items())
            rows.append([html.escape(key), wording, str(c["n"]), _rate(c, "success"), _rate(c, "grasp_any"),
                         _rate(c, "reach"), _cell(c["wrong_object"]),
                         _delta(c["vs_canonical"]["success"]) if "vs_canonical" in c else "", novelty])
    return head, rows


def _appearance_table(conds: dict) -> tuple[list[str], list[list[str]]]:
    head = ["condition", "swapped scenes", *(f"{COLOUR_NAMES[o]}: no swap → swap" for o in COLOUR_OUTCOMES),
            "Δ follows shape"]
    return head, [[html.escape(k), f"{c['swapped']} of {c['scenes']}"]
                  + [f"{_cell(c['original'][o])} → {_cell(c['swap'][o])}" for o in COLOUR_OUTCOMES]
                  + [_delta(c["shape_change"])] for k, c in conds.items()]


def _absent_table(conds: dict) -> tuple[list[str], list[list[str]]]:
    head = ["condition", "scenes (absent plays)", "success, own target named", "grasp: present → absent",
            "Δ grasp", "shortcut reach", "usual place empty", "same grasp as present"]
    return head, [[html.escape(k), f"{c['scenes']} ({c['absent_plays']})", _cell(c["success_present"]),
                   f"{_cell(c['grasp_present'])} → {_cell(c['grasp_absent'])}", _delta(c["grasp_change"]),
                   # (None in full random, where no place is usual, or for a run that kept no TCP: say which)
                   *([f"n/a (no {'usual place' if c.get('usual_regions') is None else 'TCP recorded'})"] * 2
                     if c["shortcut_reach"] is None else
                     [_cell(c["shortcut_reach"]), _cell(c["usual_place_empty"])]), _cell(c["same_grasp"])]
                  for k, c in conds.items()]


def _position_table(conds: dict) -> tuple[list[str], list[list[str]]]:
    head = ["condition", "swapped scenes", "follows object: original → swapped", "Δ follows object",
            "follows place: original → swapped", "Δ follows place",
            *(f"{PLACE_NAMES[o]}: original → swapped" for o in ("other", "none")),
            "gripper ends at the object: original → swapped", "gripper ends at the place: original → swapped"]
    return head, [[html.escape(k), f"{c['swapped']} of {c['scenes']}",
                   *_two_play_cells(c, ("follows_object", "follows_place"), ("swap", "swapped"),
                                    ("reaches_object", "reaches_place"))] for k, c in conds.items()]


def _switch_table(conds: dict) -> tuple[list[str], list[list[str]]]:
    head = ["condition", "switch at", "scenes", "follows new: original → switched", "Δ follows new",
            "stays with old: original → switched", "Δ stays with old",
            *(f"{SWITCH_NAMES[o]}: original → switched" for o in ("other", "none")),
            "gripper ends at B: original → switched", "gripper ends at A: original → switched"]
    return head, [[html.escape(k), f"step {c['switch_step']} ({c['switch_step'] / CONTROL_HZ:.2f} s)", str(c["scenes"]),
                   *_two_play_cells(c, ("follows_new", "stays_old"), ("switched", "switched"),
                                    ("reaches_new", "reaches_old"))]
                  for k, cond in conds.items() for c in cond["by_step"].values()]


def _removal_table(conds: dict) -> tuple[list[str], list[list[str]]]:
    head = ["condition", "scenes", "success: as it is → alone", "Δ success", "fails as it is, succeeds alone",
            "fails alone too", "held as it is: instructed / distractor / nothing"]
    return head, [[html.escape(k), str(c["scenes"]),
                   f"{_cell(c['success_original'])} → {_cell(c['success_alone'])}", _delta(c["success_change"]),
                   _cell(c["distractor_failures"]), _cell(c["failures_alone_too"]),
                   " / ".join(_cell(c["held_original"][o]) for o in ("instructed", "distractor", "none"))]
                  for k, c in conds.items()]


def _switch_tables(conds: dict) -> list[tuple[str, dict]]:
    """The instruction switch's per-table entries: one per condition and switch step."""
    return [(f"{key}, switch at step {k}", c) for key, cond in conds.items() for k, c in cond["by_step"].items()]


LEFT_OUT = "played in some variants only, so not scored (a variant cut short: rerun the probe command to play them)"


def left_out(data: dict) -> dict[str, int]:
    """Per condition, the scenes the probe left out (evaluation/grounding.py common_scenes), where there are any
    (probe.json from before they were counted: none)."""
    return {k: int(c["left_out"]) for k, c in data["conditions"].items() if c.get("left_out")}


def table_html(data: dict) -> str:
    """The probe's table: one row per condition (and wording for the paraphrase probe, step for the switch), and
    the scenes left out, where any were."""
    view = _view(data["probe"])
    head, rows = view.table(data["conditions"])
    out = left_out(data)
    missing = "" if not out else (f"<p class=note><b>Scenes left out</b>, {LEFT_OUT}: "
                                  + ", ".join(f"{html.escape(k)}: {n}" for k, n in out.items()) + ".</p>")
    return _table(head, rows) + f"<p class=note>In %, 95% intervals in brackets{view.unit}.</p>" + missing


def matrices_html(data: dict) -> str:
    """The pooled count tables: instructed x held (instruction swap), named x held (absent object), what is held
    in the first play x the second (the appearance and position swaps, the instruction switch)."""
    view = _view(data["probe"])
    if view.counts is None:
        return ""
    key, corner = view.counts
    parts = []
    for cond, c in view.tables(data["conditions"]):
        m = c[key]
        rows = [[f"<b>{html.escape(r)}</b>", *map(str, counts)] for r, counts in zip(m["rows"], m["counts"])]
        parts.append(f"<p>{html.escape(cond)}</p>" + _table([corner, *map(html.escape, m["columns"])], rows))
    return "<details><summary>Counts</summary>" + "".join(parts) + "</details>"


def section(data: dict, figures: list[str], where: str) -> str:
    """The HTML of one probe: heading, what it measures, its table, figures (already <img> tags), counts."""
    spec = short_labels([data["policy"].get("spec", "?")])[0]
    done = "" if data.get("complete", True) else " <b>(incomplete: rerun the probe command to finish it)</b>"
    return (f"<h3>{html.escape(data['probe'])}: {html.escape(spec)} <span class=ci>{html.escape(where)}</span></h3>"
            f"<p class=note>{_view(data['probe']).explain}{done}</p>" + table_html(data) + "".join(figures)
            + matrices_html(data))


# ---------------------------------------------------------------------- figures
def plot_probe(data: dict, path: str | Path) -> list[Path]:
    """The probe's figure at `path` (and, for the instruction swap and the absent object, its matrices next to
    it)."""
    path, view = Path(path), _view(data["probe"])
    out = [view.plot(data, path)]
    if view.matrix_label is not None:
        # (absent-object: the rows are the named objects, all absent, so every grasp counted is a substitute)
        panels = {k: {"confusion": c["matrix"]} for k, c in data["conditions"].items()}
        out.append(plot_confusion(panels, path.with_name(path.stem + "_matrix.png"), view.matrix_label))
    return out


def _bars(ax, groups: list[str], series: dict[str, list[dict]], ylabel: str) -> None:
    """Grouped bars with interval whiskers: series name -> one {value, ci95} per group (in [0, 1])."""
    width = 0.8 / max(len(series), 1)
    for j, (label, entries) in enumerate(series.items()):
        v = np.array([e["value"] for e in entries], dtype=float) * 100
        ci = np.array([e["ci95"] for e in entries], dtype=float).reshape(-1, 2) * 100
        err = np.nan_to_num(np.abs(np.stack([v - ci[:, 0], ci[:, 1] - v])))
        # (yerr as nested lists: matplotlib 3.10 warns on a (2, 1) array)
        ax.bar(np.arange(len(groups)) + (j - (len(series) - 1) / 2) * width, np.nan_to_num(v), width,
               yerr=err.tolist(), capsize=3, label=label, alpha=0.85)
    ax.set_xticks(range(len(groups)), [g.replace("/", "\n", 1) for g in groups], fontsize=7)
    ax.set_ylim(0, 105)
    ax.set_ylabel(ylabel)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7)


def _plot_metrics(data: dict, path: Path, metrics: dict[str, str], ylabel: str, title: str,
                  legend_below: bool = False) -> Path:
    """Grouped bars of each condition's `metrics` (key -> label), one {value, ci95} entry each."""
    plt = _plt()
    conds = data["conditions"]
    fig, ax = plt.subplots(figsize=(max(5.0, 2.2 * len(conds)), 3.8 if legend_below else 3.6))
    _bars(ax, list(conds), {label: [c[m] for c in conds.values()] for m, label in metrics.items()}, ylabel)
    if legend_below:  # the bars reach 100
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    ax.set_title(f"{title}: {data['policy'].get('spec', '')}")
    return _save(fig, path)


def _plot_swap(data: dict, path: Path) -> Path:
    return _plot_metrics(data, path, SWAP_METRICS, "% (NMI × 100), 95% interval", "Instruction swap")


def _plot_absent(data: dict, path: Path) -> Path:
    plt = _plt()
    conds = data["conditions"]
    missing = {"value": np.nan, "ci95": [np.nan, np.nan]}
    series = {label: [c[m] or missing for c in conds.values()] for m, label in ABSENT_SERIES.items()}
    fig, ax = plt.subplots(figsize=(max(6.0, 2.4 * len(conds)), 4.4))
    _bars(ax, list(conds), series, "% of plays, 95% interval")
    width = 0.8 / len(series)
    for i, c in enumerate(conds.values()):  # an undefined rate is no bar at all, not a bar at 0
        if c["shortcut_reach"] is None:
            j = list(ABSENT_SERIES).index("shortcut_reach")
            ax.text(i + (j - (len(series) - 1) / 2) * width, 2, "n/a", ha="center", fontsize=6, rotation=90)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)  # below: the bars reach 100
    ax.set_title(f"Absent object: {data['policy'].get('spec', '')}")
    return _save(fig, path)


def _plot_removal(data: dict, path: Path) -> Path:
    return _plot_metrics(data, path, REMOVAL_SERIES, "% of scenes, 95% Wilson interval", "Distractor removal",
                         legend_below=True)


def _plot_paraphrase(data: dict, path: Path) -> Path:
    plt = _plt()
    conds = data["conditions"]
    series = {w: [{"value": c[w]["success"], "ci95": c[w]["ci95"]["success"]} if w in c else
                  {"value": np.nan, "ci95": [np.nan, np.nan]} for c in conds.values()] for w in WORDINGS}
    fig, ax = plt.subplots(figsize=(max(5.0, 1.8 * len(conds)), 3.6))
    _bars(ax, list(conds), series, "success (%), 95% Wilson interval")
    ax.set_title(f"Paraphrases: {data['policy'].get('spec', '')}")
    return _save(fig, path)


def _plot_appearance(data: dict, path: Path) -> Path:
    return _plot_outcomes(data, path, COLOUR_NAMES, ("no swap", "swap"))


def _plot_position(data: dict, path: Path) -> Path:
    return _plot_outcomes(data, path, PLACE_NAMES, ("original", "swapped"))


def _plot_switch(data: dict, path: Path) -> Path:
    """Follows new and stays with old against the switch step, one panel per condition; at step EPISODE_STEPS (no
    switch within the episode) the original play's values, whose "follows new" is an ordinary wrong grasp of B."""
    plt = _plt()
    conds = data["conditions"]
    fig, axes = plt.subplots(1, len(conds), figsize=(3.6 * max(len(conds), 1) + 0.4, 3.4), squeeze=False)
    styles = {"follows_new": ("tab:green", "follows new (B held)"),
              "stays_old": ("tab:orange", "stays with old (A held)"),
              "reaches_new": ("tab:green", "gripper ends at B"), "reaches_old": ("tab:orange", "gripper ends at A")}
    for ax, (key, cond) in zip(axes[0], conds.items()):
        steps = cond["by_step"]
        ks = [int(k) for k in steps]
        first = next(iter(steps.values()))
        for metric, (colour, label) in styles.items():
            if first[f"{metric}_switched"] is None:
                continue
            entries = [c[f"{metric}_switched"] for c in steps.values()] + [first[f"{metric}_original"]]
            v = np.array([e["value"] for e in entries], dtype=float) * 100
            ci = np.array([e["ci95"] for e in entries], dtype=float).reshape(-1, 2) * 100
            err = np.nan_to_num(np.abs(np.stack([v - ci[:, 0], ci[:, 1] - v])))
            dashed = metric.startswith("reaches")
            style = dict(color=colour, alpha=0.6 if dashed else 1.0, capsize=3)
            ax.errorbar(ks, v[:-1], yerr=None if dashed else err[:, :-1].tolist(), marker="o",
                        linestyle="--" if dashed else "-", label=label, **style)
            # (the original play, not joined to the switched ones: it is no switch step)
            ax.errorbar([EPISODE_STEPS], v[-1:], yerr=None if dashed else err[:, -1:].tolist(), marker="s", mfc="none",
                        linestyle="none", **style)
        ax.set_xticks([*ks, EPISODE_STEPS], [*map(str, ks), "none"], fontsize=7)
        ax.set_xlim(0, EPISODE_STEPS + 2)
        ax.set_ylim(-2, 105)
        ax.set_xlabel(f"switch at control step ({CONTROL_HZ} Hz)")
        ax.set_title(key, fontsize=8)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("% of scenes, 95% Wilson interval")
    # Below the panels: inside one, the legend covers the points it explains (bbox_inches="tight" keeps it).
    fig.legend(*axes[0][0].get_legend_handles_labels(), loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=2,
               fontsize=7, frameon=False)
    fig.suptitle(f"Instruction switch: {data['policy'].get('spec', '')}", fontsize=9)
    return _save(fig, path)


def _plot_outcomes(data: dict, path: Path, names: dict[str, str], plays: tuple[str, str]) -> Path:
    """Stacked shares of what is held, one bar per condition and play (without and with the swap)."""
    plt = _plt()
    conds = data["conditions"]
    fig, ax = plt.subplots(figsize=(6.5, max(2.4, 0.9 * len(conds) + 1.2)))
    labels, rows = [], []
    for key, c in conds.items():
        for variant, text in zip(("original", "swap"), plays):
            labels.append(f"{key}  {text}")
            rows.append([c[variant][o]["value"] for o in COLOUR_OUTCOMES])
    shares = np.nan_to_num(np.array(rows, dtype=float).reshape(-1, len(COLOUR_OUTCOMES))) * 100
    left = np.zeros(len(labels))
    colours = ("tab:green", "tab:orange", "tab:gray", "lightgray")
    for j, o in enumerate(COLOUR_OUTCOMES):
        ax.barh(range(len(labels)), shares[:, j], left=left, color=colours[j], label=names[o])
        left += shares[:, j]
    ax.set_yticks(range(len(labels)), labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("share of swapped scenes (%): what is held at the end")
    ax.legend(fontsize=7, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2)
    return _save(fig, path)


def _v(entry: dict) -> str:
    """A {value, ci95} entry's value for the terminal, "nan" where it is undefined."""
    return _num(entry["value"], ".2f")


def _swap_lines(key: str, c: dict) -> list[str]:
    return [f"{key}: scenes={c['scenes']} sensitivity={_v(c['instruction_sensitivity'])} "
            f"grounded_accuracy={_v(c['grounded_accuracy'])} nmi={_v(c['nmi'])} success={_v(c['success'])}"]


def _paraphrase_lines(key: str, c: dict) -> list[str]:
    return [f"{key}: success " + ", ".join(f"{w} {_num(c[w]['success'], '.2f')}" for w in WORDINGS if w in c)]


def _appearance_lines(key: str, c: dict) -> list[str]:
    return [f"{key}: swapped={c['swapped']} follows_shape={_v(c['follows_shape'])} "
            f"(no swap {_v(c['original']['instructed'])}) follows_colour={_v(c['follows_colour'])}"]


def _absent_lines(key: str, c: dict) -> list[str]:
    reach = "n/a" if c["shortcut_reach"] is None else _v(c["shortcut_reach"])
    return [f"{key}: scenes={c['scenes']} grasp present={_v(c['grasp_present'])} "
            f"absent={_v(c['grasp_absent'])} shortcut_reach={reach} same_grasp={_v(c['same_grasp'])}"]


def _position_lines(key: str, c: dict) -> list[str]:
    return [f"{key}: swapped={c['swapped']}/{c['scenes']} follows_object "
            f"{_v(c['follows_object_original'])} -> {_v(c['follows_object_swapped'])} "
            f"follows_place {_v(c['follows_place_original'])} -> {_v(c['follows_place_swapped'])}"]


def _removal_lines(key: str, c: dict) -> list[str]:
    return [f"{key}: scenes={c['scenes']} success {_v(c['success_original'])} -> alone "
            f"{_v(c['success_alone'])} distractor_failures={_v(c['distractor_failures'])} "
            f"failures_alone_too={_v(c['failures_alone_too'])}"]


def _switch_lines(key: str, c: dict) -> list[str]:
    return [f"{key} switch@{k}: scenes={e['scenes']} follows_new "
            f"{_v(e['follows_new_original'])} -> {_v(e['follows_new_switched'])} "
            f"stays_old {_v(e['stays_old_original'])} -> {_v(e['stays_old_switched'])}"
            for k, e in c["by_step"].items()]


def summary_lines(data: dict) -> list[str]:
    """One line per condition (and switch step) for the terminal, and one for the scenes it left out, if any."""
    lines, out = _view(data["probe"]).lines, left_out(data)
    return [line for key, c in data["conditions"].items() for line in lines(key, c)
            + ([f"{key}: {out[key]} scene{'s' * (out[key] > 1)} left out, {LEFT_OUT}"] if key in out else [])]


# ---------------------------------------------------------------------- the probes
@dataclass(frozen=True)
class ProbeView:
    """How the report shows one probe's probe.json (the probe itself: experiments/probes.py PROBES)."""

    explain: str
    """what it measures and how each metric reads (HTML)"""
    table: Callable[[dict], tuple[list[str], list[list[str]]]]
    """conditions -> (the table's head, its rows of HTML cells)"""
    lines: Callable[[str, dict], list[str]]
    """(condition key, its metrics) -> the terminal's lines"""
    plot: Callable[[dict, Path], Path]
    """(probe.json, path) -> the figure written there"""
    unit: str = ""
    """what the table's note adds after "In %, 95% intervals in brackets" (units)"""
    counts: tuple[str, str] | None = None
    """(the key of each condition's count table, its corner label), if it has one"""
    tables: Callable[[dict], list[tuple[str, dict]]] = lambda conds: list(conds.items())
    """conditions -> (label, metrics) per count table"""
    matrix_label: str | None = None
    """the rows' label of the confusion figure drawn beside the probe's own, if one is"""


POINTS = "; Δ in points"
VIEWS: dict[str, ProbeView] = {
    "instruction-swap": ProbeView(EXPLAIN["instruction-swap"], _swap_table, _swap_lines, _plot_swap,
                                  unit=" (NMI on [0, 1])", counts=("matrix", "instructed \\ held"),
                                  matrix_label="instructed"),
    "paraphrase": ProbeView(EXPLAIN["paraphrase"], _paraphrase_table, _paraphrase_lines, _plot_paraphrase),
    "appearance-swap": ProbeView(EXPLAIN["appearance-swap"], _appearance_table, _appearance_lines, _plot_appearance,
                                 counts=("transitions", "no swap \\ swap")),
    "absent-object": ProbeView(EXPLAIN["absent-object"], _absent_table, _absent_lines, _plot_absent, unit=POINTS,
                               counts=("matrix", "named (absent) \\ held"), matrix_label="named (not on the table)"),
    "position-swap": ProbeView(EXPLAIN["position-swap"], _position_table, _position_lines, _plot_position,
                               unit=POINTS, counts=("transitions", "held: original \\ swapped")),
    "instruction-switch": ProbeView(EXPLAIN["instruction-switch"], _switch_table, _switch_lines, _plot_switch,
                                    unit=POINTS, counts=("transitions", "held: original \\ switched"),
                                    tables=_switch_tables),
    "distractor-removal": ProbeView(EXPLAIN["distractor-removal"], _removal_table, _removal_lines, _plot_removal,
                                    unit=POINTS),
}
"""The probes the report can show, by name (each name of experiments/probes.py PROBES has one)."""


def _view(name: str) -> ProbeView:
    if name not in VIEWS:
        raise ValueError(f"the report does not know the probe {name!r}; allowed: {', '.join(VIEWS)}")
    return VIEWS[name]
