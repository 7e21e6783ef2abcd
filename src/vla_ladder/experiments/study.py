"""`vla-ladder study CONFIG --out DIR`: a learned policy diagnosed end to end, the paper's protocol as units.

1. record: one dataset per training condition, with the config's expert (`vla-ladder record`);
2. train: every policy x dataset x (batch size, chunk size) of the grid, with LeRobot's own training;
3. select: every execution horizon <= the chunk size (diffusion: what it executes of one) on validation
   episodes of the training condition; the best model per policy x dataset is picked by success, then
   grasp-any, then reach;
4. evaluate: that model on the same seeded episodes as every other policy: every regime of the ladder for a
   canonically trained model (the train x eval regime matrix), pairings ID and OOD for a pairing-trained one,
   the configured object counts; the reference policies on the same cells;
5. report: summary.json (every cell with n, counts, rates and 95% Wilson intervals), the tables laid out as
   the paper's (Markdown and LaTeX, tables/), the learning curves, and report.html.

Every step is a unit (experiments/units.py): a re-run with the same CONFIG and DIR skips finished units and
continues interrupted ones; each unit's config and log land in DIR/units/ and DIR/logs/. `--report-only` runs step
5 alone, from the results of a finished study (experiments/study_results.py).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated

import tyro

from vla_ladder import files
from vla_ladder.checks import ascii_digits, check_ray_address, check_output_dir
from vla_ladder.conditions import parse_regimes
from vla_ladder.contract import RANK_BY
from vla_ladder.experiments.study_config import DatasetSpec, PolicySpec, StudyConfig, from_dict
from vla_ladder.experiments.units import Unit, is_done, run_units, run_units_on_ray
from vla_ladder.machine import check_workers, cores


@dataclass
class StudyCommand:
    """Record, train, evaluate and report a learned policy along the ladder (resumable)."""

    config: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="CONFIG")]
    """a preset (micro, cpu-mini, gpu-session, gpu-scratch, paper) or a study JSON file"""
    out: Path
    """study directory (a re-run with the same config resumes in it)"""
    workers: int = 0
    """simulation worker processes for recording and evaluation (0: one per core, capped by memory)"""
    writers: int = 0
    """dataset writer processes of each recording (0: one per two workers; see `vla-ladder record --writers`)"""
    num_envs: int = 1
    """evaluate and probe with one copy of each policy acting on this many envs at once (batched inference, what
    a GPU policy wants; see `vla-ladder eval --num-envs`) instead of --workers copies; the same episodes"""
    ray: bool = False
    """run the units as Ray tasks (a local Ray, or the cluster at --ray-address)"""
    ray_address: str | None = None
    """address of a running Ray cluster (implies --ray)"""
    report_only: bool = False
    """run nothing: write summary.json, tables/ and report.html again from the finished study's evaluations and
    probes, with this version's metrics (for a study copied without its datasets and models)"""

    def __post_init__(self):
        self.out = check_output_dir(self.out, "--out")  # a file, the root: now
        self.study = StudyConfig.load(self.config)
        check_workers(self.workers)
        check_ray_address(self.ray_address)
        if self.writers < 0 or (self.workers and self.workers < self.writers):
            raise ValueError(f"--writers must be >= 0 (0: one per two workers) and at most --workers, got "
                             f"{self.writers}")
        if not 1 <= self.num_envs <= cores():  # one env process each: refused here, not after the recording
            raise ValueError(f"--num-envs must be from 1 to the {cores()} CPU cores here, got {self.num_envs}")
        saved = self.out / "study.json"
        differs = saved.is_file() and _what_differs(_as_now(json.loads(saved.read_text())), asdict(self.study))
        if differs:
            raise ValueError(f"{self.out} holds another study ({saved}: its {differs} differs); use a new --out (a "
                             "study resumes with the same config, reworded, or with grounding probes added to "
                             "evaluation.probes)")
        if self.out.is_dir() and any(self.out.iterdir()) and not saved.is_file():
            raise ValueError(f"{self.out} is not empty and holds no study; use a new --out")
        if self.report_only and not (self.out / "summary.json").is_file():
            raise ValueError(f"--report-only: {self.out} holds no finished study (no summary.json); run the study "
                             "without --report-only first")
        ran_at = None if self.report_only else _where_it_ran(self.out)  # a report runs nothing of theirs
        if ran_at is not None:  # else every unit would run again, hours of recording and training
            raise ValueError(f"{self.out} was moved: its units ran in {ran_at}, and their configs and the LeRobot "
                             f"checkpoints hold that path; restore it there (docs/study.md) or use a new --out")


