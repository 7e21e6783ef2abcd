"""Misuse, as a demanding new user commits it: bad seeds, corrupted run directories, full or read-only disks, a file
where a directory belongs, a port in use, a missing checkpoint, no GPU. Each must end in one line on stderr that
names the flag, path or resource and the fix, with exit code 2, before any long work, leaving no temporary files.
docs/misuse.md lists every case tried and how it ends."""

from __future__ import annotations

import dataclasses
import errno
import importlib
import json
import os
import shutil
import socket
import subprocess
import sys
import typing
from pathlib import Path

import pandas as pd
import pytest
from report_fixtures import make_run

from vla_ladder import checks
from vla_ladder.cli import COMMANDS, main
from vla_ladder.files import write_json, write_parquet

SJ = ("small_jitter", "canonical", 5)
FR = ("full_random", "canonical", 5)


def _one_line_error(capsys, rc: int, *words: str) -> str:
    """The command failed with exit 2 and said so in exactly one stderr line containing `words`."""
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert w in err, (w, err)
    return err


# ---------------------------------------------------------------------------------------------------- seeds
NEGATIVE_SEEDS = {
    "placements": (["placements", "--n", "2"], "--first-seed"),
    "render": (["render", "--out", "{tmp}/r"], "--seed"),
    "train-expert": (["train-expert", "--out", "{tmp}/ppo"], "--train-seed"),
    "train-expert eval": (["train-expert", "--out", "{tmp}/ppo"], "--eval-first-seed"),
    "serve": (["serve", "--port", "0"], "--rng-seed"),
    "record": (["record", "--out", "{tmp}/rec", "--episodes", "1"], "--first-seed"),
    "train": (["train", "--policy-type", "act", "--dataset", "{tmp}/data", "--out", "{tmp}/t"], "--train-seed"),
    "eval": (["eval", "--policy", "scripted", "--out", "{tmp}/e"], "--first-seed"),
    "experiment": (["experiment", "ladder", "--policy", "scripted", "--out", "{tmp}/x"], "--first-seed"),
    "probe": (["probe", "instruction-swap", "--policy", "scripted", "--out", "{tmp}/p"], "--first-seed"),
    "diagnose": (["diagnose", "--policy", "scripted", "--out", "{tmp}/d"], "--first-seed"),
    "grid train": (["grid", "--out", "{tmp}/g", "--train.policy-type", "act", "--train.dataset", "{tmp}/data"],
                   "--train.train-seed"),
    "grid eval": (["grid", "--out", "{tmp}/g", "--train.policy-type", "act", "--train.dataset", "{tmp}/data"],
                  "--eval.first-seed"),
}


@pytest.mark.timeout(120)  # before the check, `serve` listened forever
@pytest.mark.parametrize("case", [c for c in NEGATIVE_SEEDS if NEGATIVE_SEEDS[c][0][0] in COMMANDS])
@pytest.mark.parametrize("value", ["-1", "=-7", str(2**32)])
def test_a_bad_seed_is_named_by_its_flag_before_anything_runs(case, value, tmp_path, capsys):
    argv, flag = NEGATIVE_SEEDS[case]
    argv = [a.format(tmp=tmp_path) for a in argv]
    argv += [flag + value] if value.startswith("=") else [flag, value]
    rc = main(argv)
    shown = value.lstrip("=")
    _one_line_error(capsys, rc, f"error: {flag} must be >= 0 and < 2**32", f"got {shown}")
    assert list(tmp_path.iterdir()) == []  # nothing was created


@pytest.mark.parametrize("argv", [["eval", "--policy", "scripted"], ["record"]])
def test_the_last_episodes_seed_is_checked_before_anything_runs(argv, tmp_path, capsys):
    rc = main([*argv, "--out", str(tmp_path / "run"), "--first-seed", "4294967294", "--episodes", "3"])
    _one_line_error(capsys, rc, "error: --first-seed must be >= 0 and --first-seed + --episodes <= 2**32",
                    "got 4294967294 + 3")
    assert list(tmp_path.iterdir()) == []


def _seed_like(cls) -> list[str]:
    """Fields of a config (nested configs included) whose name says they hold a seed."""
    hints = typing.get_type_hints(cls, include_extras=True)
    names = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        hint = typing.get_args(hint)[0] if typing.get_origin(hint) is typing.Annotated else hint
        if f.name.endswith("seed"):
            names.append(f.name)
        elif isinstance(hint, type) and dataclasses.is_dataclass(hint):
            names += _seed_like(hint)
    return names


def test_every_seed_field_of_every_command_is_checked():
    """A seed field added to any command later is found by the same check (its name ends in "_seed")."""
    flags = {}
    for name, (target, _) in COMMANDS.items():
        module, _, cls_name = target.partition(":")
        cls = getattr(importlib.import_module(module), cls_name)
        flags[name] = checks.seed_flags(cls)
        assert all(checks.is_seed_field(f) for f in _seed_like(cls)), name
        assert len(flags[name]) == len(_seed_like(cls)), (name, flags[name])
    assert set(flags["grid"]) == {"--train.train-seed", "--eval.first-seed"}
    assert set(flags["train-expert"]) == {"--train-seed", "--eval-first-seed"}
    assert set(flags["serve"]) == {"--rng-seed"} and set(flags["render"]) == {"--seed"}
    assert flags["compare"] == {} and flags["report"] == {}


def test_seed_checks_of_configs_built_in_code_say_the_same():
    from vla_ladder.ppo.config import Args
    from vla_ladder.recording.server import ServeConfig

    with pytest.raises(ValueError, match=r"^--rng-seed must be >= 0 and < 2\*\*32 \(a numpy seed\), got -1$"):
        ServeConfig(rng_seed=-1, port=0)
    with pytest.raises(ValueError, match=r"^--train-seed must be >= 0 and < 2\*\*32 \(a numpy seed\), got -2$"):
        Args(out="x", sim_backend="physx_cpu", num_envs=1, train_seed=-2)
    with pytest.raises(ValueError, match="integer seed"):
        checks.check_seed(1.5, "--seed")
    assert checks.check_seed(2**32 - 1, "--seed") == 2**32 - 1


