"""The position-swap probe: the instructed object and one distractor exchange places. Its counterfactual layouts,
its metrics on constructed plays, its commands, and its calibration by the reference policies in the real simulator
(CPU, state only)."""

import json

import numpy as np
import pandas as pd
import pytest
from report_fixtures import first_table_row

from vla_ladder.conditions import Condition
from vla_ladder.evaluation import grounding
from vla_ladder.experiments.probes import ProbeConfig, ProbeGrid, run_probe
from vla_ladder.task.layouts import MIN_GAP, _on_workspace, layout_from_dict, sample_layout
from vla_ladder.task.objects import OBJECT_NAMES, OBJECTS, object_index


def _gaps(lay) -> np.ndarray:
    """Free space between every pair of footprints."""
    r = np.array([OBJECTS[object_index(n)].footprint_radius for n in lay.objects])
    d = np.linalg.norm(lay.xy[:, None] - lay.xy[None], axis=-1) - r[:, None] - r[None]
    return d[np.triu_indices(len(r), 1)]


# ---------------------------------------------------------------------- layouts
def test_positions_swapped_exchanges_two_places_and_keeps_the_rest():
    swapped = fallback = 0
    for regime, split, k, seed in ((r, s, k, seed) for r, s in (("small_jitter", "canonical"),
                                                               ("large_jitter", "pairings_id"),
                                                               ("full_random", "canonical"))
                                   for k in (2, 5) for seed in range(40)):
        base = sample_layout(Condition(regime, split, k), seed, appearance="swap")
        lay = base.positions_swapped()
        assert lay.to_dict() == base.positions_swapped().to_dict()  # deterministic from the seed
        assert lay.objects == base.objects and lay.instruction == base.instruction and np.array_equal(lay.yaw, base.yaw)
        assert lay.colour_swap == base.colour_swap
        d = lay.to_dict()
        assert layout_from_dict(d).to_dict() == d
        if lay.position_swap is None:  # no distractor fits: the scene is unchanged and says so
            assert d == base.to_dict() and "position_swap" not in d
            continue
        swapped += 1
        target, partner = lay.position_swap
        assert target == base.target and partner in base.position_partners()
        fallback += partner != base.position_partners()[0]
        p = base.objects.index(partner)
        assert np.array_equal(lay.xy[0], base.xy[p]) and np.array_equal(lay.xy[p], base.xy[0])
        others = [i for i in range(k) if i not in (0, p)]
        assert np.array_equal(lay.xy[others], base.xy[others])
        if base.regions is not None:  # regions say where each object stands
            assert lay.regions[0] == base.regions[p] and lay.regions[p] == base.regions[0]
            assert d["regions"][target] == base.regions[p]
        else:
            assert _on_workspace(lay.xy, tuple(OBJECTS[object_index(n)].footprint_radius for n in lay.objects))
        assert (_gaps(lay) >= MIN_GAP - 1e-12).all()  # the sampler's rule, for every pair
        assert d["position_swap"] == [target, partner]
        assert d["positions"][target] == base.to_dict()["positions"][partner]
    assert swapped >= 200 and fallback >= 1  # the seed's partner does not always fit; another one then does
    assert "position_swap" not in sample_layout(Condition("small_jitter"), 3).to_dict()
    with pytest.raises(ValueError, match="cannot swap positions in seed 1: the instructed object .* not on the table"):
        sample_layout(Condition("small_jitter", num_objects=3), 1).instructed_absent(0).positions_swapped()