def _where_it_ran(root: Path) -> Path | None:
    """The directory a study's done units ran in, if not `root` (every unit writes to root/<stage dir>/<name>)."""
    here = root.resolve()
    for path in sorted((root / "units").glob("*.json")):
        out = json.loads(path.read_text()).get("config", {}).get("out")
        if out and Path(out).resolve().parent.parent != here:
            return Path(out).parent.parent
    return None


def _what_it_runs(study: dict) -> dict:
    """A study config as a request: a preset whose description is reworded still resumes its finished studies."""
    return {k: v for k, v in files.plain(study).items() if k != "description"}


def _as_now(saved: dict) -> dict:
    """A saved study.json read as this version reads a config: fields added since it was written (a policy's
    train_seed) take their defaults, as its units do. One this version cannot read is compared as it is."""
    try:
        return asdict(from_dict(StudyConfig, saved, ""))
    except ValueError:
        return saved


def _what_differs(saved: dict, now: dict) -> str:
    """Why a study directory that ran `saved` does not go on under `now` (the first field that differs, "" if it
    does): it goes on under the same request, or the same with grounding probes added (its done units stay done, the
    new probes run, the summary and report are written again)."""
    def without_probes(study: dict) -> tuple[dict, set]:
        request = _what_it_runs(study)
        evaluation = request.get("evaluation", {})
        request["evaluation"] = {k: v for k, v in evaluation.items() if k != "probes"}
        return request, set(evaluation.get("probes", []))

    (before, old_probes), (after, new_probes) = without_probes(saved), without_probes(now)
    if not old_probes <= new_probes:
        return "evaluation.probes (a probe was dropped)"
    return files.first_difference(before, after)


# ---------------------------------------------------------------------- planning
def model_id(policy: PolicySpec, dataset: DatasetSpec, batch: int, chunk: int) -> str:
    return f"{policy.name}-{dataset.name}-b{batch}c{chunk}"


def eval_grid(dataset: DatasetSpec, study: StudyConfig) -> dict:
    """The cells a model trained on `dataset` is evaluated on: the ladder for a canonical condition, the
    pairings ID and OOD of its regime for a pairing split (the only pairs it could have held out)."""
    c, ev = dataset.cond, study.evaluation
    if c.split == "canonical":
        return {"regimes": list(parse_regimes(ev.regimes)), "splits": ["canonical"], "num_objects": ev.num_objects}
    return {"regimes": [c.regime], "splits": ["pairings_id", "pairings_ood"], "num_objects": ev.num_objects}


