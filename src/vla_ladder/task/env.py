"""GraspObject-v1: "grasp the <object>" with a Franka Panda among up to five YCB objects.

One task class in the ManiSkill style; every tensor is batched over parallel envs, so the same code
runs one env on the CPU backend and thousands on physx_cuda. Layouts come from the simulator-free
`layouts` module, seeded per episode: env i reset with seed s + i starts exactly the episode a single
env starts with seed s + i (layout, target, instruction), on either backend; what follows is the backend's
physics (on physx_cpu a seed replays bit for bit; physx_cuda's solver and controller differ from the CPU's).
"""

from __future__ import annotations

import gc
from typing import Any, Sequence

import numpy as np
import sapien
import torch

from mani_skill.agents.robots.panda.panda_wristcam import PandaWristCam
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import sapien_utils
from mani_skill.utils.geometry.rotation_conversions import quaternion_to_matrix
from mani_skill.utils.registration import register_env
from mani_skill.utils.structs.pose import Pose
from mani_skill.utils.structs.types import GPUMemoryConfig, SimConfig

from vla_ladder import contract
from vla_ladder.checks import SEED_LIMIT
from vla_ladder.conditions import Condition
from vla_ladder.contract import CAMERAS, CONTROL_HZ, EPISODE_STEPS, REACH_THRESHOLD, SIM_HZ
from vla_ladder.task import appearance, assets, object_sets, robot
from vla_ladder.task.appearance import check_appearance
from vla_ladder.task.instructions import check_instruction_set
from vla_ladder.task.layouts import (REST_QPOS, ROBOT_INIT_QPOS_NOISE, WORKSPACE_CENTER, Layout, initial_qpos,
                                     sample_layout)
from vla_ladder.task.objects import NUM_OBJECTS, OBJECT_NAMES, object_index

LIFT_HEIGHT = 0.05
ROBOT_BASE = (-0.615, 0.0, 0.0)
# Where absent objects wait: a collision-only shelf beside the table, out of both cameras' view and
# well inside ManiSkill's 5 m spacing between parallel sub-scenes.
PARK_XY = np.array([[-0.6 + 0.3 * i, 1.8] for i in range(NUM_OBJECTS)])
HAND_CAMERA, FIXED_CAMERA = CAMERAS


def auto_render_backend(needs_render: bool, cuda: bool) -> str:
    """The renderer an env picks by itself: the GPU's wherever CUDA is, else the CPU's (lavapipe) when it needs
    pictures and none when it does not.

    A state-only env on a GPU machine keeps the GPU renderer: loading the robot's URDF makes render materials,
    which need a Vulkan instance even without a renderer, so with none SAPIEN creates and destroys one at every
    scene rebuild (on an H100 a state-only reset took 0.57 s, one with the GPU renderer 0.22 s), and NVIDIA's
    driver refused a new one after about 25 (vk::createInstanceUnique: ErrorIncompatibleDriver): PPO's CPU envs
    died there. lavapipe has no such limit."""
    if cuda:
        return "gpu"
    return "cpu" if needs_render else "none"


_FROZEN = False


def freeze_long_lived_objects() -> None:
    """Move the objects alive now to the garbage collector's permanent generation, once per process.

    A CPU env rebuilds its scene every episode, and ManiSkill frees the old one with gc.collect(), which walks
    every object the process tracks: with torch and ManiSkill imported about 300k, 0.14 s of a 0.18 s reset on
    the 2-core machine. What exists before the first env is built (modules, classes, functions, a loaded policy)
    lives as long as the process; frozen (gc.freeze), it is no longer walked and a reset takes 0.04 s. Frozen
    objects are still freed when nothing refers to them; only reference cycles among them would stay, so garbage
    is collected first and this runs once, not at every rebuild (which would keep every old scene)."""
    global _FROZEN
    if not _FROZEN:
        gc.collect()
        gc.freeze()
        _FROZEN = True


# Reset options that may be given as a list with one value per reset env (GraspObjectEnv.reset); "conditions" only so.
PER_ENV_OPTIONS = ("conditions", "instruct", "instruct_absent", "swap_positions", "switch_at", "alone")


def _per_env(value, n: int) -> list:
    """A reset option given once for all reset envs, or as a list with one value each, as a list of n."""
    return list(value) if isinstance(value, (list, tuple)) else [value] * n


