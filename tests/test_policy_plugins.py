"""Policy plugins: an installed distribution's `vla_ladder.policies` entry points are --policy kinds.

The plugin is the shipped example (examples/policy_plugin), "installed" the way pip leaves a distribution: a
dist-info folder whose entry_points.txt is the one its pyproject.toml declares, on the path. Beside it: a plugin
that fails in the workers, one whose module is missing, two that may not take their names, an expert (the scripted
one under another name) and one that names its weights file."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pandas as pd
import pytest
import torch

from vla_ladder import policies
from vla_ladder.contract import ACTION_DIM, STATE_DIM

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "policy_plugin"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """A folder holding the plugins' distribution metadata and the test plugins' modules."""
    root = tmp_path_factory.mktemp("site")
    declared = tomllib.loads((EXAMPLE / "pyproject.toml").read_text())["project"]["entry-points"][policies.PLUGIN_GROUP]
    assert declared == {"constant": "constant_policy:make_policy"}
    (root / "failing_plugin.py").write_text(
        "def make(arg, **kwargs):\n    raise ValueError(f'failing: no weights at {arg}')\n")
    (root / "weighted_plugin.py").write_text(  # a plugin whose argument is its weights file
        "from constant_policy import make_policy\n\n"
        "def make(arg, **kwargs):\n    return make_policy(None)\n\n"
        "make.weights_file = lambda arg: arg\n")
    info = root / "vla_ladder_example_policy-0.1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: vla-ladder-example-policy\nVersion: 0.1.0\n")
    entries = {**declared, "failing": "failing_plugin:make", "missing": "no_such_module:make",
               "ppo": "failing_plugin:make", "bad?name": "failing_plugin:make",
               "my-expert": "vla_ladder.policies.scripted:make_policy",  # someone's expert: the scripted one
               "weighted": "weighted_plugin:make"}
    (info / "entry_points.txt").write_text(f"[{policies.PLUGIN_GROUP}]\n"
                                           + "".join(f"{k} = {v}\n" for k, v in entries.items()))
    return root


@pytest.fixture
def installed(site, monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE))
    monkeypatch.syspath_prepend(str(site))
    policies._plugins.cache_clear()
    yield
    policies._plugins.cache_clear()


def test_a_plugin_is_a_kind_beside_the_built_in_ones(installed, capsys):
    assert "constant[:ARG] (plugin)" in policies.allowed_specs()
    err = capsys.readouterr().err
    # A plugin cannot replace a built-in kind nor take a name a spec cannot hold: skipped, and said.
    assert "policy plugin 'ppo' (failing_plugin:make) skipped: its name is a built-in kind's" in err
    assert "policy plugin 'bad?name'" in err
    assert policies.policy_kinds()["ppo"] == policies.POLICY_KINDS["ppo"] and "bad?name" not in policies.policy_kinds()
    # Every built-in kind, then the plugins' (whichever kind the registry lists last).
    built_in = ", ".join(map(policies._spec_form, policies.POLICY_KINDS))
    with pytest.raises(ValueError, match=re.escape(f"unknown policy 'octo:x'; allowed: {built_in}, constant[:ARG] "
                                                   "(plugin)")):
        policies.parse_spec("octo:x")

    policy = policies.load_policy("constant:0.5,0,-1,0,0,0,-1")
    assert policy.obs_mode == "rgb" and policy.describe()["action"] == [0.5, 0, -1, 0, 0, 0, -1]
    action = policy.act({"extra": {"proprio": torch.zeros(3, STATE_DIM)}}, ["grasp the mug"] * 3)
    assert action.shape == (3, ACTION_DIM) and action[:, 0].eq(0.5).all() and action[:, 6].eq(-1).all()
    assert policies.load_policy("constant").describe()["action"] == [0, 0, 0, 0, 0, 0, 1]

    from vla_ladder.experiments.diagnose import default_label  # a plugin's label on the diagnosis page: kind first
    assert [default_label(s) for s in ("constant", "constant:0,0,1,0,0,0,1", "ppo:runs/x")] == \
        ["constant", "constant-0_0_1_0_0_0_1", "x"]


def test_a_kind_two_plugins_declare_is_refused_naming_both(installed, tmp_path, monkeypatch, capsys):
    """Two distributions declaring one kind: the one entry_points() listed first (the file system's order) was used,
    and the other skipped with a warning that called its name a built-in kind's."""
    info = tmp_path / "other_policy-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: other-policy\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{policies.PLUGIN_GROUP}]\nconstant = other_policy:make\n"
                                           "weighted = weighted_plugin:make\n")  # (the same factory: no clash)
    monkeypatch.syspath_prepend(str(tmp_path))
    policies._plugins.cache_clear()
    with pytest.raises(ValueError, match=r"policy 'constant' is declared by two plugins, (vla-ladder-example-policy "
                                         r"\(constant_policy:make_policy\)|other-policy \(other_policy:make\)) and "):
        policies.check_spec("constant:0,0,0,0,0,0,1")
    assert "constant" not in policies.policy_kinds() and "'constant'" not in capsys.readouterr().err
    assert policies.check_spec("weighted:x") == ("weighted", "x")


