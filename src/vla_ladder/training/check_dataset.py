"""`vla-ladder check-dataset DATASET`: what no LeRobot validator checks and this project's claims rest on.

A pairings experiment means something only if its training data never showed a held-out object-region pair; a
ladder rung only if its data hold the layouts their seeds say. Before training on a recorded dataset, this
command checks, from LeRobot's files and the provenance the recorder writes (vla_ladder.recordings):

- structure: LeRobot v3 features of the contract, one provenance row per episode;
- seeds: no seed recorded twice (a duplicate is a replayed scene counted twice);
- layouts: every episode's seed regenerates its recorded layout (objects, positions, yaw, regions, target,
  wording) in the recording's condition and instruction set, and LeRobot's task is its instruction: a recording
  holds no probe's counterfactual (another object instructed, a colour or position swap, a held-out wording), so
  the layout is compared with what the seed gives, not with what the layout's own options make of it;
- start: every episode's first state holds its seed's start (layouts.initial_qpos: the arm's joints, drawn from the
  seed), so each episode's frames were played from its seed, for every episode and without a simulator (the replay
  re-simulates a few); episodes simulated on physx_cuda are counted, not compared;
- frames: every episode has contract.EPISODE_STEPS frames, numbered 0..T-1, as many as its provenance says;
- actions: finite and inside the normalised action box [-1, 1]; states finite;
- quantiles: stats.json's q01...q99 of every numeric feature are those over all frames (pi0.5 normalises state and
  action with q01/q99), not LeRobot's average of per-episode quantiles or those of a recording's first frames;
- stats: stats.json's mean, std, min, max and count of the state and the action are those of all frames (SmolVLA
  and ACT normalise them with mean/std, diffusion with min/max): not an edited file, or one of other frames;
- balance: every object instructed about equally often (chi-square against uniform, when at least five
  episodes per object are expected);
- coverage: every object-region pair the recording's condition produces (expected >= --min-expected times)
  occurs at least once;
- leakage: a canonical or pairings_id dataset holds no held-out object-region pair (layouts.HELD_OUT_REGIONS),
  for any object on the table, instructed or not;
- blind: an instruction-blind copy (training/blind.py) names only contract.BLIND_INSTRUCTION wherever LeRobot reads
  a task (tasks.parquet, each frame's task_index, meta/episodes), carries no text feature, and holds its source's
  frames and videos: the blind twin must differ from the sighted one by the instruction alone;
- replay: --replay episodes, spread over the dataset, re-simulated from their seed and recorded actions
  (task/replay.py): one recorded on a rebuilt physx_cpu scene (provenance `replayable`, `record`'s default) must
  give back its recorded states and held object to the bit; any other may drift (PhysX solver caches of a reused
  scene: up to ~0.02 in the 2-core machine's test) but not by more than REPLAY_DRIFT_TOLERANCE. An action stored
  a frame late moved the states by more than 1.

Every violation is one line on stderr and the exit status is 1; the JSON summary (counts, tables, p-value,
violations) goes to --out or stdout.
"""

from __future__ import annotations

import filecmp
import json
import os
import sys
from collections import Counter
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Annotated

import numpy as np
import pandas as pd
import tyro

from vla_ladder import files
from vla_ladder.checks import check_output_file
from vla_ladder.conditions import REGIMES, Condition
from vla_ladder.contract import (ACTION_DIM, ACTION_KEY, BLIND_INSTRUCTION, EPISODE_STEPS, STATE_DIM, STATE_KEY,
                                  contract_changes)
from vla_ladder.recordings import (STATS_FILE, exact_quantiles, frames, numeric_features, read_provenance,
                                  read_recording, read_recording_state)
from vla_ladder.task.layouts import HELD_OUT_REGIONS, REGION_CENTERS, condition_of, initial_qpos, sample_layout
from vla_ladder.task.objects import NUM_OBJECTS, OBJECT_NAMES
from vla_ladder.task.replay import Replayer
from vla_ladder.training.blind import STAMP as BLIND_STAMP
from vla_ladder.training.dataset import check_features, read_info

