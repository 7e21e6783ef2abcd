"""`vla-ladder` command line: one subcommand per pipeline stage, each a config dataclass parsed by tyro.

A command's config dataclass is its command line: its fields are the flags and their docstrings the help,
validated in __post_init__, so a bad value ends in one line naming what is allowed (exit 2) before any
work. Each command module defines that dataclass and `run(config) -> int`; modules are imported only when
their command runs, so `vla-ladder placements` never loads the simulator.
"""

from __future__ import annotations

import importlib
import os
import sys

from vla_ladder.checks import check_seed_args, os_error_message
from vla_ladder.commandline import parse_config

ABOUT = ("Does a vision-language-action policy follow its instruction, or the place its object usually stands? "
         "GraspObject-v1\nand the placement ladder: record, train, evaluate, probe and diagnose (docs/ in the "
         "repository).")
"""what `vla-ladder --help` says of the project (the module docstring is the developers')"""

# name -> ("module:ConfigClass", one-line help). The module defines run(config) -> int.
COMMANDS: dict[str, tuple[str, str]] = {
    "placements": ("vla_ladder.report.placements:PlacementsConfig",
                   "sample layouts of the placement ladder (no simulator)"),
    "render": ("vla_ladder.task.render:RenderConfig", "render both cameras of an episode's first frame"),
    "train-expert": ("vla_ladder.ppo.train:Args", "train the PPO privileged-state expert"),
    "serve": ("vla_ladder.recording.server:ServeConfig", "serve expert episodes over WebSockets"),
    "record": ("vla_ladder.recording.record:RecordConfig", "record successful episodes into a LeRobotDataset"),
    "train": ("vla_ladder.training.train:TrainConfig", "train a LeRobot policy on a recorded dataset"),
    "eval": ("vla_ladder.evaluation.runner:EvalConfig", "evaluate a policy on seeded episodes"),
    "compare": ("vla_ladder.evaluation.compare:CompareConfig", "test whether two evaluation runs differ"),
    "grid": ("vla_ladder.experiments.grid:GridConfig", "grid search over batch, chunk size and execution horizon"),
    "experiment": ("vla_ladder.experiments.experiment:ExperimentCommand", "run one of the paper's experiments"),
    "report": ("vla_ladder.report.html:ReportConfig", "write a self-contained HTML report of runs"),
    "probe": ("vla_ladder.experiments.probes:ProbeConfig",
              "probe instruction grounding: instruction swap, paraphrases, appearance swap, absent object, "
              "position swap, instruction switch, distractor removal"),
    "rebuild-provenance": ("vla_ladder.recording.provenance:RebuildProvenanceConfig",
                           "give a dataset made by lerobot-edit-dataset its vla-ladder provenance back"),
    "check-dataset": ("vla_ladder.training.check_dataset:CheckDatasetConfig",
                      "check a recorded dataset: balance, coverage, leakage, seeds, frames, actions"),
    "study": ("vla_ladder.experiments.study:StudyCommand", "record, train, evaluate and report a learned policy"),
    "serve-policy": ("vla_ladder.policies.serving:ServePolicyConfig",
                     "serve a LeRobot checkpoint over WebSockets (openpi's protocol), for eval --policy remote:URL"),
    "diagnose": ("vla_ladder.experiments.diagnose:DiagnoseConfig",
                 "the ladder and seven grounding probes of a policy (or several), beside the references, one page"),
}
# Commands that pass everything after `--` to lerobot-train.
LEROBOT_FLAGS_AFTER_DASHES = ("train", "grid")
# Commands that train LeRobot policies on recorded videos: restarted with PyAV's FFmpeg where torchcodec has none
# (training/decoding.py).
DECODE_VIDEOS = ("train", "grid", "study")
# Commands whose run() lives in another module than their config.
RUNNERS = {"serve": "vla_ladder.recording.serve"}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: vla-ladder COMMAND [OPTIONS]   (vla-ladder COMMAND --help for its options)", "",
             ABOUT, "", "commands:"]
    lines += [f"  {name:<{width}}  {help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines)


def parse(name: str, argv: list[str]):
    """The config of command `name` from its arguments (tyro; extra LeRobot flags after `--` for train)."""
    target, help_ = COMMANDS[name]
    module_name, _, cls_name = target.partition(":")
    module = importlib.import_module(module_name)
    check_seed_args(getattr(module, cls_name), argv)  # one message for a bad seed, whichever command
    if hasattr(module, "cli_config"):  # a command with its own parsing (train-expert's --resume)
        return module.cli_config(argv)
    cls, default = getattr(module, cls_name), None
    if name in LEROBOT_FLAGS_AFTER_DASHES and "--" in argv:
        # Raw lerobot-train flags, handed over untouched (tyro would read them as its own), in the config that the
        # flags build: its checks read them (diffusion's --policy.n_obs_steps, --policy.down_dims), where one built
        # without them first refused what they allow.
        from vla_ladder.training.train import TrainConfig
        cut = argv.index("--")
        argv, tail = argv[:cut], argv[cut + 1:]
        train = _holding(TrainConfig, lerobot_args=tuple(tail))
        default = _holding(cls, train=train) if name == "grid" else train
    return parse_config(cls, argv, prog=f"vla-ladder {name}", description=help_, default=default)


def _holding(cls, **values):
    """parse_config's `default`: an unchecked `cls` holding `values`, its other fields at their defaults and those
    without one still required."""
    import dataclasses

    import tyro

    from vla_ladder.commandline import unchecked

    required = {f.name: tyro.MISSING for f in dataclasses.fields(cls)
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
    return unchecked(cls, {**required, **values})


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # OpenMP threads that outnumber free cores spin for each other (10x slower steps measured on a busy 2-core
    # machine), so workers sleep between parallel regions. In-process `eval` of SmolVLA-scratch on 2 cores gains
    # nothing from spinning: the policy's 7.8 ms a step become 4.0, the renderer's 16.8 become 23.3 (its threads
    # lose their cores to the spinning ones). A policy server keeps libgomp's default (spin a while, then sleep):
    # its forward passes are back-to-back small matmuls, 11.5 ms a SmolVLA chunk against 34 ms passive on 2 idle
    # cores, 24 ms against 18 and 33 beside one and two busy processes (benchmarks/results/openmp_wait_cpu.json).
    # Read when torch first loads.
    if argv[:1] != ["serve-policy"]:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"vla-ladder: error: unknown command {name!r}; allowed: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    try:
        cfg = parse(name, rest)
        if name in DECODE_VIDEOS:
            from vla_ladder.training.decoding import restart_with_torchcodec
            restart_with_torchcodec(argv)
        runner = importlib.import_module(RUNNERS.get(name, COMMANDS[name][0].partition(":")[0]))
        return int(runner.run(cfg) or 0)
    except ValueError as e:  # bad input: one clear line, no traceback
        print(f"vla-ladder {name}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of our output went away (`| head`): nothing left to say, no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # (what the Python docs advise)
        return 1
    except OSError as e:  # disk full, read-only, a file in the way, a port in use: the path and the fix
        print(f"vla-ladder {name}: error: {os_error_message(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"vla-ladder {name}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
