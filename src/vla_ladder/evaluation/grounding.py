"""Grounding metrics of the probes: the same scenes played under changed instructions, wordings or colours.

Each probe plays the same seeded scenes in several variants (experiments/probes.py); these functions take the
variants' episodes (episodes.parquet rows) and say, with 95% intervals, how much the grasped object depends
on what the instruction says:

- instruction swap: per scene, which object is held under each instruction. Instruction sensitivity (the held
  object is not the same under all instructions) and scene accuracy (the instructed object is held under every
  instruction) are scene-level proportions: Wilson intervals. Grounded accuracy P(held = instructed | something
  held) and success over all plays pool correlated plays of a scene: Wilson on their design-effect sample size
  (pooled_rate). The normalised mutual information I(instructed; held | objects) / H(instructed | objects): the
  jackknife over scenes, bias-corrected, with its normal interval (the plug-in estimate is biased up, and a
  bootstrap over scenes adds to that bias), beside the plug-in's permutation null and p (nmi_null).
- paraphrases and appearance swaps: rates of each variant on the same scenes (Wilson), their paired difference
  (Newcombe's paired interval, stats.paired_difference) and McNemar's exact test.
- absent object: the same scenes instructing an object that is not on the table. The grasp rate (something held)
  and the share of plays whose gripper ends at the named object's usual place (shortcut reach), pooled over a
  scene's absent plays (Wilson on their design-effect sample size), next to the scene's ordinary play (Wilson);
  the named x held matrix.
- position swap: the same scenes with the instructed object and one distractor (its partner) exchanging places.
  What is held in each play (instructed, partner, other, none) over the scenes that had a swap: shares (Wilson),
  follows-object and follows-place in both plays and their paired changes (Newcombe's paired interval, McNemar's
  exact p), the transition table original -> swapped.
- instruction switch: the same scenes with the instruction switching mid-episode, at control step K, from the
  instructed object A to a distractor B. What is held at the end (B: follows the new instruction, A: stays with
  the old one, another, none) and where the gripper ends, per K, next to the unswitched play: shares (Wilson),
  paired changes (Newcombe's paired interval, McNemar's exact p), the transition table original -> switched.
- distractor removal: the same scenes with every distractor taken off the table. Success in both plays (Wilson)
  and its paired change (Newcombe, McNemar), and the original play's failures split into those that succeed alone
  and those that fail alone too.

An object "held" is the one grasped at the final step ("none" when nothing is), as for success. Every probe pairs
its variants' plays of a scene (condition and episode index: seed first_seed + j in every variant) in one place,
common_scenes: it scores the scenes every variant played and counts, per condition, those it left out (`left_out`).
"""

from __future__ import annotations

import json
from statistics import NormalDist
from typing import Callable, Iterable

import numpy as np
import pandas as pd

from vla_ladder.conditions import MAX_OBJECTS, Condition
from vla_ladder.contract import METRICS, REACH_THRESHOLD
from vla_ladder.evaluation.compare import mcnemar_exact
from vla_ladder.evaluation.metrics import CONDITION_KEYS, HELD_COLUMNS, NONE, condition_key, confusion
from vla_ladder.stats import CONFIDENCE, difference_interval, paired_difference, rates, wilson
from vla_ladder.task.instructions import CANONICAL, NOVELTIES, parse_instruction
from vla_ladder.task.layouts import REGION_CENTERS, usual_regions
from vla_ladder.task.objects import OBJECT_NAMES, OBJECTS, object_index

RESAMPLES = 2000
PERMUTATION_SEED = 0
NMI_METHOD = "jackknife over scenes, bias-corrected"
COLOUR_OUTCOMES = ("instructed", "partner", "other", "none")
"""What is held under an appearance swap: the instructed object (follows its shape and the words), the
partner that wears the instructed object's usual colour (follows colour), another object, nothing."""
PLACE_OUTCOMES = COLOUR_OUTCOMES
"""What is held in a position-swap scene, by the same rule (held_outcome): the instructed object (follows the
object), its partner, which in the swapped play stands where the instructed object stood (follows the place),
another object, nothing."""


def _interval(value: float, lo: float, hi: float, method: str, n: int) -> dict:
    return {"value": value, "ci95": [lo, hi], "method": method, "n": n}


def wilson_rate(k: int, n: int) -> dict:
    lo, hi = wilson(k, n)
    return _interval(k / n if n else float("nan"), lo, hi, "wilson", n)


def jackknife(stat: Callable[[np.ndarray], np.ndarray], clusters: int) -> tuple[float, float, float]:
    """(bias-corrected value, lo, hi) of `stat` by the jackknife over `clusters` scenes: each left out once, the
    bias removed (n·full - (n-1)·mean of the leave-one-out values) and a normal interval from the jackknife standard
    error, both clipped to [0, 1] (`stat` is a share). `stat` takes a (k, m) index array and returns k values. Fewer
    than two scenes, or a leave-one-out value that is undefined: the plain value and no interval."""
    full = float(np.asarray(stat(np.arange(clusters)[None]), dtype=float)[0]) if clusters else float("nan")
    if clusters < 2:
        return full, float("nan"), float("nan")
    keep = ~np.eye(clusters, dtype=bool)
    left_out = np.asarray(stat(np.broadcast_to(np.arange(clusters), keep.shape)[keep].reshape(clusters, -1)), float)
    if not np.isfinite(left_out).all() or not np.isfinite(full):
        return full, float("nan"), float("nan")
    mean = left_out.mean()
    value = clusters * full - (clusters - 1) * mean
    se = float(np.sqrt((clusters - 1) / clusters * ((left_out - mean) ** 2).sum()))
    z = NormalDist().inv_cdf(1 - (1 - CONFIDENCE) / 2)
    return float(np.clip(value, 0, 1)), float(np.clip(value - z * se, 0, 1)), float(np.clip(value + z * se, 0, 1))


