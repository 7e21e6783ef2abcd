"""Training checkpoints of the PPO expert: the network (the policy's own format), the optimizer state and the
run state, written so that a crash leaves the previous checkpoint in charge and `--resume` continues from it:
the same weights, optimizer state, step count and training seeds, with fresh (seeded) action noise and minibatch
order, so a resumed run is reproducible but not the uninterrupted run's twin."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import safe_open, save_file

from vla_ladder import files
from vla_ladder.policies.ppo import Agent, save_agent


def save_optimizer(path: Path, optimizer: torch.optim.Optimizer) -> None:
    sd = optimizer.state_dict()
    tensors = {f"state.{pid}.{k}": torch.as_tensor(v).detach().cpu().contiguous()
               for pid, st in sd["state"].items() for k, v in st.items()}
    with files.atomic_path(path) as tmp:
        save_file(tensors, str(tmp), {"param_groups": json.dumps(sd["param_groups"])})


def load_optimizer(path: Path, optimizer: torch.optim.Optimizer) -> None:
    try:
        with safe_open(str(path), framework="pt") as sf:
            groups = json.loads(sf.metadata()["param_groups"])
            state: dict[int, dict] = {}
            for key in sf.keys():
                _, pid, name = key.split(".", 2)
                state.setdefault(int(pid), {})[name] = sf.get_tensor(key)
        optimizer.load_state_dict({"state": state, "param_groups": groups})
    except (SafetensorError, OSError, KeyError, ValueError, RuntimeError) as e:
        raise ValueError(f"unreadable optimizer state {path}: {e}") from e


def save_checkpoint(out: Path, agent: Agent, optimizer: torch.optim.Optimizer, state: dict, keep: int,
                    best: bool, selected_on: dict | None = None) -> None:
    """Write checkpoints/step_N/ in full, then point state.json at it: a crash leaves the previous
    checkpoint in charge. `selected_on` (the evaluation's first_seed, episodes per condition and conditions) goes into
    checkpoints/best/state.json: the best model was chosen on those seeds, so its success there is biased upward,
    and `vla-ladder eval` says so when asked to play them."""
    name = f"checkpoints/step_{state['global_step']:012d}"
    ck = out / name
    save_agent(ck / "model.safetensors", agent)
    save_optimizer(ck / "optimizer.safetensors", optimizer)
    files.write_json(ck / "state.json", state)
    if best:
        best_dir = out / "checkpoints" / "best"
        save_agent(best_dir / "model.safetensors", agent)
        files.write_json(best_dir / "state.json", {**state, **({"selected_on": selected_on} if selected_on else {})})
    files.write_json(out / "state.json", {**state, "checkpoint": name})
    # Directory names sort by step. Those past this one are a killed run's unfinished saves (a resumed run may count
    # in other batches); they go first, so that the newest `keep` never leave out the one state.json points to.
    steps = sorted((out / "checkpoints").glob("step_*"))
    for old in [d for d in steps if d.name > ck.name] + [d for d in steps if d.name <= ck.name][:-keep]:
        shutil.rmtree(old)


def load_run_state(out: Path) -> dict:
    """A run's state.json, to resume it. checkpoints/best is written before state.json: a run killed between the two
    has a best model that state.json's best_success does not know, which a lesser evaluation would then replace."""
    state = json.loads((out / "state.json").read_text())
    best = out / "checkpoints" / "best" / "state.json"
    if best.is_file():
        state["best_success"] = max(state["best_success"], json.loads(best.read_text())["best_success"])
    return state