# ------------------------------------------------------------------------------------------ run directories
def _runs(tmp_path) -> tuple[Path, Path]:
    a = make_run(tmp_path / "a", "nearest", [SJ, FR], ["success", "nothing", "wrong_object", "success"])
    b = make_run(tmp_path / "b", "scripted", [SJ, FR], ["success"] * 4)
    return a, b


def _edit_episodes(run: Path, edit) -> None:
    write_parquet(run / "episodes.parquet", edit(pd.read_parquet(run / "episodes.parquet")))


def _edit_summary(run: Path, edit) -> None:
    summary = json.loads((run / "summary.json").read_text())
    edit(summary)
    write_json(run / "summary.json", summary)


def _killed(run: Path, drop: int) -> None:
    """What a run killed mid-way leaves: one episode fewer, and a summary.json that counts what is there."""
    from vla_ladder.evaluation.metrics import summarize

    _edit_episodes(run, lambda df: df.drop(index=drop))
    _edit_summary(run, lambda s: s.update(conditions=summarize(pd.read_parquet(run / "episodes.parquet"))))


CORRUPTIONS = {
    "an episode twice": (lambda r: _edit_episodes(r, lambda df: pd.concat([df, df.iloc[[2]]], ignore_index=True)),
                         ["small_jitter/canonical/5 episode 2 (2 rows)", "evaluate again into a new --out"]),
    "an episode missing (a killed run)": (
        lambda r: _killed(r, drop=1), ["incomplete", "lacks episodes 1 of 0..3",
         "rerun the same command that wrote it (`vla-ladder eval`, or the `probe`"]),
    "an episode missing from episodes.parquet": (
        lambda r: _edit_episodes(r, lambda df: df.drop(index=1)),
        ["lacks episodes 1 of 0..3", "summary.json counts 4 episodes of small_jitter/canonical/5, episodes.parquet "
         "holds 3",
         "rerun the same command that wrote it (`vla-ladder eval`, or the `probe`"]),
    "an episode beyond the count": (
        lambda r: _edit_episodes(r, lambda df: df.assign(episode=df["episode"].where(df.index != 3, 9),
                                                         seed=df["seed"].where(df.index != 3, 9))),
        ["episodes 9 beyond episodes_per_condition 4"]),
    "a count that disagrees with summary.json": (
        lambda r: _edit_summary(r, lambda s: s["conditions"]["full_random/canonical/5"].update(n=5)),
        ["summary.json counts 5 episodes of full_random/canonical/5, episodes.parquet holds 4"]),
    "a rate that disagrees with summary.json": (
        lambda r: _edit_summary(r, lambda s: s["conditions"]["small_jitter/canonical/5"].update(success=0.25)),
        ["summary.json gives small_jitter/canonical/5 success = 0.25, episodes.parquet 4/4"]),
    "a condition summary.json does not know": (
        lambda r: _edit_summary(r, lambda s: s["conditions"].pop("full_random/canonical/5")),
        ["only in episodes.parquet: full_random/canonical/5"]),
    "a seed that is not first_seed + episode": (
        lambda r: _edit_episodes(r, lambda df: df.assign(seed=df["seed"].where(df.index != 0, 42))),
        ["1 episodes do not play seed first_seed + episode", "episode 0 has seed 42"]),
    "a metric that is not true/false": (
        lambda r: _edit_episodes(r, lambda df: df.assign(reach=df["reach"].astype(float).where(df.index != 0, 0.5))),
        ["column 'reach' holds values other than true/false"]),
    "summary.json says incomplete": (lambda r: _edit_summary(r, lambda s: s.update(complete=False)),
                                     ["incomplete", "complete: false"]),
}


@pytest.mark.parametrize("command", ["compare", "report"])
@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_compare_and_report_refuse_a_run_whose_files_disagree(command, case, tmp_path, capsys):
    a, b = _runs(tmp_path)
    corrupt, words = CORRUPTIONS[case]
    corrupt(b)
    argv = ["compare", str(a), str(b), "--json", str(tmp_path / "cmp.json")] if command == "compare" else \
        ["report", str(a), str(b), "--out", str(tmp_path / "report.html"), "--no-video", "--no-placements"]
    _one_line_error(capsys, main(argv), str(b), *words)
    assert not (tmp_path / "cmp.json").exists() and not (tmp_path / "report.html").exists()


def test_report_refuses_runs_that_played_other_seeds(tmp_path, capsys):
    a, _ = _runs(tmp_path)
    shifted = make_run(tmp_path / "shifted", "scripted", [SJ], ["success"] * 4, seed=100)
    rc = main(["report", str(a), str(shifted), "--out", str(tmp_path / "r.html"), "--no-video", "--no-placements"])
    _one_line_error(capsys, rc, "different seeds on 4 of 4 shared episodes", "seed 0 vs 100", "--first-seed")
    assert not (tmp_path / "r.html").exists()


def test_consistent_runs_still_compare(tmp_path, capsys):
    a, b = _runs(tmp_path)
    assert main(["compare", str(a), str(b)]) == 0
    assert "McNemar" in capsys.readouterr().out


