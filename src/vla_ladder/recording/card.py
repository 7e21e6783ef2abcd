"""The dataset card: README.md in a recording's root, saying what the dataset is a recording of.

LeRobot only writes a card when a dataset is pushed to the hub, and then knows nothing of what vla-ladder
recorded. A dataset copied, shared or edited on its own should still say what it holds: the condition, the
expert, the object set, the robot, the seed range and the versions. The recorder rewrites the card at every
commit from what is on disk (meta/info.json, the recording state, the per-episode provenance), so it is never
out of step with the episodes it describes. It has the YAML header of LeRobot's own cards (the
robotics task category and the data_files config the hub viewer reads) and vla-ladder's description.

`LeRobotDataset.push_to_hub` uploads this README.md and then replaces it with a card of its own; keep this
one by passing its text: `push_to_hub(dataset_description=card.description(root))`.
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from vla_ladder import files
from vla_ladder.conditions import Condition
from vla_ladder.contract import (ACTION_NAMES, CAMERAS, CONTROL_HZ, CONTROL_MODE, EPISODE_STEPS, METRICS, ROBOT,
                                 STATE_NAMES)
from vla_ladder.recordings import (DEFAULT_VCODEC, PROVENANCE_DIR, RECORDING_FILE, played_to, read_provenance,
                                   read_recording_state)
from vla_ladder.task.objects import OBJECTS

CARD_FILE = "README.md"
PAPER = ("*Robust Skills, Brittle Grounding: Diagnosing Restricted Generalization in VLA Policies via "
         "Multi-Object Picking* (Emukpere, Deffayet, Renders)")
DEFAULT_ROBOT_MESH = "lite"
"""GraspObject-v1's default robot_mesh, what a recording server uses unless its episodes say otherwise."""

_OBJECT_SETS = {
    "ycb": "ManiSkill's YCB meshes (mani_skill2_ycb)",
    "standin": "vla-ladder's stand-ins: primitive shapes with the YCB objects' sizes and masses and distinctive "
               "colours, used when the YCB meshes are not on disk",
}

_CODEC_NAMES = {"libsvtav1": "AV1 (SVT-AV1)", "h264": "H.264"}
COLUMNS = ("seed", "target", "instruction", "expert", "robot_mesh", "replayable")
"""The provenance columns the card reads."""


def description(root: str | Path, prov: pd.DataFrame | None = None) -> str:
    """The card's body (Markdown) for the recording at `root`; `prov`: its provenance (at least COLUMNS), if the
    caller has it (the recorder keeps it between commits: reading it is reading a file per commit)."""
    root = Path(root)
    info = json.loads((root / "meta/info.json").read_text())
    state = read_recording_state(root)
    if state is None:
        raise ValueError(f"{root} has no {RECORDING_FILE}: not a vla-ladder recording")
    config, counters, versions = state["config"], state["counters"], state.get("provenance", {})
    prov = read_provenance(root) if prov is None else prov
    condition = Condition.parse(config["condition"])
    object_set = state.get("object_set") or "unknown"
    expert = json.loads(prov["expert"].iloc[0]) if len(prov) else {"spec": config["policy"]}
    tasks = sorted(prov["instruction"].unique()) if len(prov) else []
    cameras = ", ".join(f"`{c.key}` ({c.width}x{c.height} RGB, {c.fov_deg:g} deg vertical FOV)" for c in CAMERAS)
    codec = _CODEC_NAMES.get(config.get("vcodec", DEFAULT_VCODEC), config.get("vcodec"))
    storage = f"{codec} video" if config.get("video", True) else "PNG images in the Parquet files"
    lines = [
        f"Synthetic robot demonstrations recorded in simulation by vla-ladder {versions.get('vla-ladder', '?')} "
        f"on GraspObject-v1 (ManiSkill3), the task of "
        f"{PAPER}: a Franka Panda is told \"grasp the <object>\" among up to five YCB objects.",
        "",
        "## What was recorded",
        "",
        f"- **Episodes**: {info['total_episodes']} ({info['total_frames']} frames), each {EPISODE_STEPS} steps at "
        f"{CONTROL_HZ} Hz, every one a *successful* expert episode: {counters['attempted']} were played, "
        f"{counters['failed']} failed and were not recorded.",
        f"- **Condition**: `{condition.key}`: regime `{condition.regime}`, split `{condition.split}`, "
        f"{condition.num_objects} object(s) on the table (the instructed one and distractors).",
        f"- **Expert**: `{expert.get('spec', config['policy'])}`"
        + (f" ({json.dumps({k: v for k, v in expert.items() if k != 'spec'})})" if len(expert) > 1 else ""),
        f"- **Object set**: `{object_set}`, {_OBJECT_SETS.get(object_set, 'not recorded')}. Objects: "
        + ", ".join(f"{o.name} (YCB {o.ycb_id})" for o in OBJECTS) + ".",
        f"- **Robot**: Franka Panda (ManiSkill `{ROBOT}`), `{CONTROL_MODE}` control; robot mesh "
        f"`{_robot_mesh(prov, state)}` (how the robot looks in the pictures; physics is the same).",
        f"- **Sensors**: two cameras, {cameras}, stored as {storage}; `observation.state` is the 15-d "
        f"proprioception: 7 joint positions (rad), 7 joint velocities (rad/s), the gripper opening (m) "
        f"({STATE_NAMES[0]}...{STATE_NAMES[-1]}).",
        f"- **Action**: 7-d ({', '.join(ACTION_NAMES)}), end-effector deltas normalised to [-1, 1]; the gripper "
        "is -1 closed, +1 open.",
        f"- **Tasks**: {len(tasks)} instruction(s): " + ", ".join(f'"{t}"' for t in tasks) + ".",
        "- **Targets** (episodes instructing each object; the expert's successes only, so an object it fails to "
        "grasp is rarer or missing): " + ", ".join(f"{name} {n}" for name, n in target_counts(prov).items()) + ".",
        f"- **Seeds**: {_seeds(config, state, prov)}",
        "- **Versions**: " + ", ".join(f"{k} {v}" for k, v in versions.items() if k != "object_set") + ".",
        "",
        "## Provenance",
        "",
        f"- `{RECORDING_FILE}`: what this is a recording of (expert, condition, first seed), counters, versions.",
        f"- `{PROVENANCE_DIR}/*.parquet`: one row per episode (by `episode_index`): seed, layout, target, "
        f"instruction, expert, object set, whether it replays bit for bit, and the episode's metrics "
        f"({', '.join(METRICS)}, lifted, held, reach_dist). vla-ladder reads these to train and evaluate by "
        "condition; LeRobot's editing tools (`lerobot-edit-dataset`) do not carry them: see vla-ladder's "
        "docs/datasets.md.",
        "- `meta/stats.json`: the quantiles (q01...q99) of numeric features are computed over "
        + _quantile_frames(state, info) + ", not averaged over episodes as LeRobot does.",
        "",
        "## Limitations",
        "",
        "- Simulation only (ManiSkill3 / SAPIEN), rendered images; no real-robot data.",
        "- Only successful demonstrations of one scripted or learned expert: no failures or recoveries.",
        "- After a grasp the gripper action stays at -1 (closed) to the end of the episode, and the state holds "
        "joint velocities: tools that flag constant actuators or jumps in joint values report them by design.",
    ]
    if object_set == "standin":
        lines.append("- Stand-in objects, not the YCB meshes: a policy trained here sees simple shapes.")
    return "\n".join(lines) + "\n"


