"""PNG figures of evaluation results: the ladder, pairings bars, object-count curve, confusion matrices, success
against the named object's displacement.

All take per-condition summaries (`metrics.summarize`, i.e. summary.json "conditions") keyed by model
label, and draw every rate with its 95% Wilson interval.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vla_ladder.contract import METRICS
from vla_ladder.files import atomic_path
from vla_ladder.report.displacement import odds_text
from vla_ladder.report.tables import METRIC_NAMES, REGIME_NAMES, REGIME_SHORT, SPLIT_NAMES
from vla_ladder.task.objects import OBJECTS


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _save(fig, path: str | Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    _plt().close(fig)
    return Path(path)


def _err(conds: list[dict], metric: str) -> tuple[np.ndarray, np.ndarray]:
    """Rates (%) and asymmetric error bars (2, k) of one metric over a list of conditions."""
    # (dtype float: an undefined rate, null in a summary.json, is NaN as it was when written as NaN)
    v = np.array([c[metric] for c in conds], dtype=float) * 100
    ci = np.array([c["ci95"][metric] for c in conds], dtype=float).reshape(-1, 2) * 100
    return v, np.abs(np.stack([v - ci[:, 0], ci[:, 1] - v]))


def _curves(results: dict[str, dict], xs: list, pick, xlabels: list[str], title: str, xlabel: str, path) -> Path:
    """One panel per metric, one line per model; pick(conditions, x) -> condition or None."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(METRICS), figsize=(4.2 * len(METRICS), 3.4), sharey=True)
    for ax, m in zip(axes, METRICS):
        for j, (model, conds) in enumerate(results.items()):
            pts = [(i, pick(conds, x)) for i, x in enumerate(xs)]
            pts = [(i, c) for i, c in pts if c is not None]
            if not pts:
                continue
            v, e = _err([c for _, c in pts], m)
            # A small horizontal offset keeps overlapping error bars of different models readable.
            x = np.array([i for i, _ in pts]) + (j - (len(results) - 1) / 2) * 0.06
            ax.errorbar(x, v, yerr=e, marker="o", capsize=3, label=model)
        ax.set_title(METRIC_NAMES[m])
        ax.set_xticks(range(len(xs)), xlabels)
        ax.set_xlabel(xlabel)
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("rate (%) with 95% Wilson interval")
    axes[-1].legend(loc="best", fontsize=8)
    fig.suptitle(title, y=1.03)
    return _save(fig, path)


def plot_ladder(results: dict[str, dict], path: str | Path, num_objects: int = 5) -> Path:
    regimes = list(REGIME_NAMES)
    return _curves(results, regimes, lambda c, r: c.get(f"{r}/canonical/{num_objects}"),
                   [REGIME_SHORT[r] for r in regimes], "Spatial task ladder", "placement regime", path)


def plot_object_count(results: dict[str, dict], path: str | Path, regime: str = "full_random") -> Path:
    ks = [1, 2, 3, 4, 5]
    return _curves(results, ks, lambda c, k: c.get(f"{regime}/canonical/{k}"), [str(k) for k in ks],
                   f"Object count ({REGIME_NAMES[regime].lower()})", "number of objects", path)


