"""`vla-ladder` command line: one subcommand per pipeline stage.

Each subcommand lives next to the code it drives and exposes `add_arguments(parser)` and `run(args)`;
they are imported only when invoked so `vla-ladder placements` never loads the simulator.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (module, one-line help). Module defines add_arguments(parser) and run(args) -> int | None.
COMMANDS: dict[str, tuple[str, str]] = {
    "placements": ("vla_ladder.task.cli", "sample layouts of the placement ladder (no simulator)"),
    "render": ("vla_ladder.task.render_cli", "render both cameras of an episode's first frame"),
    "eval": ("vla_ladder.evaluation.cli", "evaluate a policy on seeded episodes"),
    "train-expert": ("vla_ladder.experts.ppo", "train the PPO privileged-state expert"),
    "serve": ("vla_ladder.recording.serve_cli", "serve expert episodes over WebSockets"),
    "record": ("vla_ladder.recording.record_cli", "record successful episodes into a LeRobotDataset"),
    "train": ("vla_ladder.training.cli", "train a LeRobot policy on a recorded dataset"),
    "grid": ("vla_ladder.training.grid", "grid search over batch, chunk size and execution horizon"),
    "compare": ("vla_ladder.evaluation.compare", "test whether two evaluation runs differ"),
    "experiment": ("vla_ladder.report.experiments", "run one of the paper's experiments"),
    "report": ("vla_ladder.report.html", "write a self-contained HTML report of runs"),
}


def build_parser(only: str | None = None) -> tuple[argparse.ArgumentParser, dict]:
    parser = argparse.ArgumentParser(prog="vla-ladder", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = {}
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        if only in (None, name):
            mod = importlib.import_module(module)
            mod.add_arguments(p)
            modules[name] = mod
    return parser, modules


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    only = argv[0] if argv and argv[0] in COMMANDS else None
    parser, modules = build_parser(only)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(modules[args.command].run(args) or 0)
    except ValueError as e:  # bad input: one clear line, no traceback
        print(f"vla-ladder {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