ACTION_TOLERANCE = 1e-5
REPLAY_DRIFT_TOLERANCE = 0.25
"""largest |recorded - replayed| state (rad, rad/s, m) accepted from an episode that does not promise bit-exact
replay: scene reuse drifted 0.0002-0.022 in four episodes; shifting actions by one frame moved them 1.3-2.8"""
QUANTILE_TOLERANCE = 1e-6
"""largest |stats.json - exact| quantile accepted (both are float64 over the same frames; JSON keeps 17 digits)"""
START_TOLERANCE = 1e-4
"""largest |first state - the seed's start| arm joint position (rad) accepted: equal to the bit on physx_cpu, while
two seeds' starts differ by 0.04-0.07 rad (at most) in the three episodes of the tests' recording"""
STATS_TOLERANCE = 1e-4
"""largest |stats.json - exact| mean, std, min or max of the state or action accepted, relative to max(1, |exact|):
LeRobot computes each episode's in float32 and pools them (up to 2e-6 off on four recordings)"""
NORMALISED = (STATE_KEY, ACTION_KEY)
"""the features whose stats.json entries a policy normalises with"""
COVERAGE_SEEDS = 2000
"""layouts sampled to estimate how often the recording's condition puts each object in each region"""


@dataclass
class CheckDatasetConfig:
    """Check a recorded dataset: balance, coverage, leakage, seeds, layouts, frames, actions (exit 1 on a violation)."""

    dataset: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATASET")]
    """dataset directory written by `vla-ladder record`"""
    out: Annotated[Path | None, tyro.conf.arg(metavar="PATH", help_behavior_hint="(default: print it)")] = None
    """write the JSON summary here"""
    balance_alpha: float = 0.001
    """a chi-square p-value below this flags unbalanced instructions"""
    min_expected: float = 5.0
    """flag an object-region pair never recorded when the condition makes it expected at least this often"""
    replay: int = 10
    """episodes to re-simulate from their seed and recorded actions, spread evenly over the dataset (0: none; more
    than it holds: all; ~0.2 s each on a state-only CPU env, after ~5 s to build it)"""

    def __post_init__(self):
        self.dataset = Path(self.dataset)
        if not 0 < self.balance_alpha < 1:
            raise ValueError(f"--balance-alpha must be in (0, 1), got {self.balance_alpha}")
        if not 0 < self.min_expected < float("inf"):  # nan passed `<= 0`
            raise ValueError(f"--min-expected must be a positive number, got {self.min_expected}")
        if self.out is not None:
            check_output_file(self.out, "--out")  # now, not after the checks and the replay
        if self.replay < 0:
            raise ValueError(f"--replay must be >= 0 (episodes to replay; 0: none), got {self.replay}")


def region_of(xy, regions: dict | None, name: str) -> int:
    """The region an object sits in: its recorded region, or (full random) the nearest region centre."""
    if regions is not None:
        return int(regions[name])
    return int(np.argmin(np.linalg.norm(REGION_CENTERS - np.asarray(xy), axis=1)))


def occupancy(layout: dict) -> list[tuple[str, int]]:
    """(object, region) of every object on the table of a recorded layout."""
    return [(name, region_of(xy, layout.get("regions"), name)) for name, xy in layout["positions"].items()]


@lru_cache(maxsize=None)
def pair_probabilities(condition: Condition) -> np.ndarray:
    """(objects, regions) expected occupancy per episode under `condition`, from COVERAGE_SEEDS sampled layouts."""
    counts = np.zeros((NUM_OBJECTS, len(REGION_CENTERS)))
    for seed in range(COVERAGE_SEEDS):
        for name, region in occupancy(sample_layout(condition, seed).to_dict()):
            counts[OBJECT_NAMES.index(name), region] += 1
    return counts / COVERAGE_SEEDS