def plot_pairings(results: dict[str, dict], path: str | Path, regime: str = "small_jitter",
                  num_objects: int = 5) -> Path:
    plt = _plt()
    splits = ("pairings_id", "pairings_ood")
    bars = [(model, s, conds.get(f"{regime}/{s}/{num_objects}")) for model, conds in results.items() for s in splits]
    bars = [b for b in bars if b[2] is not None]
    fig, ax = plt.subplots(figsize=(max(5.0, 1.6 * len(bars)), 3.4))
    width = 0.8 / max(1, len(bars))
    for j, (model, split, c) in enumerate(bars):
        vals = np.array([c[m] for m in METRICS], dtype=float) * 100
        ci = np.array([c["ci95"][m] for m in METRICS], dtype=float).reshape(-1, 2) * 100
        errs = np.abs(np.stack([vals - ci[:, 0], ci[:, 1] - vals]))
        label = SPLIT_NAMES[split] if len(results) == 1 else f"{model}: {SPLIT_NAMES[split]}"
        ax.bar(np.arange(len(METRICS)) + (j - (len(bars) - 1) / 2) * width, vals, width, yerr=errs, capsize=3,
               label=label, hatch="//" if split == "pairings_ood" else None, alpha=0.85)
    ax.set_xticks(range(len(METRICS)), [METRIC_NAMES[m] for m in METRICS])
    ax.set_ylim(0, 105)
    ax.set_ylabel("rate (%) with 95% Wilson interval")
    ax.set_title(f"Object-region pairings ({REGIME_NAMES[regime].lower()})")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def plot_confusion(panels: dict[str, dict], path: str | Path, ylabel: str = "instructed") -> Path:
    """panels: title -> condition summary with a "confusion" entry; counts annotated, rows normalised."""
    if not panels:
        raise ValueError("no condition with a confusion matrix to draw (summaries from before them have none)")
    plt = _plt()
    k = len(panels)
    cols = min(k, 4)
    rows = int(np.ceil(k / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.4 * rows), squeeze=False)
    for ax in axes.flat[k:]:
        ax.axis("off")
    names = {o.name: o.phrase for o in OBJECTS}
    for ax, (title, cond) in zip(axes.flat, panels.items()):
        cm = cond["confusion"]
        counts = np.array(cm["counts"], dtype=float)
        frac = counts / np.maximum(counts.sum(axis=1, keepdims=True), 1)
        ax.imshow(frac, cmap="Blues", vmin=0, vmax=1)
        for (i, j), v in np.ndenumerate(counts):
            if v:
                ax.text(j, i, f"{int(v)}", ha="center", va="center", fontsize=8,
                        color="white" if frac[i, j] > 0.6 else "black")
        ax.set_xticks(range(len(cm["columns"])), [names.get(c, c) for c in cm["columns"]], rotation=45,
                      ha="right", fontsize=7)
        ax.set_yticks(range(len(cm["rows"])), [names.get(r, r) for r in cm["rows"]], fontsize=7)
        ax.set_xlabel("held at the end", fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def plot_data_scaling(stages: list[dict], path: str | Path, num_objects: int = 5) -> Path:
    """Before -> after arrows per model and regime, one panel per metric."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(METRICS), figsize=(4.2 * len(METRICS), 3.4), sharey=True)
    labels = [f"{s['model']}\n{REGIME_SHORT[s['regime']]}" for s in stages]
    for ax, m in zip(axes, METRICS):
        for i, s in enumerate(stages):
            key = f"{s['regime']}/canonical/{num_objects}"
            a, b = s["before"].get(key), s["after"].get(key)
            if a is None or b is None:
                continue
            (va,), ea = _err([a], m)
            (vb,), eb = _err([b], m)
            ax.errorbar([i - 0.12], [va], yerr=ea, fmt="o", color="tab:gray", capsize=3,
                        label="smaller set" if i == 0 else None)
            ax.errorbar([i + 0.12], [vb], yerr=eb, fmt="o", color="tab:blue", capsize=3,
                        label="larger set" if i == 0 else None)
            ax.annotate("", (i + 0.1, vb), (i - 0.1, va), arrowprops=dict(arrowstyle="->", color="black"))
        ax.set_xticks(range(len(stages)), labels, fontsize=7)
        ax.set_xlim(-0.6, len(stages) - 0.4)
        ax.set_title(METRIC_NAMES[m])
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("rate (%) with 95% Wilson interval")
    axes[0].legend(fontsize=8)
    fig.suptitle("Data scaling", y=1.03)
    return _save(fig, path)


def plot_displacement(curves: dict[str, dict], path: str | Path) -> Path:
    """One panel per metric, one line per policy: its rate in each displacement bin (evaluation/displacement.py),
    drawn at the bin's mean displacement with its Wilson interval; the legend gives each policy's odds ratio per
    10 cm of success."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(METRICS), figsize=(4.2 * len(METRICS), 3.4), sharey=True)
    for ax, m in zip(axes, METRICS):
        for j, (label, curve) in enumerate(curves.items()):
            v, e = _err(curve["bins"], m)
            x = np.array([b["mean_cm"] for b in curve["bins"]]) + (j - (len(curves) - 1) / 2) * 0.25
            odds = odds_text(curve["trend"]["success"], interval=False)  # the estimate, or the bound
            ax.errorbar(x, v, yerr=e, marker="o", capsize=3,
                        label=label + ("" if odds == "–" else f" ({odds} / 10 cm)"))
        ax.set_title(METRIC_NAMES[m])
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
    fig.supxlabel("the named object's distance from its place in training (cm)", fontsize=10)
    axes[0].set_ylabel("rate (%) with 95% Wilson interval")
    axes[0].legend(loc="best", fontsize=7)
    return _save(fig, path)
