"""Instruction sets: the paper's "grasp the <object>" and the shipped, versioned paraphrases.

A policy that grounds language should grasp the apple whether it is told "grasp the apple", "pick up the red
fruit" or "take the apple". paraphrases.json (next to this module) holds verbs and object phrases, each split
into train and held-out, so a dataset recorded with `paraphrase-train` wordings can be evaluated on
`paraphrase-heldout` ones it never saw:

- canonical: "grasp the <object>", the paper's only wording;
- paraphrase-train: a train verb and a train phrase ("lift the red apple"; the canonical wording is one of them);
- paraphrase-heldout: every wording with a held-out verb ("pick up", "grab", "take") or a held-out phrase
  ("the red fruit", "the cup", "the pen", ...), or both.

The wording of an episode is drawn from its seed and the instructed object on a random stream of its own, so
a seed gives the same text on every backend and the layout does not depend on the instruction set.
Simulator-free.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

from vla_ladder.task.objects import OBJECT_NAMES, instruction_for, object_index

CANONICAL = "canonical"
INSTRUCTION_SETS: tuple[str, ...] = (CANONICAL, "paraphrase-train", "paraphrase-heldout")
NOVELTIES: tuple[str, ...] = ("none", "verb", "object", "both")
"""What a wording holds that training wordings do not: nothing, its verb, its object phrase, or both."""
_STREAM = 0x7E47  # the wording's random stream, apart from the layout's


@dataclass(frozen=True)
class Wording:
    """One way to instruct an object."""

    text: str
    object: str
    verb: str
    phrase: str
    novelty: str
    """none (train verb and phrase), verb, object or both held out"""


def check_instruction_set(name: str) -> str:
    if name not in INSTRUCTION_SETS:
        raise ValueError(f"unknown instruction set {name!r}; allowed: {', '.join(INSTRUCTION_SETS)}")
    return name


@lru_cache(maxsize=1)
def paraphrase_data() -> dict:
    """paraphrases.json, checked: every object has phrases, no phrase or verb is in both splits, no phrase
    names two objects, and the canonical wording is a train wording."""
    data = json.loads(resources.files("vla_ladder.task").joinpath("paraphrases.json").read_text())
    verbs, objects = data["verbs"], data["objects"]
    problems = []
    if set(objects) != set(OBJECT_NAMES):
        problems.append(f"objects {sorted(objects)} are not {sorted(OBJECT_NAMES)}")
    if set(verbs["train"]) & set(verbs["heldout"]) or "grasp" not in verbs["train"]:
        problems.append("verbs: train and heldout overlap, or 'grasp' is not a train verb")
    seen: dict[str, str] = {}
    for name, phrases in objects.items():
        if instruction_for(name) != f"grasp {phrases['train'][0]}":
            problems.append(f"{name}: the first train phrase must give the canonical {instruction_for(name)!r}")
        for phrase in phrases["train"] + phrases["heldout"]:
            if phrase.lower() in seen:
                problems.append(f"phrase {phrase!r} names both {seen[phrase.lower()]} and {name}")
            seen[phrase.lower()] = name
    if problems:
        raise ValueError("paraphrases.json is inconsistent: " + "; ".join(problems))
    return data


def paraphrase_version() -> int:
    return int(paraphrase_data()["version"])


@lru_cache(maxsize=None)
def wordings(name: str, instructions: str) -> tuple[Wording, ...]:
    """Every wording of `instructions` for object `name`, in a fixed order."""
    object_index(name)
    check_instruction_set(instructions)
    if instructions == CANONICAL:
        text = instruction_for(name)
        return (Wording(text, name, "grasp", text.removeprefix("grasp "), "none"),)
    data = paraphrase_data()
    verbs, phrases = data["verbs"], data["objects"][name]
    out = []
    for verb_split in ("train", "heldout"):
        for phrase_split in ("train", "heldout"):
            novelty = NOVELTIES[(verb_split == "heldout") + 2 * (phrase_split == "heldout")]
            if (novelty == "none") != (instructions == "paraphrase-train"):
                continue
            out += [Wording(f"{verb} {phrase}", name, verb, phrase, novelty)
                    for verb in verbs[verb_split] for phrase in phrases[phrase_split]]
    return tuple(out)


def wording_for(name: str, seed: int, instructions: str = CANONICAL) -> Wording:
    """The wording episode `seed` uses to instruct object `name` (a pure function of its arguments)."""
    options = wordings(name, instructions)
    if len(options) == 1:
        return options[0]
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFFFFFFFFFF, _STREAM, object_index(name)])
    return options[int(rng.integers(len(options)))]


def instruction_text(name: str, seed: int, instructions: str = CANONICAL) -> str:
    return wording_for(name, seed, instructions).text


@lru_cache(maxsize=1)
def _lookup() -> tuple[tuple[str, ...], dict[str, str]]:
    data = paraphrase_data()
    verbs = tuple(sorted(data["verbs"]["train"] + data["verbs"]["heldout"], key=len, reverse=True))
    phrases = {p.lower(): name for name, ps in data["objects"].items() for p in ps["train"] + ps["heldout"]}
    return verbs, phrases


def parse_instruction(text: str) -> Wording:
    """The wording of an instruction text of any shipped set (case and a final full stop ignored);
    ValueError naming the accepted form otherwise."""
    verbs, phrases = _lookup()
    clean = " ".join(str(text).strip().rstrip(".").split()).lower()
    for verb in verbs:
        if clean.startswith(verb + " ") and clean[len(verb) + 1:] in phrases:
            name = phrases[clean[len(verb) + 1:]]
            for instructions in INSTRUCTION_SETS[1:]:
                for w in wordings(name, instructions):
                    if w.text.lower() == clean:
                        return w
    raise ValueError(f"cannot parse instruction {text!r}; expected '<verb> <object phrase>' with a verb of "
                     f"{', '.join(sorted(verbs))} and a phrase of paraphrases.json v{paraphrase_version()}, "
                     "e.g. 'grasp the apple'")
