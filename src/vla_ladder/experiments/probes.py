"""`vla-ladder probe NAME --policy SPEC --out DIR`: does the policy grasp what it is told, or something else?

Every probe plays the same seeded scenes in several variants, each an ordinary evaluation run directory under
DIR (so `vla-ladder compare DIR/a DIR/b` and `vla-ladder report DIR/*/` work on them), then writes
DIR/probe.json (metrics with 95% intervals, evaluation/grounding.py), DIR/<probe>.png and DIR/report.html:

- instruction-swap: each scene once per present object, instructing each in turn (instruct-0 is the layout's
  own target, instruct-k its k-th distractor; layout, colours, robot start and physics identical). Instruction
  sensitivity, scene accuracy, grounded accuracy, the normalised mutual information between instructed and
  held object, and the instructed x held matrix. This tells "follows the instruction through a location"
  (layout-prior: sensitive everywhere, grounded under small jitter only; under full random its grounded accuracy
  and NMI fall to chance) from "ignores it" (nearest: never sensitive).
- paraphrase: canonical, paraphrase-train and paraphrase-heldout wordings of the same scenes, and the
  distractor-free control (the same with one object on the table: a drop there is the wording upsetting the
  motion, not object selection).
- appearance-swap: original and swap (the instructed object and a distractor exchange colours): does the
  policy follow the named object's shape or its usual colour?
- absent-object: with fewer than five objects on the table, each scene once as it is (present) and once per
  object NOT on the table, instructing it (absent-k; the scene is identical). A policy that grounds the words in
  what it sees has nothing to grasp; one that maps the words to a place goes to where the named object usually
  stood (shortcut reach); one that ignores the instruction grasps what it grasps anyway.
- position-swap: each scene as it is (original) and with the instructed object and one distractor exchanging
  places (swapped; everything else identical). A policy that follows the named object goes to its new place; a
  location shortcut grasps the partner, which now stands where the instructed object stood.
- instruction-switch: each scene as it is (original) and once per switch step K (switch-K): the episode starts
  instructing its target A and at control step K the instruction (and the target success is judged against)
  switches to a distractor B drawn from the seed. A policy that keeps reading its instruction goes to B when the
  switch comes early; one that commits to its first reading goes on to A; one that ignores it plays the same.
- distractor-removal: each scene as it is (original) and with every distractor taken off the table (alone; the
  instructed object where it stood). A failure that turns into success alone was the distractors' doing (the
  policy chose, or was drawn to, another object); one that stays is the policy's own, with nothing to choose.

Rerunning the same command resumes every variant; another request into DIR is refused unless --overwrite. Every
probe pairs its variants' plays in one place (grounding.common_scenes): a scene some variant lacks is left out and
counted (`left_out` in probe.json, said by the report), a scene played with different seeds is an error.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, ClassVar

import pandas as pd
import tyro

from vla_ladder import files
from vla_ladder.conditions import MAX_OBJECTS, ConditionGrid
from vla_ladder.contract import EPISODE_STEPS
from vla_ladder.evaluation import grounding
from vla_ladder.evaluation.rundir import Run, load_run
from vla_ladder.evaluation.runner import EvalConfig, run_evaluation
from vla_ladder.policies import Policy, allowed_specs, check_spec, parse_spec
from vla_ladder.task.appearance import SWAPS, SWAPS_VERSION
from vla_ladder.task.instructions import INSTRUCTION_SETS, paraphrase_version
from vla_ladder.checks import check_given, check_output_dir

PROBE_FILE = "probe.json"
CONFIG_FILE = "probe_config.json"
FORMAT_VERSION = 1
NOT_THE_REQUEST = ("out", "workers", "num_envs", "overwrite", "report", "resamples")
MAX_RESAMPLES = 100_000  # 50x the default: a few minutes of numpy at most, after every episode has been played
SWITCH_STEPS = (5, 25)
"""The instruction switch's default control steps (of 50 at 20 Hz): 5 (0.25 s) comes before the scripted expert
closes its gripper in every scene measured (it closes at step 8-14, rarely later, docs/probes.md), so a policy that
re-reads its instruction can still go to the new object; 25 (1.25 s) comes after it has closed and lifted in almost
every scene, so even a re-reading expert has committed: the contrast separates reading from committing."""


@dataclass(frozen=True)
class Probe:
    """What makes a grounding probe: the variants it plays of every scene and the metrics it draws from their
    episodes. Its table, figure and text live in report/probes.py under the same name (VIEWS)."""

    variants: Callable[[ProbeConfig], dict[str, dict]]
    """the probe's config -> variant name -> the EvalConfig fields (beyond policy, seeds, players and out) that play
    it; each variant is an ordinary run directory"""
    results: Callable[[dict[str, Run], int], dict]
    """(the finished variant runs, resamples) -> the metrics per condition (evaluation/grounding.py)"""
    objects: tuple[int, int] = (1, MAX_OBJECTS)
    """the least and most objects on the table it can probe"""
    needs: str = ""
    """what it needs of the table, for the error when --num-objects falls outside `objects`"""
    default_objects: int = MAX_OBJECTS
    """objects on the table when --num-objects is not given"""
    one_env: bool = False
    """it paints each scene's objects, so plays one env per copy of the policy (never --num-envs > 1)"""
    options: tuple[str, ...] = ()
    """ProbeConfig fields only this probe reads: part of its request only, so other probes' directories (written
    before the field existed) still resume"""
    check: Callable[[ProbeConfig], None] | None = None
    """raises ValueError on a bad value of one of its options"""

    def fit(self, num_objects: int) -> int:
        """The object count nearest to `num_objects` that the probe can play (a study's or diagnosis's training
        condition with five objects is probed with four for absent-object: the nearest scenes that leave one to
        name)."""
        return min(max(num_objects, self.objects[0]), self.objects[1])


