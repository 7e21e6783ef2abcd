"""The GraspObject-v1 data contract: the one place that says what an episode is made of.

Episode length, rates, the two cameras, the 15-d state, the 7-d action, the decomposed metrics, and the
LeRobot feature keys (LeRobot's own constants, spelt here) and dataset features built from them. Every stage reads
these names from here: the env asserts it matches them, the recorder writes these features, training
checks a dataset against them, and the LeRobot adapters feed policies with them. Simulator-free.
"""

from __future__ import annotations

from dataclasses import dataclass

# LeRobot's feature-key constants (lerobot.utils.constants; tests/test_architecture.py checks they match), spelt here
# because importing lerobot.utils imports torch (1.2 s): every command's --help and bad-input check read this file.
ACTION = "action"
OBS_IMAGES = "observation.images"
OBS_STATE = "observation.state"

ENV_ID = "GraspObject-v1"
ROBOT = "panda_wristcam"
CONTROL_MODE = "pd_ee_delta_pose"
SIM_HZ = 100
CONTROL_HZ = 20
EPISODE_STEPS = 50
"""2.5 s at 20 Hz; episodes never end early, success is judged at the final step."""


@dataclass(frozen=True)
class CameraSpec:
    """One RGB camera the policy sees."""

    name: str
    fov_deg: float
    """Vertical field of view."""
    height: int = 256
    width: int = 256

    @property
    def key(self) -> str:
        """LeRobot feature key, e.g. observation.images.hand_camera."""
        return f"{OBS_IMAGES}.{self.name}"

    @property
    def shape(self) -> tuple[int, int, int]:
        """(H, W, 3): how the env renders it and the dataset stores it."""
        return (self.height, self.width, 3)


# The paper's cameras: a 58 degree wrist camera and a 45 degree fixed front camera, 256x256 RGB.
CAMERAS: tuple[CameraSpec, ...] = (CameraSpec("hand_camera", 58.0), CameraSpec("fixed_camera", 45.0))
CAMERA_NAMES: tuple[str, ...] = tuple(c.name for c in CAMERAS)
CAMERA_KEYS: tuple[str, ...] = tuple(c.key for c in CAMERAS)
IMAGE_SHAPE: tuple[int, int, int] = CAMERAS[0].shape
assert all(c.shape == IMAGE_SHAPE for c in CAMERAS), "the pipeline assumes one image size for both cameras"

STATE_NAMES: tuple[str, ...] = (*(f"joint_pos_{i}" for i in range(7)), *(f"joint_vel_{i}" for i in range(7)),
                                "gripper_width")
"""The proprioceptive state: 7 arm joint positions, 7 joint velocities, the gripper's opening (m)."""
STATE_DIM = len(STATE_NAMES)
ACTION_NAMES: tuple[str, ...] = ("dx", "dy", "dz", "drx", "dry", "drz", "gripper")
"""pd_ee_delta_pose, normalised to [-1, 1]: root-frame translation (each clipped to [-1, 1], x 0.1 m), then a
rotation about the root axes as XYZ Euler angles (at most 0.1 rad a step, where they are nearly an axis-angle):
ManiSkill 3.0.1 clips the three to norm 1 and scales them by the Panda's rot_lower, -0.1 rad, so +1 turns the TCP
the negative way about its axis; then the gripper (-1 closed, +1 open). Both deltas place the arm's target relative
to where the TCP is now, not to the last target: from rest a +1 moves the TCP 3.9 cm (0.039 rad) in its step, the
PD arm lagging the target. physx_cpu solves IK for that target (a target out of reach holds the arm where it is);
physx_cuda takes the six numbers as one damped least-squares Jacobian step, the rotation as a rotation vector."""
ACTION_DIM = len(ACTION_NAMES)

STATE_KEY = OBS_STATE
ACTION_KEY = ACTION

LAYOUTS = 2
"""Version of the placement sampler (task/layouts.py), which a seed's scene depends on. 2 (2026-11-28): full random
places its objects in an order drawn from the seed; 1 placed the target first, and it stood nearer the centre than
its distractors (CHANGELOG.md). Run directories and recordings of another version do not resume under this one."""

BLIND_INSTRUCTION = "grasp the object"
"""The one instruction an instruction-blind policy is trained and evaluated with (it names no object)."""

