"""The placement ladder: seeded, simulator-free sampling of object layouts.

A layout is a pure function of (condition, seed[, target]), so the same seed gives the
same scene, target and instruction on the CPU and GPU backends and for any number of parallel envs.

Frame: world metres, robot base at x = -0.615 facing +x, table top at z = 0 (ManiSkill convention).
The workspace is 35 cm deep (x) by 50 cm wide (y). Five canonical regions form a quincunx: four
corners and the workspace centre. In the jitter regimes object i always sits in region i (the
location shortcut the ladder removes step by step); the pairing splits permute objects over regions.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from vla_ladder.conditions import LADDER, REGIMES, Condition
from vla_ladder.task.appearance import check_appearance, swap_partner
from vla_ladder.task.instructions import CANONICAL, check_instruction_set, instruction_text, paraphrase_version
from vla_ladder.task.objects import NUM_OBJECTS, OBJECT_NAMES, OBJECTS, object_index

WORKSPACE_CENTER = np.array([-0.12, 0.0])
WORKSPACE_SIZE = np.array([0.35, 0.50])  # (x depth, y width)
# Region centres relative to the workspace centre; index 2 is the centre region.
REGION_OFFSETS = np.array([[0.105, 0.16], [0.105, -0.16], [0.0, 0.0], [-0.105, 0.16], [-0.105, -0.16]])
REGION_CENTERS = WORKSPACE_CENTER + REGION_OFFSETS
CENTER_REGION = 2

# Yaw jitter grows with the ladder so that small jitter stays benchmark-like (LIBERO rotates little).
# Object i trains in regions i, i+1, i+2 (mod 5) and is held out of i+3, i+4: every object and every
# region is seen three times in training, yet 10 of the 25 object-region pairs are never shown.
TRAIN_REGIONS: tuple[frozenset[int], ...] = tuple(
    frozenset((i + k) % NUM_OBJECTS for k in range(3)) for i in range(NUM_OBJECTS))
HELD_OUT_REGIONS: tuple[frozenset[int], ...] = tuple(
    frozenset(range(NUM_OBJECTS)) - TRAIN_REGIONS[i] for i in range(NUM_OBJECTS))
MIN_GAP = 0.01  # free space kept between object footprints
MAX_TRIES = 2000
REST_QPOS = np.array([0.0, np.pi / 8, 0, -np.pi * 5 / 8, 0, np.pi * 3 / 4, np.pi / 4, 0.04, 0.04])
"""the Panda's rest joint positions (7 arm joints, then the two fingers), around which every episode starts"""
ROBOT_INIT_QPOS_NOISE = 0.02
"""GraspObject-v1's default standard deviation (rad) of the arm's start around REST_QPOS"""
_POSITION_STREAM = 0x5A4B0  # the random stream of a position swap's partner order (Layout.position_partners)
_SWITCH_STREAM = 0x5A4B1  # the random stream of an instruction switch's new target (Layout.switch_partner)
_ORDER_STREAM = 0x5A4B2  # the random stream of the order full random places its objects in (sample_layout)


