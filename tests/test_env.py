"""GraspObject-v1 on the CPU backend: construction, observations, placement, metrics, rendering."""

import numpy as np
import pytest
import torch

from vla_ladder.conditions import REGIMES, Condition
from vla_ladder.contract import CAMERAS, EPISODE_STEPS, IMAGE_SHAPE, INFO_KEYS, METRICS
from vla_ladder.task.layouts import sample_layout
from vla_ladder.task.objects import NUM_OBJECTS, OBJECT_NAMES

CASES = [(r, s) for r, e in REGIMES.items()
         for s in (["canonical", "pairings_id", "pairings_ood"] if e else ["canonical"])]


def _seed_with(objects, regime="small_jitter", num_objects=2, target=None):
    """First seed whose layout holds exactly `objects` (pure numpy search)."""
    for s in range(10_000):
        layout = sample_layout(Condition(regime, num_objects=num_objects), seed=s, target=target)
        if set(layout.objects) == set(objects):
            return s
    raise AssertionError(objects)


@pytest.mark.slow
@pytest.mark.parametrize("regime, split", CASES)
def test_reset_and_step_every_regime_split_and_count(make_env, regime, split):
    for k in (1, 3, 5) if split == "canonical" else (5,):
        env = make_env(obs_mode="state_dict", regime=regime, split=split, num_objects=k)
        u = env.unwrapped
        for seed in (0, 1):
            obs, info = env.reset(seed=seed)
            lay = sample_layout(Condition(regime, split, k), seed)
            assert u.layouts[0].to_dict() == lay.to_dict() and u.instructions == [lay.instruction]
            assert u.present[0].sum().item() == k and OBJECT_NAMES[u.target_idx[0]] == lay.target
            # Objects stand where the layout says; absent ones wait far from the table.
            p = obs["extra"]["obj_pose"].reshape(NUM_OBJECTS, 7)[:, :3]
            for name, xy in zip(lay.objects, lay.xy):
                np.testing.assert_allclose(p[OBJECT_NAMES.index(name), :2].numpy(), xy, atol=1e-4)
            absent = [i for i, n in enumerate(OBJECT_NAMES) if n not in lay.objects]
            assert torch.all(p[absent, 1] > 1.0)
            for _ in range(3):
                obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert torch.isfinite(reward).all() and not terminated.any()
            assert {"success", "grasp_any", "reach", "held", "is_grasped"} <= info.keys()


def test_state_observation_shapes_and_dtypes(make_env):
    env = make_env(obs_mode="state_dict", regime="medium_jitter")
    obs, _ = env.reset(seed=3)
    ex = obs["extra"]
    shapes = dict(proprio=15, tcp_pose=7, obj_pose=35, obj_present=5, target_onehot=5, is_grasped=5,
                  target_site=3, tcp_to_target=3)
    for k, d in shapes.items():
        assert ex[k].shape == (1, d) and ex[k].dtype == torch.float32, k
    qpos = obs["agent"]["qpos"][0]
    np.testing.assert_allclose(ex["proprio"][0, :7].numpy(), qpos[:7].numpy())
    assert ex["proprio"][0, 14].item() == pytest.approx((qpos[7] + qpos[8]).item())  # gripper width
    assert env.action_space.shape == (7,)
    info = env.unwrapped.evaluate()  # what every step's info holds besides ManiSkill's keys: the contract's list
    assert list(info) == list(INFO_KEYS) and list(INFO_KEYS)[:len(METRICS)] == list(METRICS)
    assert info["is_grasped"].shape == (1, 5) and info["tcp_xy"].shape == (1, 2) and info["held"].shape == (1,)
    flat = make_env(obs_mode="state", regime="medium_jitter")
    fobs, _ = flat.reset(seed=3)
    assert fobs.shape == (1, 18 + sum(shapes.values())) and fobs.dtype == torch.float32