class Checker:
    """Runs every check on one dataset, collecting violations ("check: message") and the summary."""

    def __init__(self, cfg: CheckDatasetConfig):
        self.cfg, self.root = cfg, cfg.dataset
        self.info = read_info(self.root)
        self.recording = read_recording(self.root)
        if self.recording is None:
            raise ValueError(f"{self.root} is not a vla-ladder recording (no meta/vla_ladder_recording.json); "
                             "check-dataset checks datasets written by `vla-ladder record`")
        self.prov = read_provenance(self.root)
        self.layouts = [json.loads(s) for s in self.prov["layout"]] if len(self.prov) else []
        stamp = self.root / BLIND_STAMP
        self.blind_stamp: dict | None = json.loads(stamp.read_text()) if stamp.is_file() else None
        """an instruction-blind copy's stamp (its source): its tasks are BLIND_INSTRUCTION, not the instructions"""
        self.violations: list[str] = []
        self.summary: dict = {}

    def flag(self, check: str, message: str) -> None:
        self.violations.append(f"{check}: {message}")

    def run(self) -> dict:
        for check in (self.structure, self.seeds, self.layouts_regenerate, self.start, self.frames, self.actions,
                      self.quantiles, self.stats, self.balance, self.coverage, self.leakage, self.blind, self.replay):
            check()
        return {"dataset": str(self.root), "recording": self.recording.to_dict(), "episodes": int(len(self.prov)),
                "frames": int(self.info.get("total_frames", 0)), "ok": not self.violations,
                "violations": self.violations, "checks": self.summary}

    # ------------------------------------------------------------------ checks
    def structure(self) -> None:
        try:
            check_features(self.info, self.root)
        except ValueError as e:
            self.flag("structure", str(e))
        state = read_recording_state(self.root)
        for change in contract_changes(state.get("contract")):
            self.flag("structure", f"recorded under another task contract: {change}")
        total = int(self.info.get("total_episodes", 0))
        saved = state.get("counters", {}).get("saved")
        if saved is not None and saved != total:  # (an edit by other tools, or a copy of another version's state)
            self.flag("structure", f"the recording state counts {saved} episodes but info.json has {total}")
        indices = self.prov["episode_index"].tolist() if len(self.prov) else []
        if indices != list(range(total)):
            self.flag("structure", f"provenance covers episodes {_ranges(indices)} but info.json has {total} "
                                   f"(0-{total - 1})")
        self.summary["structure"] = {"total_episodes": total, "provenance_rows": len(indices)}

    def seeds(self) -> None:
        counts = Counter(int(s) for s in self.prov.get("seed", []))
        for seed, n in sorted(counts.items()):
            if n > 1:
                episodes = self.prov.loc[self.prov["seed"] == seed, "episode_index"].tolist()
                self.flag("seeds", f"seed {seed} recorded {n} times (episodes {', '.join(map(str, episodes))})")
        self.summary["seeds"] = {"distinct": len(counts), "duplicated": sum(n > 1 for n in counts.values())}

    def layouts_regenerate(self) -> None:
        condition = self.recording.condition
        tasks = self._episode_tasks()
        trained_on = self._frame_tasks()
        bad = shown = 0
        for (_, row), layout in zip(self.prov.iterrows(), self.layouts):
            ep = f"episode {row['episode_index']} (seed {row['seed']})"
            recorded_condition = condition_of(layout)
            problems = []
            if recorded_condition != condition:
                problems.append(f"layout of {recorded_condition}, the recording is of {condition}")
            elif int(layout["seed"]) != int(row["seed"]):
                problems.append(f"its layout is of seed {layout['seed']}")
            else:
                # What the seed gives in the recording's condition and instruction set; not layout_from_dict, which
                # would take another instructed object, a swap or another wording from the layout itself.
                again = sample_layout(condition, int(row["seed"]), instructions=self.recording.instructions).to_dict()
                problems += [f"{k} {layout.get(k)!r} but the seed gives {again.get(k)!r}"
                             for k in sorted(set(again) | set(layout)) if not _same(layout.get(k), again.get(k))]
            if row["target"] != layout["target"] or row["instruction"] != layout["instruction"]:
                problems.append(f"provenance target/instruction {row['target']!r}/{row['instruction']!r} differ "
                                f"from its layout's {layout['target']!r}/{layout['instruction']!r}")
            told = layout["instruction"] if self.blind_stamp is None else BLIND_INSTRUCTION
            what = f"the instruction {told!r}" if self.blind_stamp is None else f"the blind copy's {told!r}"
            task_problems = []
            task = tasks.get(int(row["episode_index"]))
            if task is not None and task != [told]:
                task_problems.append(f"LeRobot task {task} is not {what}")
            # What training reads: each frame's task_index, looked up in meta/tasks.parquet.
            frame_tasks = trained_on.get(int(row["episode_index"]))
            if frame_tasks is not None and frame_tasks != [told]:
                task_problems.append(f"its frames' task_index gives {frame_tasks}, not {what} (what training reads)")
            if self.blind_stamp is not None and task_problems:  # an instruction shown to the blind twin
                shown += 1
                self.flag("blind", f"{ep}: " + "; ".join(task_problems))
            else:
                problems += task_problems
            if problems:
                bad += 1
                self.flag("layouts", f"{ep}: " + "; ".join(problems))
        self.summary["layouts"] = {"checked": len(self.layouts), "mismatched": bad}
        if self.blind_stamp is not None:
            self.summary["blind"] = {"episodes_showing_a_task": shown}

    def start(self) -> None:
        data = self._frames
        first = data[data["frame_index"] == 0].drop_duplicates("episode_index").set_index("episode_index")
        out: dict = {"checked": 0, "differing": 0, "not_checked_gpu": 0, "max_diff": None}
        self.summary["start"] = out
        diffs, starts = [], None
        for row in self.prov.itertuples(index=False):
            ep = int(row.episode_index)
            if ep not in first.index:
                continue  # the frames check says what is missing
            backend = getattr(row, "sim_backend", None)  # absent (NaN) in older recordings, all physx_cpu
            if isinstance(backend, str) and backend != "physx_cpu":
                out["not_checked_gpu"] += 1  # (not measured there: counted, not compared)
                continue
            arm = np.asarray(first.at[ep, STATE_KEY], dtype=np.float64)[:7]
            diff = float(np.max(np.abs(arm - initial_qpos(int(row.seed))[:7])))
            diffs.append(diff)
            if not diff <= START_TOLERANCE:
                out["differing"] += 1
                if starts is None:  # which recorded seed's start it is, if any: provenance shifted against frames
                    starts = {int(s): initial_qpos(int(s))[:7] for s in self.prov["seed"]}
                like = [s for s, q in starts.items() if np.max(np.abs(arm - q)) <= START_TOLERANCE]
                self.flag("start", f"episode {ep} (seed {row.seed}): its first state's arm joints differ from the "
                                   f"seed's start by up to {diff:.3g} rad: its frames were not played from its seed"
                                   + (f" (they start as seed {like[0]} does)" if like else ""))
        out["checked"] = len(diffs)
        out["max_diff"] = max(diffs, default=None)

    def frames(self) -> None:
        data = self._frames
        lengths = self._episodes_meta().set_index("episode_index")["length"].to_dict()
        recorded = dict(zip(self.prov["episode_index"], self.prov["num_frames"])) if len(self.prov) else {}
        for ep, g in data.groupby("episode_index"):
            idx = g["frame_index"].to_numpy()
            problems = []
            if len(g) != EPISODE_STEPS:
                problems.append(f"{len(g)} frames, the contract has {EPISODE_STEPS}")
            if not np.array_equal(np.sort(idx), np.arange(len(g))):
                problems.append("frame_index is not 0..T-1")
            if lengths.get(ep) != len(g) or (ep in recorded and recorded[ep] != len(g)):
                problems.append(f"episode metadata says {lengths.get(ep)} frames, provenance {recorded.get(ep)}, "
                                f"data holds {len(g)}")
            if problems:
                self.flag("frames", f"episode {ep}: " + "; ".join(problems))
        missing = sorted(set(lengths) - set(data["episode_index"]))
        if missing:
            self.flag("frames", f"episodes {_ranges(missing)} have no frames in data/")
        per_episode = sorted({int(n) for n in data.groupby("episode_index").size()})
        self.summary["frames"] = {"total": int(len(data)), "per_episode": per_episode}

    def actions(self) -> None:
        data = self._frames
        action, state = self._values[ACTION_KEY], self._values[STATE_KEY]
        outside = ~np.isfinite(action) | (np.abs(action) > 1 + ACTION_TOLERANCE)
        for ep, g in data[outside.any(axis=1)].groupby("episode_index"):
            a = np.stack(g[ACTION_KEY].to_numpy())
            self.flag("actions", f"episode {ep}: {len(g)} frames with actions outside [-1, 1] or not finite "
                                 f"(from frame {int(g['frame_index'].min())}; extremes {np.nanmin(a):.3g}, "
                                 f"{np.nanmax(a):.3g})")
        for ep, g in data[~np.isfinite(state).all(axis=1)].groupby("episode_index"):
            self.flag("actions", f"episode {ep}: {len(g)} frames with a non-finite state")
        self.summary["actions"] = {"frames": len(action), "frames_outside": int(outside.any(axis=1).sum()),
                                   "frames_non_finite_state": int((~np.isfinite(state).all(axis=1)).sum()),
                                   "min": action.min(axis=0).tolist() if len(action) else [],
                                   "max": action.max(axis=0).tolist() if len(action) else []}

    def quantiles(self) -> None:
        try:
            exact = exact_quantiles(self.root)
            saved = json.loads((self.root / STATS_FILE).read_text())
        except (OSError, ValueError, KeyError) as e:
            self.flag("quantiles", f"cannot compare stats.json's quantiles with the frames': {e}")
            return
        over = read_recording_state(self.root).get("quantile_frames")
        total = int(self.info.get("total_frames", 0))
        worst = {}
        for key, qs in exact.items():
            for q, values in qs.items():
                diff = float(np.max(np.abs(np.asarray(saved[key][q], dtype=float) - np.asarray(values)), initial=0))
                if not diff <= QUANTILE_TOLERANCE:  # (nan too)
                    worst[f"{key} {q}"] = diff
        if worst:
            name, diff = max(worst.items(), key=lambda kv: kv[1])
            why = (f"they are of its first {over} frames: the recording stopped before it computed them again; rerun "
                   "its `record` command, which does when it stops" if over is not None and over < total else
                   "LeRobot's average of per-episode quantiles, after an edit by LeRobot's tools? "
                   "`vla-ladder rebuild-provenance` writes them over all frames (docs/datasets.md)")
            self.flag("quantiles", f"{len(worst)} quantiles in stats.json are not those of the {total} frames (the "
                                   f"furthest, {name}, by {diff:.3g}; {why})")
        self.summary["quantiles"] = {"checked": sum(len(qs) for qs in exact.values()), "differing": len(worst),
                                     "features": sorted(exact), "state_quantile_frames": over}

    def stats(self) -> None:
        try:
            saved = json.loads((self.root / STATS_FILE).read_text())
        except (OSError, ValueError) as e:
            self.flag("stats", f"cannot read {STATS_FILE}: {e}")
            return
        worst = {}
        for key in NORMALISED:
            x = self._values[key]
            if not len(x):
                continue
            exact = {"mean": x.mean(axis=0), "std": x.std(axis=0), "min": x.min(axis=0), "max": x.max(axis=0),
                     "count": np.array([len(x)])}
            for stat, values in exact.items():
                recorded = np.asarray(saved.get(key, {}).get(stat, np.nan), dtype=float)
                diff = (float(np.max(np.abs(recorded - values) / np.maximum(1, np.abs(values))))
                        if recorded.shape == values.shape else np.inf)
                if not diff <= STATS_TOLERANCE:  # (nan too)
                    worst[f"{key} {stat}"] = diff
        if worst:
            name, diff = max(worst.items(), key=lambda kv: kv[1])
            self.flag("stats", f"{len(worst)} of stats.json's mean/std/min/max/count of {' and '.join(NORMALISED)} "
                               f"are not those of the {len(self._frames)} frames (the furthest, {name}, off by "
                               f"{diff:.3g} relative): an edited stats.json, or one of other frames? "
                               "`lerobot-edit-dataset --operation.type recompute_stats`, then "
                               "stats.write_exact_quantiles, write it again (docs/datasets.md)")
        self.summary["stats"] = {"checked": 5 * len(NORMALISED), "differing": len(worst),
                                 "features": list(NORMALISED), "tolerance": STATS_TOLERANCE}

    def balance(self) -> None:
        from scipy.stats import chisquare

        counts = Counter(self.prov.get("target", []))
        observed = np.array([counts.get(o, 0) for o in OBJECT_NAMES])
        n = int(observed.sum())
        out: dict = {"counts": dict(zip(OBJECT_NAMES, observed.tolist())), "p_value": None}
        if n >= 5 * NUM_OBJECTS:
            p = float(chisquare(observed).pvalue)
            out["p_value"] = p
            if p < self.cfg.balance_alpha:
                self.flag("balance", f"instructions per object {out['counts']} are not uniform (chi-square p={p:.2g} "
                                     f"< {self.cfg.balance_alpha}); n={n}")
        else:
            out["note"] = f"{n} episodes: too few to test balance (needs {5 * NUM_OBJECTS})"
        self.summary["balance"] = out

    def coverage(self) -> None:
        counts = np.zeros((NUM_OBJECTS, len(REGION_CENTERS)), dtype=int)
        for layout in self.layouts:
            for name, region in occupancy(layout):
                counts[OBJECT_NAMES.index(name), region] += 1
        expected = pair_probabilities(self.recording.condition) * len(self.layouts)
        missing = list(zip(*np.nonzero((counts == 0) & (expected >= self.cfg.min_expected))))
        for o, r in missing:
            self.flag("coverage", f"{OBJECT_NAMES[o]} never in region {r} although {self.recording.condition} puts it "
                                  f"there {expected[o, r]:.1f} times in {len(self.layouts)} episodes on average")
        self.summary["coverage"] = {"episodes": len(self.layouts), "pairs_expected": int(
                                        (expected >= self.cfg.min_expected).sum()), "pairs_missing": len(missing),
                                    "rows": list(OBJECT_NAMES), "columns": list(range(len(REGION_CENTERS))),
                                    "counts": counts.tolist(), "expected": np.round(expected, 2).tolist()}

    def leakage(self) -> None:
        split = self.recording.condition.split
        if split == "pairings_ood" or REGIMES[self.recording.condition.regime] is None:
            self.summary["leakage"] = {"checked": False, "note": f"{split} data hold held-out pairs by design"
                                       if split == "pairings_ood" else f"{self.recording.condition.regime} has no "
                                       "regions"}
            return
        leaks = 0
        for row, layout in zip(self.prov.itertuples(index=False), self.layouts):
            held_out = [f"{name} in region {r}" for name, r in occupancy(layout)
                        if r in HELD_OUT_REGIONS[OBJECT_NAMES.index(name)]]
            if held_out:
                leaks += 1
                self.flag("leakage", f"episode {row.episode_index} (seed {row.seed}) holds held-out pairs: "
                                     + ", ".join(held_out))
        self.summary["leakage"] = {"checked": True, "episodes": len(self.layouts),
                                   "episodes_with_held_out_pairs": leaks,
                                   "held_out": {o: sorted(HELD_OUT_REGIONS[i]) for i, o in enumerate(OBJECT_NAMES)}}

    def blind(self) -> None:
        """An instruction-blind copy: only BLIND_INSTRUCTION where LeRobot reads a task (each episode's are checked
        with its layout), and its source's frames and videos."""
        out = self.summary.setdefault("blind", {})
        out["blind_copy"] = self.blind_stamp is not None
        if self.blind_stamp is None:
            return
        table = self._tasks_table()
        names = [] if table is None else list(table.index)
        if names != [BLIND_INSTRUCTION]:
            self.flag("blind", f"meta/tasks.parquet holds {names}; a blind copy's holds only {BLIND_INSTRUCTION!r}")
        text = [k for k, f in self.info.get("features", {}).items() if f.get("dtype") in ("string", "language")]
        if text:
            self.flag("blind", f"features {text} carry text with every frame; a blind copy has none")
        source = Path(self.blind_stamp.get("source", ""))
        out.update(source=str(source), tasks=names)
        if not (source / "meta" / "info.json").is_file():
            out["note"] = f"its source {source} is gone: its frames and videos not compared"
            return
        theirs = read_info(source)
        if theirs.get("total_episodes") != self.info.get("total_episodes"):
            self.flag("blind", f"its source {source} has {theirs.get('total_episodes')} episodes, the copy "
                               f"{self.info.get('total_episodes')}: make the copy again")
            return
        keys = [k for k in numeric_features(self.info) if k != "task_index"]
        try:
            mine, source_frames = frames(self.root, keys), frames(source, keys)
        except (OSError, ValueError, KeyError) as e:  # (pyarrow's errors are ValueErrors and OSErrors)
            self.flag("blind", f"cannot compare its frames with its source's ({source}): {e}")
            return
        differ = [k for k in keys if not np.array_equal(mine[k], source_frames.get(k))]
        if differ:
            self.flag("blind", f"its frames' {', '.join(differ)} are not its source's ({source}): the blind twin must "
                               "train on the same frames")
        videos = {p.relative_to(self.root) for p in (self.root / "videos").rglob("*") if p.is_file()}
        source_videos = {p.relative_to(source) for p in (source / "videos").rglob("*") if p.is_file()}
        not_shared = sorted(map(str, (videos ^ source_videos) | {v for v in videos & source_videos
                                                                 if not _same_file(self.root / v, source / v)}))
        if not_shared:
            self.flag("blind", f"{len(not_shared)} video file(s) differ from or are missing in its source's "
                               f"({not_shared[0]}{', ...' if len(not_shared) > 1 else ''}): the blind twin must see "
                               "the same pictures")
        out.update(frames_compared=len(mine[keys[0]]) if keys else 0, videos_compared=len(videos | source_videos),
                   videos_differing=len(not_shared), features_differing=differ)

    def replay(self) -> None:
        picks = _spread(len(self.prov), self.cfg.replay)
        out: dict = {"replayed": 0, "bit_exact": 0, "max_state_diff": None, "episodes": []}
        self.summary["replay"] = out
        if not len(picks):
            return
        rows = self.prov.iloc[picks]
        object_sets = rows["object_set"].astype(str).unique()
        try:
            replayer = Replayer(self.recording.condition, object_sets[0], self.recording.robot_mesh)
        except ValueError as e:  # e.g. recorded with YCB meshes that this machine lacks: cannot say, no violation
            out["note"] = f"not replayed: {e}"
            return
        data = self._frames
        episodes = {int(ep): g.sort_values("frame_index") for ep, g in data.groupby("episode_index")}
        try:
            for row in rows.itertuples(index=False):
                g = episodes.get(int(row.episode_index))
                if g is None or len(g) != EPISODE_STEPS or str(row.object_set) != object_sets[0]:
                    continue  # the frames check says what is missing; one env per object set is enough here
                backend = getattr(row, "sim_backend", None)  # absent (NaN) in older recordings, all physx_cpu
                if isinstance(backend, str) and backend != "physx_cpu":
                    out["not_replayed_gpu"] = out.get("not_replayed_gpu", 0) + 1
                    continue  # GPU PhysX solves differently: a CPU replay of its actions drifts by design
                replayed = replayer.replay(int(row.seed), np.stack(g[ACTION_KEY].to_numpy()))
                diff = np.abs(replayed.states - np.stack(g[STATE_KEY].to_numpy())).max(axis=1)
                promised = _true(getattr(row, "replayable", False))  # absent or NaN in older recordings
                ep = {"episode_index": int(row.episode_index), "seed": int(row.seed), "replayable": promised,
                      "max_state_diff": float(diff.max()),
                      "first_frame_differing": int(np.argmax(diff > 0)) if diff.max() > 0 else None,
                      "held": row.held, "held_replayed": replayed.held}
                out["episodes"].append(ep)
                exact = ep["max_state_diff"] == 0 and replayed.held == row.held
                out["bit_exact"] += exact
                where = (f"episode {ep['episode_index']} (seed {ep['seed']}): its recorded actions replayed from its "
                         f"seed give states differing by up to {ep['max_state_diff']:.3g} from frame "
                         f"{ep['first_frame_differing']}, held {replayed.held!r} (recorded {row.held!r})")
                if promised and not exact:
                    self.flag("replay", f"{where}; it was recorded on a rebuilt physx_cpu scene and must replay "
                                        "bit for bit")
                elif ep["max_state_diff"] > REPLAY_DRIFT_TOLERANCE:
                    self.flag("replay", f"{where}; more than a reused scene drifts ({REPLAY_DRIFT_TOLERANCE})")
        finally:
            replayer.close()
        out["replayed"] = len(out["episodes"])
        out["max_state_diff"] = max((e["max_state_diff"] for e in out["episodes"]), default=None)

    # ------------------------------------------------------------------ LeRobot files
    def _episodes_meta(self) -> pd.DataFrame:
        paths = sorted((self.root / "meta" / "episodes").glob("*/*.parquet"))
        if not paths:
            return pd.DataFrame(columns=["episode_index", "length", "tasks"])
        return pd.concat([pd.read_parquet(p, columns=["episode_index", "length", "tasks"]) for p in paths],
                         ignore_index=True)

    def _episode_tasks(self) -> dict[int, list[str]]:
        meta = self._episodes_meta()
        return {int(e): list(t) for e, t in zip(meta["episode_index"], meta["tasks"])}

    def _tasks_table(self) -> pd.DataFrame | None:
        path = self.root / "meta" / "tasks.parquet"
        return pd.read_parquet(path) if path.is_file() else None

    def _frame_tasks(self) -> dict[int, list]:
        """Per episode, the distinct tasks its frames' task_index names in meta/tasks.parquet (None for an index
        the table lacks): LeRobotDataset.__getitem__ reads these, not meta/episodes' `tasks`."""
        table = self._tasks_table()
        if table is None or not len(self._frames):
            return {}
        names = dict(zip(table["task_index"], table.index))
        return {int(e): [names.get(int(i)) for i in sorted(g.unique())]
                for e, g in self._frames.groupby("episode_index")["task_index"]}

    @cached_property
    def _values(self) -> dict[str, np.ndarray]:
        """Every frame's action and state, (frames, dim) float64."""
        data = self._frames
        return {key: np.stack(data[key].to_numpy()).astype(np.float64) if len(data) else np.zeros((0, dim))
                for key, dim in ((ACTION_KEY, ACTION_DIM), (STATE_KEY, STATE_DIM))}

    @cached_property
    def _frames(self) -> pd.DataFrame:
        """Every frame's indices, action and state, read once for the checks that need them."""
        paths = sorted((self.root / "data").glob("*/*.parquet"))
        cols = ["episode_index", "frame_index", "task_index", ACTION_KEY, STATE_KEY]
        if not paths:
            return pd.DataFrame(columns=cols)
        return pd.concat([pd.read_parquet(p, columns=cols) for p in paths], ignore_index=True)