# ---------------------------------------------------------------------- metrics on constructed plays
def swap_plays(policy, regime="small_jitter", k=5, scenes=12) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Original and swapped plays of a made-up policy: policy(layout) -> held object name."""
    plays = ([], [])
    for j in range(scenes):
        base = sample_layout(Condition(regime, "canonical", k), j)
        for out, lay in zip(plays, (base, base.positions_swapped())):
            held = policy(lay, base)
            xy = lay.xy[lay.objects.index(held)] if held != "none" else (-0.5, 0.0)
            out.append(dict(regime=regime, split="canonical", num_objects=k, episode=j, seed=j, target=lay.target,
                            instruction=lay.instruction, held=held, success=held == lay.target,
                            grasp_any=held != "none", reach=held == lay.target, tcp_x=xy[0], tcp_y=xy[1],
                            layout=json.dumps(lay.to_dict())))
    return pd.DataFrame(plays[0]), pd.DataFrame(plays[1])


def test_position_metrics_tell_grounded_shortcut_and_blind_policies_apart():
    key = "small_jitter/canonical/5"
    g = grounding.position_swap(*swap_plays(lambda lay, base: lay.target))[key]
    assert g["scenes"] == g["swapped"] == 12 and g["no_swap"] == 0
    assert g["follows_object_original"]["value"] == g["follows_object_swapped"]["value"] == 1
    assert g["follows_place_swapped"]["value"] == 0 and g["follows_object_change"]["value"] == 0
    assert g["reaches_object_swapped"]["value"] == 1 and g["reaches_place_swapped"]["value"] == 0

    def shortcut(lay, base):  # whatever stands where the instructed object stood in the original scene
        return lay.objects[int(np.argmin(np.linalg.norm(lay.xy - base.xy[0], axis=1)))]

    s = grounding.position_swap(*swap_plays(shortcut))[key]
    assert s["follows_object_original"]["value"] == 1 and s["follows_object_swapped"]["value"] == 0
    assert s["follows_place_swapped"]["value"] == 1 and s["follows_place_change"]["value"] == 1
    assert s["follows_place_change"]["mcnemar_p"] == pytest.approx(2 * 0.5 ** 12)
    assert s["reaches_place_swapped"]["value"] == 1 and s["reaches_object_swapped"]["value"] == 0
    assert s["transitions"]["counts"][0] == [0, 12, 0, 0]  # instructed in the original -> partner when swapped
    b = grounding.position_swap(*swap_plays(lambda lay, base: sorted(lay.objects)[0]))[key]
    assert b["follows_object_change"]["value"] == 0 and b["follows_place_change"]["value"] == 0
    assert sum(map(sum, b["transitions"]["counts"])) == 12 and sum(b["pairs"].values()) == 12
    # Full random with two objects: some scenes have no collision-free swap; they are counted, not scored.
    f = grounding.position_swap(*swap_plays(lambda lay, base: lay.target, "full_random", 2, 30))
    f = f["full_random/canonical/2"]
    assert f["scenes"] == 30 and f["no_swap"] >= 1 and f["swapped"] == 30 - f["no_swap"]
    # Runs from before tcp_x/tcp_y were kept: where the gripper ends is unknown, not 0.
    original, swapped = swap_plays(shortcut)
    old = grounding.position_swap(original.assign(tcp_x=np.nan), swapped)[key]
    assert old["reaches_place_swapped"] is None and old["follows_place_swapped"]["value"] == 1
    with pytest.raises(ValueError, match="played different seeds on 12 of 12 scenes"):
        grounding.position_swap(original, swapped.assign(seed=swapped["seed"] + 1))


# ---------------------------------------------------------------------- commands
def test_position_swap_configs_and_refusals(tmp_path, refused):
    cfg = ProbeConfig("position-swap", policy="nearest", out=tmp_path / "p")
    assert cfg.grid.num_objects == (5,)
    variants = cfg.variants()
    assert list(variants) == ["original", "swapped"]
    assert variants["original"].jobs()[0].options == ()  # exactly an ordinary evaluation
    assert variants["swapped"].jobs()[0].options == (("swap_positions", True),)
    cases = [
        (["probe", "position-swap", "--policy", "nearest", "--out", str(tmp_path / "p"), "--num-objects", "1"],
         "position-swap needs at least two objects on the table; got --num-objects 1 (allowed: 2-5)"),
        (["probe", "position-swap", "--policy", "nearest", "--out", str(tmp_path / "p"), "--num-objects", "3", "1"],
         "position-swap needs at least two objects on the table"),
        (["eval", "--policy", "nearest", "--out", str(tmp_path / "e"), "--num-objects", "1", "--swap-positions"],
         "swap_positions needs at least two objects on the table; got --num-objects 1 (allowed: 2-5)"),
        (["eval", "--policy", "nearest", "--out", str(tmp_path / "e"), "--num-objects", "3", "--swap-positions",
          "--instruct-absent", "0"], "swap_positions moves the instructed object and instruct_absent names one"),
    ]
    refused(cases, tmp_path / "p", tmp_path / "e")


# ---------------------------------------------------------------------- the real simulator
@pytest.mark.slow
def test_the_env_places_the_objects_at_the_swapped_positions(make_env):
    import torch

    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=5)
    u = env.unwrapped
    base = sample_layout(Condition("small_jitter"), 2)
    lay = base.positions_swapped()
    target, partner = lay.position_swap
    starts = {}
    for name, options in (("original", {}), ("swapped", {"swap_positions": True}),
                          ("list", {"swap_positions": [True]})):
        obs, _ = env.reset(seed=2, options=options)
        starts[name] = (obs["extra"]["obj_pose"].clone(), obs["agent"]["qpos"].clone())
        assert u.instructions[0] == base.instruction and u.layouts[0].target == target
        want = base if name == "original" else lay
        for obj, xy in zip(want.objects, want.xy):
            # the layout's xy is the bounding box's centre; the actor origin sits at centre - R(yaw) center_offset
            k = object_index(obj)
            p, q = u.objs[k].pose.p[0].cpu().numpy(), u.objs[k].pose.q[0].cpu().numpy()
            yaw = 2 * np.arctan2(q[3], q[0])
            off = u._center[k].cpu().numpy()
            centre = p[:2] + np.array([np.cos(yaw) * off[0] - np.sin(yaw) * off[1],
                                       np.sin(yaw) * off[0] + np.cos(yaw) * off[1]])
            assert np.allclose(centre, xy, atol=2e-3), (name, obj)
            assert np.isclose(yaw, want.yaw[want.objects.index(obj)], atol=1e-3)  # each keeps its own yaw
    assert torch.equal(starts["swapped"][1], starts["original"][1])  # the same robot start
    assert torch.equal(starts["swapped"][0], starts["list"][0])
    moved = {object_index(target), object_index(partner)}
    poses = [s[0].reshape(5, 7) for s in (starts["original"], starts["swapped"])]
    for k in range(5):
        same = torch.equal(poses[0][k], poses[1][k])
        assert same == (k not in moved), OBJECT_NAMES[k]
    with pytest.raises(ValueError, match="swap_positions must be True or False"):
        env.reset(seed=2, options={"swap_positions": "mug"})
    with pytest.raises(ValueError, match="got 2 swap_positions values for 1 envs"):
        env.reset(seed=2, options={"swap_positions": [True, False]})


def probe(tmp_path, policy, regimes, scenes, **kw) -> dict:
    cfg = ProbeConfig("position-swap", policy=policy, out=tmp_path / policy, grid=ProbeGrid(tuple(regimes)),
                      episodes=scenes, workers=1, **kw)
    return run_probe(cfg, progress=False)


@pytest.mark.slow
def test_position_swap_calibration_layout_prior_and_scripted(tmp_path):
    prior = probe(tmp_path, "layout-prior", ["small_jitter"], 8, report=True)["conditions"]["small_jitter/canonical/5"]
    assert prior["swapped"] == 8
    # The location shortcut goes where the instructed object usually stands: the partner stands there now.
    assert prior["follows_object_original"]["value"] >= 0.7 and prior["follows_object_swapped"]["value"] <= 0.1
    assert prior["reaches_place_swapped"]["value"] >= 0.9 and prior["reaches_object_swapped"]["value"] <= 0.1
    # Its grasp is tuned to the instructed object's shape, so it holds the partner only where the shapes allow.
    assert prior["follows_place_swapped"]["value"] > prior["follows_place_original"]["value"] == 0
    scripted = probe(tmp_path, "scripted", ["small_jitter"], 8, report=False)["conditions"]["small_jitter/canonical/5"]
    # The expert reads the true target pose: it follows the object to its new place.
    assert scripted["follows_object_original"]["value"] >= 0.85 and scripted["follows_object_swapped"]["value"] >= 0.85
    assert scripted["follows_place_swapped"]["value"] == 0 and scripted["reaches_object_swapped"]["value"] >= 0.85
    root = tmp_path / "layout-prior"
    page = (root / "report.html").read_text()
    assert "position-swap: layout-prior" in page and "follows place" in page and "held: original" in page
    assert (root / "position-swap.png").stat().st_size > 5000
    # The probe's own page, in a real browser: its figures decode, and its table shows the shortcut.
    widths, cells = first_table_row(root / "report.html", "follows place")
    assert len(widths) >= 2 and min(widths) > 300
    assert cells["condition"] == "small_jitter/canonical/5", cells
    assert cells["swapped scenes"] == "8 of 8", cells
    assert next(v for k, v in cells.items() if k.startswith("gripper ends at the place")).split("→")[1].strip(
    ).startswith("100"), cells
