"""Units of a study or grid: child processes with logs and done markers, locally and on a local Ray."""

import json

import pytest

from vla_ladder.experiments.units import Unit, is_done, run_units, run_units_on_ray

pytestmark = pytest.mark.slow  # each unit is a child process running the simulator


def _eval_unit(tmp_path, policy: str, name: str) -> Unit:
    return Unit(name, "eval", "vla_ladder.experiments.units:eval_unit",
                {"policy": policy, "out": str(tmp_path / name), "episodes": 1, "workers": 1,
                 "grid": {"regimes": ["small_jitter"], "splits": ["canonical"], "num_objects": [2]}})


def test_units_run_in_children_are_marked_done_and_skipped(tmp_path):
    units = [_eval_unit(tmp_path, "layout-prior", "a"), _eval_unit(tmp_path, "random", "b")]
    results = run_units(units, tmp_path)
    assert results["a"]["conditions"]["small_jitter/canonical/2"]["n"] == 1
    assert all(is_done(tmp_path, u) for u in units)
    assert "eval layout-prior" in (tmp_path / "logs" / "a.log").read_text()
    stamp = (tmp_path / "units" / "a.json").stat().st_mtime_ns
    assert run_units(units, tmp_path) == results  # nothing runs again
    assert (tmp_path / "units" / "a.json").stat().st_mtime_ns == stamp
    elsewhere = [Unit(u.id, u.stage, u.function, {**u.config, "workers": 2, "num_envs": 2}) for u in units]
    assert run_units(elsewhere, tmp_path) == results  # other process counts play the same episodes: skipped
    assert (tmp_path / "units" / "a.json").stat().st_mtime_ns == stamp
    more = Unit("a", "eval", units[0].function, {**units[0].config, "episodes": 2})
    assert not is_done(tmp_path, more)  # a change to what it computes runs it again
    broken = _eval_unit(tmp_path, "teleport", "c")
    with pytest.raises(RuntimeError, match="unit c failed.*c.log"):
        run_units([broken], tmp_path)
    assert not is_done(tmp_path, broken)


def test_the_same_units_run_as_ray_tasks(tmp_path):
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        units = [_eval_unit(tmp_path, "layout-prior", "a"), _eval_unit(tmp_path, "random", "b")]
        results = run_units_on_ray(units, tmp_path)
        local = json.loads((tmp_path / "a" / "summary.json").read_text())["conditions"]
        assert results["a"]["conditions"]["small_jitter/canonical/2"]["success"] == \
            local["small_jitter/canonical/2"]["success"]
        assert all(is_done(tmp_path, u) for u in units)
        assert run_units_on_ray(units, tmp_path) == results  # resumed: both skipped
    finally:
        ray.shutdown()