def test_actions_move_the_tcp_as_the_contract_says(make_env):
    """contract.ACTION_NAMES, stepped: +x translates the TCP along world x (the root frame), a component past 1 is
    clipped, +1 about z turns the TCP the negative way (ManiSkill scales by rot_lower, -0.1 rad) and the rotation is
    clipped to norm 1, the gripper closes at -1. A ManiSkill upgrade that changed a sign or a scale fails here."""
    from scipy.spatial.transform import Rotation

    env = make_env(obs_mode="state_dict", num_objects=1)
    u = env.unwrapped

    def one_step(action):
        env.reset(seed=0)  # the scene is rebuilt: every call starts from the same state, bit for bit
        before = u.agent.tcp_pose
        obs = env.step(torch.tensor([action]))[0]
        after = u.agent.tcp_pose
        turn = Rotation.from_quat((after.q[0].double()[[1, 2, 3, 0]]).numpy()) * \
            Rotation.from_quat((before.q[0].double()[[1, 2, 3, 0]]).numpy()).inv()
        return (after.p - before.p)[0].numpy(), turn.as_rotvec(), obs["extra"]["proprio"][0, 14].item()

    move, turn, width = one_step([1.0, 0, 0, 0, 0, 0, 1])
    assert 0.02 < move[0] <= 0.1 and np.abs(move[1:]).max() < 0.1 * move[0] and np.abs(turn).max() < 0.01
    assert width == pytest.approx(0.08, abs=1e-3), "+1 keeps the gripper open"
    np.testing.assert_array_equal(one_step([5.0, 0, 0, 0, 0, 0, 1])[0], move)
    move, turn, _ = one_step([0, 0, 0, 0, 0, 1.0, 1])
    assert -0.1 <= turn[2] < -0.02 and np.abs(turn[:2]).max() < 0.1 * -turn[2] and np.abs(move).max() < 0.002
    np.testing.assert_array_equal(one_step([0, 0, 0, 0, 0, 3.0, 1])[1], turn)
    assert one_step([0, 0, 0, 0, 0, 0, -1.0])[2] < 0.06, "-1 closes the gripper"


def _act(env, goal, grip):
    """P-control of the TCP towards `goal` with the gripper command `grip` (test driver, not an expert)."""
    tcp = env.unwrapped.agent.tcp_pose.p[0]
    a = torch.zeros(1, 7)
    a[0, :3] = torch.clamp((goal - tcp) / 0.1 * 2.0, -1, 1)
    a[0, 6] = grip
    return env.step(a)


def _grasp(env, name, steps=50):
    """Reach over `name`, descend, close, lift; returns the info of every step."""
    u = env.unwrapped
    k = OBJECT_NAMES.index(name)
    infos = []
    centre = u.objs[k].pose.p[0].clone()
    plan = [(centre + torch.tensor([0, 0, 0.08]), 1.0, 14), (centre, 1.0, 12), (centre, -1.0, 8),
            (centre + torch.tensor([0, 0, 0.12]), -1.0, steps - 34)]
    for goal, grip, n in plan:
        for _ in range(n):
            infos.append(_act(env, goal, grip)[4])
    return infos


@pytest.mark.slow
def test_metrics_target_grasped_and_lifted(make_env):
    # The scene kept between episodes (as PPO's envs keep it): the next episode must not inherit the grasp.
    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=1, target="rubiks_cube",
                   reconfiguration_freq=0)
    env.reset(seed=0)
    infos = _grasp(env, "rubiks_cube")
    last = infos[-1]
    assert last["success"].item() and last["grasp_any"].item() and last["reach"].item()
    assert last["lifted"].item() and last["held"].item() == OBJECT_NAMES.index("rubiks_cube")
    assert not any(i["success"].item() for i in infos[:20]), "nothing is grasped before the fingers close"
    assert infos[-1]["elapsed_steps"].item() == EPISODE_STEPS
    _, info = env.reset(seed=1)
    assert not (info["grasp_any"].item() or info["success"].item() or info["is_grasped"].any().item())
    assert info["held"].item() == -1
    for _ in range(3):
        info = env.step(torch.tensor([[0, 0, 0, 0, 0, 0, 1.0]]))[4]
    assert not info["grasp_any"].item(), "the last episode's grasp carried into this one"


@pytest.mark.slow
def test_finger_forces_are_maniskills_pairwise_forces_to_the_bit(make_env):
    """The grasp flags read every object's force on each finger from one walk over the scene's contacts instead of
    ManiSkill's ten (one per pair): the forces must be exactly what scene.get_pairwise_contact_forces gives, through
    a whole expert episode of five objects (the fingers touching the target, and the table and neighbours around)."""
    from vla_ladder.policies import load_policy

    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=5)
    u = env.unwrapped
    expert = load_policy("scripted")
    touching = 0
    for seed in (0, 1):
        obs, _ = env.reset(seed=seed)
        expert.reset([seed])
        fingers = (u.agent.finger1_link, u.agent.finger2_link)  # the reset rebuilt the scene, its robot too
        for _ in range(EPISODE_STEPS):
            obs = env.step(expert.act(obs, u.instructions).to(torch.float32))[0]
            theirs = torch.stack([torch.stack([u.scene.get_pairwise_contact_forces(f, o) for f in fingers], dim=1)
                                  for o in u.objs], dim=1)
            ours = u._finger_forces()
            assert ours.dtype == theirs.dtype and torch.equal(ours, theirs)
            touching += bool(theirs.any())
    assert touching >= 20, "the episodes should grasp: most steps after the fingers close have finger contacts"


