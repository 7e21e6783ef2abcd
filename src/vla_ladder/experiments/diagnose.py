"""`vla-ladder diagnose --policy SPEC [SPEC ...] --out DIR`: a policy (or several, side by side) through the ladder
and seven grounding probes, beside the reference policies on the same seeded scenes, and one page of answers.

The questions, each answered by one rate with its 95% interval (or, for the first and the sixth to the ninth, a
difference of two rates):

1. Does it hold up as the objects move? Success in the ladder's farthest regime minus success in the policy's own
   (the ladder of its training condition's split and object count; the same seeds in every regime, so a paired
   difference; no answer when its own regime is the farthest).
2. Does it read the instruction? The instruction swap's sensitivity: the share of scenes whose held object changes
   when another present object is named.
3. Does it follow the named object, or the place where it usually stands? The position swap: the share of swapped
   scenes in which the gripper ends at the named object, now standing in a distractor's place.
4. Told to grasp an object that is not there, does it go to that object's usual place? The absent object's
   shortcut reach.
5. Does it keep reading the instruction? The instruction switch at step 5 (0.25 s): the share of scenes in which
   the gripper ends at the object the instruction switched to.
6. Does it understand the instruction worded otherwise? The paraphrase probe: success with held-out wordings minus
   success with "grasp the <object>" on the same scenes (Newcombe's interval for paired rates).
7. Does it find the named object by its colour rather than its shape? The appearance swap (the named object and a
   distractor exchange colours): how much more often it grasps the object wearing the named object's colour in the
   swapped scenes than in the same scenes as they are.
8. Do the other objects cost it success? The distractor removal: success with every distractor taken off the
   table minus success as the scene is (Newcombe's interval for paired rates).
9. Far from its usual place, does it go to the named object or to that place? The ladder's episodes whose named
   object stood 10 cm or more from its place in the training condition: the share whose gripper ends at the place
   minus the share that reach the object (Newcombe's interval for paired rates; +1 the place, -1 the object; no
   answer for a policy trained in full random, where no place is usual). No probe: ordinary episodes.

Beside the answers, where it stops finding the object: every ladder's success against the named object's distance
from its place in the training condition (evaluation/displacement.py: rates per distance bin and the odds ratio per
10 cm), the curve between the ladder's rungs, for the policies and the references alike.

The reference policies answer the same questions on the same scenes (state only, so they cost little):
`scripted` reads its target from the state every step (grounded by construction), `committed` is the same expert
reading its target once, at the first step, `layout-prior` goes to where the named object stands in training (the
location shortcut), `nearest` grasps whatever is nearest and ignores the words.
"Resembles" names the reference whose answer is nearest the policy's: which known behaviour that answer is closest
to, not a claim that the policy works the same way. Several policies (checkpoints of two recipes, a model and its
blind twin) are played on the same scenes and answer in columns side by side, beside one set of references. Every
part is an ordinary run or probe directory (DIR/policy/... for one policy, DIR/policies/<label>/... for several,
DIR/references/<name>/...), so a rerun resumes and `vla-ladder compare`/`report` read them: `compare` pairs two
policies' episodes scene by scene.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated

import tyro

from vla_ladder import files
from vla_ladder.checks import ascii_digits, check_count, check_given, check_output_dir
from vla_ladder.conditions import REGIMES, Condition, ConditionGrid
from vla_ladder.evaluation.displacement import FAR_CM, by_displacement
from vla_ladder.evaluation.metrics import CONDITION_KEYS, condition_key
from vla_ladder.evaluation.rundir import Run, load_run
from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
from vla_ladder.experiments.probes import PROBES
from vla_ladder.experiments.probes import ProbeConfig, run_probe
from vla_ladder.policies import POLICY_KINDS, check_spec, parse_spec, reference_kinds
from vla_ladder.report.diagnosis import answer_lines, diagnosis_html
from vla_ladder.stats import paired_difference

REFERENCES = ("scripted", "committed", "layout-prior", "nearest")
"""The reference profiles: grounded and re-reading its target, grounded but reading it once, the location
shortcut, ignoring the instruction."""
ASKED = ("instruction-swap", "position-swap", "absent-object", "instruction-switch", "paraphrase", "appearance-swap",
         "distractor-removal")
"""The probes (names in experiments/probes.py's PROBES) whose results QUESTIONS read."""
SWITCH_STEP = 5
"""The instruction switch's step for question 5: before the scripted expert closes its gripper in every scene
measured (docs/probes.md), so a policy that re-reads its instruction can still turn."""
CONFIG_FILE = "diagnose_config.json"
NOT_THE_REQUEST = ("out", "workers", "num_envs", "overwrite", "references")
"""Fields that do not decide the policy's episodes: a reference added later is played into its own directory,
beside those already there."""


@dataclass
class DiagnoseConfig:
    """Diagnose a policy: the ladder and seven grounding probes on the same seeded scenes, beside the reference
    policies, with one page of answers (`vla-ladder diagnose --policy SPEC --out DIR`)."""

    policy: Annotated[tuple[str, ...], tyro.conf.arg(metavar="SPEC [SPEC ...]", help_behavior_hint="(required)")] = ()
    """policy spec, or several side by side: lerobot:DIR[?n_action_steps=H], remote:URL, ppo:PATH, scripted, committed,
    nearest, layout-prior, random, or a plugin's KIND[:ARG]"""
    out: Annotated[Path | None, tyro.conf.arg(metavar="DIR", help_behavior_hint="(required)")] = None
    """diagnosis directory: policy/ (policies/<label>/ for several), references/, diagnosis.json, report.html;
    rerunning the same request resumes in it"""
    labels: Annotated[tuple[str, ...], tyro.conf.arg(
        help_behavior_hint="(default: from each spec, e.g. a checkpoint's run directory)")] = ()
    """names of the policies on the page and of their directories, one per --policy (two or more)"""
    condition: str = "small_jitter/canonical/5"
    """the condition the policy was trained in (regime/split/objects): the probes play it (those that need two
    objects play two where it has one, absent-object four where it has five) and the ladder moves its objects
    through every regime"""
    episodes: int = 50
    """episodes per ladder regime"""
    probe_episodes: int = 50
    """scenes per probe"""
    references: Annotated[tuple[str, ...], tyro.conf.arg(help_behavior_hint=f"(default: {' '.join(REFERENCES)})")] \
        = REFERENCES
    """reference policies played on the same scenes, from scripted, committed, layout-prior, nearest, random (none: no
    comparison, and no "resembles")"""
    first_seed: int = 0
    """episode j of every condition and probe plays seed first_seed + j"""
    videos: int = 2
    """write MP4s of both cameras for the policy's first K episodes of each ladder regime and probe variant (the
    references are never filmed)"""
    workers: int = 0
    """worker processes playing episodes on the CPU backend, each with its own copy of the policy (0: one per
    core, capped by memory); any number gives the same episodes"""
    num_envs: int = 1
    """episodes one copy of the policy acts on at once (batched inference; see `vla-ladder eval --num-envs`)"""
    overwrite: bool = False
    """replace a diagnosis directory that holds another request (the same request is always resumed)"""

    def __post_init__(self):
        self.policy = (self.policy,) if isinstance(self.policy, str) else tuple(self.policy or ())
        check_given(("--policy SPEC", self.policy, "SPEC: e.g. lerobot:runs/smolvla/checkpoints/last/pretrained_model; "
                     "several side by side: --policy SPEC SPEC ..."),
                    ("--out DIR", self.out, "DIR: the diagnosis directory to write"))
        self.out = check_output_dir(self.out, "--out")  # a file, the root: now
        for name in ("episodes", "probe_episodes"):  # named here: the probes' own check said --episodes
            check_count(getattr(self, name), f"--{name.replace('_', '-')}")
        if len(set(self.policy)) != len(self.policy):
            raise ValueError(f"--policy names a policy twice: {' '.join(self.policy)}")
        for spec in self.policy:
            check_spec(spec)
        if self.labels and len(self.policy) == 1:  # one policy's directory is policy/ and its name its spec
            raise ValueError("--labels names the directories of two or more --policy; one policy needs none")
        self.labels = tuple(self.labels) or tuple(default_label(spec) for spec in self.policy)
        if len(self.labels) != len(self.policy) or len(set(self.labels)) != len(self.labels) or any(
                not _LABEL.fullmatch(label) or label in ("policy", "references") for label in self.labels):
            raise ValueError(f"--labels must give {len(self.policy)} distinct names of letters, digits, '.', '_' or "
                             f"'-' (one per --policy); got {' '.join(self.labels) or 'none'}")
        self.condition = Condition.parse(self.condition).key
        allowed = reference_kinds()
        if any(r not in allowed for r in self.references) or len(set(self.references)) != len(self.references):
            raise ValueError(f"--references must be distinct names (allowed: {', '.join(allowed)}); got "
                             f"{' '.join(self.references) or 'none'}")
        self.references = tuple(self.references)
        self.plan()  # every run is configured, and so checked, before any simulator starts

    def roots(self) -> dict[str, Path]:
        """label -> the directory of that policy's runs: DIR/policy for one policy (as ever), DIR/policies/<label>."""
        if len(self.policy) == 1:
            return {self.labels[0]: self.out / "policy"}
        return {label: self.out / "policies" / label for label in self.labels}

    def plan(self) -> list[tuple[str, EvalConfig, dict[str, ProbeConfig]]]:
        """(who, the ladder, the probes) for each policy, then for each reference."""
        mine = zip(self.policy, self.roots().values())
        return [*(self._runs("policy", spec, root, self.videos) for spec, root in mine),
                *(self._runs(r, r, self.out / "references" / r, 0) for r in self.references)]

    def _runs(self, who: str, spec: str, root: Path, videos: int) -> tuple[str, EvalConfig, dict[str, ProbeConfig]]:
        cond = Condition.parse(self.condition)
        players = dict(workers=self.workers, num_envs=self.num_envs) if who == "policy" else dict(workers=self.workers)
        ladder = EvalConfig(policy=spec, out=root / "ladder", episodes=self.episodes, first_seed=self.first_seed,
                            grid=ConditionGrid(("all",), (cond.split,), (cond.num_objects,)), videos=videos,
                            overwrite=self.overwrite, **players)
        probes = {}
        for name in ASKED:
            # The object count nearest the policy's that the probe can play, as a study does: absent-object needs an
            # object off the table (five-object policies are probed with four), the swaps, the switch and the
            # removal a second object (one-object policies are probed with two: a choice they never had in training)
            n = PROBES[name].fit(cond.num_objects)
            # the appearance swap paints each scene's objects: one env per scene, in worker processes
            plays = dict(workers=self.workers) if PROBES[name].one_env else players
            probes[name] = ProbeConfig(name, policy=spec, out=root / "probes" / name,
                                       grid=ConditionGrid((cond.regime,), (cond.split,), (n,)),
                                       episodes=self.probe_episodes, first_seed=self.first_seed, videos=videos,
                                       overwrite=self.overwrite, report=False, **plays)
        return who, ladder, probes

    def request(self) -> dict:
        out = {k: v for k, v in files.plain(asdict(self)).items()
               if k not in NOT_THE_REQUEST}
        if len(self.policy) == 1:  # as a one-policy diagnosis always wrote it: those directories still resume
            out["policy"] = self.policy[0]
            del out["labels"]
        return out


_LABEL = re.compile(r"[A-Za-z0-9._-]+")


def default_label(spec: str) -> str:
    """A policy's name on the page: the kind for a reference, a checkpoint's run directory (the path without
    checkpoints/<step>/pretrained_model), a server's host:port; a plugin's kind before that."""
    kind, arg = parse_spec(spec)
    if arg is None:
        return kind
    parts = [p for p in re.split(r"[/\\]+", arg.partition("?")[0])
             if p and p not in ("pretrained_model", "checkpoints", "last", "ws:", "wss:") and not ascii_digits(p)]
    label = re.sub(r"[^A-Za-z0-9._-]", "_", parts[-1]) if parts else kind
    return label if kind in POLICY_KINDS or label == kind else f"{kind}-{label}"


def open_diagnosis_dir(cfg: DiagnoseConfig) -> None:
    """Resume the same request, refuse another unless --overwrite (then start afresh)."""
    saved = cfg.out / CONFIG_FILE
    previous = ({k: v for k, v in json.loads(saved.read_text()).items() if k not in NOT_THE_REQUEST}
                if saved.is_file() else None)
    files.claim_dir(cfg.out, previous, cfg.request(), cfg.overwrite, "diagnosis", "a diagnosis directory")
    files.write_json(saved, cfg.request())


# ---------------------------------------------------------------------- the answers
def _rate(entry: dict | None) -> dict | None:
    """A probe.json metric as an answer; an undefined value (null in the file: a rate over no scenes) is NaN."""
    return None if entry is None else {"value": files.number(entry["value"]),
                                       "ci95": [files.number(x) for x in entry["ci95"]], "n": entry.get("n")}


def ladder_drop(run: Run, condition: str) -> dict | None:
    """Success in the ladder's farthest regime minus success in `condition`'s own, with Newcombe's interval for
    paired rates: episode j plays seed first_seed + j, with the same instructed object, in every regime, so the two
    regimes' episodes pair by index. None when `condition` is itself the farthest regime played."""
    conditions = run.summary["conditions"]
    far_key = max(conditions, key=lambda k: list(REGIMES).index(Condition.parse(k).regime))  # the farthest there
    if far_key == condition:
        return None
    keyed = run.episodes.assign(key=[condition_key(*k) for k in run.episodes[list(CONDITION_KEYS)].itertuples(
        index=False)])
    pairs = keyed[keyed["key"] == condition].merge(keyed[keyed["key"] == far_key], on="episode", suffixes=("", "_far"))
    x, y = pairs["success"].astype(bool).to_numpy(), pairs["success_far"].astype(bool).to_numpy()
    lo, hi = paired_difference(x, y)
    return {"value": float(y.mean() - x.mean()), "ci95": [lo, hi], "n": int(len(pairs)),
            "method": "newcombe paired score", "from": condition, "to": far_key, "success_from": float(x.mean()),
            "success_to": float(y.mean())}


QUESTIONS = (
    ("holds_up", "Does it hold up as the objects move?",
     "success in the ladder's farthest regime minus its own (points)"),
    ("reads", "Does it read the instruction?",
     "instruction swap: scenes whose held object changes with the named object"),
    ("follows_object", "Does it follow the named object, or its usual place?",
     "position swap: gripper ends at the named object after it exchanged places with a distractor"),
    ("empty_place", "Named an object that is not there, does it go to that object's usual place?",
     "absent object: gripper ends at the named object's (empty) usual place"),
    ("keeps_reading", f"Does it keep reading the instruction? (switched at step {SWITCH_STEP}, 0.25 s)",
     "instruction switch: gripper ends at the object the instruction switched to"),
    ("reworded", "Does it understand the instruction worded otherwise?",
     "paraphrase: success with held-out wordings minus with \"grasp the <object>\" (points)"),
    ("by_colour", "Does it find the named object by its colour rather than its shape?",
     "appearance swap: grasps of the object that wears the named object's colour, swapped minus as the scene is "
     "(points)"),
    ("distracted", "Do the other objects cost it success?",
     "distractor removal: success with the distractors taken off the table minus as the scene is (points)"),
    ("goes_to_place", "Far from its usual place, does it go to the named object or to that place?",
     f"ladder episodes whose named object stood {FAR_CM:g} cm or more from its usual place: gripper ends at the "
     "place minus gripper reaches the object (points)"),
)
# Wording cannot change what the references do (scripted, committed and nearest read their target from the state or
# not at all; layout-prior parses every shipped wording): on "reworded" they all answer 0 and none is nearer than
# another (resembles then names none). Nor can colour (none sees it): "by_colour" is the change the swap makes, 0
# for them all, where the level counted a colour-blind policy's grasps of the partner as following the colour.


def answers(root: Path, condition: str) -> tuple[dict[str, dict | None], dict | None]:
    """The answers (one per QUESTIONS) of the runs under `root` (policy/ or references/<name>/), and its ladder's
    metrics against the named object's distance from its place in `condition` (evaluation/displacement.py; None
    for a policy trained in full random, where no place is usual)."""
    ladder = load_run(root / "ladder")
    curve = by_displacement(ladder.episodes, condition)

    def probe(name: str) -> dict:
        played = json.loads((root / "probes" / name / "probe.json").read_text())["conditions"]
        # the policy's own condition (the paraphrase probe adds a one-object control; absent-object plays four)
        return played.get(condition) or next(iter(played.values()))

    switch = probe("instruction-switch")["by_step"][str(SWITCH_STEP)]
    return {"holds_up": ladder_drop(ladder, condition),
            "reads": _rate(probe("instruction-swap")["instruction_sensitivity"]),
            "follows_object": _rate(probe("position-swap")["reaches_object_swapped"]),
            "empty_place": _rate(probe("absent-object")["shortcut_reach"]),
            "keeps_reading": _rate(switch["reaches_new_switched"]),
            "reworded": _rate(probe("paraphrase")["paraphrase-heldout"]["vs_canonical"]["success"]),
            "by_colour": _rate(probe("appearance-swap")["colour_change"]),
            "distracted": _rate(probe("distractor-removal")["success_change"]),
            "goes_to_place": None if curve is None else _rate(curve["far"]["place_minus_object"])}, curve


def diagnosis(cfg: DiagnoseConfig) -> dict:
    """The answers of every policy and reference. Each question's "answers" maps a policy's label to its answer and
    the reference(s) it resembles; a one-policy diagnosis also keeps "policy" and "resembles" at the top of each
    question, as it always wrote them."""
    # Kept apart by kind: a policy may be labelled like a reference (`--policy nearest` beside `nearest`).
    played = {label: answers(root, cfg.condition) for label, root in cfg.roots().items()}
    played_refs = {r: answers(cfg.out / "references" / r, cfg.condition) for r in cfg.references}
    mine, curves = {label: a for label, (a, _) in played.items()}, {label: c for label, (_, c) in played.items()}
    refs, ref_curves = {r: a for r, (a, _) in played_refs.items()}, {r: c for r, (_, c) in played_refs.items()}
    rows = []
    for key, question, measure in QUESTIONS:
        theirs = {r: (None if a[key] is None else a[key]["value"]) for r, a in refs.items()}
        per_policy = {label: {"answer": a[key], "resembles": _resembles(a[key], theirs)} for label, a in mine.items()}
        row = {"id": key, "question": question, "measure": measure, "answers": per_policy, "references": theirs}
        if len(per_policy) == 1:
            (only,) = per_policy.values()
            row.update(policy=only["answer"], resembles=only["resembles"])
        rows.append(row)
    return {"policy": cfg.policy[0] if len(cfg.policy) == 1 else list(cfg.policy),
            "policies": dict(zip(cfg.labels, cfg.policy)), "condition": cfg.condition, "episodes": cfg.episodes,
            "probe_episodes": cfg.probe_episodes, "first_seed": cfg.first_seed, "references": list(cfg.references),
            "questions": rows, "provenance": files.provenance(),
            "displacement": None if any(c is None for c in [*curves.values(), *ref_curves.values()]) else {
                "trained_in": cfg.condition, "policies": curves, "references": ref_curves}}


def _resembles(answer: dict | None, theirs: dict[str, float | None]) -> str | None:
    """Every reference at the nearest distance (scripted and layout-prior both read the words, for one); with fewer
    than two references, or all at the same distance, there is nothing to choose between."""
    known = {r: abs(v - answer["value"]) for r, v in theirs.items() if v is not None and answer is not None}
    known = {r: d for r, d in known.items() if not math.isnan(d)}  # (an answer or reference without plays)
    if len(known) < 2 or max(known.values()) - min(known.values()) < 1e-9:
        return None  # no reference is nearer than another
    return " / ".join(r for r, d in known.items() if d <= min(known.values()) + 1e-9)


def run_diagnosis(cfg: DiagnoseConfig, progress: bool = True) -> dict:
    open_diagnosis_dir(cfg)
    plan = cfg.plan()
    for who, ladder, probes in plan:
        print(f"[diagnose] {who}: the ladder -> {ladder.out}", flush=True)
        run_evaluation(ladder, progress=progress)
        for name, probe in probes.items():
            print(f"[diagnose] {who}: {name} -> {probe.out}", flush=True)
            run_probe(probe, progress=progress)
    data = diagnosis(cfg)
    files.write_json(cfg.out / "diagnosis.json", data)
    from vla_ladder.report.html import build_report
    ladders = [load_run(lad.out) for _, lad, _ in plan]
    variants = [load_run(p.out / v) for who, _, probes in plan if who == "policy"
                for p in probes.values() for v in p.variants()]
    named = cfg.policy if len(cfg.policy) == 1 else cfg.labels
    labels = [*named, *(f"{r} (reference)" for r in cfg.references)]
    disp = data["displacement"]
    curves = None if disp is None else (cfg.condition, dict(zip(labels, [*disp["policies"].values(),
                                                                          *disp["references"].values()])))
    build_report(ladders, cfg.out / "report.html", title=f"vla-ladder diagnose: {', '.join(named)}", labels=labels,
                 sections=[("Diagnosis", diagnosis_html(data))], probe_runs=variants, displacement=curves)
    return data


def run(cfg: DiagnoseConfig) -> int:
    data = run_diagnosis(cfg)
    for line in answer_lines(data):
        print(line)
    print((cfg.out / "report.html").resolve())
    return 0