@dataclass(frozen=True)
class Layout:
    """One episode's scene: which objects, where, and which one is instructed."""

    condition: Condition
    seed: int
    objects: tuple[str, ...]
    """Present objects; the target is objects[0]."""
    xy: np.ndarray = field(repr=False)
    """(k, 2) object positions in metres, world frame."""
    yaw: np.ndarray = field(repr=False)
    """(k,) rotations about z in radians."""
    regions: tuple[int, ...] | None
    """Region index of each object (None in full_random)."""
    instructions: str = CANONICAL
    """the instruction set the wording is drawn from (task/instructions.py)"""
    colour_swap: tuple[str, str] | None = None
    """(instructed object, distractor) whose colours are exchanged (task/appearance.py); None: usual colours"""
    absent_target: str | None = None
    """an object NOT on the table that the instruction names instead of objects[0] (the absent-object probe,
    `instructed_absent`); None: the target is objects[0]"""
    position_swap: tuple[str, str] | None = None
    """(instructed object, distractor) whose positions were exchanged (the position-swap probe,
    `positions_swapped`); None: every object stands where the seed put it"""
    switch: tuple[int, str] | None = None
    """(control step K, present distractor B): from step K on the instruction names B and success is judged
    against B (the instruction-switch probe, `switched`); None: the instruction never changes"""
    removed: tuple[str, ...] | None = None
    """the distractors the seed placed and that were taken off the table, leaving the instructed object alone where
    it stood (the distractor-removal probe, `alone`); None: every object the seed placed is there"""

    @property
    def target(self) -> str:
        """The object the episode's first instruction names (for a switched episode, see `final_target`)."""
        return self.objects[0] if self.absent_target is None else self.absent_target

    @property
    def target_index(self) -> int:
        return object_index(self.target)

    @property
    def instruction(self) -> str:
        return instruction_text(self.target, self.seed, self.instructions)

    @property
    def final_target(self) -> str:
        """The object named at the final step, which success is judged against: `target`, or the switch's B."""
        return self.target if self.switch is None else self.switch[1]

    def instruction_at(self, step: int) -> str:
        """The instruction in force once `step` control steps have been taken (0: at reset): the switch's wording
        from its step on. B's wording is drawn from the seed as A's is (the same instruction set), so a canonical
        switch reads "grasp the <B>"."""
        if self.switch is None or step < self.switch[0]:
            return self.instruction
        return instruction_text(self.switch[1], self.seed, self.instructions)

    @property
    def absent(self) -> tuple[str, ...]:
        """The objects not on the table, in the object list's order (apple, orange, rubiks_cube, mug,
        large_marker): what `instructed_absent` ranks."""
        return tuple(n for n in OBJECT_NAMES if n not in self.objects)

    def instructed(self, obj: str | int) -> "Layout":
        """The same scene instructing another present object (a name, or its rank in `objects`: 0 is the
        target, k the k-th distractor): objects, positions, yaw and colours are unchanged, only which object
        comes first (the target) and so the instruction differ. The counterfactual of the instruction-swap
        probe, unlike sample_layout(..., target=), which samples another scene."""
        self._check_unswitched("instruct")
        if isinstance(obj, (int, np.integer)) and not isinstance(obj, bool):
            if not 0 <= obj < len(self.objects):
                raise ValueError(f"instruct rank {obj} is not a present object of seed {self.seed}: "
                                 f"allowed 0-{len(self.objects) - 1} ({', '.join(self.objects)})")
            k = int(obj)
        elif obj in self.objects:
            k = self.objects.index(obj)
        else:
            object_index(obj)
            raise ValueError(f"cannot instruct {obj!r}: seed {self.seed} of {self.condition} holds only "
                             f"{', '.join(self.objects)}")
        order = [k] + [i for i in range(len(self.objects)) if i != k]
        return replace(self, objects=tuple(self.objects[i] for i in order), xy=self.xy[order], yaw=self.yaw[order],
                       regions=None if self.regions is None else tuple(self.regions[i] for i in order),
                       absent_target=None)

    def instructed_absent(self, obj: str | int) -> "Layout":
        """The same scene instructing an object that is NOT on the table (a name, or its rank in `absent`): objects,
        positions, yaw and colours are unchanged; `target`, `target_index` and the instruction name the absent
        object. The counterfactual of the absent-object probe. Separate from `instructed` on purpose: there a name
        that is not on the table is a mistake (a typo in a swap) and fails; here it is the point."""
        self._check_unswitched("instruct_absent")
        absent = self.absent
        if isinstance(obj, (int, np.integer)) and not isinstance(obj, bool):
            if not 0 <= obj < len(absent):
                allowed = f"allowed 0-{len(absent) - 1} ({', '.join(absent)})" if absent else "all five are present"
                raise ValueError(f"absent rank {obj} is not an object missing from seed {self.seed} of "
                                 f"{self.condition}: {allowed}")
            name = absent[int(obj)]
        elif obj in self.objects:
            raise ValueError(f"cannot instruct {obj!r} as absent: it is on the table of seed {self.seed} of "
                             f"{self.condition} (instruct it as a present object instead)")
        else:
            name = OBJECT_NAMES[object_index(obj)]
        return replace(self, absent_target=name)

    def position_partners(self) -> tuple[str, ...]:
        """The distractors, in the order `positions_swapped` tries them: a seed-determined permutation on a random
        stream of its own (the first is the seed's partner, the others the fallbacks), so layouts are unchanged."""
        rng = np.random.default_rng([int(self.seed) & 0xFFFFFFFFFFFFFFFF, _POSITION_STREAM])
        return tuple(self.objects[1 + int(k)] for k in rng.permutation(len(self.objects) - 1))

    def positions_swapped(self) -> "Layout":
        """The same scene with the instructed object and one distractor exchanging places (xy and region; each
        keeps its own yaw): the counterfactual of the position-swap probe. Everything else (the other objects,
        colours, wording, robot start) is unchanged. The distractor is the first of `position_partners` whose
        exchange leaves every pair of footprints MIN_GAP apart, as the sampler requires (objects differ in size,
        so a place that fits one may not fit the other), and, under full random, every footprint on the
        workspace; when none fits, the scene is returned unchanged (`position_swap` None), as an appearance swap
        without a partner is. Yaw stays: footprints are circles, so it cannot change a collision, and a
        rotated object would be a second change."""
        if self.absent_target is not None:
            raise ValueError(f"cannot swap positions in seed {self.seed}: the instructed object "
                             f"{self.absent_target!r} is not on the table")
        if self.position_swap is not None:
            return self
        radii = tuple(OBJECTS[object_index(n)].footprint_radius for n in self.objects)
        for partner in self.position_partners():
            k = self.objects.index(partner)
            xy = self.xy.copy()
            xy[[0, k]] = xy[[k, 0]]
            points = [tuple(p) for p in xy.tolist()]
            if any(_collides(points, radii, i) for i in range(1, len(points))):
                continue
            if self.regions is None and not _on_workspace(xy, radii):
                continue
            regions = None if self.regions is None else tuple(
                self.regions[{0: k, k: 0}.get(i, i)] for i in range(len(self.regions)))
            return replace(self, xy=xy, regions=regions, position_swap=(self.objects[0], partner))
        return self

    def alone(self) -> "Layout":
        """The same scene with every distractor taken off the table: the instructed object stays where it stood,
        with its yaw, colour and wording, and so does the robot's start: the counterfactual of the
        distractor-removal probe. The condition (and its object count) stays the scene's: `removed` names what
        was there."""
        if self.absent_target is not None:
            raise ValueError(f"cannot leave the instructed object alone in seed {self.seed}: "
                             f"{self.absent_target!r} is not on the table")
        if self.switch is not None or self.position_swap is not None:
            raise ValueError(f"cannot take the distractors off seed {self.seed}'s table: its "
                             f"{'instruction switches to' if self.switch else 'target swapped places with'} one")
        if self.removed is not None:
            return self
        # The instructed object keeps the colour it wore (a swap's partner, parked, wears the other one).
        swap = self.colour_swap if self.colour_swap and self.objects[0] in self.colour_swap else None
        return replace(self, objects=self.objects[:1], xy=self.xy[:1], yaw=self.yaw[:1],
                       regions=None if self.regions is None else self.regions[:1], removed=self.objects[1:],
                       colour_swap=swap)

    def _check_unswitched(self, what: str) -> None:
        # The switch's B is drawn among the distractors of the instructed object: instructing another object
        # afterwards could make B the target itself. The env applies instruct first and the switch last.
        if self.switch is not None:
            raise ValueError(f"{what} names the first instruction of seed {self.seed}, which already switches at "
                             f"step {self.switch[0]}; instruct first, then switch")

    def switch_partner(self) -> str:
        """The distractor an instruction switch names: drawn from the seed on a random stream of its own (layouts
        are unchanged), uniformly among the present distractors. Any present object will do (nothing moves), so
        unlike a position swap there is no fallback."""
        if len(self.objects) < 2:
            raise ValueError(f"cannot switch the instruction in seed {self.seed} of {self.condition}: it holds only "
                             f"{self.objects[0]} (a switch names another object on the table; allowed: 2-5 objects)")
        rng = np.random.default_rng([int(self.seed) & 0xFFFFFFFFFFFFFFFF, _SWITCH_STREAM])
        return self.objects[1 + int(rng.integers(len(self.objects) - 1))]

    def switched(self, step: int) -> "Layout":
        """The same scene whose instruction switches at control step `step` (>= 1) from the instructed object A
        to the seed's `switch_partner` B: the counterfactual of the instruction-switch probe. Objects, places,
        colours and the robot start are unchanged; `target` and `instruction` stay A's (what the episode starts
        with), `final_target` and `instruction_at(step)` give B's from the switch on."""
        if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 1:
            raise ValueError(f"an instruction switch happens at a control step >= 1, got {step!r}")
        if self.absent_target is not None:
            raise ValueError(f"cannot switch the instruction in seed {self.seed}: the instructed object "
                             f"{self.absent_target!r} is not on the table")
        return replace(self, switch=(int(step), self.switch_partner()))

    def to_dict(self) -> dict:
        out = {
            "seed": self.seed, "regime": self.condition.regime, "split": self.condition.split, "target": self.target,
            "instruction": self.instruction,
            "positions": {n: [round(float(v), 5) for v in p] for n, p in zip(self.objects, self.xy)},
            "yaw": {n: round(float(a), 5) for n, a in zip(self.objects, self.yaw)},
            "regions": None if self.regions is None else dict(zip(self.objects, self.regions)),
        }
        # Only episodes that use them say so: canonical, unswapped layouts read as they always did.
        if self.instructions != CANONICAL:
            out.update(instructions=self.instructions, paraphrases_version=paraphrase_version())
        if self.colour_swap is not None:
            out["colour_swap"] = list(self.colour_swap)
        if self.absent_target is not None:  # "target" names an object that "positions" does not hold
            out["absent_target"] = True
        if self.position_swap is not None:  # "positions" and "regions" are where the objects stand after it
            out["position_swap"] = list(self.position_swap)
        if self.switch is not None:  # "target" and "instruction" are the first ones; these from step K on
            out["switch"] = {"step": self.switch[0], "target": self.switch[1],
                             "instruction": self.instruction_at(self.switch[0])}
        if self.removed is not None:  # "positions" holds the target alone; these stood there too
            out["removed"] = list(self.removed)
        return out


