"""Appearance swaps: the instructed object wears another object's colour, and that object wears its colour.

Does a policy told "grasp the apple" look for the apple's shape or for something red? Under a swap the
instructed object keeps its shape, its place and the instruction but takes the colour of one present
distractor, which takes the instructed object's colour in return; a policy that follows colour grasps the
distractor. The swaps come from one documented set, SWAPS (version SWAPS_VERSION): pairs whose usual colours
differ in both object sets (stand-ins and YCB). The Rubik's cube is never swapped: what it looks like is a
sticker pattern, not one colour. In an episode with appearance "swap", the partner is drawn from the seed
among the present distractors that pair with the instructed object (a random stream of its own, so layouts
are unchanged); when none does, the episode plays unswapped and says so (`Layout.colour_swap` is None).

How an object is repainted: the stand-ins' body materials (those of the object's own colour in
objects.OBJECTS; stems, caps and stickers stay) take the partner's colour; a textured (YCB) material is
tinted, its texture's luminance times the partner's mean texture colour, so it keeps its shading and print.
The choice is simulator-free; painting needs SAPIEN and is imported only by the env.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from vla_ladder.task.objects import OBJECTS, object_index

APPEARANCES: tuple[str, ...] = ("original", "swap")
SWAPS_VERSION = 1
SWAPS: tuple[tuple[str, str], ...] = (
    ("apple", "orange"),  # a red orange, an orange apple
    ("apple", "large_marker"),  # a red marker, a dark apple
    ("orange", "mug"),
    ("orange", "large_marker"),
    ("mug", "large_marker"),  # a blue (stand-in) or red (YCB) marker
)
_PAIRS = frozenset(frozenset(p) for p in SWAPS)
_STREAM = 0xC0105


def check_appearance(name: str) -> str:
    if name not in APPEARANCES:
        raise ValueError(f"unknown appearance {name!r}; allowed: {', '.join(APPEARANCES)}")
    return name


def swap_partner(objects: Sequence[str], seed: int) -> str | None:
    """The distractor that exchanges colours with the instructed object objects[0] in episode `seed`, or None
    when no present distractor pairs with it in SWAPS."""
    partners = [o for o in objects[1:] if frozenset((objects[0], o)) in _PAIRS]
    if not partners:
        return None
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFFFFFFFFFF, _STREAM])
    return partners[int(rng.integers(len(partners)))]


# ---------------------------------------------------------------------- painting (SAPIEN)
def _materials(entity) -> list:
    """Every render material of an entity's visual shapes ([] when the scene does not render)."""
    import sapien.render

    body = entity.find_component_by_type(sapien.render.RenderBodyComponent)
    if body is None:
        return []
    out = []
    for shape in body.render_shapes:
        if isinstance(shape, sapien.render.RenderShapePrimitive):
            out.append(shape.material)
        else:
            out += [part.material for part in shape.parts]
    return out


def _to_linear(srgb: np.ndarray) -> np.ndarray:
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def _to_srgb(linear: np.ndarray) -> np.ndarray:
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, linear * 12.92, 1.055 * linear ** (1 / 2.4) - 0.055)


def _texture_rgb(texture) -> np.ndarray:
    """(H, W, 3) linear RGB in [0, 1] and the (H, W) mask of opaque texels of a uint8 RGBA texture."""
    data = texture.download()
    rgb = data[..., :3].astype(np.float64) / 255.0
    return (_to_linear(rgb) if texture.is_srgb else rgb), (data[..., 3] > 0 if data.shape[-1] == 4 else
                                                           np.ones(data.shape[:2], bool))


class Look:
    """What one object looks like in one sub-scene, remembered so that it can be repainted and restored."""

    def __init__(self, entity, index: int):
        self.index = index
        self.materials = _materials(entity)
        self.saved = [(list(m.base_color), m.base_color_texture) for m in self.materials]

    @property
    def colour(self) -> np.ndarray:
        """The object's usual colour (linear RGB): its stand-in colour, or the mean of its textures."""
        textured = [(c, t) for c, t in self.saved if t is not None]
        if not textured:
            return np.asarray(OBJECTS[self.index].rgba[:3], dtype=np.float64)
        means = []
        for colour, texture in textured:
            rgb, mask = _texture_rgb(texture)
            means.append(rgb[mask].mean(axis=0) * np.asarray(colour[:3]))
        return np.mean(means, axis=0)

    def restore(self) -> None:
        for m, (colour, texture) in zip(self.materials, self.saved):
            m.base_color = colour
            m.base_color_texture = texture

    def paint(self, rgb: np.ndarray) -> None:
        """Body materials take colour `rgb`; textures are tinted to it."""
        import sapien.render

        body = np.asarray(OBJECTS[self.index].rgba)
        for m, (colour, texture) in zip(self.materials, self.saved):
            if texture is not None:
                m.base_color_texture = sapien.render.RenderTexture2D(
                    _tint(texture, rgb), "R8G8B8A8Unorm", srgb=bool(texture.is_srgb))
            elif np.allclose(colour, body, atol=1e-4):
                m.base_color = [*map(float, rgb), colour[3]]


def _tint(texture, rgb: np.ndarray) -> np.ndarray:
    """A uint8 RGBA texture whose texels have their own luminance (relative to the mean) times `rgb`."""
    lin, mask = _texture_rgb(texture)
    lum = lin @ np.array([0.2126, 0.7152, 0.0722])
    rel = lum / max(float(lum[mask].mean()), 1e-6)
    out = rel[..., None] * np.asarray(rgb)[None, None, :3]
    out = _to_srgb(out) if texture.is_srgb else np.clip(out, 0.0, 1.0)
    data = texture.download()
    alpha = data[..., 3:4] if data.shape[-1] == 4 else np.full((*out.shape[:2], 1), 255, np.uint8)
    return np.concatenate([np.round(out * 255).astype(np.uint8), alpha], axis=-1)


def apply_swap(looks: Sequence[Look], swap: tuple[str, str] | None) -> None:
    """Restore every object of one sub-scene, then exchange the colours of the two objects of `swap`."""
    for look in looks:
        look.restore()
    if swap is None:
        return
    a, b = (looks[object_index(n)] for n in swap)
    colour_a, colour_b = a.colour, b.colour
    a.paint(colour_b)
    b.paint(colour_a)