# ------------------------------------------------------------------------------- two writers of one output
def test_a_second_study_or_evaluation_writing_the_same_directory_is_refused_at_once(tmp_path, capsys):
    """A study or evaluation started again while the first still ran wrote the same files (two studies ran the same
    units at once). Now the second says so in one line before it plays or writes anything, and runs once the first
    has let go (training: tests/test_training.py)."""
    from importlib import resources

    from vla_ladder import files

    study = tmp_path / "study.json"
    study.write_text(resources.files("vla_ladder.configs.study").joinpath("micro.json").read_text())
    cases = {"evaluation": ["eval", "--policy", "scripted", "--regimes", "small_jitter", "--num-objects", "1",
                            "--episodes", "1", "--out", str(tmp_path / "ev")],
             "vla-ladder study": ["study", str(study), "--out", str(tmp_path / "st")],
             "probe": ["probe", "position-swap", "--policy", "nearest", "--num-objects", "2", "--episodes", "1",
                       "--overwrite", "--out", str(tmp_path / "pr")]}  # (--overwrite removed the first's variants)
    for what, argv in cases.items():
        out = tmp_path / argv[-1]
        with files.writing(out, "test"):
            _one_line_error(capsys, main(argv), f"another {what} is writing {out}", str(files.lock_path(out)))
        assert not out.exists()
        assert not files.lock_path(out).exists()  # its holder removes it: none is left beside an output
    assert main(cases["evaluation"]) == 0
    assert pd.read_parquet(tmp_path / "ev" / "episodes.parquet")["seed"].tolist() == [0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ev", "study.json"]  # (a refused --out left .NAME.lock)


def test_the_root_and_the_current_directory_are_refused_as_outputs(tmp_path, monkeypatch, capsys):
    """eval --out / made /..lock before it refused; --out . --overwrite made its aside folder inside the directory
    it removed and failed there ("Device or resource busy"), a new hidden folder left at each try."""
    for command in (["eval", "--policy", "scripted"], ["probe", "instruction-swap", "--policy", "nearest"]):
        _one_line_error(capsys, main([*command, "--episodes", "1", "--out", "/"]), "is the file system's root")
    assert not Path("/..lock").exists()
    run = tmp_path / "run"
    argv = ["eval", "--policy", "scripted", "--regimes", "small_jitter", "--num-objects", "1", "--episodes", "1",
            "--workers", "1", "--out"]
    assert main([*argv, str(run)]) == 0
    capsys.readouterr()
    monkeypatch.chdir(run)
    _one_line_error(capsys, main([*argv[:-5], "2", "--workers", "1", "--out", ".", "--overwrite"]),  # (2 episodes)
                    "holds the current directory", "run the command from elsewhere")
    assert sorted(p.name for p in run.iterdir()) == ["config.json", "episodes.parquet", "summary.json"]


# -------------------------------------------------------------------------------------------- the disk
def _no_space(monkeypatch, name: str) -> None:
    """Every write of a file called `name` (or a temporary file for it) fails as on a full disk."""
    real = Path.write_text

    def write_text(self, *args, **kwargs):
        if self.name == name or self.name.startswith(f".{name}."):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", write_text)


def test_a_full_disk_ends_in_one_line_and_leaves_no_temporary_file(tmp_path, monkeypatch, capsys):
    a, b = _runs(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    _no_space(monkeypatch, "cmp.json")
    rc = main(["compare", str(a), str(b), "--json", str(out / "cmp.json")])
    _one_line_error(capsys, rc, "No space left on device", str(out), "free some space on that disk")
    assert list(out.iterdir()) == []


def test_a_full_disk_under_report_leaves_no_temporary_folder(tmp_path, monkeypatch, capsys):
    a, b = _runs(tmp_path)
    scratch = tmp_path / "scratch"  # the report draws its figures in a temporary folder: it must go away
    scratch.mkdir()
    monkeypatch.setattr("tempfile.tempdir", str(scratch))
    _no_space(monkeypatch, "report.html")
    rc = main(["report", str(a), str(b), "--out", str(tmp_path / "report.html"), "--no-video"])
    _one_line_error(capsys, rc, "No space left on device", "report.html")
    assert list(scratch.iterdir()) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b", "scratch"]


def _read_only_shell(directory: Path) -> list[str] | None:
    """A command prefix that runs a program with `directory` read-only: a private read-only bind mount for root
    (util-linux unshare; the mount dies with the process), a directory without write permission otherwise."""
    if os.geteuid() != 0:
        directory.chmod(0o555)
        return []
    if shutil.which("unshare") is None:
        return None
    probe = subprocess.run(["unshare", "--mount", "--propagation", "private", "true"], capture_output=True)
    if probe.returncode != 0:
        return None
    return ["unshare", "--mount", "--propagation", "private", "sh", "-c",
            'mount --bind -o ro "$0" "$0" && exec "$@"', str(directory)]


@pytest.mark.slow
def test_a_read_only_output_location_ends_in_one_line(tmp_path):
    """Checked at parse time (compare --json, placements --json), before any work."""
    a, b = _runs(tmp_path)
    ro = tmp_path / "ro"
    ro.mkdir()
    prefix = _read_only_shell(ro)
    if prefix is None:
        pytest.skip("cannot make a read-only directory here (root without mount namespaces)")
    cli = [sys.executable, "-m", "vla_ladder.cli"]
    for argv, words in [
        (["compare", str(a), str(b), "--json", str(ro / "sub" / "cmp.json")], ["--json", "read-only", str(ro)]),
        (["placements", "--n", "1", "--json", str(ro / "layouts.json")], ["--json", "read-only", str(ro)]),
    ]:
        done = subprocess.run(prefix + cli + argv, capture_output=True, text=True, timeout=300)
        err = done.stderr.strip()
        assert done.returncode == 2 and len(err.splitlines()) == 1, err
        assert all(w in err for w in words), err
        if os.geteuid() == 0:  # with permissions only, the wording is "not writable"/"Permission denied"
            assert "read-only" in err.lower(), err
    assert list(ro.iterdir()) == []


def test_a_file_where_a_directory_belongs_and_the_reverse(tmp_path, capsys):
    a, b = _runs(tmp_path)
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = [
        (["compare", str(a), str(b), "--json", str(afile / "cmp.json")], ["--json", "is a file where a directory"]),
        (["compare", str(a), str(b), "--json", str(tmp_path)], ["--json", "is a directory; give the path of the file"]),
        (["report", str(a), "--out", str(tmp_path)], ["--out", "is a directory"]),
        (["train-expert", "--out", str(afile), "--sim-backend", "physx_cpu", "--num-envs", "1"],
         ["--out", "is a file, not a directory"]),
        (["placements", "--n", "1", "--json", str(afile / "layouts.json")], ["--json", str(afile),
                                                                             "is a file where a directory is needed"]),
        (["placements", "--n", "1", "--json", str(tmp_path)], ["--json", str(tmp_path), "is a directory"]),
    ]
    for argv, words in cases:
        _one_line_error(capsys, main(argv), *words)
    assert afile.read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "afile", "b"]


# ---------------------------------------------------------------------------------- ports, files, devices
@pytest.fixture
def busy_port():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield sock.getsockname()[1]


@pytest.mark.timeout(120)
def test_serve_refuses_a_port_in_use_before_starting_the_simulator(busy_port, capsys):
    rc = main(["serve", "--port", str(busy_port)])
    err = _one_line_error(capsys, rc, f"cannot listen on 127.0.0.1:{busy_port}", "Address already in use",
                          "pick another --port (0 picks a free one)")
    assert "simulator" not in err


@pytest.mark.slow  # the server resolves its object set through ManiSkill
@pytest.mark.timeout(120)
def test_the_server_binds_before_its_simulator_thread_starts(busy_port):
    """Even when the port is taken between the check and the bind, no simulator is started."""
    import asyncio

    from vla_ladder.recording.server import EpisodeServer, ServeConfig

    cfg = ServeConfig(port=0, lazy=True)
    cfg.port = busy_port  # taken after the config was checked
    server = EpisodeServer(cfg)
    with pytest.raises(OSError) as e:
        asyncio.run(server.serve())
    assert e.value.errno == errno.EADDRINUSE
    assert server._thread is None


@pytest.mark.timeout(120)
def test_serve_refuses_a_missing_expert_checkpoint(tmp_path, capsys):
    _one_line_error(capsys, main(["serve", "--port", "0", "--policy", f"ppo:{tmp_path / 'nope'}"]),
                    "no PPO checkpoint at", str(tmp_path / "nope"))
    ckpt = tmp_path / "lerobot"
    ckpt.mkdir()
    (ckpt / "config.json").write_text("{}")
    _one_line_error(capsys, main(["serve", "--port", "0", "--policy", f"lerobot:{ckpt}"]),
                    "has config.json but no model.safetensors", str(ckpt))


@pytest.mark.parametrize("command", [["eval", "--policy", "scripted"],
                                     ["probe", "instruction-swap", "--policy", "nearest"],
                                     ["diagnose", "--policy", "nearest"]])
def test_overwrite_replaces_only_a_directory_of_its_own_kind(command, tmp_path, capsys):
    """--overwrite once deleted any non-empty --out, a folder of someone's own files included."""
    mine = tmp_path / "thesis"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    _one_line_error(capsys, main([*command, "--episodes", "1", "--out", str(mine), "--overwrite"]),
                    "holds files that are not", "pick a new or empty --out")
    assert (mine / "thesis.tex").read_text() == "years of work"
    # Any config.json was read as an evaluation's request: a LeRobot checkpoint's folder was "another request", and
    # --overwrite (which that error suggested) deleted it; a config.json holding a list ended in a traceback.
    for config in ('{"type": "smolvla", "n_action_steps": 50}', "[1, 2]"):
        ckpt = tmp_path / "pretrained_model"
        ckpt.mkdir(exist_ok=True)
        (ckpt / "config.json").write_text(config)
        (ckpt / "model.safetensors").write_bytes(b"weights")
        for extra in ([], ["--overwrite"]):
            _one_line_error(capsys, main([*command, "--episodes", "1", "--out", str(ckpt), *extra]),
                            "holds files that are not", "pick a new or empty --out")
            assert sorted(p.name for p in ckpt.iterdir()) == ["config.json", "model.safetensors"]


@pytest.mark.parametrize("query, says", [("n_action_steps=0", "expected an integer >= 1"),
                                         ("n_action_steps=-1", "expected an integer >= 1"),
                                         ("n_action_steps=٣", "expected an integer >= 1, got '٣'"),
                                         ("n_action_steps=²", "expected an integer >= 1, got '²'"),
                                         ("device=foo", "expected cpu, cuda, cuda:N or mps"),
                                         ("noise_seed=99999999999999999999999", "2**63 - 1"),
                                         # (str.isdigit() took these: '٣' played seed 3, '²' said int()'s words)
                                         ("noise_seed=٣", "expected an integer from 0 to 2**63 - 1, got '٣'"),
                                         ("noise_seed=²", "expected an integer from 0 to 2**63 - 1, got '²'"),
                                         ("n_action_steps=2&n_action_steps=3", "given twice")])
def test_lerobot_options_are_checked_before_the_run_directory(query, says, tmp_path, capsys):
    out = tmp_path / "run"
    _one_line_error(capsys, main(["eval", "--policy", f"lerobot:{tmp_path}/ckpt?{query}", "--episodes", "1",
                                  "--out", str(out)]), says)
    assert not out.exists()


@pytest.mark.parametrize("spec", ["scripted:fast", "random:7", "nearest:x"])
def test_an_argument_to_a_policy_that_takes_none_is_refused_before_the_run_directory(spec, tmp_path, capsys):
    out = tmp_path / "run"
    _one_line_error(capsys, main(["eval", "--policy", spec, "--episodes", "1", "--out", str(out)]),
                    "takes no argument", spec)
    assert not out.exists()


def test_placements_bounds_its_layout_count(capsys, tmp_path):
    for n in ("0", "100000000"):  # a hundred million layouts a regime ran for minutes toward a JSON of gigabytes
        _one_line_error(capsys, main(["placements", "--n", n]), "--n must be from 1 to 100000 (layouts per regime)")
    # Both outputs are checked before either is written (the JSON was written, then the figure failed).
    _one_line_error(capsys, main(["placements", "--n", "3", "--json", str(tmp_path / "p.json"), "--plot",
                                  str(tmp_path / "p.txt")]), "the figure's format is its suffix; allowed: ")
    _one_line_error(capsys, main(["placements", "--n", "3", "--json", ""]), "--json is empty; give a path")
    assert list(tmp_path.iterdir()) == []


def test_a_ray_address_is_checked_before_anything_is_written():
    """Ray's own "Invalid address format" came after the grid had saved its settings."""
    for good in ("auto", "10.0.0.5:6379", "ray://head:10001", None):
        assert checks.check_ray_address(good) == good
    for bad in ("foo", "http://head:6379", "head:port", ""):
        with pytest.raises(ValueError, match="--ray-address must be auto, HOST:PORT or ray://HOST:PORT"):
            checks.check_ray_address(bad)


@pytest.mark.timeout(120)
def test_a_host_that_is_not_this_machines_is_refused_with_any_port(capsys):
    """With --port 0 the host went unchecked: serve-policy loaded its checkpoint, then failed to bind."""
    for port in ("0", "8765"):
        _one_line_error(capsys, main(["serve", "--port", port, "--host", "nosuch.invalid", "--token", "t"]),
                        "--host 'nosuch.invalid' is not an address of this machine")


def test_serve_refuses_bad_limits_and_names_before_binding(capsys):
    _one_line_error(capsys, main(["serve", "--port", "0", "--max-outstanding", "-1"]),
                    "max_outstanding must be >= 0 (0: 4 x num_envs, at least 8), got -1")
    _one_line_error(capsys, main(["serve", "--port", "0", "--max-clients", "0"]),
                    "--max-clients must be a positive integer, got 0")
    # Checked before the port is bound: the server listened, then its simulator failed and it served nothing.
    _one_line_error(capsys, main(["serve", "--port", "0", "--robot-mesh", "foo"]),
                    "unknown robot_mesh 'foo'; allowed: lite, full")
    _one_line_error(capsys, main(["serve", "--port", "0", "--instructions", "poetic"]),
                    "unknown instruction set 'poetic'; allowed: canonical, paraphrase-train, paraphrase-heldout")


def test_train_expert_without_a_gpu_names_the_cpu_flags(tmp_path, capsys):
    import torch

    from vla_ladder.ppo.train import cli_config

    if torch.cuda.is_available():  # the paper's default is what a GPU machine runs
        assert cli_config(["--out", str(tmp_path / "ppo")]).sim_backend == "physx_cuda"
        return
    rc = main(["train-expert", "--out", str(tmp_path / "ppo")])
    _one_line_error(capsys, rc, "--sim-backend physx_cuda", "needs a CUDA GPU and none is visible",
                    "--sim-backend physx_cpu --num-envs N")
    rc = main(["train-expert", "--out", str(tmp_path / "ppo"), "--sim-backend", "physx_cpu", "--num-envs", "4096"])
    _one_line_error(capsys, rc, "one process per env", "got 4096")
    # Minibatches of one step: one optimizer step made every weight NaN (the std of one advantage).
    rc = main(["train-expert", "--out", str(tmp_path / "ppo"), "--sim-backend", "physx_cpu", "--num-envs", "1",
               "--num-steps", "2", "--num-minibatches", "2"])
    _one_line_error(capsys, rc, "leaves minibatches of one step", "use at most 1, or --no-norm-adv")
    assert list(tmp_path.iterdir()) == []


def test_os_errors_are_described_with_their_path_and_fix():
    e = OSError(errno.EROFS, os.strerror(errno.EROFS), "/data/out.json")
    assert checks.os_error_message(e) == "/data/out.json: Read-only file system; write somewhere else (another --out)"
    e = FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), "/runs/ppo/model.safetensors")
    assert checks.os_error_message(e) == "/runs/ppo/model.safetensors: No such file or directory; check the path"
    assert checks.os_error_message(OSError("weird")) == "weird"


