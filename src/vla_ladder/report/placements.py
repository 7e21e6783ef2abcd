"""The paper's Figure 1: sampled initial object positions per regime, one colour per object."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Sequence

import numpy as np
import tyro

from vla_ladder.checks import SEED_LIMIT, check_output_file
from vla_ladder.files import atomic_path
from vla_ladder.conditions import REGIMES, Condition, parse_regimes
from vla_ladder.report.tables import REGIME_NAMES
from vla_ladder.task.layouts import REGION_CENTERS, WORKSPACE_CENTER, WORKSPACE_SIZE, Layout, sample_layouts
from vla_ladder.task.objects import OBJECT_NAMES, OBJECTS



def plot_layouts(layouts_by_regime: dict[str, Sequence[Layout]], path: str | Path) -> Path:
    """One panel per regime; the robot base is at the bottom of each panel (x grows upwards)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    n = len(layouts_by_regime)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.6), squeeze=False)
    lo = WORKSPACE_CENTER - WORKSPACE_SIZE / 2
    for ax, (regime, layouts) in zip(axes[0], layouts_by_regime.items()):
        ax.add_patch(Rectangle((-lo[1] - WORKSPACE_SIZE[1], lo[0]), WORKSPACE_SIZE[1], WORKSPACE_SIZE[0],
                               fill=False, ls="--", lw=0.8, color="grey"))
        extent = REGIMES[regime]
        if extent is not None:
            for c in REGION_CENTERS:
                ax.add_patch(Rectangle((-(c[1] + extent[1] / 2), c[0] - extent[0] / 2), extent[1], extent[0],
                                       fill=False, lw=0.6, color="black", alpha=0.4))
        for i, spec in enumerate(OBJECTS):
            pts = np.array([xy for lay in layouts for name, xy in zip(lay.objects, lay.xy) if name == spec.name])
            if len(pts):
                # Plot as seen from the robot: +y (robot's left) to the left.
                ax.scatter(-pts[:, 1], pts[:, 0], s=6, alpha=0.6, color=spec.rgba[:3] if i != 2 else (0.1, 0.6, 0.2),
                           label=spec.phrase, edgecolors="none")
        ax.set_title(REGIME_NAMES.get(regime, regime))
        ax.set_aspect("equal")
        ax.set_xlim(-lo[1] - WORKSPACE_SIZE[1] - 0.03, -lo[1] + 0.03)
        ax.set_ylim(lo[0] - 0.03, lo[0] + WORKSPACE_SIZE[0] + 0.03)
        ax.set_xlabel("-y (m)")
        ax.set_ylabel("x (m)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(OBJECT_NAMES), markerscale=3, frameon=False)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=150, format=path.suffix.lstrip(".") or "png")
    plt.close(fig)
    return path


def plot_placements(regimes: Sequence[str], n: int, seed: int, path: str | Path, split: str = "canonical",
                    num_objects: int = 5) -> Path:
    return plot_layouts({r: sample_layouts(Condition(r, split, num_objects), range(seed, seed + n)) for r in regimes},
                        path)


MAX_LAYOUTS = 100_000


@dataclass
class PlacementsConfig:
    """Sample layouts of the placement ladder (no simulator): print them, write JSON, draw the paper's Figure 1."""

    n: int
    """layouts per regime, 1-100000"""
    regimes: tuple[str, ...] = ("all",)
    """placement regimes: small_jitter, medium_jitter, large_jitter, full_random, or all"""
    split: str = "canonical"
    """object-region split: canonical (object i in region i), pairings_id or pairings_ood (held-out pairs)"""
    num_objects: int = 5
    """objects on the table, 1-5 (the instructed one and its distractors)"""
    target: Annotated[str | None, tyro.conf.arg(metavar="OBJECT", help_behavior_hint="(default: each seed's own)")] \
        = None
    """instruct this object in every layout: apple, orange, rubiks_cube, mug or large_marker"""
    first_seed: int = 0
    """layout j of every regime uses seed first_seed + j (the layout `vla-ladder eval` plays with that seed)"""
    json: Path | None = None
    """write the layouts here (JSON); without --json and --plot they are printed"""
    plot: Path | None = None
    """write the placement figure here (its suffix says the format: png, pdf, svg, ...)"""

    def __post_init__(self):
        self.regimes = parse_regimes(self.regimes)
        self.conditions = [Condition(r, self.split, self.num_objects) for r in self.regimes]
        if self.target is not None:
            from vla_ladder.task.objects import object_index
            object_index(self.target)
        if not 1 <= self.n <= MAX_LAYOUTS:  # ~0.1 ms and ~1 KB of JSON a layout: 10^5 a regime is a minute
            raise ValueError(f"--n must be from 1 to {MAX_LAYOUTS} (layouts per regime), got {self.n}")
        if not 0 <= self.first_seed <= SEED_LIMIT - self.n:
            raise ValueError(f"--first-seed must be from 0 to 2**32 - --n = {SEED_LIMIT - self.n} (layout j uses seed "
                             f"--first-seed + j, a numpy seed), got {self.first_seed}")
        # Both outputs checked before either is written (a bad --plot failed after the JSON was written).
        for flag, path in (("--json", self.json), ("--plot", self.plot)):
            if path is not None:
                check_output_file(path, flag)
        if self.plot is not None:
            from matplotlib.backend_bases import FigureCanvasBase
            kinds = FigureCanvasBase.get_supported_filetypes()
            if self.plot.suffix.lstrip(".").lower() not in kinds:
                raise ValueError(f"--plot {str(self.plot)!r}: the figure's format is its suffix; allowed: "
                                 f"{', '.join(sorted(kinds))}")


def run(cfg: PlacementsConfig) -> int:
    from vla_ladder.files import write_json

    seeds = range(cfg.first_seed, cfg.first_seed + cfg.n)
    layouts = {c.regime: sample_layouts(c, seeds, cfg.target) for c in cfg.conditions}
    if cfg.json:
        write_json(cfg.json, {"split": cfg.split, "num_objects": cfg.num_objects, "units": "metres",
                              "episodes": [lay.to_dict() for r in cfg.regimes for lay in layouts[r]]})
        print(f"wrote {cfg.n * len(cfg.regimes)} layouts to {cfg.json}")
    if cfg.plot:
        plot_layouts(layouts, cfg.plot)
        print(f"wrote placement figure to {cfg.plot}")
    if not cfg.json and not cfg.plot:
        for r in cfg.regimes:
            for lay in layouts[r]:
                pos = ", ".join(f"{n} ({x:+.3f}, {y:+.3f})" for n, (x, y) in zip(lay.objects, lay.xy))
                print(f"{r} seed {lay.seed}: {lay.instruction!r}: {pos}")
    return 0