def _nmi_interval(value: float, lo: float, hi: float, n: int) -> dict:
    """The NMI's entry: the jackknife's, or, where it gave no interval (fewer than two scenes, an undefined
    leave-one-out value), the plug-in value named as such."""
    return _interval(value, lo, hi, NMI_METHOD if np.isfinite(lo) else "plug-in (no jackknife: too few scenes or an "
                     "undefined leave-one-out value)", n)


def pooled_rate(num: np.ndarray, den: np.ndarray) -> dict:
    """sum(num) / sum(den) over scenes (num[i] of den[i] correlated plays of scene i), with the Wilson interval of its
    effective number of plays: sum(den) divided by the design effect, the ratio of the rate's variance between scenes
    (linearised, with n / (n - 1)) to its variance were every play independent, kept between the number of scenes (a
    scene decides all its plays) and the number of plays (they are independent). Where every play counts (or none does),
    or only one scene has plays, there is no variance to measure, and each contributing scene counts as one trial (49 of
    49 grasps in 19 scenes: [83, 100]). With one play a scene this is the Wilson interval of the plays. Measured
    coverage of the nominal 95% on beta-binomial scenes (10 to 50 scenes of 2 to 5 plays, rates 0.1 to 0.95,
    intra-scene correlation 0.05 to 0.8; benchmarks/pooled_rate_coverage.py): 90-98%, the lowest at rates near 0.1 and
    0.95 with correlated plays; a percentile bootstrap over scenes gave 89-93% at 10-20 scenes (docs/probes.md)."""
    num, den = np.asarray(num, dtype=float), np.asarray(den, dtype=float)
    k, total = float(num.sum()), float(den.sum())
    if not total:
        return _interval(float("nan"), float("nan"), float("nan"), "wilson, design effect over scenes", 0)
    rate, scenes = k / total, int((den > 0).sum())
    if k in (0.0, total):
        lo, hi = wilson(scenes if k else 0, scenes)
        return _interval(rate, lo, hi, "wilson over scenes (every play alike)", int(total))
    if scenes < 2:
        # One scene's residual is 0 by construction: no variance between scenes can be measured, and its plays count
        # as one trial, as where every play counts (2 of 5 must not come out narrower than 5 of 5).
        return _interval(rate, *wilson(rate, 1), "wilson over scenes (one scene)", int(total))
    n = len(num)
    between = n / (n - 1) * float(((num - rate * den) ** 2).sum()) / total ** 2
    independent = rate * (1 - rate) / total
    effective = total if between <= 0 else total * min(1.0, independent / between)
    effective = min(max(effective, float(scenes)), total)
    return _interval(rate, *wilson(rate * effective, effective), "wilson, design effect over scenes", int(total))