@pytest.mark.parametrize("argv, flag", [
    (["experiment", "ladder", "--policy", "scripted", "--policy", "nearest", "--out", "x"], "--policy"),
    (["record", "--server", "ws://127.0.0.1:1", "--server=ws://127.0.0.1:2", "--episodes", "1", "--out", "x"],
     "--server"),
    (["eval", "--policy", "random", "--episodes", "1", "--episodes", "2", "--out", "x"], "--episodes"),
])
def test_a_flag_given_twice_is_refused_not_silently_dropped(argv, flag, capsys, tmp_path, monkeypatch):
    """tyro keeps a repeated flag's last value: `--policy a --policy b` would evaluate b alone."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{flag} is given twice" in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("argv, says", [
    # tyro reads --num_objects as --num-objects and --no-alone as --alone's other value: the last one won.
    (["eval", "--policy", "scripted", "--num-objects", "3", "--num_objects", "5"],
     "--num-objects is given twice (as --num-objects and --num_objects); give a list's values after one "
     "--num-objects (e.g. --num-objects A B)"),
    (["eval", "--policy", "scripted", "--alone", "--no-alone"],
     "--alone is given twice (as --alone and --no-alone); give it once"),
    (["grid", "--train.policy-type", "act", "--train.policy_type", "diffusion"],
     "--train.policy-type is given twice (as --train.policy-type and --train.policy_type); give it once"),
    # A scalar's message said to give a list's values after one flag.
    (["train-expert", "--resume", "a", "--resume", "b"], "--resume is given twice; give it once"),
])
def test_a_field_given_twice_under_any_spelling_is_refused_with_the_fix_for_its_kind(argv, says, tmp_path, capsys,
                                                                                     monkeypatch):
    monkeypatch.chdir(tmp_path)
    _one_line_error(capsys, main([*argv, "--out", "x"]), f"error: {says}")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("extra, says", [
    (["--writers", "-1"], "--writers must be >= 0 (0: one per two servers), got -1"),
    (["--encoder-threads", "-2"], "--encoder-threads must be >= 0 (0: the encoder's choice), got -2"),
    (["--vcodec", "hevc"], "--vcodec 'hevc': allowed: libsvtav1, h264"),
    (["--no-video", "--vcodec", "h264"], "--vcodec h264 needs video; --no-video stores PNG images, no codec"),
    (["--writers", "2", "--workers", "1"], "--writers 2 needs at least 2 local servers, got --workers 1"),
    (["--writers", "3", "--server", "ws://127.0.0.1:1", "ws://127.0.0.1:2"],
     "--writers 3 needs at least 3 --server URLs (each writer draws from its own), got 2"),
    # Checked here, not by the local servers after they start (a multi-line failure that said to rerun).
    (["--num-envs", "0"], "--num-envs must be >= 1, got 0"),
    (["--commit-seconds", "nan"], "--commit-seconds must be > 0, got nan"),
    (["--commit-every", "0"], "--commit-every must be a positive integer, got 0"),
    (["--commit-seconds", "-5"], "--commit-seconds must be > 0, got -5.0"),
    # Malformed server URLs (a websockets traceback, or its words without the flag's), a missing expert (each local
    # server refused it after starting, and the recorder said to rerun), an unknown robot mesh.
    (["--server", "ws://"], "--server is a WebSocket URL, ws://HOST:PORT or wss://HOST:PORT; got 'ws://'"),
    (["--server", "ws://localhost:notaport"], "--server is a WebSocket URL"),
    (["--policy", "ppo:/nonexistent"], "no PPO checkpoint at '/nonexistent'"),
    (["--robot-mesh", "foo"], "unknown robot_mesh 'foo'; allowed: lite, full"),
    (["--server", "ws://127.0.0.1:1", "ws://127.0.0.1:1"], "--server ws://127.0.0.1:1 is given twice"),
    # One server spelt two ways passed that check and was drawn from twice.
    (["--server", "ws://127.0.0.1:1", "ws://localhost:1"], "--server ws://127.0.0.1:1 and ws://localhost:1 are one "
     "server; name each server once"),
    (["--server", "ws://Gpu-Box:1", "ws://gpu-box.:1/"], "--server ws://Gpu-Box:1 and ws://gpu-box.:1/ are one server"),
    (["--server", "wss://h", "ws://h:8", "ws://h:443"], "--server wss://h and ws://h:443 are one server"),
    (["--server", "ws://[::ffff:127.0.0.1]:1", "ws://127.0.0.1:1"], "are one server"),
    (["--ledger", "ledger.json"], "--ledger is for the writers `record --writers` starts: it needs their --server"),
])
def test_record_writers_each_need_a_server(extra, says, tmp_path, capsys):
    rc = main(["record", "--out", str(tmp_path / "rec"), "--episodes", "1", *extra])
    _one_line_error(capsys, rc, says)
    assert list(tmp_path.iterdir()) == []


def test_distinct_servers_are_not_taken_for_one():
    from vla_ladder.checks import check_distinct_ws_urls

    check_distinct_ws_urls(["ws://127.0.0.1:1", "ws://127.0.0.1:2", "ws://127.0.0.2:1", "ws://h:1", "ws://h:1/a",
                            "ws://h:1/b", "ws://g:1", "wss://g"], "--server")


def test_record_refuses_the_root_and_a_directory_that_holds_no_recording_leaving_nothing_beside_it(tmp_path, capsys):
    """`--out /` wrote its work directory as /..recording; a directory that is not a recording was refused after an
    empty .NAME.recording/ had been made beside it."""
    _one_line_error(capsys, main(["record", "--out", "/", "--episodes", "1"]), "--out '/' is the file system's root")
    assert not Path("/..recording").exists()
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "mine.txt").write_text("keep me")
    _one_line_error(capsys, main(["record", "--out", str(notes), "--episodes", "1"]), "is not a vla-ladder recording")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes"] and (notes / "mine.txt").read_text() == "keep me"


@pytest.mark.parametrize("state, says", [
    ("", "not a vla-ladder recording state (Expecting value: line 1 column 1 (char 0))"),  # cut short
    ('{"config": {"policy": "scripted"}}', "not a vla-ladder recording state (expected an object with config, "
     "counters and next_seed)"),
    ('{"format": 2, "config": {"policy": "scripted"}, "counters": {}, "next_seed": 0}',
     "not a vla-ladder recording state (KeyError: 'condition')"),
    ("[1]", "not a vla-ladder recording state (expected an object with config, counters and next_seed)"),
])
@pytest.mark.parametrize("command", ["check-dataset", "record"])
def test_a_damaged_recording_state_is_named_by_its_path(command, state, says, tmp_path, capsys):
    """json's message without the file's name, or a KeyError's traceback."""
    root = tmp_path / "data"
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text('{"codebase_version": "v3.0"}')
    (root / "meta" / "vla_ladder_recording.json").write_text(state)
    argv = [command, str(root)] if command == "check-dataset" else [command, "--out", str(root), "--episodes", "1"]
    _one_line_error(capsys, main(argv), f"error: {root / 'meta' / 'vla_ladder_recording.json'}: {says}")
    assert list(tmp_path.iterdir()) == [root] and sorted(p.name for p in (root / "meta").iterdir()) == \
        ["info.json", "vla_ladder_recording.json"]


