"""The label a run is shown under: its policy spec, a checkpoint's path cut to the folders that name its model.

A checkpoint's whole path (`lerobot:/home/me/runs/act/checkpoints/last/pretrained_model`) made tables, legends and
headings unreadable and named the machine's folders in a page meant to be shared.
"""

from __future__ import annotations

import itertools
from collections import Counter
from pathlib import Path

from vla_ladder.checks import ascii_digits
from vla_ladder.policies.lerobot import checkpoint_name


def _checkpoint_path(spec: str) -> tuple[str, tuple[str, ...], str] | None:
    """A spec of a kind that names a checkpoint by its path -> (kind, the folders that name its model, what follows
    them: the step, `@step20000`, and the options, which make another policy); None for other specs."""
    kind, _, arg = spec.partition(":")
    path, query, options = arg.partition("?")
    if kind == "lerobot" and path:
        parts, step = checkpoint_name(path)
    elif kind == "ppo" and path:
        parts, step = Path(path).parts[1 if Path(path).anchor else 0:], None
    else:
        return None
    at = "" if step is None else f"@step{step}" if ascii_digits(step) else f"@{step}"
    return (kind, parts, f"{at}{query}{options}") if parts else None


def short_labels(specs: list[str]) -> list[str]:
    """Each policy spec with its checkpoint's path cut to the last folders of its training run and its step, as few
    as tell the report's models apart (`lerobot:/home/me/runs/act/checkpoints/last/pretrained_model` ->
    `lerobot:act@step20000`; two experiments' runs named alike -> `lerobot:expA/act@step20000` and
    `lerobot:expB/act@step20000`). Other specs, and two specs still shown alike (one checkpoint written two ways),
    keep their whole spec."""
    paths = {s: _checkpoint_path(s) for s in dict.fromkeys(specs)}
    models = {p[1] for p in paths.values() if p}
    shown = {}
    for spec, p in paths.items():
        if p is None:
            shown[spec] = spec
            continue
        kind, parts, rest = p
        depth = next(d for d in itertools.count(1) if all(m[-d:] != parts[-d:] for m in models - {parts}))
        shown[spec] = f"{kind}:{'/'.join(parts[-depth:])}{rest}"
    counts = Counter(shown.values())
    return [shown[s] if counts[shown[s]] == 1 else s for s in specs]
