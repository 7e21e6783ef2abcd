import json
import os
from pathlib import Path

import pytest

from vla_ladder import files
from vla_ladder.files import atomic_path, write_json


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "sub" / "summary.json"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash mid-write")
    assert not target.exists() and os.listdir(target.parent) == []


def test_atomic_write_replaces_whole_and_respects_umask(tmp_path):
    target = tmp_path / "r.json"
    write_json(target, {"a": 1})
    write_json(target, {"a": 2})
    assert target.read_text().strip().endswith("}") and '"a": 2' in target.read_text()
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_an_atomic_write_leaves_the_umask_alone(tmp_path, monkeypatch):
    """It set the umask to 0 to read it: a file another thread created meanwhile was writable by everyone."""
    calls = []
    monkeypatch.setattr(os, "umask", lambda mask: calls.append(mask) or 0o022)
    write_json(tmp_path / "r.json", {"a": 1})
    assert calls == [] and (tmp_path / "r.json").stat().st_mode & 0o777 == 0o666 & ~files._umask()


def test_a_file_or_directory_of_the_longest_name_is_written_through_a_temporary_name_that_fits(tmp_path):
    """The temporary sibling's name was `.NAME.` + 8 characters + `.tmp`: a valid 245-character name made one
    too long for the file system, "File name too long" once the work was done."""
    for name in ("r" * 245 + ".json", "é" * 127):  # 250 and 254 bytes, each a valid name
        write_json(tmp_path / name, {"a": 1})
        assert json.loads((tmp_path / name).read_text()) == {"a": 1}
        (tmp_path / name).unlink()
        with files.atomic_dir(tmp_path / name) as tmp:
            (tmp / "config.json").write_text("{}")
        assert (tmp_path / name / "config.json").is_file()
        files.remove_dir(tmp_path / name)
    assert list(tmp_path.iterdir()) == []



def test_an_output_of_the_longest_name_is_locked_by_a_sibling_that_fits(tmp_path):
    """The lock beside an output was `.NAME.lock`: a valid 250-byte directory name made one too long to open, and
    every command refused that --out with "File name too long". Long names are cut and told apart by a hash."""
    long_a, long_b = tmp_path / ("r" * 240 + "a" * 10), tmp_path / ("r" * 240 + "b" * 10)
    assert files.lock_path(long_a) != files.lock_path(long_b)
    assert len(os.fsencode(files.lock_path(long_a).name)) <= 255
    assert files.lock_path(tmp_path / "run").name == ".run.lock"  # a name that fits is kept whole
    with files.writing(long_a, "test"):
        with pytest.raises(ValueError, match="another test is writing"):
            with files.writing(long_a, "test"):
                pass
        with files.writing(long_b, "test"):  # another output, another lock
            pass
    assert list(tmp_path.iterdir()) == []

def test_atomic_write_syncs_the_data_before_the_rename_and_the_rename_after(tmp_path, monkeypatch):
    """What a host crash needs (a kill does not): the temp file's bytes on disk before it takes the name, then the
    directory entry. Watched through the calls the kernel gets, since a crash cannot be staged in a test."""
    events, fsync, replace = [], os.fsync, os.replace

    def watched_fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"), os.fstat(fd).st_size))
        fsync(fd)

    def watched_replace(src, dst):
        events.append(("replace", str(src), str(dst)))
        replace(src, dst)

    monkeypatch.setattr(os, "fsync", watched_fsync)
    monkeypatch.setattr(os, "replace", watched_replace)
    target = tmp_path / "summary.json"
    write_json(target, {"a": 1})
    (_, synced, size), (_, src, dst), (_, directory, _) = events
    assert synced == src != dst == str(target) and size == target.stat().st_size > 0
    assert directory == str(tmp_path)


def test_provenance_names_the_checkouts_version_when_run_uninstalled(monkeypatch):
    import importlib.metadata
    import tomllib

    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", not_installed)  # as on the GPU kit: src/ on the path
    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert files.provenance()["vla-ladder"] == pyproject["project"]["version"]
    assert files.provenance()["torch"] is None