@pytest.mark.slow
def test_metrics_wrong_object_grasped(make_env):
    seed = _seed_with({"apple", "rubiks_cube"}, target="apple")
    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=2, target="apple")
    env.reset(seed=seed)
    last = _grasp(env, "rubiks_cube")[-1]
    assert last["grasp_any"].item() and not last["success"].item() and not last["reach"].item()
    assert last["held"].item() == OBJECT_NAMES.index("rubiks_cube") and last["wrong_grasp"].item()


def test_held_names_the_instructed_object_when_it_is_among_those_held(make_env, monkeypatch):
    """Two objects held at once (the contact flags forced so: rare in play): held must agree with success, which the
    confusion matrix and held_outcome read together; it named the lower-indexed object, here the apple."""
    seed = _seed_with({"apple", "mug"}, target="mug")
    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=2, target="mug")
    env.reset(seed=seed)
    u = env.unwrapped
    both = torch.zeros(1, NUM_OBJECTS, dtype=torch.bool)
    both[0, [OBJECT_NAMES.index("apple"), OBJECT_NAMES.index("mug")]] = True
    monkeypatch.setattr(u, "_grasp_flags", lambda: both)
    info = env.step(torch.zeros(1, 7))[4]
    assert info["success"].item() and info["held"].item() == OBJECT_NAMES.index("mug")
    only_apple = both & (torch.arange(NUM_OBJECTS) == OBJECT_NAMES.index("apple"))
    monkeypatch.setattr(u, "_grasp_flags", lambda: only_apple)
    info = env.step(torch.zeros(1, 7))[4]
    assert not info["success"].item() and info["held"].item() == OBJECT_NAMES.index("apple")
    assert info["wrong_grasp"].item()


@pytest.mark.slow
def test_metrics_hovering_near_target_and_doing_nothing(make_env):
    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=5, target="orange")
    env.reset(seed=4)
    for _ in range(50):
        info = env.step(torch.tensor([[0, 0, 0, 0, 0, 0, 1.0]]))[4]
    assert not (info["success"].item() or info["grasp_any"].item() or info["reach"].item())
    assert info["held"].item() == -1
    env.reset(seed=4)
    site = env.unwrapped.grasp_sites()[0, OBJECT_NAMES.index("orange")]
    for _ in range(50):
        info = _act(env, site + torch.tensor([0, 0, 0.07]), 1.0)[4]
    assert info["reach"].item() and not info["success"].item() and not info["grasp_any"].item()
    assert 0.0 < info["reach_dist"].item() <= 0.05


@pytest.mark.slow
def test_rendering_both_cameras(make_env):
    env = make_env(obs_mode="rgb", regime="large_jitter")
    obs, _ = env.reset(seed=2)
    imgs = {c: obs["sensor_data"][c]["rgb"][0] for c in ("hand_camera", "fixed_camera")}
    for cam, img in imgs.items():
        assert img.shape == IMAGE_SHAPE and img.dtype == torch.uint8, cam
        assert img.float().std() > 10, f"{cam} is blank"
    assert not torch.equal(imgs["hand_camera"], imgs["fixed_camera"])
    assert obs["extra"]["proprio"].shape == (1, 15)
    assert env.unwrapped.metadata["object_set"] == env.unwrapped.object_set == "standin"


@pytest.mark.slow
def test_cameras_are_the_contracts_and_another_is_refused(make_env):
    """Both cameras render at the contract's size and vertical field of view, the wrist one on the hand's camera
    link; a camera the contract does not describe is refused when the env is made. A field-of-view override passed
    (only the size was checked), and a recording made with it would have claimed 58 and 45 degrees."""
    sensors = make_env(obs_mode="rgb").unwrapped.scene.sensors
    for cam in CAMERAS:
        seen = sensors[cam.name].camera._render_cameras[0]
        assert (seen.height, seen.width) == (cam.height, cam.width), cam.name
        assert seen.fovy == pytest.approx(np.deg2rad(cam.fov_deg)), cam.name
    assert sensors["hand_camera"].config.mount.name == "camera_link"
    for override, message in (({"height": 128}, "hand_camera missing or not 256x256"),
                              ({"fov": 1.0}, "hand_camera fov 57.2958 deg, contract 58")):
        with pytest.raises(RuntimeError, match=message):
            make_env(obs_mode="rgb", sensor_configs={"hand_camera": override})


