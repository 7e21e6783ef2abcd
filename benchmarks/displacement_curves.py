"""Success against the named object's distance from its place in training, from a finished study's run directories
(no simulation): the model trained in small jitter, its instruction-blind twin and the reference policies, every
run that played the same ladder (the same conditions and seeds).

    python benchmarks/displacement_curves.py    # the committed cpu-mini and gpu-session studies

writes benchmarks/results/displacement_<study>.json (evaluation/displacement.py's curves, by run) and .png.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import tyro

from vla_ladder import files
from vla_ladder.evaluation.displacement import by_displacement
from vla_ladder.evaluation.rundir import load_run
from vla_ladder.report.displacement import odds_text
from vla_ladder.report.plots import plot_displacement

RESULTS = Path(__file__).parent / "results"


@dataclass
class Args:
    studies: tuple[Path, ...] = (RESULTS / "study_cpu_mini", RESULTS / "study_gpu_session")
    """study directories (`vla-ladder study --out DIR`) whose eval/ holds the runs"""
    runs: tuple[str, ...] = ("SmolVLA-scratch-sj", "SmolVLA-scratch-blind-sj", "reference-layout-prior-0",
                             "reference-nearest-0")
    """runs under eval/ that played the same conditions and seeds: models trained in `trained_in` and references"""
    trained_in: str = "small_jitter/canonical/5"
    """the condition the models were trained in"""
    out: Path = RESULTS
    """where displacement_<study>.json and .png go"""


def curves(study: Path, names: tuple[str, ...], trained_in: str) -> dict[str, dict]:
    runs = {name: load_run(study / "eval" / name) for name in names}
    if len({r.played for r in runs.values()}) > 1:
        raise SystemExit(f"{study}: the runs {', '.join(names)} did not all play the same episodes")
    return {name: by_displacement(r.episodes, trained_in) for name, r in runs.items()}


def main(args: Args) -> None:
    for study in args.studies:
        found = curves(study, args.runs, args.trained_in)
        name = study.name.removeprefix("study_")
        files.write_json(args.out / f"displacement_{name}.json", {
            "study": name, "trained_in": args.trained_in, "runs": found, "provenance": files.provenance()})
        plot_displacement(found, args.out / f"displacement_{name}.png")
        for label, curve in found.items():
            bins = ", ".join(f"{b['from_cm']:g}-{b['to_cm']:g} cm {100 * b['success']:.0f}% (n={b['n']})"
                             for b in curve["bins"])
            print(f"{name} {label}: {bins}; odds {odds_text(curve['trend']['success'])} per 10 cm")


if __name__ == "__main__":
    main(tyro.cli(Args))
