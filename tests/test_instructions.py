"""Instruction sets, appearance swaps and the counterfactual layouts they rest on (simulator-free)."""

import itertools

import numpy as np
import pytest

from vla_ladder.conditions import Condition
from vla_ladder.task.appearance import SWAPS, swap_partner
from vla_ladder.task.instructions import (INSTRUCTION_SETS, paraphrase_data, parse_instruction, wording_for,
                                          wordings)
from vla_ladder.task.layouts import layout_from_dict, sample_layout
from vla_ladder.task.objects import OBJECT_NAMES, instruction_for


def test_paraphrase_sets_are_split_and_every_wording_parses_back_to_its_object():
    data = paraphrase_data()
    assert data["version"] == 1
    for name in OBJECT_NAMES:
        canonical, train, heldout = (set(w.text for w in wordings(name, s)) for s in INSTRUCTION_SETS)
        assert canonical == {instruction_for(name)} and canonical <= train
        assert not train & heldout and len(train) == 8 and len(heldout) == 13
        for w in wordings(name, "paraphrase-heldout"):
            assert w.novelty in ("verb", "object", "both")
            assert (w.verb in data["verbs"]["heldout"]) == (w.novelty in ("verb", "both"))
        for s in INSTRUCTION_SETS:
            for w in wordings(name, s):
                assert parse_instruction(w.text) == w
                assert parse_instruction(w.text.upper() + ".").object == name
    heldout = {w.text for w in wordings("apple", "paraphrase-heldout")}
    assert {"pick up the apple", "grab the red fruit", "take the red apple", "grasp the red fruit"} <= heldout
    assert parse_instruction("pick up the cup").object == "mug" and parse_instruction("take the pen").object == \
        "large_marker"
    with pytest.raises(ValueError, match="cannot parse instruction 'grasp the banana'.*grab"):
        parse_instruction("grasp the banana")
    with pytest.raises(ValueError, match="unknown instruction set 'paraphrases'; allowed: canonical"):
        wordings("apple", "paraphrases")


def test_a_seed_picks_one_wording_and_seeds_cover_the_set():
    texts = {wording_for("mug", s, "paraphrase-heldout").text for s in range(400)}
    assert texts == {w.text for w in wordings("mug", "paraphrase-heldout")}
    assert all(wording_for("mug", s, "paraphrase-train") == wording_for("mug", s, "paraphrase-train")
               for s in range(20))
    assert {wording_for("mug", s).text for s in range(20)} == {"grasp the mug"}


def test_wording_and_colours_never_move_objects_and_instructing_another_object_keeps_the_scene():
    for regime, seed in itertools.product(("small_jitter", "full_random"), range(20)):
        c = Condition(regime, num_objects=4)
        base = sample_layout(c, seed)
        for s, a in itertools.product(INSTRUCTION_SETS, ("original", "swap")):
            lay = sample_layout(c, seed, instructions=s, appearance=a)
            assert lay.objects == base.objects and np.array_equal(lay.xy, base.xy)
            assert np.array_equal(lay.yaw, base.yaw) and lay.regions == base.regions
            assert parse_instruction(lay.instruction).object == lay.target
        assert base.to_dict().keys() == {"seed", "regime", "split", "target", "instruction", "positions", "yaw",
                                         "regions"}
        swapped = sample_layout(c, seed, instructions="paraphrase-heldout", appearance="swap")
        for rank, name in enumerate(base.objects):
            other = swapped.instructed(rank)
            assert other.target == name == swapped.instructed(name).target
            assert other.colour_swap == swapped.colour_swap  # the scene looks the same, whoever is instructed
            assert parse_instruction(other.instruction).object == name
            pos = {n: tuple(p) for n, p in zip(other.objects, other.xy)}
            assert pos == {n: tuple(p) for n, p in zip(base.objects, base.xy)}
            assert other.to_dict()["positions"] == {n: swapped.to_dict()["positions"][n] for n in other.objects}
            for played in (other, other.positions_swapped(), other.switched(7)):  # the env's order of options
                assert layout_from_dict(played.to_dict()).to_dict() == played.to_dict()
        assert layout_from_dict(swapped.to_dict()).to_dict() == swapped.to_dict()
    lay = sample_layout(Condition("small_jitter", num_objects=2), 1)
    with pytest.raises(ValueError, match="instruct rank 2 is not a present object.*allowed 0-1"):
        lay.instructed(2)
    missing = next(n for n in OBJECT_NAMES if n not in lay.objects)
    with pytest.raises(ValueError, match=f"cannot instruct '{missing}'"):
        lay.instructed(missing)


def test_swaps_pair_the_instructed_object_with_a_present_partner_from_the_documented_set():
    pairs = {frozenset(p) for p in SWAPS}
    assert "rubiks_cube" not in {o for p in SWAPS for o in p}
    partners = set()
    for seed in range(300):
        lay = sample_layout(Condition("full_random", num_objects=3), seed, appearance="swap")
        if lay.colour_swap is None:
            assert not any(frozenset((lay.target, o)) in pairs for o in lay.objects[1:])
            continue
        target, partner = lay.colour_swap
        assert target == lay.target and partner in lay.objects[1:] and frozenset(lay.colour_swap) in pairs
        assert lay.to_dict()["colour_swap"] == [target, partner]
        partners.add(lay.colour_swap)
    assert len(partners) == 2 * len(SWAPS)  # every documented swap, in both directions
    assert swap_partner(("rubiks_cube", "apple", "orange"), 0) is None
    assert swap_partner(("apple",), 0) is None


