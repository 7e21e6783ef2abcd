"""The paper's Figure 1: sampled initial object positions per regime, one colour per object."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from vla_ladder.io import atomic_path
from vla_ladder.task.layouts import REGIMES, REGION_CENTERS, WORKSPACE_CENTER, WORKSPACE_SIZE, Layout
from vla_ladder.task.objects import OBJECT_NAMES, OBJECTS

TITLES = {"small_jitter": "Small jitter", "medium_jitter": "Medium jitter", "large_jitter": "Large jitter",
          "full_random": "Full random"}


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
        ax.set_title(TITLES.get(regime, regime))
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
    from vla_ladder.task.layouts import sample_layouts
    return plot_layouts({r: sample_layouts(r, split, num_objects, range(seed, seed + n)) for r in regimes}, path)