@lru_cache(maxsize=None)
def region_assignments(objects: tuple[int, ...], split: str) -> tuple[tuple[int, ...], ...]:
    """Every injective object->region map allowed by a split (objects[0] is the target)."""
    if split == "canonical":
        return (tuple(objects),)
    out = []
    for regions in itertools.permutations(range(NUM_OBJECTS), len(objects)):
        ok_distractors = all(r in TRAIN_REGIONS[o] for o, r in zip(objects[1:], regions[1:]))
        target_pool = TRAIN_REGIONS[objects[0]] if split == "pairings_id" else HELD_OUT_REGIONS[objects[0]]
        if ok_distractors and regions[0] in target_pool:
            out.append(regions)
    return tuple(out)


def usual_regions(obj: str, condition: Condition) -> tuple[int, ...] | None:
    """The regions where object `obj` stands in the training layouts of the condition: region i for object i
    (canonical split), its three training regions TRAIN_REGIONS[i] (pairings_id and pairings_ood: an OOD
    evaluation tests a policy trained on pairings_id layouts); None in full_random, where no place is usual."""
    i = object_index(obj)
    if REGIMES[condition.regime] is None:
        return None
    return (i,) if condition.split == "canonical" else tuple(sorted(TRAIN_REGIONS[i]))


def _collides(xy: list[tuple[float, float]], radii: tuple[float, ...], i: int) -> bool:
    # Scalar floats, not NumPy: this runs ~10 times a layout and a batched reset samples thousands of layouts.
    # sqrt(dx*dx + dy*dy) and (r_j + r_i) + gap are the operations np.linalg.norm and the array sums did, in the
    # same order, so every comparison (and so every layout of every seed) is what the NumPy version gave.
    x, y = xy[i]
    for j in range(i):
        dx, dy = xy[j][0] - x, xy[j][1] - y
        if math.sqrt(dx * dx + dy * dy) < radii[j] + radii[i] + MIN_GAP:
            return True
    return False