def test_an_env_picks_the_gpu_renderer_wherever_cuda_is(make_env):
    from vla_ladder.task.env import auto_render_backend

    # A state-only env too: without a renderer, every scene rebuild creates a Vulkan instance, and NVIDIA's driver
    # refused one after about 25 rebuilds (PPO's CPU envs on an H100).
    assert auto_render_backend(needs_render=False, cuda=True) == auto_render_backend(True, True) == "gpu"
    assert (auto_render_backend(True, cuda=False), auto_render_backend(False, cuda=False)) == ("cpu", "none")
    env = make_env(obs_mode="state", num_objects=1)
    env.reset(seed=0)
    assert env.unwrapped.backend.render_backend == ("sapien_cuda" if torch.cuda.is_available() else "none")


@pytest.mark.parametrize("kwargs, allowed", [
    (dict(regime="random"), "small_jitter, medium_jitter, large_jitter, full_random"),
    (dict(split="heldout"), "canonical, pairings_id, pairings_ood"),
    (dict(num_objects=6), "1 to 5"),
    (dict(target="banana"), "apple, orange, rubiks_cube, mug, large_marker"),
    (dict(object_set="shapenet"), "auto, ycb, standin"),
    (dict(robot_init_qpos_noise=-0.1), "finite standard deviation >= 0"),
    (dict(robot_init_qpos_noise=float("nan")), "finite standard deviation >= 0"),
])
def test_bad_input_lists_what_is_allowed(kwargs, allowed):
    import gymnasium as gym

    import vla_ladder.task.env  # noqa: F401
    with pytest.raises(ValueError) as e:
        gym.make("GraspObject-v1", **kwargs)
    assert allowed in str(e.value)


def test_a_control_mode_other_than_the_contracts_is_refused():
    """pd_ee_pose and pd_ee_target_delta_pose have 7-d actions too, so the action's shape let them through: their
    actions mean other things (an absolute pose, a delta from the last target) under a contract that says
    pd_ee_delta_pose."""
    import gymnasium as gym

    import vla_ladder.task.env  # noqa: F401
    for mode in ("pd_ee_pose", "pd_ee_target_delta_pose"):
        with pytest.raises(RuntimeError, match=f"control mode {mode}, contract pd_ee_delta_pose"):
            gym.make("GraspObject-v1", control_mode=mode)


def test_target_not_in_scene_rejected(make_env):
    env = make_env(obs_mode="state_dict", regime="small_jitter", num_objects=2)
    with pytest.raises(ValueError, match="allowed"):
        env.reset(seed=0, options={"target": "pear"})
    with pytest.raises(ValueError, match="seeds for"):
        env.reset(seed=[1, 2])
    # A seed numpy cannot take is refused by name (it was numpy's "expected non-negative integer", or OverflowError).
    for seed in (-1, 2**32, [2**63]):
        with pytest.raises(ValueError, match=r"episode seeds must be integers in \[0, 2\*\*32\)"):
            env.reset(seed=seed)


@pytest.mark.slow
def test_render_command_writes_both_cameras_and_episode(tmp_path):
    import json

    from PIL import Image

    from vla_ladder.cli import main
    assert main(["render", "--regimes", "small_jitter", "--seed", "5", "--out", str(tmp_path)]) == 0
    for cam in ("hand_camera", "fixed_camera"):
        img = np.asarray(Image.open(tmp_path / f"small_jitter_seed5_{cam}.png"))
        assert img.shape == IMAGE_SHAPE and img.std() > 10
    ep = json.loads((tmp_path / "small_jitter_seed5.json").read_text())
    assert ep["seed"] == 5 and ep["provenance"]["object_set"] == "standin"
    assert ep["instruction"] == sample_layout(Condition("small_jitter"), seed=5).instruction