@register_env(contract.ENV_ID, max_episode_steps=EPISODE_STEPS)
class GraspObjectEnv(BaseEnv):
    """Grasp the instructed object among up to five: "grasp the <object>".

    Randomisations, all from the episode seed (env i reset with seed s plays seed s + i):
    - the condition's layout (`layouts.sample_layout`): which objects, where, their yaw, and the target;
    - the robot's initial joint positions (Gaussian noise, `robot_init_qpos_noise` rad).

    `robot_mesh` picks how the robot looks in pictures: "lite" (default; decimated visual meshes, 6x cheaper to
    render on a CPU, see task/robot.py) or "full" (ManiSkill's meshes as shipped). Physics is the same.

    How an episode is presented, also from its seed, never changing the layout or the physics:
    - `instructions`: the wording, "canonical" ("grasp the <object>"), "paraphrase-train" or "paraphrase-heldout"
      (task/instructions.py, paraphrases.json);
    - `appearance`: "original", or "swap": the instructed object and one present distractor exchange colours
      (task/appearance.py; needs one env per scene, i.e. physx_cpu or num_envs=1).
    Both are also reset options (they override the env's own for that reset), next to "instruct": an object
    name or a present-object rank (0 the target, k the k-th distractor), one for all reset envs or a list with
    one each, which keeps the seed's whole scene (layout, colours, robot start, physics) and instructs that object
    instead (the instruction-swap probe; "target" instead samples another scene with that target), and
    "instruct_absent": an object that is not on the table (a name, or its rank among the absent objects in the
    object list's order), which keeps the same scene and instructs that object (the absent-object probe): it stays
    parked off the table, so success and reach are False by construction. A name given to "instruct" must be on
    the table: asking for an absent object takes the explicit "instruct_absent", so a mistyped swap still fails.
    "swap_positions" (True, or a list of bools, one per reset env) exchanges the places of the instructed object
    and one distractor chosen from the seed (`Layout.positions_swapped`: collision-free, each keeps its yaw), the
    rest of the scene unchanged (the position-swap probe); a scene where no distractor fits plays unswapped.
    "switch_at" (a control step K from 1 to 49, or a list with one per reset env, None for none) switches the
    instruction mid-episode (the instruction-switch probe, `Layout.switched`): the episode starts instructing its
    target A, and from step K on `target_idx` (so success, reach, the state observation's target) and
    `instructions` name B, a present distractor drawn from the seed; the scene itself never changes. The switch
    is applied as step K starts: the action of step K was chosen under A, the observation and info step K returns
    already refer to B, so a policy has acted K times on A's instruction and acts on B's from then on.
    "alone" (True, or a list of bools) takes every distractor off the table (parked, as absent objects are), the
    instructed object staying where the seed put it (the distractor-removal probe, `Layout.alone`).

    Success: the instructed object is grasped (both fingers push on it) at the final step. Episodes
    always run 50 steps (2.5 s at 20 Hz, physics at 100 Hz) and never terminate early. `info` also holds
    grasp_any (some object grasped at some step), reach (TCP within 5 cm of the target's box at the end),
    held (index of the object grasped now, -1 for none), reach_dist, lift, lifted and tcp_xy (the TCP's
    horizontal position, world frame: where the gripper went, whatever it grasped): contract.INFO_KEYS.
    """

    SUPPORTED_ROBOTS = [contract.ROBOT, robot.LITE_UID]
    agent: PandaWristCam

    def __init__(self, *args, regime: str = "small_jitter", split: str = "canonical", num_objects: int = 5,
                 target: str | None = None, object_set: str = "auto", robot_mesh: str = "lite",
                 instructions: str = "canonical", appearance: str = "original",
                 robot_init_qpos_noise: float = ROBOT_INIT_QPOS_NOISE, robot_uids=None, render_backend: str = "auto",
                 obs_mode: str | None = None,
                 render_mode: str | None = None, sensor_configs: dict | None = None,
                 reconfiguration_freq: int | None = None, **kwargs):
        self.condition = Condition(regime, split, num_objects)
        if target is not None:
            object_index(target)
        self.target = target
        self.instruction_set = check_instruction_set(instructions)
        self.appearance = check_appearance(appearance)
        self.object_set = object_sets.resolve_object_set(object_set)
        robot.check_robot_mesh(robot_mesh)
        self.robot_mesh = robot_mesh
        # Checked now, not by numpy at the first reset: a negative one failed there with "scale < 0" once the scene
        # was built, and nan or inf gave every episode a robot at nan joint positions without a word.
        if not 0 <= robot_init_qpos_noise < float("inf"):
            raise ValueError(f"robot_init_qpos_noise must be a finite standard deviation >= 0 (radians), got "
                             f"{robot_init_qpos_noise!r}")
        if robot_uids is None:
            robot_uids = robot.register_lite_panda() if robot_mesh == "lite" else contract.ROBOT
        self.robot_init_qpos_noise = robot_init_qpos_noise
        self.layouts: list[Layout | None] = []
        self._layout_seeds = np.zeros(0, dtype=np.int64)
        self._seed_rng = np.random.default_rng()
        obs_mode = obs_mode or "state"
        kwargs.setdefault("control_mode", contract.CONTROL_MODE)
        if render_backend == "auto":
            needs_render = obs_mode not in ("state", "state_dict", "none") or render_mode is not None
            render_backend = auto_render_backend(needs_render, torch.cuda.is_available())
        # The contract's cameras: the wrist one is the robot's own (resized here), the front one is below.
        cams = {HAND_CAMERA.name: dict(width=HAND_CAMERA.width, height=HAND_CAMERA.height,
                                       fov=np.deg2rad(HAND_CAMERA.fov_deg))}
        for k, v in (sensor_configs or {}).items():
            cams[k] = {**cams.get(k, {}), **v} if isinstance(v, dict) else v
        if reconfiguration_freq is None:
            # PhysX keeps solver caches across resets, so on the CPU an episode replayed in a used scene
            # drifts by millimetres (enough to flip a grasp). Rebuilding the scene each episode (~0.04 s)
            # makes a seed replay bit for bit, whatever ran before: policies are compared on identical
            # episodes. GPU sub-scenes cannot be rebuilt one at a time, so physx_cuda keeps its scene.
            backend = kwargs.get("sim_backend", "auto")
            on_cpu = backend in ("physx_cpu", "cpu") or (backend == "auto" and kwargs.get("num_envs", 1) == 1)
            reconfiguration_freq = 1 if on_cpu else 0
        if reconfiguration_freq:
            freeze_long_lived_objects()
        super().__init__(*args, robot_uids=robot_uids, render_backend=render_backend, obs_mode=obs_mode,
                         render_mode=render_mode, sensor_configs=cams, reconfiguration_freq=reconfiguration_freq,
                         **kwargs)
        self.metadata = {**self.metadata, "object_set": self.object_set, "robot_mesh": self.robot_mesh}
        if appearance != "original":
            self._check_paintable()
        self._check_contract()

    def _check_paintable(self) -> None:
        # Parallel GPU sub-scenes share their render materials (ManiSkill builds every sub-scene's shapes from one
        # builder), so colours cannot differ between envs.
        if self.num_envs > 1:
            raise ValueError("appearance='swap' paints each scene's objects and needs one env per scene: "
                             f"num_envs=1 (physx_cpu, or physx_cuda with one env); got num_envs={self.num_envs}")

    def _check_contract(self) -> None:
        """Every stage reads the episode's shape from vla_ladder.contract: make sure this env is that."""
        problems = []
        if (self.sim_freq, self.control_freq) != (SIM_HZ, CONTROL_HZ):
            problems.append(f"rates {self.sim_freq}/{self.control_freq} Hz, contract {SIM_HZ}/{CONTROL_HZ}")
        if self.control_mode != contract.CONTROL_MODE:  # pd_ee_pose and pd_ee_target_delta_pose are 7-d too
            problems.append(f"control mode {self.control_mode}, contract {contract.CONTROL_MODE}")
        if self.single_action_space.shape != (contract.ACTION_DIM,):
            problems.append(f"action {self.single_action_space.shape}, contract ({contract.ACTION_DIM},)")
        sensors = getattr(self, "_sensor_configs", None)  # only set up when the scene renders
        for cam in CAMERAS if sensors is not None else ():
            cfg = sensors.get(cam.name)
            if cfg is None or (cfg.height, cfg.width) != (cam.height, cam.width):
                problems.append(f"camera {cam.name} missing or not {cam.height}x{cam.width}")
            elif not np.isclose(np.rad2deg(cfg.fov), cam.fov_deg):  # the fingerprint records it: a dataset would lie
                problems.append(f"camera {cam.name} fov {np.rad2deg(cfg.fov):g} deg, contract {cam.fov_deg:g}")
        if problems:
            raise RuntimeError("GraspObject-v1 no longer matches vla_ladder.contract: " + "; ".join(problems))

    # ------------------------------------------------------------------ configuration
    @property
    def _default_sim_config(self):
        return SimConfig(sim_freq=SIM_HZ, control_freq=CONTROL_HZ, gpu_memory_config=GPUMemoryConfig(
            max_rigid_contact_count=2**21, max_rigid_patch_count=2**19, found_lost_pairs_capacity=2**25))

    @property
    def _default_sensor_configs(self):
        pose = sapien_utils.look_at(eye=[0.5, 0.0, 0.45], target=[WORKSPACE_CENTER[0] - 0.04, 0.0, 0.02])
        return [CameraConfig(FIXED_CAMERA.name, pose, FIXED_CAMERA.width, FIXED_CAMERA.height,
                             np.deg2rad(FIXED_CAMERA.fov_deg), 0.01, 100)]

    @property
    def _default_human_render_camera_configs(self):
        pose = sapien_utils.look_at(eye=[0.5, 0.6, 0.6], target=[-0.15, 0.0, 0.05])
        return CameraConfig("render_camera", pose, 512, 512, 1.0, 0.01, 100)

    def _load_agent(self, options: dict):
        super()._load_agent(options, sapien.Pose(p=list(ROBOT_BASE)))

    def _load_scene(self, options: dict):
        render = self.scene.can_render()
        # Table top at z = 0 (ManiSkill convention); a collision-only shelf parks absent objects.
        for name, half, p, rgba in (("table", [0.6, 0.8, 0.02], [-0.15, 0, -0.02], (0.55, 0.42, 0.3, 1)),
                                    ("floor", [3.0, 3.0, 0.01], [0, 0, -0.93], (0.35, 0.35, 0.38, 1)),
                                    ("shelf", [1.0, 0.3, 0.02], [0.0, PARK_XY[0, 1], -0.02], None)):
            b = self.scene.create_actor_builder()
            b.add_box_collision(half_size=half)
            if render and rgba is not None:
                b.add_box_visual(half_size=half, material=sapien.render.RenderMaterial(base_color=list(rgba)))
            b.initial_pose = sapien.Pose(p=p)
            b.build_static(name=name)
        self.objs = assets.build_objects(self.scene, self.object_set, render)
        geo = assets.object_geometry(self.object_set)
        self._half = torch.tensor(geo["half_extents"], dtype=torch.float32, device=self.device)
        self._center = torch.tensor(geo["center_offset"], dtype=torch.float32, device=self.device)
        self._rest_z = torch.tensor(geo["rest_z"], dtype=torch.float32, device=self.device)
        self._grasp_local = torch.tensor(geo["grasp_point"], dtype=torch.float32, device=self.device)
        n = self.num_envs
        self.target_idx = torch.zeros(n, dtype=torch.long, device=self.device)
        # The instruction switch of each env: the control step it happens at (0: none) and the new target.
        self._switch_step = torch.zeros(n, dtype=torch.long, device=self.device)
        self._switch_idx = torch.zeros(n, dtype=torch.long, device=self.device)
        self.present = torch.zeros(n, NUM_OBJECTS, dtype=torch.bool, device=self.device)
        self._grasp_any = torch.zeros(n, dtype=torch.bool, device=self.device)
        self.layouts = [None] * n
        # Each sub-scene's objects' materials as built, to repaint for colour swaps and restore after them.
        self._looks = [[appearance.Look(obj._objs[i], k) for k, obj in enumerate(self.objs)] for i in range(n)] \
            if render else None

    # ------------------------------------------------------------------ episodes
    def reset(self, seed: None | int | Sequence[int] = None, options: dict | None = None):
        """seed=s (int) gives env i the episode seed s + i; a list gives one seed per reset env.
        options["conditions"], one Condition (or key) per reset env, overrides the env's own condition for
        these episodes (one GPU env can then train on a mixture of conditions). options["instructions"] and
        options["appearance"] override the env's own for these episodes; options["instruct"] (an object name or
        present-object rank, or a list with one per reset env) instructs another object of the same scene,
        options["instruct_absent"] (a name or rank among the absent objects, or a list) an object not on it, and
        options["swap_positions"] (a bool, or a list) exchanges the instructed object's place with a distractor's,
        options["switch_at"] (a control step 1-49, or a list) switches the instruction to a distractor there, and
        options["alone"] (a bool, or a list) takes the distractors off the table."""
        options = dict(options or {})
        env_idx = options.get("env_idx")
        idx = np.arange(self.num_envs) if env_idx is None else np.asarray(
            env_idx.cpu() if torch.is_tensor(env_idx) else env_idx).reshape(-1)
        # Each reset env's row (seed, layout, options) is built in idx order, and ManiSkill writes a partial reset's
        # poses in ascending env order: another order, or an env twice, would give one env another's robot start.
        if len(idx) == 0 or np.any(np.diff(idx) <= 0) or idx[0] < 0 or idx[-1] >= self.num_envs:
            raise ValueError(f"env_idx must list distinct envs of 0..{self.num_envs - 1} in increasing order, got "
                             f"{idx.tolist()}"[:200])
        if len(self._layout_seeds) != self.num_envs:
            self._layout_seeds = np.zeros(self.num_envs, dtype=np.int64)
        if seed is not None:  # checked before numpy sees them (its errors do not say what is allowed)
            span = [int(s) for s in seed] if np.iterable(seed) else [int(seed), int(seed) + int(idx.max())]
            if not all(0 <= s < SEED_LIMIT for s in span):
                raise ValueError(f"episode seeds must be integers in [0, 2**32) (numpy seeds), got {seed!r}"[:200])
        if seed is None:
            seeds = self._seed_rng.integers(0, 2**31, size=len(idx))
        elif np.iterable(seed):
            seeds = np.asarray([int(s) for s in seed], dtype=np.int64)
            if len(seeds) != len(idx):
                raise ValueError(f"got {len(seeds)} seeds for {len(idx)} envs being reset")
        else:
            seeds = int(seed) + idx  # env i plays s + i, in a partial reset (env_idx) as in a full one
            self._seed_rng = np.random.default_rng(int(seed))
        self._layout_seeds[idx] = seeds
        if options.get("target") is not None:
            object_index(options["target"])
        if "conditions" in options:
            if len(options["conditions"]) != len(idx):
                raise ValueError(f"got {len(options['conditions'])} conditions for {len(idx)} envs being reset")
            options["conditions"] = [Condition.of(c) for c in options["conditions"]]
        if options.get("instructions") is not None:
            check_instruction_set(options["instructions"])
        if options.get("appearance") is not None and check_appearance(options["appearance"]) != "original":
            self._check_paintable()
        for name in PER_ENV_OPTIONS:  # (conditions' count was checked above, in its own words)
            value = options.get(name)
            if isinstance(value, (list, tuple)) and len(value) != len(idx):
                raise ValueError(f"got {len(value)} {name} values for {len(idx)} envs being reset")
        both = [_per_env(options.get(name), len(idx)) for name in ("instruct", "instruct_absent")]
        if any(a is not None and b is not None for a, b in zip(*both)):
            raise ValueError("instruct (a present object) and instruct_absent (an absent one) name the instructed "
                             "object each; give one per env")
        swap = _per_env(options.get("swap_positions"), len(idx))
        if any(v is not None and not isinstance(v, (bool, np.bool_)) for v in swap):
            raise ValueError(f"swap_positions must be True or False (or a list with one per env), got "
                             f"{options['swap_positions']!r}")
        if any(s and a is not None for s, a in zip(swap, both[1])):
            raise ValueError("swap_positions moves the instructed object, and instruct_absent names one that is not "
                             "on the table; give one per env")
        switch = _per_env(options.get("switch_at"), len(idx))
        if any(k is not None and (isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer))
                                  or not 1 <= k < EPISODE_STEPS) for k in switch):
            raise ValueError(f"switch_at must be a control step from 1 to {EPISODE_STEPS - 1} (or None, or a list with "
                             f"one per env), got {options['switch_at']!r}")
        if any(k is not None and a is not None for k, a in zip(switch, both[1])):
            raise ValueError("switch_at switches from the instructed object to another present one, and "
                             "instruct_absent names one that is not on the table; give one per env")
        alone = _per_env(options.get("alone"), len(idx))
        if any(v is not None and not isinstance(v, (bool, np.bool_)) for v in alone):
            raise ValueError(f"alone must be True or False (or a list with one per env), got {options['alone']!r}")
        if any(v and (a is not None or s or k is not None) for v, a, s, k in zip(alone, both[1], swap, switch)):
            raise ValueError("alone takes the distractors off the table, which instruct_absent, swap_positions and "
                             "switch_at each need; give one per env")
        return super().reset(seed=None if seed is None else [int(s) for s in seeds] if env_idx is None
                             else None, options=options)

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        target = options.get("target", self.target)
        ids = env_idx.cpu().numpy()
        b = len(ids)
        pos = np.zeros((b, NUM_OBJECTS, 3), dtype=np.float32)
        quat = np.zeros((b, NUM_OBJECTS, 4), dtype=np.float32)
        quat[..., 0] = 1
        pos[:, :, :2] = PARK_XY
        pos[:, :, 2] = self._rest_z.cpu().numpy()
        qpos = np.tile(REST_QPOS, (b, 1)).astype(np.float32)
        present = np.zeros((b, NUM_OBJECTS), dtype=bool)
        tgt = np.zeros(b, dtype=np.int64)
        conditions = options.get("conditions") or [self.condition] * b
        instructions = options.get("instructions") or self.instruction_set
        look = options.get("appearance") or self.appearance
        instruct = _per_env(options.get("instruct"), b)
        instruct_absent = _per_env(options.get("instruct_absent"), b)
        swap_positions = _per_env(options.get("swap_positions"), b)
        switch_at = _per_env(options.get("switch_at"), b)
        alone = _per_env(options.get("alone"), b)
        switch_step = np.zeros(b, dtype=np.int64)  # 0: no switch
        switch_tgt = np.zeros(b, dtype=np.int64)
        centers = self._center.cpu().numpy()  # once, not per object and env: on CUDA each .cpu() waits on the GPU
        for row, i in enumerate(ids):
            seed = int(self._layout_seeds[i])
            lay = sample_layout(conditions[row], seed, target, instructions, look)
            if instruct[row] is not None:
                lay = lay.instructed(instruct[row])
            if instruct_absent[row] is not None:
                # Only the target changes: the absent object stays parked, present stays the layout's objects.
                lay = lay.instructed_absent(instruct_absent[row])
            if swap_positions[row]:
                # After "instruct": the object the instruction names is the one that moves.
                lay = lay.positions_swapped()
            if alone[row]:
                # After "instruct": the object the instruction names is the one that stays.
                lay = lay.alone()
            if switch_at[row] is not None:
                # Last: the switch names a distractor of the scene as played (after instruct and the swap).
                lay = lay.switched(int(switch_at[row]))
                switch_step[row], switch_tgt[row] = lay.switch[0], object_index(lay.switch[1])
            # A rebuilt scene has fresh materials (layouts[i] is None); a kept one may still wear the last swap.
            worn = self.layouts[i] is not None and self.layouts[i].colour_swap is not None
            if self._looks is not None and (lay.colour_swap is not None or worn):
                appearance.apply_swap(self._looks[i], lay.colour_swap)
            self.layouts[i] = lay
            tgt[row] = lay.target_index
            for name, xy, yaw in zip(lay.objects, lay.xy, lay.yaw):
                k = OBJECT_NAMES.index(name)
                present[row, k] = True
                # The layout gives the bounding-box centre; the actor origin may sit elsewhere (YCB).
                c, s = np.cos(yaw), np.sin(yaw)
                off = centers[k]
                pos[row, k, :2] = xy - np.array([c * off[0] - s * off[1], s * off[0] + c * off[1]])
                quat[row, k] = [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
            qpos[row] = initial_qpos(seed, self.robot_init_qpos_noise)
        with torch.device(self.device):
            for k, obj in enumerate(self.objs):
                obj.set_pose(Pose.create_from_pq(torch.from_numpy(pos[:, k]), torch.from_numpy(quat[:, k])))
            self.agent.reset(torch.from_numpy(qpos))
            self.agent.robot.set_pose(Pose.create_from_pq(torch.tensor([ROBOT_BASE] * b)))
            self.target_idx[env_idx] = torch.from_numpy(tgt).to(self.device)
            self._switch_step[env_idx] = torch.from_numpy(switch_step).to(self.device)
            self._switch_idx[env_idx] = torch.from_numpy(switch_tgt).to(self.device)
            self.present[env_idx] = torch.from_numpy(present).to(self.device)
            self._grasp_any[env_idx] = False

    @property
    def instructions(self) -> list[str]:
        """The instruction of each parallel env's current episode, as it stands now: after an instruction switch
        (reset option "switch_at") the new one. Read it again after the switch step; nothing else changes it."""
        if all(lay is None or lay.switch is None for lay in self.layouts):
            return [lay.instruction for lay in self.layouts]
        steps = self.elapsed_steps.tolist()  # (one device sync: a switch is read once an episode)
        return [lay.instruction_at(int(k)) for lay, k in zip(self.layouts, steps)]

    @property
    def episode_seeds(self) -> list[int]:
        return [int(s) for s in self._layout_seeds]

    def step(self, action):
        # An instruction switch due at this step takes effect before it, so that the info (success, reach) and the
        # observation (target_onehot, target_site) this step returns, which the policy's next action reads,
        # already name the new target, as `instructions` does from now on. Physics never reads target_idx: the
        # action being applied, chosen under the old instruction, plays out unchanged. No branch, no device sync.
        due = self._switch_step == self.elapsed_steps + 1
        self.target_idx.copy_(torch.where(due, self._switch_idx, self.target_idx))
        obs, reward, terminated, truncated, info = super().step(action)
        # Success is judged at the final step, so grasping early must not end the episode.
        return obs, reward, torch.zeros_like(terminated), truncated, info

    # ------------------------------------------------------------------ state and metrics
    def _refresh(self) -> dict[str, torch.Tensor]:
        """Object poses, rotations and grasp sites, gathered once per step: evaluate, observations and
        reward all reuse them (small-tensor torch ops dominate the CPU step, not physics)."""
        p = torch.stack([o.pose.p for o in self.objs], dim=1)  # (N, 5, 3)
        q = torch.stack([o.pose.q for o in self.objs], dim=1)  # (N, 5, 4) wxyz
        rot = quaternion_to_matrix(q)  # (N, 5, 3, 3)
        sites = p + (rot @ (self._center + self._grasp_local)[..., None])[..., 0]
        self._cache = dict(p=p, q=q, rot=rot, sites=sites, tcp=self.agent.tcp_pose.p)
        return self._cache

    def _target_select(self, x: torch.Tensor) -> torch.Tensor:
        return x[torch.arange(self.num_envs, device=self.device), self.target_idx]

    def grasp_sites(self) -> torch.Tensor:
        """(N, 5, 3) world positions where each object is meant to be grasped."""
        return self._cache["sites"]

    def _dist_to_boxes(self) -> torch.Tensor:
        """(N, 5) distance from the TCP to each object's oriented bounding box (0 inside)."""
        c = self._cache
        rel = (c["tcp"][:, None, :] - c["p"])[..., None]
        local = (c["rot"].transpose(-1, -2) @ rel)[..., 0] - self._center
        return torch.linalg.norm(torch.clamp(local.abs() - self._half, min=0.0), dim=-1)

    def _grasp_flags(self, min_force: float = 0.5, max_angle_deg: float = 85.0) -> torch.Tensor:
        """(N, 5) Panda.is_grasping for all objects at once: both fingers push on the object, each
        roughly along its closing direction (the finger directions are computed once, not per object)."""
        a = self.agent
        dirs = torch.stack([a.finger1_link.pose.to_transformation_matrix()[..., :3, 1],
                            -a.finger2_link.pose.to_transformation_matrix()[..., :3, 1]], dim=1)  # (N, 2, 3)
        forces = self._finger_forces()
        norm = torch.linalg.norm(forces, dim=-1)  # (N, 5, 2)
        cos = (forces * dirs[:, None]).sum(-1) / norm.clamp(min=1e-9)
        ok = (norm >= min_force) & (cos >= np.cos(np.deg2rad(max_angle_deg)))
        return ok.all(dim=-1)

    def _finger_forces(self) -> torch.Tensor:
        """(N, 5, 2, 3) the contact force of each object on each finger, as scene.get_pairwise_contact_forces(finger,
        object) gives it. On the CPU that call walks all the scene's contacts in Python once per pair: 10 walks a
        step took 30% of the step (2 cores, 2026-11-27). Here one walk adds up every pair, each in the order and the
        arithmetic ManiSkill's walk uses, so the forces are the same to the bit (tests/test_env.py)."""
        fingers = (self.agent.finger1_link, self.agent.finger2_link)
        if self.gpu_sim_enabled:  # one batched query per pair already
            return torch.stack([torch.stack([self.scene.get_pairwise_contact_forces(f, o) for f in fingers], dim=1)
                                for o in self.objs], dim=1)
        # Keyed by global_id, which names the entity itself: SAPIEN's Entity wrappers compare and hash by Python
        # identity, which stands for the entity only while one wrapper of it is alive.
        finger_of = {f._bodies[0].entity.global_id: i for i, f in enumerate(fingers)}
        object_of = {o._bodies[0].entity.global_id: k for k, o in enumerate(self.objs)}
        impulses = np.zeros((len(self.objs), len(fingers), 3))  # float64, as sapien_utils.compute_total_impulse
        for contact in self.scene.px.get_contacts():
            first, second = contact.bodies[0].entity.global_id, contact.bodies[1].entity.global_id
            if first in finger_of and second in object_of:
                pair, sign = (object_of[second], finger_of[first]), 1
            elif second in finger_of and first in object_of:  # the impulse acts on the first body
                pair, sign = (object_of[first], finger_of[second]), -1
            else:
                continue
            impulses[pair] += np.sum([point.impulse for point in contact.points], axis=0) * sign
        return torch.tensor(impulses).to(torch.float32)[None] / self.scene.px.timestep

    def proprio(self) -> torch.Tensor:
        """The 15-d state the VLA sees: 7 arm joint positions, 7 velocities, gripper width."""
        qpos, qvel = self.agent.robot.get_qpos(), self.agent.robot.get_qvel()
        return torch.cat([qpos[:, :7], qvel[:, :7], (qpos[:, 7] + qpos[:, 8])[:, None]], dim=1)

    def evaluate(self) -> dict[str, torch.Tensor]:
        c = self._refresh()
        # At reset (step 0) nothing has been simulated yet: the contacts PhysX reports are the previous episode's last
        # ones wherever the scene is kept between episodes (PPO's envs, record --no-rebuild-scenes, physx_cuda), and
        # would count a grasp the new episode never made.
        grasped = self._grasp_flags() & self.present & (self.elapsed_steps > 0)[:, None]
        any_now = grasped.any(dim=1)
        self._grasp_any |= any_now
        success = self._target_select(grasped)
        # The instructed object when it is among those held (two at once is rare), so that held agrees with success.
        held = torch.where(success, self.target_idx, torch.where(any_now, grasped.float().argmax(dim=1),
                                                                 torch.full_like(self.target_idx, -1)))
        dist = self._target_select(self._dist_to_boxes())
        lift = self._target_select(c["p"][..., 2]) - self._rest_z[self.target_idx]
        return dict(success=success, grasp_any=self._grasp_any.clone(), reach=dist <= REACH_THRESHOLD,
                    is_grasped=grasped, held=held, reach_dist=dist, lift=lift,
                    lifted=success & (lift >= LIFT_HEIGHT), wrong_grasp=any_now & ~success, tcp_xy=c["tcp"][:, :2])

    def _get_obs_extra(self, info: dict):
        obs = dict(proprio=self.proprio())
        if "state" in self.obs_mode:
            c = self._cache
            site = self._target_select(self.grasp_sites())
            poses = torch.cat([c["p"], c["q"]], dim=-1)
            obs.update(
                tcp_pose=self.agent.tcp_pose.raw_pose,
                obj_pose=poses.reshape(self.num_envs, -1),
                obj_present=self.present.float(),
                target_onehot=torch.nn.functional.one_hot(self.target_idx, NUM_OBJECTS).float(),
                is_grasped=info["is_grasped"].float(),
                target_site=site,
                tcp_to_target=site - c["tcp"],
            )
        return obs

    def compute_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        d = torch.linalg.norm(self._target_select(self.grasp_sites()) - self._cache["tcp"], dim=1)
        grasped = info["success"].float()
        lift = torch.clamp(info["lift"] / LIFT_HEIGHT, 0.0, 1.0) * grasped
        return (1 - torch.tanh(5 * d)) + grasped + lift - info["wrong_grasp"].float()

    def compute_normalized_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        return self.compute_dense_reward(obs, action, info) / 3.0