def _same(a, b) -> bool:
    """Equal, with floats compared to the 1e-5 m / rad the layout dict is rounded to."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and abs(a - b) <= 2e-5
    return a == b


def _same_file(a: Path, b: Path) -> bool:
    """The same file (a hard link, as blind copies make) or one with the same bytes."""
    return os.path.samefile(a, b) or filecmp.cmp(a, b, shallow=False)


def _true(value) -> bool:
    return not pd.isna(value) and bool(value)


def _spread(n: int, k: int) -> np.ndarray:
    """min(k, n) distinct positions spread evenly over 0..n-1, first and last included."""
    if k <= 0 or n == 0:
        return np.zeros(0, dtype=int)
    return np.unique(np.linspace(0, n - 1, min(k, n)).round().astype(int))


def _ranges(values) -> str:
    values = sorted(int(v) for v in values)
    return f"{values[0]}-{values[-1]} ({len(values)})" if values else "none"


def check_dataset(cfg: CheckDatasetConfig) -> dict:
    """The summary of every check (`ok`, `violations`, per-check tables); ValueError if DIR is not a dataset."""
    return Checker(cfg).run()


def run(cfg: CheckDatasetConfig) -> int:
    summary = check_dataset(cfg)
    for line in summary["violations"]:
        print(f"check-dataset: {line}", file=sys.stderr)
    if cfg.out is not None:
        files.write_json(cfg.out, summary)
        print(f"wrote {cfg.out}")
    else:
        print(files.dumps(summary, indent=2))
    state = "ok" if summary["ok"] else f"{len(summary['violations'])} violation(s)"
    print(f"{cfg.dataset}: {summary['episodes']} episodes, {summary['frames']} frames: {state}", file=sys.stderr)
    return 0 if summary["ok"] else 1