def _on_workspace(xy: np.ndarray, radii: tuple[float, ...]) -> bool:
    """Every footprint lies on the workspace: what full_random's sampling boxes guarantee (_boxes)."""
    r = np.asarray(radii)[:, None]
    lo, hi = WORKSPACE_CENTER - WORKSPACE_SIZE / 2, WORKSPACE_CENTER + WORKSPACE_SIZE / 2
    return bool(((xy - r >= lo) & (xy + r <= hi)).all())


@lru_cache(maxsize=None)
def _boxes(names: tuple[str, ...], regime: str, regions: tuple[int, ...] | None) -> tuple:
    """Per object, where its position is drawn, as Python floats: (low, range, offset) for offset + (low + range * u)
    with u uniform in [0, 1)^2 (offset None: 0), or (None, None, xy) for a fixed place (small jitter's centre)."""
    def floats(a: np.ndarray) -> tuple[float, ...]:
        return tuple(a.tolist())

    out = []
    for name, region in zip(names, regions or (None,) * len(names)):
        if region is None:  # full_random: the whole footprint stays on the workspace
            r = OBJECTS[object_index(name)].footprint_radius
            lo, hi = WORKSPACE_CENTER - WORKSPACE_SIZE / 2 + r, WORKSPACE_CENTER + WORKSPACE_SIZE / 2 - r
            out.append((floats(lo), floats(hi - lo), None))
        elif regime == "small_jitter" and region == CENTER_REGION:
            out.append((None, None, floats(REGION_CENTERS[CENTER_REGION])))
        else:
            half = np.asarray(REGIMES[regime]) / 2
            lo, hi = -half, half
            out.append((floats(lo), floats(hi - lo), floats(REGION_CENTERS[region])))
    return tuple(out)