# ---------------------------------------------------------------------- in the simulator
@pytest.mark.slow
def test_instruct_keeps_the_scene_and_the_expert_grasps_whoever_is_named(make_env):
    import torch

    from vla_ladder.policies import load_policy

    env = make_env(obs_mode="state_dict", regime="full_random", num_objects=3)
    u, expert = env.unwrapped, load_policy("scripted")
    starts = []
    for rank in range(3):
        obs, _ = env.reset(seed=11, options={"instruct": rank, "instructions": "paraphrase-heldout"})
        lay = sample_layout(Condition("full_random", num_objects=3), 11, instructions="paraphrase-heldout")
        assert u.layouts[0].target == lay.objects[rank] and u.instructions == [lay.instructed(rank).instruction]
        starts.append(torch.cat([obs["extra"]["obj_pose"], obs["agent"]["qpos"]], dim=1))
        expert.reset([11])
        for _ in range(50):
            obs, _, _, _, info = env.step(expert.act(obs, u.instructions))
        assert OBJECT_NAMES[int(info["held"][0])] == lay.objects[rank]
    assert all(torch.equal(starts[0], s) for s in starts[1:])  # the same scene, to the bit
    env.reset(seed=11)
    assert u.instructions == [sample_layout(Condition("full_random", num_objects=3), 11).instruction]
    with pytest.raises(ValueError, match="unknown instruction set"):
        env.reset(seed=11, options={"instructions": "rhymes"})
    para = make_env(obs_mode="state_dict", regime="small_jitter", instructions="paraphrase-train")
    para.reset(seed=5)
    text = para.unwrapped.instructions[0]
    assert text == sample_layout(Condition("small_jitter"), 5, instructions="paraphrase-train").instruction
    assert parse_instruction(text).novelty == "none"


def _patch_colour(obs, xyz) -> np.ndarray:
    """Mean RGB of a 5x5 pixel patch of the front camera around world point xyz."""
    param = obs["sensor_param"]["fixed_camera"]
    p = param["extrinsic_cv"][0].numpy() @ np.append(xyz, 1.0)
    u, v, w = param["intrinsic_cv"][0].numpy() @ p
    col, row = int(round(u / w)), int(round(v / w))
    return obs["sensor_data"]["fixed_camera"]["rgb"][0].numpy()[row - 2:row + 3, col - 2:col + 3].reshape(-1, 3).mean(0)


@pytest.mark.slow
def test_a_swap_repaints_the_pair_in_each_others_colours_and_a_kept_scene_is_restored(make_env):
    lay = sample_layout(Condition("small_jitter"), 3, appearance="swap")
    assert lay.colour_swap == ("apple", "orange")
    # A kept scene (no rebuild between episodes) must take the swap off again.
    env = make_env(obs_mode="rgb", regime="small_jitter", reconfiguration_freq=0)
    colours = {}
    for look in ("original", "swap", "original"):
        obs, _ = env.reset(seed=3, options={"appearance": look})
        centres = {n: np.array([*xy, 0.038]) for n, xy in zip(lay.objects, lay.xy)}
        colours.setdefault(look, []).append({n: _patch_colour(obs, centres[n]) for n in ("apple", "orange", "mug")})
    before, swapped, after = colours["original"][0], colours["swap"][0], colours["original"][1]
    for a, b in (("apple", "orange"), ("orange", "apple")):
        assert np.linalg.norm(swapped[a] - before[b]) < np.linalg.norm(swapped[a] - before[a]) / 3, (a, swapped, before)
    assert np.allclose(swapped["mug"], before["mug"], atol=2)
    assert all(np.allclose(after[n], before[n], atol=1) for n in before)
    assert env.unwrapped.layouts[0].colour_swap is None


@pytest.mark.slow
def test_a_textured_material_is_tinted_and_restored():
    import sapien
    import sapien.render

    from vla_ladder.task.appearance import Look

    rng = np.random.default_rng(0)
    texels = np.concatenate([rng.integers(60, 200, (16, 16, 1)).repeat(3, -1) * np.array([1.0, 0.2, 0.2]),
                             np.full((16, 16, 1), 255)], -1).astype(np.uint8)  # a red, speckled texture
    texture = sapien.render.RenderTexture2D(texels, "R8G8B8A8Unorm", srgb=True)
    material = sapien.render.RenderMaterial(base_color=[1, 1, 1, 1])
    material.base_color_texture = texture
    body = sapien.render.RenderBodyComponent()
    body.attach(sapien.render.RenderShapeBox([0.02, 0.02, 0.02], material))
    entity = sapien.Entity()
    entity.add_component(body)
    look = Look(entity, 0)
    red = look.colour
    assert red[0] > 3 * red[1]
    look.paint(np.array([0.0, 0.1, 0.8]))  # blue
    tinted = material.base_color_texture.download()[..., :3].astype(float)
    assert tinted[..., 2].mean() > 3 * tinted[..., 0].mean()
    luminance = texels[..., 0].astype(float).ravel()
    assert np.corrcoef(luminance, tinted[..., 2].ravel())[0, 1] > 0.95  # the print survives the tint
    look.restore()
    assert np.array_equal(material.base_color_texture.download(), texels)
