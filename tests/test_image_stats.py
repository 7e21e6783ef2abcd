"""The cameras' running statistics (recording/image_stats.py): LeRobot's RunningQuantileStats state, computed
from value counts. Compared with LeRobot's own class on the same frames."""

import numpy as np
import pytest
from lerobot.datasets import compute_stats

from vla_ladder.contract import IMAGE_SHAPE
from vla_ladder.recording import image_stats
from vla_ladder.recording.image_stats import CountingQuantileStats

LEROBOTS = CountingQuantileStats.__base__
"""LeRobot's own RunningQuantileStats (the module attribute is CountingQuantileStats once a writer installed it)"""


def camera_frames(seed: int, low: int, high: int, n: int = 12) -> list[np.ndarray]:
    """n (H*W, 3) uint8 frames: a gradient between low and high with noise that grows along the episode, so the
    range widens frame by frame (the histograms are rebinned) and the values are far from uniform."""
    rng = np.random.default_rng(seed)
    h, w, _ = IMAGE_SHAPE
    base = np.stack(np.broadcast_arrays(np.linspace(low, high, w)[None], np.linspace(high, low, h)[:, None],
                                        np.full((h, w), (low + high) / 2)), axis=-1)
    return [np.clip(base + rng.normal(0, 1 + t * (high - low) / 20, base.shape), low, high).round()
            .astype(np.uint8).reshape(-1, 3) for t in range(n)]


def run(cls, frames) -> tuple:
    stats = cls()
    for frame in frames:
        stats.update(frame)
    return stats, stats.get_statistics()


@pytest.mark.parametrize("low,high", [(0, 255), (100, 110), (200, 201)])
def test_counting_statistics_are_lerobots_with_an_exact_std(low, high):
    frames = camera_frames(low, low, high)
    theirs, a = run(LEROBOTS, frames)
    mine, b = run(CountingQuantileStats, frames)
    for h1, h2, e1, e2 in zip(theirs._histograms, mine._histograms, theirs._bin_edges, mine._bin_edges):
        assert np.array_equal(h1, h2) and np.array_equal(e1, e2)
    for key in ("min", "max", "count", "q01", "q10", "q50", "q90", "q99"):
        assert np.array_equal(a[key], b[key]) and a[key].dtype == b[key].dtype, key
    assert np.allclose(a["mean"], b["mean"], rtol=1e-6, atol=0) and a["mean"].dtype == b["mean"].dtype
    pixels = np.concatenate(frames).astype(np.float64)
    truth = pixels.std(axis=0)
    assert np.allclose(b["std"], truth, rtol=1e-6, atol=0) and np.allclose(b["mean"], pixels.mean(0), rtol=1e-7)
    if high - low <= 10:  # LeRobot's float32 mean of squares: its std is off by several percent on a narrow range
        assert np.abs(a["std"] / truth - 1).max() > 0.03


@pytest.mark.filterwarnings("ignore:Mean of empty slice", "ignore:invalid value encountered")
def test_other_inputs_take_lerobots_own_update():
    rng = np.random.default_rng(0)
    batches = [rng.normal(size=(200, 7)).astype(np.float32) for _ in range(3)]
    _, a = run(LEROBOTS, batches)
    _, b = run(CountingQuantileStats, batches)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    for cls in (LEROBOTS, CountingQuantileStats):  # an empty batch is refused as LeRobot refuses it
        with pytest.raises(ValueError, match="zero-size array"):
            cls().update(np.zeros((0, 3), np.uint8))
    # uint8 frames after a float batch: LeRobot's running moments from then on, the same as LeRobot's class
    frames = camera_frames(3, 0, 255, n=3)
    mixed = [frames[0].astype(np.float32), *frames[1:]]
    _, a = run(LEROBOTS, mixed)
    _, b = run(CountingQuantileStats, mixed)
    assert np.array_equal(a["min"], b["min"]) and np.array_equal(a["q50"], b["q50"])
    truth = np.concatenate(mixed).astype(np.float64).std(axis=0)
    assert np.allclose(b["std"], truth, rtol=2e-3) and np.allclose(a["std"], truth, rtol=2e-3)


def test_install_puts_it_where_the_encoder_threads_look_and_uninstall_takes_it_back():
    before = compute_stats.RunningQuantileStats
    try:
        assert image_stats.install() and compute_stats.RunningQuantileStats is CountingQuantileStats
        assert image_stats.install()  # twice is once
        image_stats.uninstall()
        assert compute_stats.RunningQuantileStats is LEROBOTS
    finally:
        compute_stats.RunningQuantileStats = before