def _index(name: str) -> int:
    """k of a variant named like "instruct-k", "absent-k" or "switch-k"."""
    return int(name.rsplit("-", 1)[1])


def _swap_variants(cfg: ProbeConfig) -> dict[str, dict]:
    g = cfg.grid  # instruct-0 is the layout's own target, instruct-k its k-th distractor (scenes with more than k)
    return {f"instruct-{r}": dict(grid=ConditionGrid(g.regimes, g.splits, tuple(k for k in g.num_objects if k > r)),
                                  instruct=r) for r in range(max(g.num_objects))}


def _swap_results(runs: dict[str, Run], resamples: int) -> dict:
    plays = pd.concat([r.episodes.assign(instruct=_index(name)) for name, r in runs.items()], ignore_index=True)
    return grounding.instruction_swap(plays, resamples)


def _paraphrase_variants(cfg: ProbeConfig) -> dict[str, dict]:
    g = cfg.grid  # with the distractor-free control: one object on the table
    control = ConditionGrid(g.regimes, g.splits, tuple(sorted({*g.num_objects, 1}, reverse=True)))
    return {s: dict(grid=control, instructions=s) for s in INSTRUCTION_SETS}


def _absent_variants(cfg: ProbeConfig) -> dict[str, dict]:
    g = cfg.grid  # absent-k names the k-th object off the table (fewer objects: more of them)
    return {"present": dict(grid=g), **{
        f"absent-{k}": dict(grid=ConditionGrid(g.regimes, g.splits, tuple(n for n in g.num_objects
                                                                          if n < MAX_OBJECTS - k)), instruct_absent=k)
        for k in range(MAX_OBJECTS - min(g.num_objects))}}


def _absent_results(runs: dict[str, Run], resamples: int) -> dict:
    absent = pd.concat([r.episodes.assign(absent=_index(name)) for name, r in runs.items() if name != "present"],
                       ignore_index=True)
    return grounding.absent_object(runs["present"].episodes, absent)


def _switch_variants(cfg: ProbeConfig) -> dict[str, dict]:
    # original: exactly `vla-ladder eval`
    return {"original": dict(grid=cfg.grid), **{f"switch-{k}": dict(grid=cfg.grid, switch_at=k)
                                                for k in sorted(cfg.switch_steps)}}


def _switch_results(runs: dict[str, Run], resamples: int) -> dict:
    return grounding.instruction_switch(runs["original"].episodes, {_index(name): r.episodes for name, r in runs.items()
                                                                    if name != "original"})


def _check_switch(cfg: ProbeConfig) -> None:
    if (not cfg.switch_steps or len(set(cfg.switch_steps)) != len(cfg.switch_steps)
            or any(isinstance(k, bool) or not isinstance(k, int) or not 1 <= k < EPISODE_STEPS
                   for k in cfg.switch_steps)):
        raise ValueError(f"--switch-steps must be distinct control steps from 1 to {EPISODE_STEPS - 1} (the "
                         f"episode has {EPISODE_STEPS}), got {' '.join(map(str, cfg.switch_steps)) or 'none'}")