def test_an_empty_cache_variable_is_unset_not_the_current_directory(tmp_path, monkeypatch):
    from vla_ladder.machine import cache_root

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("VLA_LADDER_CACHE", "")
    assert cache_root() == Path.home() / ".cache" / "vla-ladder"
    monkeypatch.setenv("VLA_LADDER_CACHE", str(tmp_path / "c"))
    assert cache_root() == tmp_path / "c"


def test_eval_batches_cpu_envs_one_per_core_and_not_with_workers(tmp_path, capsys):
    from vla_ladder.machine import cores

    base = ["eval", "--policy", "scripted", "--episodes", "1", "--out", str(tmp_path / "run")]
    _one_line_error(capsys, main([*base, "--num-envs", str(cores() + 1)]),
                    f"--num-envs must be at most the {cores()} CPU cores here, got {cores() + 1}")
    _one_line_error(capsys, main([*base, "--num-envs", "2", "--workers", "2"]), "choose one, --workers N")
    # A worker is a process with a simulator and a policy: a thousand were started when asked for (~600 MB each).
    _one_line_error(capsys, main([*base, "--workers", "100000"]), "--workers must be at most")
    _one_line_error(capsys, main(["record", "--out", str(tmp_path / "rec"), "--episodes", "1", "--workers",
                                  "100000"]), "each worker takes about 2 GiB; 0: one per core), got 100000")
    assert list(tmp_path.iterdir()) == []