def _quantile_frames(state: dict, info: dict) -> str:
    over, total = state.get("quantile_frames"), info["total_frames"]
    if over is None or over == total:
        return "all frames"
    return (f"the first {over} of the {total} frames (computed again over all frames when the recording stops, and "
            "whenever the dataset has grown by a tenth)")


def target_counts(prov: pd.DataFrame) -> dict[str, int]:
    """Episodes per instructed object, every object named (0 where none)."""
    counts = prov["target"].value_counts() if len(prov) else {}
    return {o.name: int(counts.get(o.name, 0)) for o in OBJECTS}


def missing_targets(counts: dict[str, int], at_least: int = 30) -> list[str]:
    """Objects no episode instructs, once there are `at_least` episodes: targets are drawn uniformly from the five
    objects, so a missing one by chance has probability 0.8^30 < 0.002 there; it means the expert fails it."""
    return [name for name, n in counts.items() if n == 0] if sum(counts.values()) >= at_least else []


def render(root: str | Path, prov: pd.DataFrame | None = None, name: str | None = None) -> str:
    """The whole README.md: the YAML header LeRobot's own cards carry (so the hub files it under robotics and
    its viewer finds data/*/*.parquet), then `description`. `name`: the dataset's, the title (default: root's; the
    recorder writes the card into a staging copy, whose name it is not)."""
    from huggingface_hub import DatasetCardData

    header = DatasetCardData(license="apache-2.0", task_categories=["robotics"],
                             tags=["LeRobot", "vla-ladder", "GraspObject-v1", "ManiSkill3", "simulation", "synthetic"],
                             configs=[{"config_name": "default", "data_files": "data/*/*.parquet"}])
    return f"---\n{header.to_yaml()}\n---\n\n# {name or Path(root).name}\n\n{description(root, prov)}"


def write_card(root: str | Path, prov: pd.DataFrame | None = None, name: str | None = None) -> Path:
    """(Re)write README.md in the dataset root, atomically (`prov`: as in `description`; `name`: as in `render`)."""
    return files.write_text(Path(root) / CARD_FILE, render(root, prov, name))


def _robot_mesh(prov: pd.DataFrame, state: dict) -> str:
    if "robot_mesh" in prov and len(prov):
        return ", ".join(sorted(prov["robot_mesh"].astype(str).unique()))
    return state.get("config", {}).get("robot_mesh") or state.get("robot_mesh") or DEFAULT_ROBOT_MESH


def _seeds(config: dict, state: dict, prov: pd.DataFrame) -> str:
    played = f"seeds {config['first_seed']} to {played_to(state) - 1} were played, each episode recorded at most once"
    if not len(prov):
        return played + "."
    return (f"{played}; the recorded episodes have seeds {int(prov['seed'].min())} to "
            f"{int(prov['seed'].max())} (per episode in `{PROVENANCE_DIR}`). Episode seed s fixes the layout, "
            "the target and the robot's initial pose (`env.reset(seed=s)`)." + _replay(prov))


def _replay(prov: pd.DataFrame) -> str:
    replayable = int(prov["replayable"].fillna(False).astype(bool).sum()) if "replayable" in prov else 0
    if not replayable:
        return ""
    return (f" {replayable} of the {len(prov)} episodes were simulated on a scene rebuilt for them (physx_cpu): their "
            "seed and recorded actions replay them bit for bit (`vla-ladder check-dataset` replays some).")