METRICS: tuple[str, ...] = ("success", "grasp_any", "reach")
"""success: the instructed object is held at the final step; grasp_any: some object was grasped at some step;
reach: the TCP ends within REACH_THRESHOLD of the instructed object's bounding box."""
RANK_BY: tuple[str, ...] = ("success", "grasp_any", "reach")
"""The order models are ranked in (a grid's best run, a study's selected model): success, ties broken by grasp_any,
then reach. A choice, not part of the fingerprint: a new metric ranks models only once it is added here."""
REACH_THRESHOLD = 0.05
INFO_KEYS: dict[str, str] = {
    "success": "(N,) bool: the instructed object is grasped now (judged at the final step)",
    "grasp_any": "(N,) bool: some object was grasped at some step of the episode",
    "reach": "(N,) bool: the TCP is within REACH_THRESHOLD of the instructed object's bounding box",
    "is_grasped": "(N, 5) bool: each object grasped now (both fingers push on it)",
    "held": "(N,) int: index (task/objects.py) of the object grasped now (the instructed one if it is), -1 for none",
    "reach_dist": "(N,) m: TCP distance to the instructed object's bounding box",
    "lift": "(N,) m: height of the instructed object above its resting height",
    "lifted": "(N,) bool: success and lift >= 5 cm",
    "wrong_grasp": "(N,) bool: an object other than the instructed one is grasped now",
    "tcp_xy": "(N, 2) m: the TCP's horizontal position, world frame (where the gripper went)",
}
"""What GraspObject-v1's `info` holds after every step (its evaluate()), besides ManiSkill's own keys: METRICS
first. The LeRobot env plugin forwards the scalar ones; evaluation keeps METRICS, held, reach_dist and tcp_xy."""

FEATURE_SHAPES: dict[str, tuple[int, ...]] = {
    **{c.key: c.shape for c in CAMERAS}, STATE_KEY: (STATE_DIM,), ACTION_KEY: (ACTION_DIM,)}
"""Every LeRobot feature a GraspObject-v1 dataset holds, and its shape."""


def dataset_features(video: bool = True) -> dict[str, dict]:
    """The LeRobotDataset schema of a recording (paper, appendix "Dataset format")."""
    cam = {"dtype": "video" if video else "image", "names": ["height", "width", "channels"]}
    return {
        **{c.key: {**cam, "shape": c.shape} for c in CAMERAS},
        STATE_KEY: {"dtype": "float32", "shape": (STATE_DIM,), "names": list(STATE_NAMES)},
        ACTION_KEY: {"dtype": "float32", "shape": (ACTION_DIM,), "names": list(ACTION_NAMES)},
    }


def fingerprint() -> dict:
    """This contract as plain values. Run directories and recordings keep it, so that resuming one made under
    another contract (an episode length, a rate, a camera, the state or the action changed here) is refused instead
    of mixing episodes of two tasks (contract_changes names what differs)."""
    return {"env_id": ENV_ID, "robot": ROBOT, "control_mode": CONTROL_MODE, "sim_hz": SIM_HZ,
            "control_hz": CONTROL_HZ, "episode_steps": EPISODE_STEPS,
            "cameras": [{"key": c.key, "fov_deg": c.fov_deg, "height": c.height, "width": c.width} for c in CAMERAS],
            "state": {"key": STATE_KEY, "names": list(STATE_NAMES)},
            "action": {"key": ACTION_KEY, "names": list(ACTION_NAMES)}, "metrics": list(METRICS),
            "reach_threshold": REACH_THRESHOLD, "blind_instruction": BLIND_INSTRUCTION, "layouts": LAYOUTS}


POLICY_FIELDS: tuple[str, ...] = ("env_id", "robot", "control_mode", "sim_hz", "control_hz", "cameras", "state",
                                  "action")
"""The fingerprint's fields that decide what a policy sees and what its actions do. A policy trained under other
values would be scored on a task it never saw, so trained checkpoints keep these (policy_fingerprint) and are
refused under another contract; the episode length, the metrics, the reach threshold and the blind instruction
change only how episodes are scored or worded."""


TRAINED_CONTRACT_FILE = "vla_ladder_contract.json"
"""Beside a trained LeRobot checkpoint's config.json: the policy_fingerprint() of the data it was trained on."""


def policy_fingerprint() -> dict:
    """fingerprint() cut to POLICY_FIELDS: what a trained policy keeps of the contract it was trained under."""
    now = fingerprint()
    return {k: now[k] for k in POLICY_FIELDS}


def contract_changes(saved: dict | None, fields: tuple[str, ...] | None = None) -> list[str]:
    """How a saved fingerprint() differs from this contract, one "name was X, now Y" per value that differs (a
    camera's field of view reads cameras[1].fov_deg; each line cut to 200 characters), only in `fields` when given;
    none when nothing was saved (files written before fingerprints were kept resume unchecked, and keep this
    contract's from then on)."""
    if saved is None:
        return []
    saved = {"layouts": 1, **saved}  # (kept before the sampler had a version: its first)
    now = fingerprint()
    names = sorted({*saved, *now}) if fields is None else fields
    return [line for k in names for line in _differences(k, saved.get(k), now.get(k))]


def _differences(name: str, was, now) -> list[str]:
    if isinstance(was, dict) and isinstance(now, dict):
        return [line for k in sorted({*was, *now}) for line in _differences(f"{name}.{k}", was.get(k), now.get(k))]
    if isinstance(was, list) and isinstance(now, list) and len(was) == len(now):
        return [line for i, (a, b) in enumerate(zip(was, now)) for line in _differences(f"{name}[{i}]", a, b)]
    return [] if was == now else [f"{name} was {was!r}, now {now!r}"[:200]]