def test_help_never_prints_a_secret_from_the_environment(monkeypatch, capsys):
    """The servers' secrets default to environment variables, read when the command runs, not when --help shows
    the defaults (it printed them before)."""
    from vla_ladder.recording.server import ServeConfig

    secret = "s3cr3t-from-env"
    monkeypatch.setenv("VLA_LADDER_TOKEN", secret)
    monkeypatch.setenv("VLA_LADDER_API_KEY", secret)
    for command in COMMANDS:
        with pytest.raises(SystemExit) as e:
            main([command, "--help"])
        assert e.value.code == 0
        out = capsys.readouterr().out
        assert "--" in out and secret not in out, command
    assert ServeConfig().token == secret  # still the default
    assert ServeConfig(token="given").token == "given"


@pytest.mark.parametrize("text, says", [
    ("[1, 2]", "expected an object with name, table, conditions and optionally episodes"),
    ('{"name": "x", "conditions": ["small_jitter/canonical/5"]}', "got ['conditions', 'name']"),
    ('{"name": "x", "table": "ladder", "conditions": ["small_jitter/canonical/5"], "episodes": "3"}',
     "episodes must be a positive integer, got '3'"),
    ('{"name": "x", "table": "ladder", "conditions": "small_jitter/canonical/5"}',
     "conditions: expected a list of conditions"),
    ("{not json", "not a JSON experiment config"),
])
def test_an_experiment_config_of_the_wrong_shape_is_named_in_one_line(text, says, tmp_path, capsys):
    """A custom experiment's JSON: a list, a missing table or a string count ended in TypeError tracebacks (raised
    while building the unknown-keys message, the dataclass constructor, a comparison), and a parse error did not
    name the file."""
    path = tmp_path / "mine.json"
    path.write_text(text)
    _one_line_error(capsys, main(["experiment", str(path), "--policy", "scripted", "--out", str(tmp_path / "x")]),
                    says)
    assert not (tmp_path / "x").exists()


