"""Conditions: which placement regime, which object-region split, how many objects.

A `Condition` is validated once, when it is made, and has one text form, its key "regime/split/k"
(`Condition.parse` reads it back). A `ConditionGrid` is the set of conditions a command runs over:
regimes x splits x object counts, where "all" stands for every regime. Simulator-free.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from vla_ladder.checks import ascii_digits


@dataclass(frozen=True)
class Regime:
    """One rung of the placement ladder: everything the task, the sampler and the report know about it."""

    extent: tuple[float, float] | None
    """(x, y) extent of each of the five regions in metres; None: anywhere in the workspace (no regions, so no
    pairing splits)"""
    yaw: float
    """objects' yaw is drawn uniformly in [-yaw, yaw] radians"""
    title: str
    """the regime as tables and figures name it"""
    short: str
    """the same in a narrow column"""


LADDER: dict[str, Regime] = {
    # In ladder order, easiest first: tables, figures and "all" follow it. A new regime here joins "all".
    "small_jitter": Regime((0.04, 0.06), math.pi / 12, "Small jitter", "Small jitter"),
    "medium_jitter": Regime((0.08, 0.12), math.pi / 6, "Medium jitter", "Med. jitter"),
    "large_jitter": Regime((0.12, 0.16), math.pi / 4, "Large jitter", "Lrg. jitter"),
    "full_random": Regime(None, math.pi, "Full random", "Full random"),
}
REGIMES: dict[str, tuple[float, float] | None] = {name: r.extent for name, r in LADDER.items()}
"""Each regime's region extent (LADDER's, by name): None for the whole workspace."""
JITTER_REGIMES: tuple[str, ...] = tuple(r for r, e in REGIMES.items() if e is not None)
SPLITS: tuple[str, ...] = ("canonical", "pairings_id", "pairings_ood")
MAX_OBJECTS = 5
ALL = "all"


@dataclass(frozen=True)
class Condition:
    """One evaluation or training condition of GraspObject-v1."""

    regime: str = "small_jitter"
    """placement regime: small_jitter, medium_jitter, large_jitter or full_random (the ladder's rungs, easiest first)"""
    split: str = "canonical"
    """object-region split: canonical (object i in region i), pairings_id or pairings_ood (held-out pairs)"""
    num_objects: int = MAX_OBJECTS
    """objects on the table, 1-5 (the instructed one and its distractors)"""

    def __post_init__(self):
        if self.regime not in REGIMES:
            raise ValueError(f"unknown regime {self.regime!r}; allowed: {', '.join(REGIMES)}")
        if self.split not in SPLITS:
            raise ValueError(f"unknown split {self.split!r}; allowed: {', '.join(SPLITS)}")
        if self.split != "canonical" and REGIMES[self.regime] is None:
            raise ValueError(f"split {self.split!r} needs a jitter regime (regions); allowed: "
                             f"{', '.join(JITTER_REGIMES)}")
        k = self.num_objects
        if isinstance(k, bool) or not hasattr(k, "__index__") or not 1 <= k <= MAX_OBJECTS:
            raise ValueError(f"num_objects must be an integer from 1 to {MAX_OBJECTS}, got {k!r}")
        object.__setattr__(self, "num_objects", int(k))

    @property
    def key(self) -> str:
        """"regime/split/num_objects", the one text form of a condition (file names, result keys)."""
        return f"{self.regime}/{self.split}/{self.num_objects}"

    def __str__(self) -> str:
        return self.key

    @property
    def slug(self) -> str:
        """The key as a file name: regime-split-Kobj."""
        return f"{self.regime}-{self.split}-{self.num_objects}obj"

    @classmethod
    def parse(cls, key: str) -> "Condition":
        """The inverse of `key`: "full_random/canonical/5" -> Condition("full_random", "canonical", 5)."""
        parts = str(key).split("/")
        if len(parts) != 3 or not ascii_digits(parts[2].strip()):
            raise ValueError(f"bad condition {key!r}; expected regime/split/num_objects, e.g. small_jitter/canonical/5")
        return cls(parts[0].strip(), parts[1].strip(), int(parts[2]))

    @classmethod
    def of(cls, value: "Condition | str | dict | tuple") -> "Condition":
        """A condition from a Condition, a key, a {regime, split, num_objects} dict or a tuple."""
        if isinstance(value, Condition):
            return value
        if isinstance(value, str):
            return cls.parse(value)
        if isinstance(value, dict):
            unknown = set(value) - {"regime", "split", "num_objects"}
            if unknown:
                raise ValueError(f"unknown condition fields {sorted(unknown)}; allowed: regime, split, num_objects")
            return cls(**value)
        return cls(*value)


def parse_regimes(names) -> tuple[str, ...]:
    """Regime names, or "all" for every regime (a comma list in one string is accepted too)."""
    if isinstance(names, str):
        names = [names]
    flat = [r.strip() for n in names for r in str(n).split(",") if r.strip()]
    if flat and set(flat) == {ALL}:
        return tuple(REGIMES)
    if ALL in flat:
        raise ValueError(f"{ALL} already names every regime; give it alone or name regimes, got {' '.join(flat)}")
    if not flat:
        raise ValueError(f"no regime given; allowed: {', '.join(REGIMES)} or {ALL}")
    for r in flat:
        if r not in REGIMES:
            raise ValueError(f"unknown regime {r!r}; allowed: {', '.join(REGIMES)} or {ALL}")
    if len(set(flat)) != len(flat):  # as splits and object counts: a repeat is a typo, not a request
        raise ValueError(f"regimes must be distinct, got {' '.join(flat)}")
    return tuple(flat)


@dataclass(frozen=True)
class ConditionGrid:
    """Every (regime, split, num_objects) of regimes x splits x object counts. Pairing splits need regions,
    so they pair with the jitter regimes only (full_random x pairings_* is left out, not an error)."""

    regimes: tuple[str, ...] = (ALL,)
    """placement regimes: small_jitter, medium_jitter, large_jitter, full_random, or all"""
    splits: tuple[str, ...] = ("canonical",)
    """object-region splits: canonical, pairings_id, pairings_ood"""
    num_objects: tuple[int, ...] = (MAX_OBJECTS,)
    """objects on the table, 1-5 (several give several conditions)"""

    def __post_init__(self):
        object.__setattr__(self, "regimes", parse_regimes(self.regimes))
        object.__setattr__(self, "splits", tuple(self.splits))
        object.__setattr__(self, "num_objects", tuple(self.num_objects))
        if not self.splits or not self.num_objects:
            raise ValueError("a condition grid needs at least one split and one object count")
        for name in ("splits", "num_objects"):  # a repeat would play its episodes twice under one key
            values = getattr(self, name)
            if len(set(values)) != len(values):
                raise ValueError(f"{name} must be distinct, got {' '.join(map(str, values))}")
        for s in self.splits:
            Condition(JITTER_REGIMES[0], s)
        for k in self.num_objects:
            Condition(num_objects=k)
        if not self.conditions:
            raise ValueError(f"no valid condition: splits {', '.join(self.splits)} need a jitter regime "
                             f"({', '.join(JITTER_REGIMES)})")

    @property
    def conditions(self) -> list[Condition]:
        """The conditions in order: regime-major, then split, then object count."""
        return [Condition(r, s, k) for r, s, k in itertools.product(self.regimes, self.splits, self.num_objects)
                if s == "canonical" or REGIMES[r] is not None]