class Study:
    """Plans a study's units from its config and runs them phase by phase."""

    def __init__(self, cmd: StudyCommand):
        self.cmd, self.cfg, self.root = cmd, cmd.study, cmd.out

    def run_phase(self, units: list[Unit]) -> dict:
        if self.cmd.ray or self.cmd.ray_address:
            return run_units_on_ray(units, self.root, self.cmd.ray_address)
        return run_units(units, self.root)

    # -- record
    def record_units(self) -> list[Unit]:
        return [Unit(f"record-{d.name}", "record", "vla_ladder.experiments.units:record_unit",
                     {"out": str(self.dataset_dir(d)), "episodes": d.episodes, "condition": d.condition,
                      "policy": d.expert, "first_seed": d.first_seed, "workers": self.cmd.workers,
                      "writers": self.cmd.writers}, cpus=2)
                for d in self.cfg.datasets]

    def dataset_dir(self, d: DatasetSpec) -> Path:
        return self.root / "data" / d.name

    # -- train
    def vlm_dir(self, p: PolicySpec) -> Path:
        return self.root / "assets" / f"vlm-{p.vlm}"

    def lerobot_args(self, p: PolicySpec) -> list[str]:
        args = list(p.lerobot_args)
        if p.vlm is not None:
            from vla_ladder.training.tiny import SIZES, scratch_smolvla_args
            args = [*scratch_smolvla_args(self.vlm_dir(p), p.image_size or SIZES[p.vlm].image_size), *args]
        return args

    def build_vlms(self) -> None:
        """The from-scratch VLM directories (config and tokenizer, no weights) the train units name; written here,
        before the train phase, so that listing the units writes nothing (check_sources lists them first)."""
        from vla_ladder.training.tiny import build_vlm_dir
        for p in self.cfg.policies:
            if p.vlm is not None:
                build_vlm_dir(self.vlm_dir(p), p.vlm)

    def train_units(self) -> list[Unit]:
        units = []
        for p, d, bcs in self.models():
            args = self.lerobot_args(p)
            for b, c in bcs:
                mid = model_id(p, d, b, c)
                save_freq = max(p.steps // 4, 1) if self.cfg.evaluation.curve_episodes else p.steps
                data = self.blind_dir(d) if p.blind else self.dataset_dir(d)
                config = {"policy_type": p.type, "dataset": str(data),
                          "out": str(self.root / "models" / mid), "pretrained": p.pretrained,
                          "batch_size": b, "chunk_size": c, "n_action_steps": self.max_steps(p, c), "steps": p.steps,
                          "save_freq": save_freq, "log_freq": max(p.steps // 20, 1),
                          "num_workers": self.cfg.num_workers, "device": self.cfg.device,
                          "lerobot_args": args}
                if p.train_seed is not None:  # (only when given: a unit marked done before the field is still done)
                    config["train_seed"] = p.train_seed
                units.append(Unit(f"train-{mid}", "train", "vla_ladder.experiments.units:train_unit",
                                  config, cpus=2, after=[f"record-{d.name}"]))
        return units

    def blind_dir(self, d: DatasetSpec) -> Path:
        return self.root / "data" / f"{d.name}-blind"

    def make_blind_copies(self) -> None:
        """Instruction-blind copies of the recorded datasets, for the blind policies (hard links, seconds)."""
        from vla_ladder.training.blind import blind_copy
        for p, d, _ in self.models():
            if p.blind:  # a second blind policy on the same dataset reuses the copy
                blind_copy(self.dataset_dir(d), self.blind_dir(d))

    def spec(self, p: PolicySpec, mid: str, horizon: int, step: str = "last") -> str:
        """The policy spec of a trained model (blind ones get the blind instruction in every episode)."""
        from vla_ladder.contract import BLIND_INSTRUCTION
        blind = f"&instruction={BLIND_INSTRUCTION}" if p.blind else ""
        return f"lerobot:{self.checkpoint(mid, step)}?n_action_steps={horizon}{blind}"

    def checkpoint(self, mid: str, step: str = "last") -> Path:
        return self.root / "models" / mid / "checkpoints" / step / "pretrained_model"

    # -- select and evaluate
    def models(self):
        """(policy, dataset, [(batch, chunk), ...]) for every policy and each dataset it is trained on."""
        g = self.cfg.grid
        for p in self.cfg.policies:
            for d in self.cfg.datasets:
                if not p.datasets or d.name in p.datasets:
                    yield p, d, [(b, c) for b in g.batch_sizes for c in g.chunk_sizes]

    def eval_config(self, spec: str, out: Path, grid: dict, episodes: int, first_seed: int, videos: int) -> dict:
        return {"policy": spec, "out": str(out), "grid": grid, "episodes": episodes, "first_seed": first_seed,
                "videos": videos, **self.players()}

    def players(self, probe: str = "") -> dict:
        """How evaluations and probes play their episodes: --workers policy copies or one on --num-envs envs
        (not the probes that paint each scene: they play one env per policy copy)."""
        from vla_ladder.experiments.probes import PROBES
        if self.cmd.num_envs > 1 and not (probe and PROBES[probe].one_env):
            return {"workers": 1, "num_envs": self.cmd.num_envs}
        return {"workers": self.cmd.workers}

    def select_units(self) -> list[Unit]:
        g = self.cfg.grid
        units = []
        for p, d, bcs in self.models():
            own = {"regimes": [d.cond.regime], "splits": [d.cond.split], "num_objects": [d.cond.num_objects]}
            for b, c in bcs:
                mid = model_id(p, d, b, c)
                for h in self.horizons(p, c):
                    if g.select_episodes == 0:
                        break
                    cfg = self.eval_config(self.spec(p, mid, h), self.root / "select" / f"{mid}-h{h}", own,
                                           g.select_episodes,
                                           g.select_first_seed, 0)
                    units.append(Unit(f"select-{mid}-h{h}", "select", "vla_ladder.experiments.units:eval_unit",
                                      cfg, cpus=2, after=[f"train-{mid}"]))
        return units

    def horizons(self, p: PolicySpec, chunk: int) -> list[int]:
        """The grid's horizons that `p` executes of a chunk of `chunk` (diffusion: the chunk - n_obs_steps + 1)."""
        return [h for h in self.cfg.grid.horizons if h <= self.max_steps(p, chunk)]

    @staticmethod
    def max_steps(p: PolicySpec, chunk: int) -> int:
        from vla_ladder.training.train import max_action_steps
        return max_action_steps(p.type, chunk, p.lerobot_args)

    def best(self, results: dict) -> dict[tuple[str, str], dict]:
        """(policy, dataset) -> the chosen model and horizon, with the validation rates it was chosen on (None where
        the grid has no selection phase, --select-episodes 0: nothing was measured, the first candidate is used)."""
        chosen = {}
        for p, d, bcs in self.models():
            rows = []
            for b, c in bcs:
                mid = model_id(p, d, b, c)
                for h in self.horizons(p, c):
                    r = results.get(f"select-{mid}-h{h}")
                    rates = next(iter(r["conditions"].values())) if r else {}
                    rows.append({"model": mid, "batch_size": b, "chunk_size": c, "horizon": h,
                                 **{m: rates.get(m) for m in RANK_BY}})
            # Stable sort: on a full tie (or with nothing measured) the first in grid order wins.
            rows.sort(key=lambda r: tuple(-1.0 if r[m] is None else r[m] for m in RANK_BY), reverse=True)
            chosen[(p.name, d.name)] = {**rows[0], "candidates": rows}
        return chosen

    def eval_units(self, chosen: dict) -> list[Unit]:
        ev = self.cfg.evaluation
        units = []
        for p, d, _ in self.models():
            best = chosen[(p.name, d.name)]
            cfg = self.eval_config(self.spec(p, best["model"], best["horizon"]), self.root / "eval" /
                                   f"{p.name}-{d.name}", eval_grid(d, self.cfg),
                                   ev.episodes, ev.first_seed, ev.videos)
            units.append(Unit(f"eval-{p.name}-{d.name}", "eval", "vla_ladder.experiments.units:eval_unit", cfg,
                              cpus=2, after=[f"train-{best['model']}"]))
        grids = {json.dumps(eval_grid(d, self.cfg), sort_keys=True) for d in self.cfg.datasets}
        for ref in ev.reference_policies:
            for i, grid in enumerate(sorted(grids)):
                cfg = self.eval_config(ref, self.root / "eval" / f"reference-{ref}-{i}", json.loads(grid),
                                       ev.episodes, ev.first_seed, 0)
                units.append(Unit(f"eval-reference-{ref}-{i}", "eval", "vla_ladder.experiments.units:eval_unit",
                                  cfg, cpus=2))
        return units

    def curve_units(self, chosen: dict) -> list[Unit]:
        """Every saved checkpoint of each chosen model on validation episodes of its training condition."""
        ev, g = self.cfg.evaluation, self.cfg.grid
        if not ev.curve_episodes:
            return []
        units = []
        for p, d, _ in self.models():
            best = chosen[(p.name, d.name)]
            own = {"regimes": [d.cond.regime], "splits": [d.cond.split], "num_objects": [d.cond.num_objects]}
            steps = sorted(x.name for x in (self.root / "models" / best["model"] / "checkpoints").iterdir()
                           if ascii_digits(x.name))
            for step in steps:
                cfg = self.eval_config(self.spec(p, best["model"], best["horizon"], step),
                                       self.root / "curves" / f"{best['model']}-{step}", own,
                                       ev.curve_episodes, g.select_first_seed + g.select_episodes, 0)
                units.append(Unit(f"curve-{best['model']}-{step}", "curve",
                                  "vla_ladder.experiments.units:eval_unit", cfg, cpus=2))
        return units

    def probe_units(self, chosen: dict) -> list[Unit]:
        from vla_ladder.experiments.probes import PROBES
        ev = self.cfg.evaluation
        units = []
        for p, d, _ in self.models():
            if p.blind:
                continue
            best = chosen[(p.name, d.name)]
            for name in ev.probes:
                # In the training condition; absent-object needs an object off the table, so five-object data are
                # probed with four, the nearest scenes to training that leave one to name.
                n = PROBES[name].fit(d.cond.num_objects)
                own = {"regimes": [d.cond.regime], "splits": [d.cond.split], "num_objects": [n]}
                cfg = {"name": name, "policy": self.spec(p, best["model"], best["horizon"]),
                       "out": str(self.root / "probes" / f"{p.name}-{d.name}-{name}"), "grid": own,
                       "episodes": ev.probe_episodes, "first_seed": ev.first_seed, **self.players(name)}
                units.append(Unit(f"probe-{p.name}-{d.name}-{name}", "probe",
                                  "vla_ladder.experiments.units:probe_unit", cfg, cpus=2))
        return units

    # -- the whole study
    def check_sources(self) -> None:
        """Read every expert and pretrained checkpoint a unit still to run will load, and look for the packages of
        every policy type still to train (diffusion's diffusers, ...), so a missing or unreadable one is refused in
        one line now, not in a unit's traceback after hours of recording. (On Ray the trainers' machines are not
        this one: their packages are theirs.)"""
        from vla_ladder.policies import check_spec
        from vla_ladder.training.train import NO_PRETRAINED, check_policy_packages, pretrained_config
        for d, unit in zip(self.cfg.datasets, self.record_units()):
            if not is_done(self.root, unit):
                try:
                    check_spec(d.expert)
                except ValueError as e:
                    raise ValueError(f"datasets[{d.name}].expert: {e}") from None
        train_units = iter(self.train_units())  # one per (batch, chunk) of each model, in models()' order
        for p, d, bcs in self.models():
            trained = all([is_done(self.root, next(train_units)) for _ in bcs])  # (a list: every unit is taken)
            if not trained and not (self.cmd.ray or self.cmd.ray_address):
                try:
                    check_policy_packages(p.type)
                except ValueError as e:
                    raise ValueError(f"policies[{p.name}]: {e}") from None
            if p.pretrained not in NO_PRETRAINED and not trained:
                try:
                    pretrained_config(p.pretrained, p.type)
                except ValueError as e:
                    raise ValueError(f"policies[{p.name}].pretrained: {e}") from None

    def run(self) -> Path:
        if not self.cmd.report_only:
            self.check_sources()
        with files.writing(self.root, "vla-ladder study"):  # a second study here would run the same units at once
            return self._run()

    def _run(self) -> Path:
        from vla_ladder.experiments.study_results import write_report, write_results

        root = self.root
        if self.cmd.report_only:
            return write_report(root, json.loads((root / "summary.json").read_text()))
        root.mkdir(parents=True, exist_ok=True)
        files.write_json(root / "study.json", asdict(self.cfg))
        self.run_phase(self.record_units())
        self.make_blind_copies()
        self.build_vlms()
        self.run_phase(self.train_units())
        selected = self.run_phase(self.select_units())
        chosen = self.best(selected)
        files.write_json(root / "selection.json", {f"{p}/{d}": v for (p, d), v in chosen.items()})
        results = self.run_phase(self.eval_units(chosen))
        self.run_phase(self.curve_units(chosen))  # read back from their directories (curve_points)
        results.update(self.run_phase(self.probe_units(chosen)))
        return write_results(self, chosen, results)


def run(cmd: StudyCommand) -> int:
    out = Study(cmd).run()
    print(out.resolve())
    return 0