def test_the_reviews_last_bad_inputs_are_refused_before_work(tmp_path, capsys):
    """A run given twice to report (shown twice), check-dataset's --min-expected nan (accepted) and its --out, and
    render's --out (checked after the checks, the replay, the simulator), an appearance swap with --instruct k (it
    swapped the seed's own target's colours, not the instructed object's)."""
    a, _ = _runs(tmp_path)
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = [
        (["report", str(a), str(a), "--out", str(tmp_path / "r.html")], "a run directory is given twice"),
        (["check-dataset", str(tmp_path / "nowhere"), "--min-expected", "nan"],
         "--min-expected must be a positive number, got nan"),
        (["check-dataset", str(a), "--out", str(afile / "summary.json")], "is a file where a directory is needed"),
        (["render", "--seed", "0", "--out", str(afile)], "--out"),
        (["eval", "--policy", "nearest", "--out", str(tmp_path / "e"), "--num-objects", "2", "--appearance", "swap",
          "--instruct", "1"], "appearance=swap swaps the colours of the seed's own instructed object"),
    ]
    for argv, words in cases:
        _one_line_error(capsys, main(argv), words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "afile", "b"] and afile.read_text() == "x"


def test_inputs_a_cli_review_found_accepted_are_refused_before_work(tmp_path, refused):
    """Found by a review that tried researchers' mistakes on every command (2026-11-27): each was accepted, or
    refused only after another policy's whole evaluation had run."""
    out, broken = tmp_path / "out", tmp_path / "broken"
    broken.mkdir()
    (broken / "config.json").write_text("{")
    (broken / "model.safetensors").write_bytes(b"")
    refused([
        (["eval", "--policy", f"lerobot:{broken}", "--out", str(out)],
         f"{broken}/config.json: not a JSON config (Expecting property name"),  # named no file
        (["eval", "--policy", f"lerobot:{broken}?n_action_steps=", "--out", str(out)],
         "option n_action_steps='' in lerobot:"),  # dropped silently, the checkpoint's horizon played
        (["eval", "--policy", f"lerobot:{broken}?n_action_steps", "--out", str(out)],
         "options are key=value pairs joined by '&'; allowed: n_action_steps, device"),
        (["eval", "--policy", "lerobot:?n_action_steps=4", "--out", str(out)],
         "gives options but no PATH before the '?'"),  # looked for a checkpoint in the current directory
        (["record", "--out", str(out), "--episodes", "2", "--policy", "random"],
         "--policy random is not an expert; allowed: scripted, ppo:PATH"),  # looped at 0% success, forever
        (["compare", str(out), str(out)], "is given twice; compare two different run directories"),
        (["placements", "--n", "3", "--first-seed", "4294967295", "--json", str(out / "p.json")],
         "--first-seed must be from 0 to 2**32 - --n = 4294967293"),  # seeds past numpy's were written
        (["probe", "instruction-swap", "--policy", "scripted", "--resamples", "1000000000", "--out", str(out)],
         "--resamples must be from 100 to 100000, got 1000000000"),
        (["experiment", "ladder", "--policy", "scripted", "lerobot:/nonexistent", "--episodes", "1", "--out",
          str(out)], "no LeRobot checkpoint at '/nonexistent'"),  # after scripted's evaluation
        (["experiment", "ladder", "--policy", "label=a,spec=scripted,label=b", "--out", str(out)],
         "label given twice"),  # kept b
        (["experiment", "ladder", "--policy", "label=modèle,spec=scripted", "label=modéle,spec=nearest", "--out",
          str(out)], "'modèle' and 'modéle' both name runs/mod_le"),  # said only "share a label"
    ], out)