def _draw(rng: np.random.Generator, box: tuple) -> tuple[float, float]:
    # rng.uniform(low, high) on arrays is low + (high - low) * next_double per element (NumPy's random_uniform),
    # drawn in element order: rng.random(2) gives the same doubles at a tenth of the cost (no argument checks),
    # and the float operations below are NumPy's, in its order, so every layout is bit for bit what NumPy gave.
    low, span, offset = box
    if low is None:
        return offset
    u0, u1 = rng.random(2).tolist()
    x, y = low[0] + span[0] * u0, low[1] + span[1] * u1
    return (x, y) if offset is None else (offset[0] + x, offset[1] + y)


def sample_layout(condition: Condition, seed: int = 0, target: str | None = None, instructions: str = CANONICAL,
                  appearance: str = "original") -> Layout:
    """Sample one layout; a given condition and seed always give the same layout. `instructions` (an
    instruction set) picks the wording and `appearance` ("swap") the colour swap, each on a random stream of its
    own: neither changes where the objects are."""
    if not isinstance(condition, Condition):
        raise TypeError(f"sample_layout takes a Condition, got {type(condition).__name__}")
    check_instruction_set(instructions)
    check_appearance(appearance)
    regime, split, num_objects = condition.regime, condition.split, condition.num_objects
    if target is not None:
        object_index(target)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFFFFFFFFFF, 0x1ADDE2]))
    t = object_index(target) if target is not None else int(rng.integers(NUM_OBJECTS))
    others = [i for i in range(NUM_OBJECTS) if i != t]
    distractors = rng.permutation(others)[: num_objects - 1]
    idx = (t, *map(int, distractors))
    names = tuple(OBJECT_NAMES[i] for i in idx)
    radii = tuple(OBJECTS[i].footprint_radius for i in idx)
    regions: tuple[int, ...] | None = None
    if REGIMES[regime] is not None:
        choices = region_assignments(idx, split)
        regions = choices[int(rng.integers(len(choices)))]
    boxes = _boxes(names, regime, regions)
    # Each object is drawn again until it clears those placed before it, so the first one lands uniformly and the
    # later ones are pushed away from it. Full random places them in an order drawn from the seed: placed first, the
    # target stood nearer the workspace's centre than its distractors (the nearest in 26% of five-object layouts
    # against 20%; benchmarks/layout_bias.py). In the jitter regimes each object keeps to its region.
    order = (np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFFFFFFFFFF, _ORDER_STREAM]))
             .permutation(num_objects).tolist() if regions is None else list(range(num_objects)))
    placed_boxes, placed_radii = [boxes[j] for j in order], tuple(radii[j] for j in order)
    for _ in range(MAX_TRIES):
        xy: list[tuple[float, float]] = []
        for i, box in enumerate(placed_boxes):
            for _ in range(MAX_TRIES):
                xy[i:] = [_draw(rng, box)]  # the i-th placed object's draw, replacing its rejected one
                if not _collides(xy, placed_radii, i):
                    break
            else:  # it found no free place: start the layout again
                break
        else:  # every object placed
            break
    else:  # pragma: no cover - the regions are sized so this cannot happen with the shipped objects
        raise RuntimeError(f"no collision-free layout after {MAX_TRIES} tries ({regime}, seed {seed})")
    xy = np.array(xy)[np.argsort(order)]  # back in the layout's order, the target first
    low = -LADDER[regime].yaw
    yaw = low + (LADDER[regime].yaw - low) * rng.random(num_objects)  # rng.uniform(low, high, k), as in _draw
    partner = swap_partner(names, seed) if appearance == "swap" else None
    return Layout(condition, int(seed), names, xy, yaw, regions, instructions,
                  None if partner is None else (names[0], partner))