def test_provenance_says_which_simulator_build_and_cpu_measured_it():
    """The same seed replays bit for bit on one machine; another CPU or SAPIEN build may flip a marginal grasp (the
    reference ladder's layout-prior: 18/20 small-jitter successes on 2026-11-24's machine, 17/20 here)."""
    import importlib.metadata

    prov = files.provenance("standin")
    assert prov["sapien"] == importlib.metadata.version("sapien")
    assert prov["numpy"] == importlib.metadata.version("numpy")
    assert prov["object_set"] == "standin"
    if Path("/proc/cpuinfo").is_file():
        assert prov["cpu"] and prov["cpu"].split(", ")[0] in Path("/proc/cpuinfo").read_text()


def test_a_directory_is_built_whole_or_not_at_all_and_removed_the_same_way(tmp_path):
    """atomic_dir: a build that fails leaves nothing under the name (the tiny VLM's directory was trusted once two of
    its four files were written); one that finishes appears with all its files. remove_dir: the name goes first."""
    target = tmp_path / "vlm"
    with pytest.raises(RuntimeError):
        with files.atomic_dir(target) as tmp:
            (tmp / "config.json").write_text("{}")
            raise RuntimeError("killed before processor_config.json")
    assert not target.exists() and list(tmp_path.iterdir()) == []
    with files.atomic_dir(target) as tmp:
        for name in ("config.json", "processor_config.json"):
            (tmp / name).write_text("{}")
    assert sorted(p.name for p in target.iterdir()) == ["config.json", "processor_config.json"]
    with files.atomic_dir(target) as tmp:  # built meanwhile by another process: its copy stays
        (tmp / "other.json").write_text("{}")
    assert sorted(p.name for p in target.iterdir()) == ["config.json", "processor_config.json"]
    assert [p.name for p in tmp_path.iterdir()] == ["vlm"]

    def killed(path, *args, **kwargs):
        raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as mp, pytest.raises(KeyboardInterrupt):
        mp.setattr(files.shutil, "rmtree", killed)  # killed while deleting: the name is already gone
        files.remove_dir(target)
    assert not target.exists()
    (tmp_path / "run").mkdir()
    files.remove_dir(tmp_path / "run")
    assert not (tmp_path / "run").exists()


def strict_json(text: str):
    """`text` parsed as JSON.parse, jq and most languages' parsers read it: NaN and Infinity refused."""
    return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(f"not strict JSON: {c}")))


def test_results_are_strict_json_with_undefined_numbers_as_null(tmp_path):
    """Python's json wrote NaN (a rate over no scenes) as a bare NaN token, which JSON.parse, jq and most other
    languages' parsers refuse: write_json writes null for every non-finite number, numpy's and those in arrays too;
    number() reads null back as the NaN it was."""
    import numpy as np

    from vla_ladder.files import dumps, number, plain

    data = {"value": float("nan"), "ci95": (np.float64("nan"), float("inf")), "f32": np.float32("nan"),
            "neg": -np.inf, "array": np.array([0.5, np.nan]), "nested": [{"x": np.float32(0.25)}], "n": np.int64(3),
            "ok": True, "path": Path("a/b"), "none": None}
    expected = {"value": None, "ci95": [None, None], "f32": None, "neg": None, "array": [0.5, None],
                "nested": [{"x": 0.25}], "n": 3, "ok": True, "path": "a/b", "none": None}
    assert strict_json(write_json(tmp_path / "r.json", data).read_text()) == expected
    assert strict_json(dumps(data)) == expected and plain(data) == expected
    assert np.isnan(number(None)) and number(0.5) == 0.5 and number("x") == "x"
    # Files written before hold NaN itself, which Python's json still reads.
    assert np.isnan(json.loads('{"value": NaN}')["value"])