def _against_original(second: str, options: dict, metrics: Callable[[pd.DataFrame, pd.DataFrame], dict],
                      **kw) -> Probe:
    """A probe playing each scene as it is (original: exactly `vla-ladder eval`) and once more with `options` (the
    variant `second`), scored by metrics(original episodes, second episodes)."""
    return Probe(lambda cfg: {"original": dict(grid=cfg.grid), second: dict(grid=cfg.grid, **options)},
                 lambda runs, _: metrics(runs["original"].episodes, runs[second].episodes), **kw)


TWO = dict(objects=(2, MAX_OBJECTS), needs="at least two objects on the table")
PROBES: dict[str, Probe] = {
    "instruction-swap": Probe(_swap_variants, _swap_results, **TWO, options=("resamples",)),
    "paraphrase": Probe(_paraphrase_variants, lambda runs, _: grounding.paraphrase(
        {name: r.episodes for name, r in runs.items()})),
    "appearance-swap": _against_original("swap", {"appearance": "swap"}, grounding.appearance_swap, **TWO,
                                         one_env=True),
    # with three objects on the table, two are absent in every scene
    "absent-object": Probe(_absent_variants, _absent_results, objects=(1, MAX_OBJECTS - 1),
                           needs="an object off the table", default_objects=3),
    # scenes without a collision-free swap play unswapped (left out of the metrics)
    "position-swap": _against_original("swapped", {"swap_positions": True}, grounding.position_swap, **TWO),
    "instruction-switch": Probe(_switch_variants, _switch_results, **TWO, options=("switch_steps",),
                                check=_check_switch),
    "distractor-removal": _against_original("alone", {"alone": True}, grounding.distractor_removal, **TWO),
}
"""The probes by name, in the order the CLI and reports list them."""
_OWN_COUNTS = "".join(f"; {name}: {p.default_objects}" for name, p in PROBES.items()
                      if p.default_objects != MAX_OBJECTS)


@dataclass(frozen=True)
class ProbeGrid(ConditionGrid):
    """A ConditionGrid whose object counts, left out, are the probe's own (Probe.default_objects): ProbeConfig
    resolves it to a plain ConditionGrid once it knows the probe."""

    num_objects: Annotated[tuple[int, ...], tyro.conf.arg(
        help_behavior_hint=f"(default: {MAX_OBJECTS}{_OWN_COUNTS})")] = ()
    """objects on the table, 1-5 (several give several conditions)"""

    def __post_init__(self):
        if self.num_objects:
            super().__post_init__()