@pytest.mark.slow
def test_a_seed_replays_bit_for_bit_whatever_ran_before(make_env):
    """Layout, target, instruction and the whole physical rollout are a function of the seed alone
    (a grasp replayed in a used CPU scene drifted by millimetres before scenes were rebuilt per episode)."""
    from vla_ladder.policies import load_policy

    env = make_env(obs_mode="state_dict", regime="medium_jitter")

    def rollout(seed):
        policy = load_policy("layout-prior")
        obs, _ = env.reset(seed=seed)
        policy.reset([seed])
        qpos = []
        for _ in range(50):
            obs = env.step(policy.act(obs, env.unwrapped.instructions))[0]
            qpos.append(obs["agent"]["qpos"][0])
        return torch.stack(qpos).numpy()

    first = rollout(0)
    rollout(1)  # another episode in between
    np.testing.assert_array_equal(rollout(0), first)


@pytest.mark.slow
def test_rebuilt_scenes_are_freed_without_walking_long_lived_objects(make_env):
    """A CPU env's per-episode rebuild frees the old scene (ManiSkill's gc.collect), and that collection no longer
    walks what lived before the first env: it was frozen once (0.14 s of a 0.18 s reset before)."""
    import gc
    import weakref

    from vla_ladder.task import env as task_env

    env = make_env(obs_mode="state_dict")
    assert task_env._FROZEN and gc.get_freeze_count() > 10_000
    env.reset(seed=0)
    frozen, old = gc.get_freeze_count(), [weakref.ref(env.unwrapped.scene), weakref.ref(env.unwrapped.agent)]
    env.reset(seed=1)
    env.reset(seed=2)  # the scene replaced at a rebuild is garbage by the next one's collection
    assert all(ref() is None for ref in old), "a rebuilt scene stayed in memory"
    assert gc.get_freeze_count() == frozen  # once per process, never a rebuilt scene


@pytest.mark.slow
def test_lite_robot_renders_like_the_full_one_with_identical_physics(make_env):
    """The lite robot only changes pictures: the same seed and actions give the same states, and the two
    pictures differ by a few grey levels on average."""
    runs = {}
    for mesh in ("full", "lite"):
        env = make_env(obs_mode="rgb", regime="small_jitter", robot_mesh=mesh)
        obs, _ = env.reset(seed=3)
        for _ in range(5):
            obs, *_ = env.step(torch.tensor([[0.3, 0.2, -0.3, 0, 0, 0, 1.0]]))
        runs[mesh] = obs
        assert env.unwrapped.metadata["robot_mesh"] == mesh
    np.testing.assert_array_equal(runs["full"]["agent"]["qpos"].numpy(), runs["lite"]["agent"]["qpos"].numpy())
    for cam in ("hand_camera", "fixed_camera"):
        a, b = (runs[m]["sensor_data"][cam]["rgb"][0].float() for m in ("full", "lite"))
        assert (a - b).abs().mean() < 6, cam
    with pytest.raises(ValueError, match="allowed: lite, full"):
        make_env(robot_mesh="cartoon")


def test_a_partial_reset_names_distinct_envs_in_increasing_order(make_env):
    """Rows are built in env_idx order and ManiSkill writes poses in ascending env order: an env named twice, out of
    order or out of range would get another env's robot start, so it is refused."""
    env = make_env(obs_mode="state_dict")
    env.reset(seed=3, options={"env_idx": torch.tensor([0])})
    for bad in ([0, 0], [1], [], [-1]):
        with pytest.raises(ValueError, match=r"env_idx must list distinct envs of 0\.\.0 in increasing order"):
            env.reset(seed=3, options={"env_idx": torch.tensor(bad, dtype=torch.long)})


def test_each_cpu_worker_takes_its_own_row_of_per_env_reset_options(make_env):
    """AsyncVectorEnv sends every worker the batch's options whole: each (SlotEnv) must play its own row of every
    option given per env, as one batched env would, not refuse a list of N for its one env."""
    from vla_ladder.task.vector import SlotEnv

    options = {"conditions": [Condition("small_jitter", "canonical", 3), Condition("full_random", "canonical", 2)],
               "alone": [False, True], "switch_at": [10, None]}
    base = make_env(obs_mode="state_dict")
    first, second = SlotEnv(base, 0), SlotEnv(base, 1)
    first.reset(seed=5, options=options)
    lay = base.unwrapped.layouts[0]
    assert lay.condition == options["conditions"][0] and lay.switch is not None and lay.removed is None
    second.reset(seed=5, options=options)
    lay = base.unwrapped.layouts[0]
    assert lay.condition == options["conditions"][1] and lay.switch is None and lay.removed is not None
