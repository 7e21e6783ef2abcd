"""`vla-ladder eval`: a policy on seeded episodes of every condition, written to a run directory.

Episode j of every condition plays seed `first_seed + j`, so every policy meets the same layouts. Episodes
are played by `player.play` (in worker processes on the CPU backend; any number of workers gives the same
episodes) and each becomes one row of episodes.parquet with the final step's decomposed metrics.

A run directory is whole at every moment: episodes.parquet and summary.json are rewritten atomically every
few seconds, so a killed run keeps what it finished. Running the same request again resumes it (only the
missing episodes are played); a different request into the same directory is refused unless --overwrite.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from vla_ladder import files
from vla_ladder.checks import check_count, check_given, check_output_dir
from vla_ladder.conditions import MAX_OBJECTS, Condition, ConditionGrid
from vla_ladder.contract import EPISODE_STEPS, METRICS, contract_changes, fingerprint
from vla_ladder.evaluation.player import PHASES, EnvSettings, Job, play
from vla_ladder.machine import auto_workers, check_workers, cores
from vla_ladder.evaluation.rundir import EPISODE_COLUMNS, read_episodes, run_config
from vla_ladder.policies import (Policy, allowed_specs, check_spec, selection_episodes, training_seeds,
                                 weights_identity)
from vla_ladder.task.object_sets import resolve_object_set
from vla_ladder.task.physx_gpu import check_sim_backend
from vla_ladder.task.robot import check_robot_mesh

FLUSH_SECONDS = 10.0
# Fields of EvalConfig that do not change which episodes are played or what they give: a run directory
# written with other values of these is the same request and is resumed.
NOT_THE_REQUEST = ("out", "workers", "num_envs", "overwrite", "policy_weights", "contract")
# Fields added after run directories existed, with the value a config.json without them meant; they become env
# reset options of every episode when not at that value (the probes, experiments/probes.py, set them).
PRESENTATION = {"instructions": "canonical", "appearance": "original", "instruct": 0, "instruct_absent": None,
                "swap_positions": False, "switch_at": None, "alone": False}


@dataclass
class EvalConfig:
    """Evaluate a policy on seeded episodes of every condition and write a run directory (`vla-ladder eval`)."""

    policy: Annotated[str | None, tyro.conf.arg(metavar="SPEC", help_behavior_hint="")] = None
    """policy spec: scripted, committed, nearest, layout-prior, random, ppo:PATH, lerobot:DIR[?n_action_steps=H&...]
    or remote:ws://HOST:PORT[?n_action_steps=H], or KIND[:ARG] of an installed policy plugin (required on the
    command line; the grid and the study set it per model)"""
    out: Annotated[Path | None, tyro.conf.arg(metavar="DIR", help_behavior_hint="")] = None
    """run directory to write: episodes.parquet, summary.json, config.json, videos/ (required on the command line;
    the grid and the study set it per model); rerunning the same request resumes in it"""
    grid: Annotated[ConditionGrid, tyro.conf.arg(name="")] = field(default_factory=ConditionGrid)
    """the conditions evaluated (every regime of the ladder, canonical, five objects by default)"""
    episodes: int = 100
    """episodes per condition"""
    first_seed: int = 0
    """episode j of every condition plays seed first_seed + j, so every policy meets the same layouts"""
    workers: int = 0
    """worker processes playing episodes on the CPU backend, each with its own copy of the policy (0: one per
    core, capped by memory); any number gives the same episodes"""
    num_envs: int = 1
    """episodes played at once by one copy of the policy, acting on them as a batch (a GPU policy's batched
    inference): physx_cuda simulates them in one process, physx_cpu in num_envs processes in lockstep; any
    number gives the same layouts, targets and instructions, and the same outcomes where the policy rounds alike
    in any batch (docs/evaluation.md says which do); not with --workers > 1"""
    sim_backend: str = "physx_cpu"
    """physx_cpu or physx_cuda (needs a CUDA GPU)"""
    videos: int = 0
    """write MP4s of both cameras for the first K episodes of each condition"""
    object_set: str = "auto"
    """ycb, standin, or auto (YCB when its meshes are on disk, else standin; $VLA_LADDER_OBJECT_SET overrides
    auto)"""
    robot_mesh: str = "lite"
    """lite (decimated visual meshes, fast on a CPU renderer) or full (ManiSkill's); physics is the same"""
    overwrite: bool = False
    """replace a run directory that holds another request (the same request is always resumed)"""
    instructions: str = "canonical"
    """instruction wording: canonical ("grasp the <object>"), paraphrase-train or paraphrase-heldout (drawn per
    episode from its seed, task/paraphrases.json)"""
    appearance: str = "original"
    """original, or swap: the instructed object and a distractor exchange colours (task/appearance.py; one env per
    scene: --num-envs 1)"""
    instruct: int = 0
    """which present object the instruction names: 0 the layout's target, k its k-th distractor, in the same scene
    (the instruction-swap probe plays 0..num_objects-1)"""
    instruct_absent: int | None = None
    """instruct an object that is NOT on the table instead: k names the k-th absent object in the object list's
    order (apple, orange, rubiks_cube, mug, large_marker); the scene is unchanged (the absent-object probe plays
    0..4-num_objects); None: instruct a present object"""
    swap_positions: bool = False
    """the instructed object and one distractor (chosen from the seed) exchange places, everything else unchanged
    (the position-swap probe; task/layouts.py Layout.positions_swapped; needs 2+ objects): scenes where no
    distractor fits collision-free play unswapped and say so (no position_swap in their layout)"""
    switch_at: int | None = None
    """switch the instruction at this control step (1-49) from the instructed object to a distractor chosen from
    the seed, which success is then judged against (the instruction-switch probe; task/layouts.py Layout.switched;
    needs 2+ objects): episodes.parquet's target and instruction are the new ones, the layout's "switch" says
    when and what came first; None: the instruction never changes"""
    alone: bool = False
    """take every distractor off the table, the instructed object staying where the seed put it (the
    distractor-removal probe; task/layouts.py Layout.alone): the layout's "removed" names what stood there"""

    def __post_init__(self):
        self.out = None if self.out is None else check_output_dir(self.out, "--out")  # a file, the root: now
        if not isinstance(self.grid, ConditionGrid):
            self.grid = ConditionGrid(**self.grid)
        for name in ("episodes", "num_envs"):
            check_count(getattr(self, name), name)
        check_count(self.videos, "videos", least=0)
        check_workers(self.workers)
        if self.first_seed < 0 or self.first_seed + self.episodes > 2**32:
            raise ValueError(f"--first-seed must be >= 0 and --first-seed + --episodes <= 2**32 (episode j plays "
                             f"numpy seed first_seed + j), got {self.first_seed} + {self.episodes}")
        check_sim_backend(self.sim_backend)
        if self.sim_backend == "physx_cpu" and self.num_envs > cores():
            raise ValueError(f"--sim-backend physx_cpu runs one process per env: --num-envs must be at most the "
                             f"{cores()} CPU cores here, got {self.num_envs}")
        if self.num_envs > 1 and self.workers > 1:
            raise ValueError(f"--workers {self.workers} and --num-envs {self.num_envs}: choose one, --workers N (N "
                             "copies of the policy, one per process) or --num-envs N (one policy acting on N envs)")
        if self.sim_backend == "physx_cuda":
            from vla_ladder.task.physx_gpu import check_physx_cuda
            check_physx_cuda("sim_backend=physx_cuda needs a CUDA GPU; allowed here: physx_cpu")
        # A known set, YCB's meshes on disk, and $VLA_LADDER_OBJECT_SET (for auto) naming a set: said here, not once the
        # run directory is written and the workers are building their envs.
        resolve_object_set(self.object_set)
        check_robot_mesh(self.robot_mesh)
        from vla_ladder.task.appearance import check_appearance
        from vla_ladder.task.instructions import check_instruction_set
        check_instruction_set(self.instructions)
        if check_appearance(self.appearance) != "original" and self.num_envs > 1:
            raise ValueError(f"appearance={self.appearance} paints each scene: needs num_envs=1, got {self.num_envs}")
        fewest = min(self.grid.num_objects)
        if isinstance(self.instruct, bool) or not 0 <= self.instruct < fewest:
            raise ValueError(f"instruct must be a present-object rank from 0 to {fewest - 1} (the grid's fewest "
                             f"objects: {fewest}), got {self.instruct!r}")
        if check_appearance(self.appearance) != "original" and self.instruct != 0:
            # The colour swap pairs the seed's own target with a distractor, not the object instructed instead.
            raise ValueError(f"appearance={self.appearance} swaps the colours of the seed's own instructed object "
                             f"(instruct 0) and a distractor; instruct {self.instruct} names another: give one")
        if self.instruct_absent is not None:
            missing = MAX_OBJECTS - max(self.grid.num_objects)  # the fewest absent objects of any condition
            if isinstance(self.instruct_absent, bool) or not 0 <= self.instruct_absent < missing:
                allowed = (f"from 0 to {missing - 1} (the grid's most objects: {max(self.grid.num_objects)})"
                           if missing else "none: 5 objects leave none off the table (allowed: --num-objects 1-4)")
                raise ValueError(f"instruct_absent must be an absent-object rank {allowed}, got "
                                 f"{self.instruct_absent!r}")
            if self.instruct != 0:
                raise ValueError(f"instruct {self.instruct} and instruct_absent {self.instruct_absent} each name the "
                                 "instructed object; give one")
        if self.switch_at is not None and (isinstance(self.switch_at, bool)
                                           or not 1 <= self.switch_at < EPISODE_STEPS):
            raise ValueError(f"switch_at must be a control step from 1 to {EPISODE_STEPS - 1} (the episode has "
                             f"{EPISODE_STEPS}), got {self.switch_at!r}")
        # Each acts on a present distractor beside the instructed object, which must itself be on the table.
        if self.alone and (self.swap_positions or self.switch_at is not None):
            raise ValueError("alone takes the distractors off the table, which swap_positions and switch_at need; "
                             "give one")
        for name, active, does in (("swap_positions", self.swap_positions, "moves the instructed object"),
                                   ("switch_at", self.switch_at is not None,
                                    "switches from the instructed object to another present one"),
                                   ("alone", self.alone, "leaves the instructed object alone")):
            if active and min(self.grid.num_objects) < 2:
                raise ValueError(f"{name} needs at least two objects on the table; got --num-objects "
                                 f"{' '.join(map(str, self.grid.num_objects))} (allowed: 2-5)")
            if active and self.instruct_absent is not None:
                raise ValueError(f"{name} {does} and instruct_absent names one that is not on the table; give one")

    @property
    def conditions(self) -> list[Condition]:
        return self.grid.conditions

    def request(self) -> dict:
        """What decides the run's episodes: config.json without the fields that do not."""
        return {k: v for k, v in files.plain(asdict(self)).items()
                if k not in NOT_THE_REQUEST}

    def reset_options(self) -> tuple[tuple[str, object], ...]:
        """Env reset options of every episode: the presentation fields that are not at their defaults."""
        return tuple((k, getattr(self, k)) for k, default in PRESENTATION.items() if getattr(self, k) != default)

    def jobs(self) -> list[Job]:
        out, options = self.out, self.reset_options()
        return [Job(c, j, self.first_seed + j, options, video=str(out / video_name(c, j, self.first_seed + j))
                    if out is not None and j < self.videos else "")
                for c in self.conditions for j in range(self.episodes)]


def video_name(condition: Condition, episode: int, seed: int) -> str:
    return f"videos/{condition.slug}-ep{episode:03d}-seed{seed}.mp4"


def saved_request(config: dict) -> dict:
    """A saved EvalConfig (config.json) as the request it made, as EvalConfig.request() gives it now: without the
    fields that do not decide its episodes, and with fields added since at the value their absence meant."""
    return {k: v for k, v in {**PRESENTATION, **config}.items() if k not in NOT_THE_REQUEST}


def open_run_dir(cfg: EvalConfig, weights: dict | None = None) -> list[dict]:
    """Make cfg.out ready and return the rows it already holds for this request (resume). A directory that
    holds another request, or is not a run directory, is refused unless cfg.overwrite; so is one whose episodes
    were played with other weights at the same path (`weights`: policies.weights_identity, kept in config.json
    as policy_weights) or under another task contract (contract.fingerprint, kept as contract); run directories
    from before either was kept resume unchecked on it."""
    out, saved = cfg.out, cfg.out / "config.json"
    config = run_config(saved)
    previous = saved_request(config) if config is not None else None
    before = (config or {}).get("policy_weights")
    other = []
    if before and weights and before["sha256"] != weights["sha256"]:
        other.append(f"other weights at {cfg.policy} (sha256 {before['sha256'][:12]}, now {weights['sha256'][:12]}: "
                     "retrained?)")
    if changed := contract_changes((config or {}).get("contract")):
        other.append(f"another task contract ({'; '.join(changed)})")
    if other and previous == cfg.request():
        if not cfg.overwrite:
            raise ValueError(f"{out} holds episodes of {' and '.join(other)}; evaluate into a new --out, or pass "
                             "--overwrite to start again")
        previous = {}  # another model or task: --overwrite starts afresh
    files.claim_dir(out, previous, cfg.request(), cfg.overwrite, "evaluation", "a run directory")
    for name in ("episodes.parquet", "summary.json", "config.json"):  # writes a kill -9 cut short (files.atomic_path;
        for stale in out.glob(f".{name}.*.tmp"):  # nobody else writes here: this process holds the directory's lock)
            stale.unlink(missing_ok=True)
    files.write_json(saved, {**asdict(cfg), **({"policy_weights": weights} if weights else {}),
                             "contract": fingerprint()})
    path = out / "episodes.parquet"
    if not path.is_file():
        return []
    rows = read_episodes(path).to_dict("records")
    played_with, here = {r.get("object_set") for r in rows} - {None}, resolve_object_set(cfg.object_set)
    if played_with and played_with != {here}:  # "auto" resolves per machine: a resume elsewhere may not match
        raise ValueError(f"{path} holds episodes played with the {'/'.join(sorted(played_with))} objects, and "
                         f"object_set={cfg.object_set!r} plays the {here} objects here; resume where its episodes were "
                         f"played (or with $VLA_LADDER_OBJECT_SET={next(iter(played_with))}), or evaluate into a new "
                         "--out")
    # What this request plays, each once: anything else (an edited or mixed file) would be counted in its summary.
    played = Counter((r["regime"], r["split"], r["num_objects"], r["episode"]) for r in rows)
    planned = {(j.condition.regime, j.condition.split, j.condition.num_objects, j.episode) for j in cfg.jobs()}
    if odd := sorted({k for k, n in played.items() if n > 1 or k not in planned}):
        raise ValueError(f"{path} holds episodes this request does not play, or holds them twice ("
                         f"{', '.join(f'{Condition(*k[:3]).key} episode {k[3]}' for k in odd[:3])}"
                         f"{f' and {len(odd) - 3} more' if len(odd) > 3 else ''}); its files were edited or mixed: "
                         "evaluate into a new --out")
    return rows


def timing_summary(totals: dict[str, float]) -> dict:
    """summary.json's `timing` from the played episodes' summed shares of their batches' time (player.PHASES).
    Worker processes play side by side, so with workers > 1 the seconds add up to more than the wall time;
    per_step_ms is the time of one step of a batch (num_envs episodes at once) in the policy and in the env;
    wall_s is the commands' own time (process start-up and policy loading included)."""
    steps = totals["lockstep_steps"]
    untimed = {"untimed_episodes": int(totals["untimed_episodes"])} if totals.get("untimed_episodes") else {}
    return {"episodes": int(totals["episodes"]), **untimed, "wall_s": round(totals["wall_s"], 1),
            "lockstep_steps": round(steps), **{f"{p}_s": round(totals[f"{p}_s"], 3) for p in PHASES},
            "per_step_ms": {p: round(1e3 * totals[f"{p}_s"] / steps, 2) if steps else None for p in ("policy", "env")}}


def timing_totals(saved: dict) -> dict[str, float]:
    """A run's timing totals, going on from a saved summary.json `timing` (zeros for a new run, or one written
    before timings were kept)."""
    return {k: float(saved.get(k, 0)) for k in ("episodes", "untimed_episodes", "wall_s", "lockstep_steps",
                                                *(f"{p}_s" for p in PHASES))}


def add_timing(totals: dict[str, float], timing: dict[str, float]) -> None:
    """Add one episode's share of its batch's time (a player row's `timing`) to a run's totals."""
    totals["episodes"] += 1
    totals["lockstep_steps"] += timing["steps"]
    for p in PHASES:
        totals[f"{p}_s"] += timing[f"{p}_s"]


def summarize_run(rows: list[dict], cfg: EvalConfig, policy_info: dict, timing: dict | None = None) -> tuple:
    """Rows in condition order, and the summary.json of a (possibly partial) run; `timing`: the totals that
    add_timing kept, for summary.json's `timing`."""
    import pandas as pd

    from vla_ladder.evaluation.metrics import summarize

    order = {c.key: i for i, c in enumerate(cfg.conditions)}
    rows = sorted(rows, key=lambda r: (order[Condition(r["regime"], r["split"], r["num_objects"]).key],
                                       r["episode"]))
    df = pd.DataFrame(rows, columns=list(EPISODE_COLUMNS))
    summary = {"policy": policy_info, "provenance": {**files.provenance(df["object_set"].iloc[0] if len(df) else None),
                                                     "robot_mesh": cfg.robot_mesh},
               "first_seed": cfg.first_seed, "episodes_per_condition": cfg.episodes,
               "complete": len(df) == len(cfg.conditions) * cfg.episodes, "conditions": summarize(df)}
    if timing is not None:
        summary["timing"] = timing_summary(timing)
    return df, summary


def selection_overlap(cfg: EvalConfig) -> int:
    """How many of the run's episodes the checkpoint was chosen on (said before the run, and kept in summary.json as
    episodes_seen_in_selection): a train-expert run's checkpoints/best is the best of its evaluations on seeds
    eval_first_seed + j of its training conditions, and its success on those episodes leans high."""
    held = selection_episodes(cfg.policy)
    seeds = range(cfg.first_seed, cfg.first_seed + cfg.episodes)
    overlap = sum(len(range(max(seeds.start, held[c.key].start), min(seeds.stop, held[c.key].stop)))
                  for c in cfg.conditions if c.key in held)
    if overlap:
        last = max(r.stop for r in held.values())
        print(f"[eval] warning: {cfg.policy} was chosen as the best of its training evaluations, on seeds "
              f"{min(r.start for r in held.values())} to {last - 1}; {overlap} of the "
              f"{len(cfg.conditions) * cfg.episodes} episodes here are among them, so its rates lean high; "
              f"--first-seed {last} or above plays held-out episodes")
    return overlap


def training_overlap(cfg: EvalConfig) -> int:
    """How many of the run's episodes play a seed the checkpoint's training demonstrations were recorded on (said
    before the run, and kept in summary.json as episodes_on_training_seeds): a seed is a scene, in the data's
    condition its very layout, target and instruction, in the other jitter regimes nearly the same one, so its rates
    there lean high. `record` starts at RECORD_FIRST_SEED for that reason; a recording made from seed 0 and
    evaluated from 0 played the model's own demonstrations."""
    seeds, jobs = training_seeds(cfg.policy), cfg.jobs()
    overlap = sum(j.seed in seeds for j in jobs)
    if overlap:
        print(f"[eval] warning: {overlap} of the {len(jobs)} episodes here play seeds that {cfg.policy}'s "
              f"training data were recorded on ({min(seeds)} to {max(seeds)}): the same scenes in the data's "
              f"condition, nearly the same in the other jitter regimes, so its rates lean high; --first-seed "
              f"{max(seeds) + 1} or above plays unseen ones")
    return overlap


def run_evaluation(cfg: EvalConfig, policy: Policy | None = None, progress: bool = True) -> dict:
    """Evaluate cfg.policy (or `policy`, an instance labelled cfg.policy, played in this process) on every
    condition and return the summary dict; with cfg.out, also write (or resume) the run directory, holding its
    lock (files.writing)."""
    started = time.monotonic()
    if policy is None:
        if not cfg.policy:
            raise ValueError("--policy SPEC is required; allowed: " + allowed_specs())
        # An unknown spec or a missing checkpoint fails before any file is written; a policy server must take a
        # connection per worker process (one for a batch of envs).
        check_spec(cfg.policy, connections=1 if cfg.num_envs > 1 else min(auto_workers(cfg.workers),
                                                                           max(len(cfg.jobs()), 1)))
    spec = cfg.policy or policy.name
    overlap = selection_overlap(cfg) if policy is None else 0
    seen = training_overlap(cfg) if policy is None else 0
    weights = weights_identity(cfg.policy) if policy is None and cfg.out is not None else None
    with files.writing(cfg.out, "evaluation") if cfg.out is not None else contextlib.nullcontext():
        return _evaluate(cfg, policy, spec, overlap, weights, progress, started, seen)


def _evaluate(cfg: EvalConfig, policy: Policy | None, spec: str, overlap: int, weights: dict | None,
              progress: bool, started: float, seen: int = 0) -> dict:
    from tqdm.auto import tqdm

    rows = open_run_dir(cfg, weights) if cfg.out is not None else []
    done = {(r["regime"], r["split"], r["num_objects"], r["episode"]) for r in rows}
    jobs = [j for j in cfg.jobs() if (j.condition.regime, j.condition.split, j.condition.num_objects, j.episode)
            not in done]
    if rows and cfg.out is not None:
        print(f"[eval] resuming {cfg.out}: {len(rows)} episodes done, {len(jobs)} to play")
    obs_mode = policy.obs_mode if policy is not None else None
    settings = EnvSettings(cfg.sim_backend, cfg.num_envs, cfg.object_set, cfg.robot_mesh, render=cfg.videos > 0)
    saved = json.loads((cfg.out / "summary.json").read_text()) \
        if rows and cfg.out is not None and (cfg.out / "summary.json").is_file() else {}
    policy_info = saved.get("policy", {"name": spec})
    # A resumed run's timing goes on from the seconds its earlier invocations recorded.
    timing = timing_totals(saved.get("timing", {}))
    # A kill between the two files' writes leaves episodes.parquet ahead of summary.json: those episodes' time is
    # lost, and said (untimed_episodes), so that the timed and the untimed still add up to the rows.
    timing["untimed_episodes"] += max(0, len(rows) - timing["episodes"] - timing["untimed_episodes"])
    wall_before = timing["wall_s"]
    workers = 1 if obs_mode is not None else min(auto_workers(cfg.workers), max(len(jobs), 1))
    bar = tqdm(total=len(cfg.conditions) * cfg.episodes, initial=len(rows), desc=f"eval {spec}", unit="ep",
               disable=not progress)
    last_flush = time.monotonic()
    summary: dict = {}

    def flush() -> dict:
        timing["wall_s"] = wall_before + time.monotonic() - started
        df, summary = summarize_run(rows, cfg, policy_info, timing)
        if overlap:
            summary["episodes_seen_in_selection"] = overlap
        if seen:
            summary["episodes_on_training_seeds"] = seen
        if cfg.out is not None:
            files.write_parquet(cfg.out / "episodes.parquet", df)
            files.write_json(cfg.out / "summary.json", summary)
        return summary

    try:
        for job, row in play(jobs, spec, settings, workers=workers, policy=policy):
            policy_info = row.pop("policy_info")
            add_timing(timing, row.pop("timing"))
            c = job.condition
            rows.append(dict(policy=spec, regime=c.regime, split=c.split, num_objects=c.num_objects,
                             episode=job.episode, **{**row, "layout": files.dumps(row["layout"])},
                             video=job.video and str(Path(job.video).relative_to(cfg.out))))
            bar.update(1)
            bar.set_postfix(condition=c.key, success=f"{np.mean([r['success'] for r in rows]):.2f}")
            if time.monotonic() - last_flush >= FLUSH_SECONDS:
                flush()
                last_flush = time.monotonic()
    finally:
        bar.close()
        if rows:
            summary = flush()
    return summary


def run(cfg: EvalConfig) -> int:
    check_given(("--policy SPEC", cfg.policy, "SPEC: " + allowed_specs()),
                ("--out DIR", cfg.out, "DIR: the run directory to write"))
    summary = run_evaluation(cfg)
    for key, c in summary["conditions"].items():
        print(f"{key}: n={c['n']} " + " ".join(f"{m}={c[m]:.3f}" for m in METRICS))
    t = summary.get("timing", {})
    if t.get("lockstep_steps"):
        print(f"time: {t['per_step_ms']['policy']} ms a step in the policy, {t['per_step_ms']['env']} ms in the env "
              f"({cfg.num_envs} at once); resets {t['reset_s']:.1f} s, filming {t['film_s']:.1f} s and encoding the "
              f"videos {t['encode_s']:.1f} s in all")
    print(f"wrote {cfg.out}/episodes.parquet, summary.json, config.json")
    return 0
