"""Decomposed metrics of a set of evaluated episodes (success, grasp-anything, reach).

Every rate comes with a 95% Wilson score interval (statsmodels), because a policy evaluated on 100
episodes per condition cannot be told apart from one 8 points better without one. Summaries also say
which object was held instead of the instructed one (a confusion matrix) and how each failure looked.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from vla_ladder.conditions import Condition
from vla_ladder.stats import rates
from vla_ladder.task.objects import OBJECT_NAMES

CONDITION_KEYS = ("regime", "split", "num_objects")
"""The columns of episodes.parquet that make up an episode's Condition."""
NONE = "none"
HELD_COLUMNS = (*OBJECT_NAMES, NONE)
# Each episode ends in exactly one of these; the order is from best to worst.
OUTCOMES = ("success", "wrong_object", "grasp_lost", "reached_no_grasp", "nothing")
OUTCOME_TEXT = {
    "success": "the instructed object is held at the end",
    "wrong_object": "another object is held at the end",
    "grasp_lost": "something was grasped during the episode, nothing is held at the end",
    "reached_no_grasp": "the gripper ends within 5 cm of the instructed object, nothing was ever grasped",
    "nothing": "no grasp and the gripper ends away from the instructed object",
}


def outcome(row) -> str:
    """The kind of one episode's result (see OUTCOMES)."""
    if bool(row["success"]):
        return "success"
    if row["held"] not in (NONE, row["target"]):
        return "wrong_object"
    if bool(row["grasp_any"]):
        return "grasp_lost"
    if bool(row["reach"]):
        return "reached_no_grasp"
    return "nothing"


def outcomes(episodes: pd.DataFrame) -> pd.Series:
    return episodes.apply(outcome, axis=1) if len(episodes) else pd.Series([], dtype=str)


def confusion(episodes: pd.DataFrame) -> pd.DataFrame:
    """Counts of instructed object (rows) x object held at the final step (columns, plus "none")."""
    # Plain columns, then reindex: crosstab of empty Categoricals with dropna=False repeats its columns (pandas 2.3),
    # and a condition whose scenes all lack a probe variant has no episodes.
    table = pd.crosstab(episodes["target"].astype(object), episodes["held"].astype(object))
    table.index.name, table.columns.name = "instructed", "held"
    return table.reindex(index=list(OBJECT_NAMES), columns=list(HELD_COLUMNS), fill_value=0).astype(int)


def summarize_condition(df: pd.DataFrame) -> dict:
    """rates() plus per-object rates, the confusion matrix and outcome counts of one condition."""
    per_object = {name: rates(g) for name, g in df.groupby("target", sort=False)}
    cm = confusion(df)
    kinds = outcomes(df).value_counts()
    return {
        **rates(df),
        "per_object": {name: per_object[name] for name in OBJECT_NAMES if name in per_object},
        "confusion": {"rows": list(cm.index), "columns": list(cm.columns), "counts": cm.values.tolist()},
        "outcomes": {k: int(kinds.get(k, 0)) for k in OUTCOMES},
    }


def summarize(episodes: pd.DataFrame) -> dict:
    """Per-condition figures, keyed "regime/split/num_objects"."""
    out = {}
    for key, df in episodes.groupby(list(CONDITION_KEYS), sort=False):
        out[condition_key(*key)] = {**dict(zip(CONDITION_KEYS, _plain(key))), **summarize_condition(df)}
    return out


def condition_key(regime: str, split: str, num_objects: int) -> str:
    """The Condition key of an episodes.parquet row's condition columns."""
    return Condition(regime, split, int(num_objects)).key


def _plain(values) -> list:
    return [v.item() if isinstance(v, np.generic) else v for v in values]