@dataclass
class ProbeConfig:
    """Probe instruction grounding on the same seeded scenes (`vla-ladder probe NAME --policy SPEC --out DIR`)."""

    name: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="NAME", help=f"the probe: {', '.join(PROBES)}")]
    policy: Annotated[str | None, tyro.conf.arg(metavar="SPEC", help_behavior_hint="(required)")] = None
    """policy spec, as `vla-ladder eval --policy`: scripted, committed, nearest, layout-prior, random, ppo:PATH,
    lerobot:DIR[?...], remote:ws://HOST:PORT or a plugin's KIND[:ARG]"""
    out: Annotated[Path | None, tyro.conf.arg(metavar="DIR", help_behavior_hint="(required)")] = None
    """probe directory: one run directory per variant, probe.json, the figure, report.html; rerunning the same
    request resumes in it"""
    grid: Annotated[ProbeGrid, tyro.conf.arg(name="")] = field(
        default_factory=lambda: ProbeGrid(("small_jitter", "full_random")))
    """the conditions probed (by default the two ends of the ladder, canonical, five objects; absent-object:
    three)"""
    episodes: int = 50
    """scenes per condition (scene j plays seed first_seed + j in every variant)"""
    first_seed: int = 0
    """scene j of every condition plays seed first_seed + j, the seeds `vla-ladder eval` uses"""
    workers: int = 0
    """worker processes playing episodes on the CPU backend, each with its own copy of the policy (0: one per
    core, capped by memory); any number gives the same episodes"""
    num_envs: int = 1
    """episodes played at once by one copy of the policy (physx_cuda: in one process; physx_cpu: in num_envs
    processes in lockstep; not with --workers > 1; appearance-swap needs 1)"""
    sim_backend: str = "physx_cpu"
    """physx_cpu or physx_cuda (needs a CUDA GPU)"""
    object_set: str = "auto"
    """ycb, standin, or auto (YCB when its meshes are on disk, else standin; $VLA_LADDER_OBJECT_SET overrides
    auto)"""
    robot_mesh: str = "lite"
    """lite (decimated visual meshes, fast on a CPU renderer) or full (ManiSkill's); physics is the same"""
    videos: int = 0
    """write MP4s of both cameras for the first K scenes of each condition, in every variant"""
    resamples: int = grounding.RESAMPLES
    """instruction-swap only: shuffles of its permutation null (its NMI's p-value)"""
    report: bool = True
    """write report.html (the variants' results and the probe's section)"""
    overwrite: bool = False
    """replace a probe directory that holds another request (the same request is always resumed)"""
    switch_steps: tuple[int, ...] = SWITCH_STEPS
    """instruction-switch only: the control steps (1-49) at which the instruction switches, one variant each"""

    REQUIRED_ON_COMMAND_LINE: ClassVar[tuple[str, ...]] = ("policy", "out")

    def __post_init__(self):
        if self.name not in PROBES:
            raise ValueError(f"unknown probe {self.name!r}; allowed: {', '.join(PROBES)}")
        probe = PROBES[self.name]
        self.out = None if self.out is None else check_output_dir(self.out, "--out")  # a file, the root: now
        if not isinstance(self.grid, ConditionGrid):
            self.grid = ProbeGrid(**self.grid)
        g = self.grid
        self.grid = ConditionGrid(g.regimes, g.splits, g.num_objects or (probe.default_objects,))
        if self.policy is not None:
            parse_spec(self.policy)
        if not 100 <= self.resamples <= MAX_RESAMPLES:  # bounded, since they come after every episode
            raise ValueError(f"--resamples must be from 100 to {MAX_RESAMPLES}, got {self.resamples}")
        counts, (least, most) = self.grid.num_objects, probe.objects
        if min(counts) < least or max(counts) > most:
            raise ValueError(f"{self.name} needs {probe.needs}; got --num-objects {' '.join(map(str, counts))} "
                             f"(allowed: {least}-{most})")
        self.switch_steps = tuple(self.switch_steps)
        for other, p in PROBES.items():  # another probe's option, given here, would be ignored
            for option in set(p.options) - set(probe.options):
                if getattr(self, option) != ProbeConfig.__dataclass_fields__[option].default:
                    raise ValueError(f"--{option.replace('_', '-')} is {other}'s option; {self.name} has none")
        if probe.check is not None:
            probe.check(self)
        self.switch_steps = tuple(sorted(self.switch_steps))  # the same variants in any order: the same request
        if probe.one_env and self.num_envs != 1:
            raise ValueError(f"{self.name} paints each scene's objects and needs --num-envs 1, got {self.num_envs}")
        self.variants()  # every evaluation is configured, and so checked, before a simulator starts

    def variants(self) -> dict[str, EvalConfig]:
        """Variant name -> the evaluation that plays it (its run directory is out/<name>)."""
        plays = PROBES[self.name].variants(self)
        return {name: EvalConfig(policy=self.policy, out=None if self.out is None else self.out / name,
                                 episodes=self.episodes, first_seed=self.first_seed, workers=self.workers,
                                 num_envs=self.num_envs, sim_backend=self.sim_backend, videos=self.videos,
                                 object_set=self.object_set, robot_mesh=self.robot_mesh, overwrite=self.overwrite,
                                 **kw) for name, kw in plays.items()}

    def request(self) -> dict:
        return the_request(files.plain(asdict(self)), self.name)


def the_request(config: dict, name: str) -> dict:
    """What decides probe `name`'s episodes: its config without the fields that do not, and without other probes'
    own options (Probe.options: so directories written before such an option existed still resume)."""
    others = {o for p in PROBES.values() for o in p.options} - set(PROBES[name].options)
    return {k: v for k, v in config.items() if k not in NOT_THE_REQUEST and k not in others}


def open_probe_dir(cfg: ProbeConfig) -> None:
    """Make cfg.out ready: resume the same request, refuse another unless --overwrite (then start afresh)."""
    saved = cfg.out / CONFIG_FILE
    previous = the_request(json.loads(saved.read_text()), cfg.name) if saved.is_file() else None
    files.claim_dir(cfg.out, previous, cfg.request(), cfg.overwrite, "probe", "a probe directory")
    files.write_json(saved, asdict(cfg))