def test_a_plugin_spec_is_checked_before_any_work(installed):
    assert policies.check_spec("constant:0,0,0,0,0,0,1") == ("constant", "0,0,0,0,0,0,1")
    with pytest.raises(ValueError, match=r"constant:A0,...,A6 takes 7 comma-separated numbers in \[-1, 1\], got '1,2'"):
        policies.check_spec("constant:1,2")  # the factory's own check(arg)
    with pytest.raises(ValueError, match=r"policy plugin 'missing' \(no_such_module:make\) does not load: "
                                         r"ModuleNotFoundError: No module named 'no_such_module'"):
        policies.check_spec("missing")
    assert policies.check_spec("failing:x") == ("failing", "x")  # no check(arg): its error comes from the workers
    # Recording takes a plugin as its expert (its author knows), never a built-in reference.
    policies.check_expert("my-expert", "--policy my-expert")
    with pytest.raises(ValueError, match=r"--policy random is not an expert; allowed: scripted, ppo:PATH, or a policy"):
        policies.check_expert("random", "--policy random")



def test_an_experiments_policy_entry_takes_a_spec_with_commas(installed):
    """`experiment --policy label=L,spec=constant:A0,...,A6` was split at every comma: the documented plugin form was
    refused as a bad entry. Only a known key after a comma starts the next pair; only spec= may hold commas."""
    from vla_ladder.experiments.experiment import PolicyEntry

    spec = "constant:0,0,0,0,0,0,1"
    assert PolicyEntry.parse(f"label=const,spec={spec}") == PolicyEntry(spec, "const")
    assert PolicyEntry.parse(f"spec={spec},label=const") == PolicyEntry(spec, "const")
    for bad in (f"label=a,b,spec={spec}", f"label=a,colour=red,spec={spec}"):
        with pytest.raises(ValueError, match="expected SPEC or comma-separated key=value pairs with keys label, spec"):
            PolicyEntry.parse(bad)


def test_a_plugin_that_names_its_weights_file_has_them_checked_on_resume(installed, tmp_path):
    """weights_identity, which a run directory keeps so that a resume with other weights at the same path is refused,
    hashes the file a plugin's weights_file(arg) names; a plugin without weights_file has none, like a reference."""
    import hashlib

    weights = tmp_path / "model.bin"
    weights.write_bytes(b"first")
    first = policies.weights_identity(f"weighted:{weights}")
    assert first == {"file": str(weights), "sha256": hashlib.sha256(b"first").hexdigest()}
    weights.write_bytes(b"retrained")
    assert policies.weights_identity(f"weighted:{weights}")["sha256"] == hashlib.sha256(b"retrained").hexdigest()
    assert policies.weights_identity("constant") is None


@pytest.mark.slow  # the real simulator and both cameras, in worker processes
def test_eval_plays_a_plugin_in_worker_processes(site, tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(EXAMPLE), os.environ.get("PYTHONPATH", "")])}
    cli = [sys.executable, "-m", "vla_ladder.cli", "eval", "--regimes", "small_jitter", "--episodes", "2",
           "--workers", "2"]
    out = tmp_path / "run"
    done = subprocess.run(cli + ["--policy", "constant:0,0,0.2,0,0,0,1", "--out", str(out)], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    # The fixture's misnamed plugins are said once, by the command, not again by each worker.
    assert done.stderr.count("policy plugin 'ppo' (failing_plugin:make) skipped") == 1, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["policy"] == {"name": "constant", "action": pytest.approx([0, 0, 0.2, 0, 0, 0, 1])}
    rows = pd.read_parquet(out / "episodes.parquet")
    # The arm rose with its gripper open the whole episode: it ends far from every object, holding none.
    assert len(rows) == 2 and not rows["grasp_any"].any() and (rows["reach_dist"] > 0.3).all(), rows

    # A plugin that fails in the workers (it has no check) ends in its own one-line error, not a broken pool.
    done = subprocess.run(cli + ["--policy", "failing:x", "--out", str(tmp_path / "failing")], env=env,
                          capture_output=True, text=True, timeout=600)
    last = done.stderr.splitlines()[-1]
    assert done.returncode == 2 and last == "vla-ladder eval: error: failing: no weights at x", done.stderr


@pytest.mark.slow  # the real simulator, both cameras, a LeRobotDataset
def test_record_takes_a_plugin_expert_and_gives_up_on_one_that_never_succeeds(site, tmp_path):
    from vla_ladder.recordings import read_provenance, read_recording_state

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(EXAMPLE), os.environ.get("PYTHONPATH", "")])}
    cli = [sys.executable, "-m", "vla_ladder.cli", "record", "--regime", "small_jitter", "--num-objects", "2",
           "--episodes", "1"]
    out = tmp_path / "demos"
    done = subprocess.run(cli + ["--workers", "1", "--policy", "my-expert", "--out", str(out)], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert read_recording_state(out)["config"]["policy"] == "my-expert" and len(read_provenance(out)) == 1

    # The arm held still: no success in the first 3 episodes, so nothing to record (before: a loop until killed);
    # with two writers the recorder counts their episodes and stops them.
    for name, writers in (("never", ["--workers", "1"]), ("never2", ["--workers", "2", "--writers", "2"])):
        out = tmp_path / name
        done = subprocess.run(cli + writers + ["--policy", "constant", "--give-up-after", "3", "--out", str(out)],
                              env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 1, done.stderr
        assert re.search(r"constant succeeded in none of the first \d+ episodes of small_jitter/canonical/2: nothing "
                         "to record", done.stderr), done.stderr
        state = read_recording_state(out) if out.exists() else None
        assert state is None or state["counters"]["saved"] == 0