def sample_layouts(condition: Condition, seeds=(0,), target: str | None = None, instructions: str = CANONICAL,
                   appearance: str = "original") -> list[Layout]:
    return [sample_layout(condition, int(s), target, instructions, appearance) for s in seeds]


def initial_qpos(seed: int, noise: float = ROBOT_INIT_QPOS_NOISE) -> np.ndarray:
    """(9,) float32 joint positions episode `seed` starts from: REST_QPOS, the arm's seven with Gaussian noise on a
    random stream of the seed's own. The env's reset sets them; check-dataset compares each recorded episode's first
    state with them, tying its frames to its seed without a simulator."""
    qpos = REST_QPOS.astype(np.float32)
    qpos[:7] += np.random.default_rng([int(seed), 7]).normal(0, noise, 7).astype(np.float32)
    return qpos


def condition_of(data: dict) -> Condition:
    """The condition a recorded `Layout.to_dict()` was sampled in: its objects on the table and, after a distractor
    removal, the ones taken off it."""
    return Condition(data["regime"], data["split"], len(data["positions"]) + len(data.get("removed") or ()))


def layout_from_dict(data: dict) -> Layout:
    """The layout that the seed of a recorded `Layout.to_dict()` gives, sampled again (dataset checks compare
    the two): condition, object count, instruction set, appearance, the instructed object (an instruction swap's
    `instructed`), position swap and instruction switch as the dict says, applied in the env's order."""
    lay = sample_layout(condition_of(data), int(data["seed"]), instructions=data.get("instructions", CANONICAL),
                        appearance="swap" if data.get("colour_swap") else "original")
    if not data.get("absent_target") and data["target"] != lay.target and data["target"] in lay.objects:
        lay = lay.instructed(data["target"])  # the same scene, another present object named
    if data.get("position_swap"):
        lay = lay.positions_swapped()
    if data.get("switch"):
        lay = lay.switched(int(data["switch"]["step"]))
    if data.get("removed") is not None:
        lay = lay.alone()
    return lay.instructed_absent(data["target"]) if data.get("absent_target") else lay