def normalised_mutual_information(joint: np.ndarray) -> np.ndarray:
    """I(X; Y | S) / H(X | S) of count tables (..., s, x, y): X the instructed object, Y the held one, S which
    objects are on the table (a stratum of scenes). The share of the instruction's entropy that the held object
    carries: 0 when the held object does not depend on the instruction (within each set of objects), 1 when it
    determines it. Conditioning on S keeps "both are among the objects present" from counting as information
    when fewer than five objects are on the table (with five there is one stratum and this is I(X; Y) / H(X))."""
    joint = np.asarray(joint, dtype=float)
    total = joint.sum(axis=(-3, -2, -1), keepdims=True)
    p = np.divide(joint, total, out=np.zeros_like(joint), where=total > 0)  # p(s, x, y)
    ps = p.sum(axis=(-2, -1), keepdims=True)
    psx, psy = p.sum(-1, keepdims=True), p.sum(-2, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        mi = np.where(p > 0, p * np.log(p * ps / (psx * psy)), 0.0).sum(axis=(-3, -2, -1))
        hx = np.where(psx > 0, -psx * np.log(psx / ps), 0.0).sum(axis=(-3, -2, -1))
    # (clipped: float sums of an exactly independent table can land a hair below 0)
    return np.where(hx > 0, np.clip(mi / np.where(hx > 0, hx, 1.0), 0.0, 1.0), np.nan)


def nmi_null(instructed: np.ndarray, held: np.ndarray, stratum: np.ndarray, outcomes: int,
             resamples: int = RESAMPLES, seed: int = PERMUTATION_SEED) -> np.ndarray:
    """The NMI of `resamples` tables where, within each scene, what was held is shuffled among the scene's plays: what
    the estimate gives when the held object does not depend on the instruction. The plug-in estimate is biased upwards,
    so that is not 0 (about 0.07 for 20 scenes of five plays holding one of the five objects or none, uniformly at
    random); the permutation p-value is the share of shuffles at least as high as the observed NMI. instructed, held:
    (scenes, plays) row and column indices of the count tables; stratum: each scene's set of objects."""
    n, plays = instructed.shape
    if n == 0:
        return np.zeros(0)
    rng = np.random.default_rng(seed)
    order = np.argsort(rng.random((resamples, n, plays)), axis=-1)
    shuffled = np.take_along_axis(np.broadcast_to(held, (resamples, n, plays)), order, axis=-1)
    strata, rows = int(stratum.max()) + 1, len(OBJECT_NAMES)
    cell = ((np.arange(resamples)[:, None, None] * strata + stratum[None, :, None]) * rows
            + instructed[None]) * outcomes + shuffled
    counts = np.bincount(cell.ravel(), minlength=resamples * strata * rows * outcomes)
    return normalised_mutual_information(counts.reshape(resamples, strata, rows, outcomes))


def _by_condition(df: pd.DataFrame):
    for key, g in df.groupby(list(CONDITION_KEYS), sort=False):
        yield condition_key(*key), g


def _conditions(df: pd.DataFrame, left_out: dict[str, int]):
    """(condition key, its rows of df) for every condition of common_scenes' `left_out`, in its order: one whose
    scenes were all left out is scored over none (undefined rates) rather than missing from the results."""
    groups = dict(_by_condition(df))
    for key in left_out:
        yield key, groups.get(key, df.iloc[:0])


# ---------------------------------------------------------------------- pairing the variants' plays
SCENE_KEYS = (*CONDITION_KEYS, "episode")
"""What makes a scene: its condition and its index j there, which every variant plays with seed first_seed + j."""


def common_scenes(variants: dict, plays_in: Callable[[Condition], Iterable] | None = None
                  ) -> tuple[dict[object, pd.DataFrame], dict[str, int]]:
    """The one place every probe pairs its variants' plays (episodes.parquet rows): each variant's plays of the
    scenes that every variant playing their condition played (`plays_in(condition)` names those variants, all of
    them by default), and per condition, in the order the plays first name them, how many of the scenes played
    are left out because some variant lacks them (a variant cut short: the probe command, run again, plays them).
    Those are counted, for probe.json and the report to say, never dropped without a word. Plays that are not of
    the same scenes are a ValueError, not a scene left out: a scene played with different seeds in two variants,
    or a condition played with both object sets (one_object_set)."""
    names = list(variants)
    plays = pd.concat([df[list(SCENE_KEYS) + ["seed", *(["object_set"] if "object_set" in df else [])]]
                       .assign(_variant=i) for i, df in enumerate(variants.values())], ignore_index=True)
    seeds = plays.groupby(list(SCENE_KEYS), sort=False)["seed"].nunique()
    if (seeds > 1).any():
        regime, split, k, j = seeds[seeds > 1].index[0]
        raise ValueError(f"the variants played different seeds on {int((seeds > 1).sum())} of {len(seeds)} scenes "
                         f"(e.g. {condition_key(regime, split, k)} episode {j}); a probe compares the same scenes")
    left_out, kept = {}, []
    for key, g in plays.groupby(list(CONDITION_KEYS), sort=False):
        one_object_set(g)
        wanted = {names.index(v) if v in names else None for v in (plays_in(Condition(*key)) if plays_in else names)}
        played = g.groupby("episode")["_variant"].apply(frozenset)
        whole = [j for j, got in played.items() if got == wanted]
        left_out[condition_key(*key)] = len(played) - len(whole)
        kept += [(*key, j) for j in whole]
    kept = pd.MultiIndex.from_tuples(kept, names=list(SCENE_KEYS))
    return {name: df[pd.MultiIndex.from_frame(df[list(SCENE_KEYS)]).isin(kept)] for name, df in variants.items()}, \
        left_out


# ---------------------------------------------------------------------- instruction swap
def instruction_swap(plays: pd.DataFrame, resamples: int = RESAMPLES) -> dict:
    """Per condition: the instruction-swap metrics of plays (episodes.parquet rows with an `instruct` column,
    the rank of the instructed object; `target` is the instructed object), over the scenes played under every
    instruction (common_scenes: the others are counted in `left_out`)."""
    kept, left_out = common_scenes(dict(iter(plays.groupby("instruct"))), lambda c: range(c.num_objects))
    per_scene = plays.groupby([*SCENE_KEYS])["target"].agg(["nunique", "size"])  # each object instructed once
    if (per_scene["nunique"] != per_scene["size"]).any():
        raise ValueError("the variants instructed an object twice in a scene; a probe compares the same scenes")
    out = {}
    for key, full in _conditions(pd.concat(kept.values()) if kept else plays, left_out):
        ranks = Condition.parse(key).num_objects
        scenes = [s.sort_values("instruct") for _, s in full.groupby("episode", sort=True)]
        n = len(scenes)
        held = [s["held"].tolist() for s in scenes]
        sensitive = sum(len(set(h)) > 1 for h in held)
        accurate = sum(all(h == t for h, t in zip(s["held"], s["target"])) for s in scenes)
        # Per-scene tables: the jackknife and the permutations build tables of scenes by summing theirs.
        rows, cols = list(OBJECT_NAMES), list(HELD_COLUMNS)
        tables = np.zeros((n, len(rows), len(cols)))
        for i, s in enumerate(scenes):
            for t, h in zip(s["target"], s["held"]):
                tables[i, rows.index(t), cols.index(h)] += 1
        objects = tables[..., :len(rows)]  # the "none" column left out
        diag, grasped = np.trace(objects, axis1=-2, axis2=-1), objects.sum(axis=(-2, -1))
        success = np.array([s["success"].astype(bool).sum() for s in scenes], dtype=float)

        plays_per_scene = np.full(n, float(ranks))
        # Scenes grouped by their set of objects (the strata S of the conditional mutual information).
        sets = [frozenset(s["target"]) for s in scenes]
        stratum = np.array([list(dict.fromkeys(sets)).index(x) for x in sets], dtype=int)
        onehot = np.eye(max(len(set(sets)), 1))[stratum] if n else np.zeros((0, 1))

        def nmi(idx):
            return normalised_mutual_information(np.einsum("bns,bnxy->bsxy", onehot[idx], tables[idx]))

        nmi_value = float(nmi(np.arange(n)[None])[0]) if n else float("nan")
        null = nmi_null(np.array([[rows.index(t) for t in s["target"]] for s in scenes], dtype=int).reshape(n, ranks),
                        np.array([[cols.index(h) for h in s["held"]] for s in scenes], dtype=int).reshape(n, ranks),
                        stratum, len(cols), resamples)
        out[key] = {
            "scenes": n, "plays": int(n * ranks), "left_out": left_out[key],
            "instruction_sensitivity": wilson_rate(sensitive, n),
            "scene_accuracy": wilson_rate(accurate, n),
            "grounded_accuracy": pooled_rate(diag, grasped),
            "nmi": {**_nmi_interval(*jackknife(nmi, n), int(n * ranks)), "plug_in": nmi_value,
                    "null_mean": float(null.mean()) if n else float("nan"),
                    "permutation_p": float((1 + (null >= nmi_value - 1e-12).sum()) / (1 + len(null))) if n
                    else float("nan")},
            "success": pooled_rate(success, plays_per_scene),
            "matrix": _matrix(confusion(full)),
            "by_rank": {str(r): rates(gr) for r, gr in full.groupby("instruct")},
        }
    return out


def _matrix(table: pd.DataFrame) -> dict:
    return {"rows": list(table.index), "columns": list(table.columns), "counts": table.values.tolist()}


# ---------------------------------------------------------------------- paired variants
def paired_change(x: np.ndarray, y: np.ndarray) -> dict:
    """y - x of paired per-scene outcomes (bool arrays): its mean, Newcombe's paired score interval
    (stats.paired_difference) and McNemar's exact p; over no scenes all three are undefined (NaN), where the p of
    no discordant pairs would say 1, as if the scenes had been played alike."""
    d = y.astype(float) - x.astype(float)
    return {"value": float(d.mean()) if len(d) else float("nan"), "ci95": list(paired_difference(x, y)),
            "method": "newcombe paired score", "n": int(len(d)),
            "mcnemar_p": mcnemar_exact(int((x & ~y).sum()), int((~x & y).sum())) if len(d) else float("nan")}


def transitions(before: list[str], after: list[str], outcomes: tuple[str, ...]) -> dict:
    """Counts of what is held in one play (rows) against the other (columns), every outcome shown."""
    counts = np.zeros((len(outcomes), len(outcomes)), dtype=int)
    for a, b in zip(before, after):
        counts[outcomes.index(a), outcomes.index(b)] += 1
    return {"rows": list(outcomes), "columns": list(outcomes), "counts": counts.tolist()}


def same_scenes(a: pd.DataFrame, b: pd.DataFrame, suffixes: tuple[str, str], same_target: bool = False
                ) -> tuple[pd.DataFrame, dict[str, int]]:
    """Two variants' plays of the scenes both played, side by side (columns suffixed `suffixes`), and per condition
    the scenes left out (common_scenes); ValueError when they played different seeds (or, `same_target`, named
    different targets)."""
    kept, left_out = common_scenes({0: a, 1: b})
    merged = kept[0].merge(kept[1], on=list(SCENE_KEYS), suffixes=suffixes)
    first, second = suffixes
    if same_target and (merged[f"target{first}"] != merged[f"target{second}"]).any():
        raise ValueError("the variants instructed different objects in the same scene; a probe compares the same "
                         "scenes")
    return merged, left_out


DIFFERENT_OBJECT_SETS = ("the variants played different object sets (ycb and standin: resumed on another machine?); "
                         "a probe compares the same scenes")


def one_object_set(*plays: pd.DataFrame) -> None:
    """ValueError when the plays (of one condition, from several variants) hold both object sets (common_scenes
    checks it for every probe): a resume on another machine (object_set auto) can play a variant with the other
    set."""
    sets = {s for p in plays if "object_set" in p for s in p["object_set"].dropna()}  # (older runs: none kept)
    if len(sets) > 1:
        raise ValueError(DIFFERENT_OBJECT_SETS)


def paired(a: pd.DataFrame, b: pd.DataFrame, metrics=METRICS) -> dict:
    """Per condition: per metric the paired difference b - a with Newcombe's paired interval over the scenes both
    played (same_scenes) and McNemar's exact p-value. Episodes pair on condition and episode index."""
    merged, left_out = same_scenes(a, b, ("_a", "_b"))
    out = {}
    for key, g in _conditions(merged, left_out):
        diffs = {}
        for m in metrics:
            diffs[m] = paired_change(g[f"{m}_a"].astype(bool).to_numpy(), g[f"{m}_b"].astype(bool).to_numpy())
        out[key] = {"n": int(len(g)), "left_out": left_out[key], "difference": diffs}
    return out


# ---------------------------------------------------------------------- paraphrases
def by_novelty(episodes: pd.DataFrame) -> dict:
    """Success by what the wording holds that training wordings do not (none, verb, object, both)."""
    novelty = pd.Series([parse_instruction(t).novelty for t in episodes["instruction"]], index=episodes.index)
    return {kind: wilson_rate(int(episodes.loc[novelty == kind, "success"].astype(bool).sum()),
                              int((novelty == kind).sum())) for kind in NOVELTIES if (novelty == kind).any()}


def paraphrase(variants: dict[str, pd.DataFrame]) -> dict:
    """Per condition and instruction set (variants[CANONICAL] is the reference), over the scenes every wording
    played (common_scenes; the others counted in the condition's `left_out`): the rates, the share of wrong-object
    grasps, success by novelty, and the paired difference to the canonical wording."""
    kept, left_out = common_scenes(variants)
    nothing = paired_change(np.zeros(0, bool), np.zeros(0, bool))  # (a condition whose every scene was left out)
    out: dict = {}
    for name, df in kept.items():
        diff = paired(kept[CANONICAL], df) if name != CANONICAL else {}
        for key, g in _conditions(df, left_out):
            wrong = int(((g["held"] != NONE) & (g["held"] != g["target"])).sum())
            entry = {**rates(g), "wrong_object": wilson_rate(wrong, len(g))}
            if name != CANONICAL:
                entry.update(by_novelty=by_novelty(g), vs_canonical=diff[key]["difference"] if key in diff else
                             {m: nothing for m in METRICS})
            out.setdefault(key, {"left_out": left_out[key]})[name] = entry
    return out


# ---------------------------------------------------------------------- appearance swap
def held_outcome(held: str, first: str, second: str, names: tuple[str, ...] = COLOUR_OUTCOMES) -> str:
    """What is held, as one of `names` (first object, second object, another, nothing): the appearance and position
    swaps' (instructed, partner, other, none) and the instruction switch's (new, old, other, none)."""
    if held == first:
        return names[0]
    if held == second:
        return names[1]
    return names[3] if held == NONE else names[2]


def appearance_swap(original: pd.DataFrame, swapped: pd.DataFrame) -> dict:
    """Per condition, on the scenes whose instructed object had a swap partner: what is held under the swap and
    without it (the same scenes), as shares of COLOUR_OUTCOMES with Wilson intervals; the transition table
    original -> swap; follows-shape and follows-colour (the partner held) minus their no-swap values with Newcombe's
    paired interval and McNemar's p (a policy blind to colour takes the partner as often either way)."""
    merged, left_out = same_scenes(original, swapped, ("_o", "_s"), same_target=True)
    merged["partner"] = [(json.loads(lay).get("colour_swap") or [None, None])[1] for lay in merged["layout_s"]]
    out = {}
    for key, g in _conditions(merged, left_out):
        s = g[g["partner"].notna()]
        before = [held_outcome(h, t, p) for h, t, p in zip(s["held_o"], s["target_o"], s["partner"])]
        after = [held_outcome(h, t, p) for h, t, p in zip(s["held_s"], s["target_s"], s["partner"])]
        n = len(s)
        x = np.array([o == "instructed" for o in before], bool)
        y = np.array([o == "instructed" for o in after], bool)
        out[key] = {
            "scenes": int(len(g)), "swapped": n, "left_out": left_out[key],
            "original": {o: wilson_rate(before.count(o), n) for o in COLOUR_OUTCOMES},
            "swap": {o: wilson_rate(after.count(o), n) for o in COLOUR_OUTCOMES},
            "follows_shape": wilson_rate(after.count("instructed"), n),
            "follows_colour": wilson_rate(after.count("partner"), n),
            "shape_change": paired_change(x, y),
            "colour_change": paired_change(np.array([o == "partner" for o in before], bool),
                                           np.array([o == "partner" for o in after], bool)),
            "transitions": transitions(before, after, COLOUR_OUTCOMES),
            "pairs": {f"{a}/{b}": int(c) for (a, b), c in
                      s.groupby(["target_s", "partner"]).size().items()},
        }
    return out


# ---------------------------------------------------------------------- absent object
def at_usual_place(plays: pd.DataFrame, condition: Condition) -> tuple[np.ndarray, np.ndarray] | None:
    """Per play (episodes.parquet rows naming an absent object): whether the named object has an empty usual place
    in the scene, and whether the TCP ends within REACH_THRESHOLD (5 cm, horizontally) of the centre of one. Its
    usual places are the regions where it stands in the condition's training layouts (layouts.usual_regions);
    empty: no present object stands in that region (always so in the canonical split, where object j sits in
    region j; in the pairing splits present objects often fill some of the three, and ending there is grasping
    whatever stands there, not going where the named object would be). None where no place is usual (full
    random) or a play has no recorded TCP (a run from before tcp_x/tcp_y were kept)."""
    tcp = plays[["tcp_x", "tcp_y"]].to_numpy(dtype=float)
    usual = [usual_regions(n, condition) for n in plays["target"]]
    if not len(plays) or any(r is None for r in usual) or not np.isfinite(tcp).all():
        return None
    occupied = [set((json.loads(lay).get("regions") or {}).values()) for lay in plays["layout"]]
    empty = [[r for r in regions if r not in taken] for regions, taken in zip(usual, occupied)]
    eligible = np.array([bool(e) for e in empty])
    at = np.array([bool(e) and np.linalg.norm(REGION_CENTERS[e] - xy, axis=1).min() <= REACH_THRESHOLD
                   for e, xy in zip(empty, tcp)])
    return eligible, at


def absent_object(present: pd.DataFrame, absent: pd.DataFrame) -> dict:
    """Per condition: what a policy does when told to grasp an object that is not on the table. `absent`: the
    absent plays (episodes.parquet rows with an `absent` column, the named object's rank among the absent ones;
    `target` is the named object), `present`: the same scenes' ordinary plays (their own target instructed).
    Scenes missing a play are left out and counted (common_scenes: `left_out`). Rates over the present plays (one a
    scene) are Wilson; rates pooled over a scene's absent plays get pooled_rate's interval; the change absent -
    present Newcombe's paired interval with one absent play a scene (four objects), and with several the same
    construction from the present rate's Wilson interval, the absent rate's pooled one and their correlation over
    scenes (stats.difference_interval). Measured
    coverage of the nominal 95% (beta-binomial scenes, 2-3 absent plays, rates 0.1-0.9, present and absent
    correlated through the scene): 90-96% at 10 scenes, 92-96% at 20-50, where the bootstrap over scenes used
    before gave 87-95% at 10 (docs/probes.md); it keeps a width where every scene plays alike."""
    kept, left_out = common_scenes({"present": present, **dict(iter(absent.groupby("absent")))},
                                   lambda c: ["present", *range(MAX_OBJECTS - c.num_objects)])
    absent_kept = pd.concat([df for name, df in kept.items() if name != "present"]) if len(kept) > 1 else absent
    present_kept = dict(_conditions(kept["present"], left_out))
    out = {}
    for key, g in _conditions(absent_kept, left_out):
        cond = Condition.parse(key)
        missing = MAX_OBJECTS - cond.num_objects
        if not missing:  # (five objects: none to name; the probe never plays them)
            continue
        full = g.sort_values(["episode", "absent"])
        own = present_kept[key].set_index("episode").sort_index()
        n = len(own)
        # (scenes, absent plays) arrays: the rows are sorted by scene, then by rank.
        held = (full["held"] != NONE).to_numpy().reshape(n, missing)
        same = (full["held"].to_numpy().reshape(n, missing) == own["held"].to_numpy()[:, None]) & held
        held_present = (own["held"] != NONE).to_numpy()
        plays = np.full(n, float(missing))
        shortcut = at_usual_place(full, cond)
        grasp_present = wilson_rate(int(held_present.sum()), n)
        grasp_absent = pooled_rate(held.sum(1).astype(float), plays)
        if missing == 1:  # one absent play a scene: a paired binary difference
            grasp_change = paired_change(held_present, held[:, 0])
        else:  # a share of the scene's absent plays minus a 0/1
            grasp_change = share_change(grasp_present, grasp_absent, held_present, held.mean(1))
        regions = {o: usual_regions(o, cond) for o in OBJECT_NAMES}  # all None in full random
        out[key] = {
            "scenes": n, "absent_plays": int(n * missing), "left_out": left_out[key],
            "usual_regions": None if None in regions.values() else {o: list(r) for o, r in regions.items()},
            "grasp_present": grasp_present,
            "grasp_absent": grasp_absent,
            "grasp_change": grasp_change,
            "shortcut_reach": None if shortcut is None else
            pooled_rate(shortcut[1].reshape(n, missing).sum(1).astype(float),
                        shortcut[0].reshape(n, missing).sum(1).astype(float)),
            "usual_place_empty": None if shortcut is None else
            pooled_rate(shortcut[0].reshape(n, missing).sum(1).astype(float), plays),
            "same_grasp": pooled_rate(same.sum(1).astype(float), plays),
            "success_present": wilson_rate(int(own["success"].astype(bool).sum()), n),
            "matrix": _matrix(confusion(full)),
        }
    return out


def share_change(first: dict, second: dict, x: np.ndarray, y: np.ndarray) -> dict:
    """second - first of two rates over the same scenes, each with its own interval, x and y their per-scene values
    (a 0/1 and a share of the scene's plays): stats.difference_interval with the correlation of x and y over
    scenes (0 where either does not vary)."""
    n = len(x)
    if n == 0:
        return _interval(float("nan"), float("nan"), float("nan"), "mover", 0)
    r = float(np.corrcoef(x, y)[0, 1]) if np.std(x) > 0 and np.std(y) > 0 else 0.0
    lo, hi = difference_interval((first["value"], *first["ci95"]), (second["value"], *second["ci95"]), r)
    return _interval(second["value"] - first["value"], lo, hi,
                     "mover: wilson and pooled wilson, correlated over scenes", n)


# ---------------------------------------------------------------------- position swap
def ends_near(plays: pd.DataFrame, target: str, partner: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Per play: whether the TCP ends at the instructed object or at the partner, whatever it grasped: within
    REACH_THRESHOLD (5 cm, horizontally) of that object's footprint circle (centre from the play's layout), and
    nearer to it than to the other. Where a policy goes tells a place-follower whose grasp does not fit the
    partner's shape (layout-prior grasps at the instructed object's height) from one that goes nowhere. None when
    a play has no recorded TCP (a run from before tcp_x/tcp_y were kept)."""
    tcp = plays[["tcp_x", "tcp_y"]].to_numpy(dtype=float)
    if not np.isfinite(tcp).all():
        return None
    out = []
    for names in (target, partner):
        pos = [json.loads(lay)["positions"][n] for lay, n in zip(plays["layout"], names)]
        radius = np.array([OBJECTS[object_index(n)].footprint_radius for n in names])
        out.append(np.linalg.norm(tcp - np.array(pos, dtype=float).reshape(-1, 2), axis=1) - radius)
    at_obj, at_partner = out
    return (at_obj <= REACH_THRESHOLD) & (at_obj <= at_partner), (at_partner <= REACH_THRESHOLD) & (at_partner < at_obj)


def _two_plays(s: pd.DataFrame, before: list[str], after: list[str], outcomes: tuple[str, ...],
               second: tuple[str, str], follows: dict[str, str], ends_at: dict[str, pd.Series]) -> dict:
    """What a probe playing each scene twice (merged rows `s`: columns suffixed _o and _s) measures: the shares of
    `outcomes` in each play ("original" and second[0], Wilson); for each `follows` metric (name -> outcome) and each
    `ends_at` metric (name -> the object whose footprint the TCP ends at, ends_near: exactly two, the first nearer
    than the second) its rate in each play (suffixes "original" and second[1]) and their paired change; the
    transition table."""
    n = len(s)
    entry: dict = {"original": {o: wilson_rate(before.count(o), n) for o in outcomes},
                   second[0]: {o: wilson_rate(after.count(o), n) for o in outcomes}}
    pairs = {m: (np.array([o == want for o in before], bool), np.array([o == want for o in after], bool))
             for m, want in follows.items()}
    (a, objects_a), (b, objects_b) = ends_at.items()
    ends = [ends_near(s[[f"{c}_{v}" for c in ("tcp_x", "tcp_y", "layout")]].set_axis(
        ["tcp_x", "tcp_y", "layout"], axis=1), objects_a, objects_b) for v in "os"]
    for i, metric in enumerate((a, b)):
        pairs[metric] = None if ends[0] is None or ends[1] is None else (ends[0][i], ends[1][i])
    for metric, xy in pairs.items():
        if xy is None:  # runs written before the TCP was kept
            entry.update({f"{metric}_{p}": None for p in ("original", second[1], "change")})
            continue
        x, y = xy
        entry[f"{metric}_original"] = wilson_rate(int(x.sum()), n)
        entry[f"{metric}_{second[1]}"] = wilson_rate(int(y.sum()), n)
        entry[f"{metric}_change"] = paired_change(x, y)
    entry["transitions"] = transitions(before, after, outcomes)
    return entry


def position_swap(original: pd.DataFrame, swapped: pd.DataFrame) -> dict:
    """Per condition, on the scenes where the instructed object exchanged places with a partner (the swapped play's
    layout names it in "position_swap"; scenes where no distractor fitted played unswapped and are counted, not
    scored): what is held in the original and the swapped play, as shares of PLACE_OUTCOMES (Wilson over scenes).
    follows_object: the instructed object is held; follows_place: the partner is held (in the swapped play it
    stands at the instructed object's original place; in the original play it is a wrong grasp like any other).
    reaches_object / reaches_place: the TCP ends at the instructed object / at the partner (`ends_near`), whatever
    is held. Their paired changes swapped - original get Newcombe's paired interval and McNemar's exact p."""
    merged, left_out = same_scenes(original, swapped, ("_o", "_s"), same_target=True)
    merged["partner"] = [(json.loads(lay).get("position_swap") or [None, None])[1] for lay in merged["layout_s"]]
    out = {}
    for key, g in _conditions(merged, left_out):
        s = g[g["partner"].notna()]
        n = len(s)
        before = [held_outcome(h, t, p) for h, t, p in zip(s["held_o"], s["target_o"], s["partner"])]
        after = [held_outcome(h, t, p) for h, t, p in zip(s["held_s"], s["target_s"], s["partner"])]
        entry = {"scenes": int(len(g)), "swapped": n, "no_swap": int(len(g) - n), "left_out": left_out[key],
                 **_two_plays(s, before, after, PLACE_OUTCOMES, ("swap", "swapped"),
                              {"follows_object": "instructed", "follows_place": "partner"},
                              # where the gripper ends, for policies whose grasp can miss
                              {"reaches_object": s["target_o"], "reaches_place": s["partner"]})}
        entry["pairs"] = {f"{a}/{b}": int(c) for (a, b), c in s.groupby(["target_s", "partner"]).size().items()}
        out[key] = entry
    return out


# ---------------------------------------------------------------------- instruction switch
SWITCH_OUTCOMES = ("new", "old", "other", "none")
"""What is held at the end of an instruction-switch scene: B, the object the instruction switched to (follows the
new instruction), A, the object it named first (stays with the old one), another object, nothing. In the original
play, which never switches, B is a distractor like any other and holding it an ordinary wrong grasp."""


def instruction_switch(original: pd.DataFrame, switched: dict[int, pd.DataFrame]) -> dict:
    """Per condition and switch step K: the same scenes played as they are (`original`) and with the instruction
    switching at step K from A to B (`switched[K]`; its rows' target is B, their layout's "switch" says K and B,
    its "target" A). What is held at the end, as shares of SWITCH_OUTCOMES in each play (Wilson over scenes);
    follows_new (B held) and stays_old (A held) in both plays with their paired changes switched - original
    (Newcombe's paired interval, McNemar's exact p); where the gripper ends, at B or at A (`ends_near`: within 5 cm
    horizontally of the footprint, nearer it than the other); the transition table original -> switched. Each
    condition holds them per K under "by_step", and at its top, like every probe's flat metrics (the study's probe
    table lists those), the switched play's follows_new_at_K and stays_old_at_K. Every K over the same scenes, those
    that the original and every switched variant played (common_scenes: the others counted in `left_out`)."""
    kept, left_out = common_scenes({"original": original, **switched})  # the scenes every step played
    out: dict = {}
    for step in sorted(switched):
        merged, _ = same_scenes(kept["original"], kept[step], ("_o", "_s"))
        switch = [json.loads(lay).get("switch") or {} for lay in merged["layout_s"]]
        if any(s.get("step") != step or s.get("target") != t for s, t in zip(switch, merged["target_s"])):
            raise ValueError(f"the switch-{step} plays do not all switch at step {step} to their target; "
                             "a probe compares the same scenes")
        merged["new"] = merged["target_s"]
        merged["old"] = [json.loads(lay)["target"] for lay in merged["layout_s"]]
        if (merged["old"] != merged["target_o"]).any():
            raise ValueError("the switched plays do not start with the original plays' instruction")
        for key, s in _conditions(merged, left_out):
            n = len(s)
            before = [held_outcome(h, b, a, SWITCH_OUTCOMES) for h, a, b in zip(s["held_o"], s["old"], s["new"])]
            after = [held_outcome(h, b, a, SWITCH_OUTCOMES) for h, a, b in zip(s["held_s"], s["old"], s["new"])]
            entry = {"scenes": n, "switch_step": step,
                     **_two_plays(s, before, after, SWITCH_OUTCOMES, ("switched", "switched"),
                                  {"follows_new": "new", "stays_old": "old"},
                                  # where the gripper ends, at B or at A (nothing moves: one layout, both places)
                                  {"reaches_new": s["new"], "reaches_old": s["old"]})}
            entry["pairs"] = {f"{a}/{b}": int(c) for (a, b), c in s.groupby(["old", "new"]).size().items()}
            cond = out.setdefault(key, {"scenes": n, "left_out": left_out[key], "switch_steps": [], "by_step": {}})
            cond["switch_steps"].append(step)
            cond[f"follows_new_at_{step}"] = entry["follows_new_switched"]
            cond[f"stays_old_at_{step}"] = entry["stays_old_switched"]
            cond["by_step"][str(step)] = entry
    return out


# ---------------------------------------------------------------------- distractor removal
REMOVAL_OUTCOMES = ("instructed", "distractor", "none")


def distractor_removal(original: pd.DataFrame, alone: pd.DataFrame) -> dict:
    """Per condition: the same scenes played as they are and with every distractor taken off the table (the
    instructed object alone where it stood). What is held in the original play (the instructed object, a
    distractor, nothing: Wilson), success in each play and its paired change alone - original (Newcombe's paired
    interval, McNemar's exact p), and the original play's failures split by what the alone play did: distractor
    failures (it succeeds alone: with the others on the table the policy chose, or was drawn to, something else,
    or, for a policy whose outcomes vary from play to play, chance) and failures alone too (it fails with nothing
    to choose between as well: reaching, grasping, or going to a place where the object is not), so success as
    it is + distractor failures + failures alone too = 1. Shares of all scenes (Wilson). Δ success nets the
    distractor failures against the opposite flips (succeeds as it is, fails alone)."""
    merged, left_out = same_scenes(original, alone, ("_o", "_a"), same_target=True)
    out = {}
    for key, g in _conditions(merged, left_out):
        n = len(g)
        x, y = g["success_o"].astype(bool).to_numpy(), g["success_a"].astype(bool).to_numpy()
        held = ["none" if h == NONE else "instructed" if h == t else "distractor"
                for h, t in zip(g["held_o"], g["target_o"])]
        out[key] = {
            "scenes": n, "left_out": left_out[key],
            "success_original": wilson_rate(int(x.sum()), n), "success_alone": wilson_rate(int(y.sum()), n),
            "success_change": paired_change(x, y),
            "held_original": {o: wilson_rate(held.count(o), n) for o in REMOVAL_OUTCOMES},
            "distractor_failures": wilson_rate(int((~x & y).sum()), n),
            "failures_alone_too": wilson_rate(int((~x & ~y).sum()), n),
            "grasp_any_alone": wilson_rate(int(g["grasp_any_a"].astype(bool).sum()), n),
        }
    return out
