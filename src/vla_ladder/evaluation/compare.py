"""`vla-ladder compare RUN_A RUN_B`: do two evaluation runs differ, metric by metric?

Both runs must have played the same seeded episodes (same conditions, same seeds), so outcomes pair up
episode by episode. The primary test is McNemar's exact test on the discordant pairs, the right test for
paired binary outcomes; the unpaired two-proportion z-test is reported next to it because it is what
readers usually compute from two published rates.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import pandas as pd
import tyro
from statsmodels.stats.contingency_tables import mcnemar

from vla_ladder.checks import check_output_file
from vla_ladder.contract import METRICS
from vla_ladder.evaluation.metrics import CONDITION_KEYS, condition_key
from vla_ladder.evaluation.rundir import EPISODE_KEY, Run, check_same_seeds, load_run
from vla_ladder.files import number, write_json
from vla_ladder.stats import detectable_difference, paired_difference, wilson


DETECT_POWER = 0.8
"""The power at which `compare` reports the smallest difference its scenes could find."""


def mcnemar_exact(b: int, c: int) -> float:
    """Two-sided exact McNemar p-value from the discordant counts b (A only) and c (B only)."""
    if b + c == 0:
        return 1.0
    return float(mcnemar([[0, b], [c, 0]], exact=True).pvalue)


def two_proportion_z(k1: int, n1: int, k2: int, n2: int) -> tuple[float, float]:
    """Pooled two-proportion z statistic (p1 - p2) and its two-sided p-value."""
    from statsmodels.stats.proportion import proportions_ztest
    pooled = (k1 + k2) / (n1 + n2)
    if pooled in (0.0, 1.0):  # no variance: the rates are equal by construction
        return 0.0, 1.0
    z, p = proportions_ztest([k1, k2], [n1, n2])
    return float(z), float(p)


def conditions(run: Run) -> list[str]:
    """The condition keys a run played, in its order."""
    return [condition_key(*k) for k in run.episodes[list(CONDITION_KEYS)].drop_duplicates().itertuples(index=False)]


def pair_episodes(a: Run, b: Run, in_both: bool = False) -> pd.DataFrame:
    """Episodes of both runs joined on condition and episode index; ValueError if they do not match. With
    `in_both`, only the conditions both runs played are joined (at least one)."""
    ea, eb = a.episodes, b.episodes
    ka, kb = set(conditions(a)), set(conditions(b))
    if ka != kb and not (in_both and ka & kb):
        hint = ("they share none" if in_both else "compare the conditions both played with --conditions-in-both")
        raise ValueError(f"the runs evaluated different conditions: only in {a.path}: "
                         f"{sorted(ka - kb) or 'none'}; only in {b.path}: {sorted(kb - ka) or 'none'}; {hint}")
    if ka != kb:
        ea, eb = _in(ea, ka & kb), _in(eb, ka & kb)
    merged = ea.merge(eb, on=list(EPISODE_KEY), how="outer", suffixes=("_a", "_b"), indicator=True)
    unpaired = merged[merged["_merge"] != "both"]
    if len(unpaired):
        raise ValueError(f"the runs have different episodes: {len(unpaired)} episodes are in only one run "
                         f"(e.g. {_describe(unpaired.iloc[0])}); evaluate both with the same --episodes")
    check_same_seeds(a, b)
    # The same seed is the same scene only with the same objects. (With another object named, as a probe's variants
    # or `eval --instruct K` play, it is the same scene under another instruction: paired still, and said.)
    bad = merged[merged["object_set_a"] != merged["object_set_b"]]
    if len(bad):
        r = bad.iloc[0]
        raise ValueError(f"the runs played {len(bad)} of {len(merged)} episodes with different object sets (e.g. "
                         f"{_describe(r)}: {r['object_set_a']} in {a.path}, {r['object_set_b']} in {b.path}), so "
                         "the same seeds are other scenes; evaluate both with the same --object-set")
    return merged.drop(columns="_merge")


def _in(episodes: pd.DataFrame, keys: set[str]) -> pd.DataFrame:
    return episodes[[condition_key(*k) in keys for k in episodes[list(CONDITION_KEYS)].itertuples(index=False)]]


def _describe(row) -> str:
    return f"{condition_key(row['regime'], row['split'], row['num_objects'])} episode {row['episode']}"


def compare_runs(a: Run, b: Run, alpha: float = 0.05, in_both: bool = False) -> dict:
    """Per condition and metric: both rates with Wilson intervals, their paired difference B - A with Newcombe's
    paired interval, McNemar's exact test, the z-test (its z of B - A), and the difference these n scenes would
    find with probability DETECT_POWER (stats.detectable_difference). With `in_both`, the conditions both runs
    played (the others under "left_out")."""
    merged = pair_episodes(a, b, in_both)
    played_a, played_b = conditions(a), conditions(b)
    groups = dict(list(merged.groupby(list(CONDITION_KEYS), sort=False)))
    # Conditions in run A's order (the outer join sorts its keys alphabetically).
    order = [tuple(k) for k in a.episodes[list(CONDITION_KEYS)].drop_duplicates().itertuples(index=False)
             if tuple(k) in groups]
    rows = []
    for key in order:
        df = groups[key]
        n = len(df)
        for m in METRICS:
            xa, xb = df[f"{m}_a"].astype(bool), df[f"{m}_b"].astype(bool)
            ka, kb = int(xa.sum()), int(xb.sum())
            only_a, only_b = int((xa & ~xb).sum()), int((~xa & xb).sum())
            z, pz = two_proportion_z(kb, n, ka, n)  # (B - A, the sign of "diff")
            rows.append({
                "condition": condition_key(*key), "metric": m, "n": n,
                "rate_a": ka / n, "ci95_a": list(wilson(ka, n)), "rate_b": kb / n, "ci95_b": list(wilson(kb, n)),
                "diff": (kb - ka) / n, "ci95_diff": list(paired_difference(xa.to_numpy(), xb.to_numpy())),
                "only_a": only_a, "only_b": only_b,
                "mcnemar_p": mcnemar_exact(only_a, only_b), "z": z, "z_p": pz,
                "detectable_diff": detectable_difference((ka + kb) / (2 * n), n, alpha, DETECT_POWER),
            })
    return {"run_a": str(a.path), "run_b": str(b.path), "policy_a": a.label, "policy_b": b.label,
            "tests": {"paired": "McNemar exact (binomial on discordant pairs), two-sided; each row at alpha, not "
                                "corrected for the number of rows",
                      "ci95_diff": "Newcombe's hybrid score interval for paired proportions (stats.paired_difference)",
                      "unpaired": "pooled two-proportion z-test, two-sided",
                      "detectable_diff": f"the difference around the pooled rate that McNemar's test at alpha={alpha} "
                                         f"finds with probability {DETECT_POWER} when outcomes are independent "
                                         "draws (stats.detectable_difference)"},
            "rows": rows,
            # The same scenes with another object named (a probe's variants, `eval --instruct K`): paired by scene.
            "other_target": int((merged["target_a"] != merged["target_b"]).sum()),
            "left_out": {"only_a": [c for c in played_a if c not in played_b],
                         "only_b": [c for c in played_b if c not in played_a]}}


def format_table(result: dict, alpha: float = 0.05) -> str:
    lines = [f"A = {result['policy_a']} ({result['run_a']})", f"B = {result['policy_b']} ({result['run_b']})", ""]
    head = f"{'condition':<28} {'metric':<9} {'n':>4} {'A %':>5} {'B %':>5} {'B-A':>6} {'95% CI':>11} " \
           f"{'A only':>6} {'B only':>6} {'McNemar p':>10} {'z':>6} {'z-test p':>9} {'MDD':>5}"
    lines += [head, "-" * len(head)]
    for r in result["rows"]:
        r = {k: number(v) for k, v in r.items()}  # (a result read back from --json holds null for NaN)
        star = " *" if r["mcnemar_p"] < alpha else ""
        z = "" if math.isnan(r["z"]) else f"{r['z']:6.2f}"
        lo, hi = map(number, r["ci95_diff"])
        ci = f"[{100 * lo:+.0f}, {100 * hi:+.0f}]"
        lines.append(f"{r['condition']:<28} {r['metric']:<9} {r['n']:>4} {100 * r['rate_a']:5.0f} "
                     f"{100 * r['rate_b']:5.0f} {100 * r['diff']:+6.0f} {ci:>11} {r['only_a']:>6} {r['only_b']:>6} "
                     f"{r['mcnemar_p']:10.4f} {z:>6} {r['z_p']:9.4f} {100 * r['detectable_diff']:5.0f}{star}")
    if other := result.get("other_target"):
        lines += ["", f"B named another object than A in {other} of the paired episodes (the same scenes under "
                      "another instruction, as a probe's variants play them): the pairs are scenes, not tasks"]
    left = result.get("left_out", {})
    if left.get("only_a") or left.get("only_b"):
        lines += ["", f"left out, played by one run only: A {', '.join(left['only_a']) or 'none'}; "
                      f"B {', '.join(left['only_b']) or 'none'}"]
    lines += ["", f"* paired difference significant at {alpha} (McNemar exact), row by row: with many rows, expect "
              "some stars by chance (no correction for multiple comparisons)",
              "95% CI: of B-A, Newcombe's interval for paired rates; z: pooled two-proportion z of B-A, unpaired",
              "     (the interval is approximate and McNemar's exact test conservative: near the edge one may "
              "exclude 0",
              "     while the other is not significant, e.g. 4 A-only of 10: [-69, -4] and p 0.125; read both)",
              f"MDD: the smallest difference (points) these n scenes find with probability {DETECT_POWER} at this rate",
              "     when episodes are independent draws; a smaller B-A without * is not evidence of no difference"]
    return "\n".join(lines)


@dataclass
class CompareConfig:
    """Test whether two evaluation runs of the same seeded episodes differ, metric by metric."""

    run_a: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_A")]
    """first run directory (from `vla-ladder eval --out`)"""
    run_b: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_B")]
    """second run directory, evaluated on the same seeds"""
    json: Path | None = None
    """also write the comparison as JSON here (the table is always printed)"""
    alpha: float = 0.05
    """significance level for the * marks"""
    conditions_in_both: bool = False
    """compare the conditions both runs played (e.g. a ladder run against one of small jitter only) and list the
    others, instead of refusing runs of different conditions"""

    def __post_init__(self):
        if not 0 < self.alpha < 1:
            raise ValueError(f"--alpha must be in (0, 1), got {self.alpha}")
        if Path(self.run_a).resolve() == Path(self.run_b).resolve():
            raise ValueError(f"{self.run_a} is given twice; compare two different run directories")
        if self.json is not None:
            check_output_file(self.json, "--json")
            for run in (self.run_a, self.run_b):  # its summary.json, say: the run would no longer load
                if Path(self.json).resolve().is_relative_to(Path(run).resolve()):
                    raise ValueError(f"--json {str(self.json)!r} is inside the run directory {str(run)!r}, which holds "
                                     "what eval wrote; write the comparison elsewhere")


def run(cfg: CompareConfig) -> int:
    result = compare_runs(load_run(cfg.run_a), load_run(cfg.run_b), cfg.alpha, cfg.conditions_in_both)
    print(format_table(result, cfg.alpha))
    if cfg.json:
        write_json(cfg.json, result)
        print(f"wrote {cfg.json}", file=sys.stderr)
    return 0