def test_an_empty_path_is_refused_not_read_as_the_current_directory(tmp_path, monkeypatch, refused):
    """`--out ""` (an unset shell variable) was Path(""), that is ".": results went into the current directory."""
    monkeypatch.chdir(tmp_path)
    says = "--out is empty; give a path (an empty one would mean the current directory)"
    refused([(["eval", "--policy", "scripted", "--out", ""], says),
             (["record", "--episodes", "1", "--out="], says),
             (["study", "micro", "--out", " "], says),
             (["train-expert", "--out", ""], says)])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, says", [
    (["eval", "--polcy", "scripted"], "unknown flag --polcy (did you mean --policy?); `vla-ladder eval --help` lists"),
    (["eval", "--policy", "scripted", "--num_episodes", "3", "--zzz"], "unknown flag --num_episodes (and 1 more) "
                                                                       "(did you mean --episodes?)"),
    (["eval", "--policy", "scripted", "--episodes"], "--episodes needs a value;"),
    (["eval", "--policy", "scripted", "stray"], "unexpected argument 'stray' (a value must follow its flag)"),
    (["compare", "a"], "missing RUN_B;"),
    (["grid", "--out", "g", "--train.polcy-type", "act"], "unknown flag --train.polcy-type (did you mean "
                                                          "--train.policy-type?)"),
    # a positional's field name as a flag was "did you mean --runs?" for --runs; tyro's "name needs a value" hid
    # the unknown flag before a missing positional; int()'s own words named no flag's type
    (["report", "--runs", "r", "--out", "r.html"], "RUN... is given without a flag, not as --runs;"),
    (["compare", "--run-a", "a", "b"], "RUN_A is given without a flag, not as --run-a;"),
    (["probe", "--probe", "instruction-swap", "--policy", "scripted"], "unknown flag --probe; `vla-ladder probe"),
    (["eval", "--policy", "scripted", "--out", "r", "--episodes", "1.5"], "--episodes takes INT, got '1.5'"),
    (["eval", "--policy", "scripted", "--out", "r", "--first-seed=x"], "--first-seed takes INT, got 'x'"),
    (["eval", "--policy", "scripted", "--out", "r", "--switch-at", "1.5"], "--switch-at takes INT, got '1.5'"),
    (["eval", "--policy", "scripted", "--out", "r", "--noise-std", "1"], "unknown flag --noise-std; `vla-ladder"),
])
def test_a_flag_tyro_does_not_know_is_named_in_one_line(argv, says, tmp_path, monkeypatch, capsys):
    """An unknown or misspelt flag, a flag without its value, a stray value and a missing argument were drawn in
    tyro's box (9 lines or more for `--polcy`); each is one line naming the nearest flag where there is one."""
    monkeypatch.chdir(tmp_path)
    _one_line_error(capsys, main(argv), f"vla-ladder {argv[0]}: error: {says}")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, says", [
    (["eval"], "--policy SPEC and --out DIR are required (SPEC: scripted, "),
    (["probe", "paraphrase"], "--policy SPEC and --out DIR are required (SPEC: scripted, "),
    (["diagnose"], "--policy SPEC and --out DIR are required (SPEC: e.g. lerobot:"),
    (["probe"], "missing NAME, --policy, --out;"),
    (["train"], "missing --policy-type, --dataset, --out;"),
    (["experiment"], "missing NAME, --out, --policy;"),
    (["experiment", "ladder", "--policy", "scripted"], "missing --out;"),
])
def test_a_command_names_every_required_flag_left_out_at_once(argv, says, tmp_path, monkeypatch, capsys):
    """`eval` alone said "--out DIR is required", and given --out, "--policy SPEC is required"; `train` alone named
    --policy-type and --dataset, and --out only once they were given: flags a grid or a study fills in (a default
    of None) are named with tyro's missing ones, all in one line."""
    monkeypatch.chdir(tmp_path)
    _one_line_error(capsys, main(argv), f"vla-ladder {argv[0]}: error: {says}")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["compare", "experiment", "probe", "rebuild-provenance", "check-dataset", "study"])
def test_a_missing_positional_is_named_as_the_usage_line_spells_it(command, capsys):
    """`compare` alone said "missing RUN_A, RUN_B" under a usage line of "PATH PATH", `check-dataset` "missing
    DATASET" under "DIR", `experiment` and `study` NAME and CONFIG under "STR": the words differ no more."""
    with pytest.raises(SystemExit):
        main([command, "--help"])
    usage = capsys.readouterr().out.splitlines()[0]
    err = _one_line_error(capsys, main([command]), f"vla-ladder {command}: error: missing ")
    named = err.split("missing ", 1)[1].split(";")[0].split(", ")
    positionals = [n for n in named if not n.startswith("-")]
    assert positionals and all(f" {n}" in usage for n in positionals), (usage, err)


def test_render_refuses_an_unknown_object_set_before_the_simulator(tmp_path):
    """`render --object-set foo` was refused by the env once built (5 s of imports on the 2-core machine); render's
    config now makes eval's check, before the simulator loads."""
    from vla_ladder.task.render import RenderConfig

    with pytest.raises(ValueError, match="unknown object_set 'foo'; allowed: auto, ycb, standin"):
        RenderConfig(seed=0, out=tmp_path / "r", object_set="foo")
    assert list(tmp_path.iterdir()) == []



def test_help_text_flows_as_paragraphs_not_as_the_source_lines():
    """tyro kept the break at the end of every continuation line of an indented field docstring, so each flag's help
    broke where the source line did: `(0: one per` / `core, capped by memory)`."""
    out = subprocess.run([sys.executable, "-m", "vla_ladder.cli", "eval", "--help"], capture_output=True, text=True,
                         env={**os.environ, "COLUMNS": "300"}, check=True).stdout
    workers = next(line for line in out.splitlines() if "--workers" in line)
    assert "(0: one per core, capped by memory); any number gives the same episodes" in workers

def test_every_command_names_the_sim_backends_alike(tmp_path, capsys):
    """eval, train-expert and the LeRobot env check the backend with one function (three copies said it three ways:
    `sim backend`, and the allowed ones in two orders)."""
    for argv in (["eval", "--policy", "scripted", "--sim-backend", "gpu", "--out", str(tmp_path / "e")],
                 ["train-expert", "--sim-backend", "gpu", "--out", str(tmp_path / "p")]):
        _one_line_error(capsys, main(argv), f"vla-ladder {argv[0]}: error: --sim-backend: unknown sim_backend 'gpu'; "
                                            "allowed: physx_cpu, physx_cuda")
    assert list(tmp_path.iterdir()) == []