def probe_results(probe: str, runs: dict[str, Run], resamples: int) -> dict:
    """The probe's metrics per condition from its finished variant runs."""
    if probe not in PROBES:
        raise ValueError(f"unknown probe {probe!r}; allowed: {', '.join(PROBES)}")
    return PROBES[probe].results(runs, resamples)


def rescore_probe(out: Path) -> dict:
    """Recompute a finished probe's metrics from its variants' episodes (no policy loaded, nothing played) and
    rewrite probe.json and its figure. A study's report does this for each probe, so a re-run of a finished
    study brings the current metrics and intervals to plays made with an older vla-ladder. As when the probe
    ran, scenes some variant lacks are left out and counted (grounding.common_scenes). An interrupted probe has
    no probe.json yet (it is written once every variant has played), and its cut-short variant is an incomplete
    run directory, which load_run refuses: both say to run the command again, which resumes it."""
    if not (out / PROBE_FILE).is_file():
        raise ValueError(f"{out} holds no {PROBE_FILE}: its probe has not finished (interrupted?); rerun the same "
                         "`vla-ladder probe` command, which resumes it")
    data = json.loads((out / PROBE_FILE).read_text())
    runs = {name: load_run(out / rel) for name, rel in data["variants"].items()}
    data["conditions"] = probe_results(data["probe"], runs, data["config"]["resamples"])
    save_probe(out, data)
    return data


def save_probe(out: Path, data: dict) -> None:
    """probe.json and the probe's figure."""
    from vla_ladder.report import probes as probe_report

    files.write_json(out / PROBE_FILE, data)
    probe_report.plot_probe(data, out / f"{data['probe']}.png")


def run_probe(cfg: ProbeConfig, policy: Policy | None = None, progress: bool = True) -> dict:
    """Play every variant (resuming), then write probe.json, the figure and (cfg.report) report.html."""
    check_given(("--policy SPEC", cfg.policy or policy is not None, "SPEC: " + allowed_specs()),
                ("--out DIR", cfg.out, "DIR: the probe directory to write"))
    if policy is None:
        check_spec(cfg.policy)  # a missing checkpoint or server fails before the probe directory is written
    with files.writing(cfg.out, "probe"):  # a second one with --overwrite would remove this one's variants
        return _play_probe(cfg, policy, progress)


def _play_probe(cfg: ProbeConfig, policy: Policy | None, progress: bool) -> dict:
    open_probe_dir(cfg)
    runs: dict[str, Run] = {}
    for name, ec in cfg.variants().items():
        print(f"[probe {cfg.name}] {name}: {', '.join(c.key for c in ec.conditions)}, {ec.episodes} scenes -> {ec.out}")
        run_evaluation(ec, policy=policy, progress=progress)
        runs[name] = load_run(ec.out)
    first = next(iter(runs.values()))
    data = {
        "probe": cfg.name, "format": FORMAT_VERSION, "policy": {"spec": cfg.policy or policy.name,
                                                                **first.summary.get("policy", {})},
        "complete": all(r.summary.get("complete", False) for r in runs.values()),
        "variants": {name: str(r.path.relative_to(cfg.out)) for name, r in runs.items()},
        "config": asdict(cfg), "provenance": {**first.summary.get("provenance", {}),
                                              "paraphrases_version": paraphrase_version(),
                                              "swaps_version": SWAPS_VERSION, "swaps": [list(p) for p in SWAPS]},
        "conditions": probe_results(cfg.name, runs, cfg.resamples),
    }
    save_probe(cfg.out, data)
    if cfg.report:
        from vla_ladder.report.html import build_report
        from vla_ladder.report.labels import short_labels
        spec = short_labels([data["policy"]["spec"]])[0]  # (a checkpoint's whole path named the machine's folders)
        build_report(list(runs.values()), cfg.out / "report.html", title=f"vla-ladder probe {cfg.name}: {spec}",
                     labels=[f"{spec} [{name}]" for name in runs], placements=False)
    return data


def run(cfg: ProbeConfig) -> int:
    from vla_ladder.report.probes import summary_lines

    data = run_probe(cfg)
    for line in summary_lines(data):
        print(line)
    print((cfg.out / ("report.html" if cfg.report else PROBE_FILE)).resolve())
    return 0
