"""LeRobot's running image statistics, computed from each frame's counts of its 256 values.

LeRobot's streaming video encoder (lerobot.datasets.video_utils._CameraEncoderThread, one thread per camera)
feeds every frame to RunningQuantileStats for the episode's image statistics: moments of a (H*W, 3) float32
array reduced along its long axis, min and max the same way, and a Python loop over its 5000 histogram bins
whenever the range grows. On a 256x256 camera that costs ~5 ms a frame, 0.47 CPU s of the writer's 0.73 a demo
on the 2-core machine (the AV1 encoder itself: 0.19), and the writer is what bounds recording on the 16-core
GPU machine (docs/benchmarks.md, "The GPU machine").

A frame's pixels are uint8, so everything RunningQuantileStats keeps follows from each channel's counts of the
values 0-255 (np.bincount): min and max, the mean and the mean of squares, and the histogram (each value's
count added to the bin np.histogram would put it in). CountingQuantileStats keeps the same state that way, about
ten times faster: the histograms, bin edges, min and max, and so the quantiles, are LeRobot's bit for bit, the
mean agrees to float32 rounding (tests/test_image_stats.py). Its mean and std come from exact integer sums of x
and x^2: LeRobot's float32 running mean of squares leaves std = sqrt(E[x^2] - E[x]^2) to cancellation, 9-13% off
on frames whose values span ten grey levels, all of it (0 for 0.5) on frames of two adjacent levels. Any other
input (not uint8, or empty) goes to LeRobot's own update, and a statistic that has seen one keeps LeRobot's
running moments from then on.

`install()` puts it where the encoder thread looks the class up (lerobot.datasets.compute_stats, read at each
episode's start); the recorder's writer processes call it before they open a dataset. In those processes it also
serves LeRobot's other users of the class (compute_stats.get_feature_stats: the sampled images of an image-mode
recording, and the numeric features), which hand it float arrays, so LeRobot's update.
"""

from __future__ import annotations

import logging

import numpy as np
from lerobot.datasets import compute_stats
from lerobot.datasets.compute_stats import RunningQuantileStats

log = logging.getLogger(__name__)

_VALUES = np.arange(256, dtype=np.float64)
_SQUARES = _VALUES**2
_INTEGERS = np.arange(256, dtype=object)  # Python ints: sums of squares over a long recording stay exact
_LEROBOTS = RunningQuantileStats
# What CountingQuantileStats relies on of LeRobot's class; without it, install() leaves LeRobot's in place.
_RELIED_ON = ("_adjust_histograms", "_compute_quantiles", "get_statistics")
_STATE = ("_count", "_mean", "_mean_of_squares", "_min", "_max", "_histograms", "_bin_edges", "_num_quantile_bins")


class CountingQuantileStats(RunningQuantileStats):
    """RunningQuantileStats whose update of uint8 batches works from per-channel value counts (module docstring)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._sums: list | None = [0, 0]  # exact sums of x and x^2 per channel while every batch was uint8

    def update(self, batch: np.ndarray) -> None:
        if batch.dtype != np.uint8 or batch.size == 0:
            self._sums = None
            return super().update(batch)
        batch = batch.reshape(-1, batch.shape[-1])
        num_elements, vector_length = batch.shape
        counts = np.stack([np.bincount(batch[:, i], minlength=256) for i in range(vector_length)])
        present = counts > 0
        low = present.argmax(axis=1).astype(np.float32)
        high = (255 - present[:, ::-1].argmax(axis=1)).astype(np.float32)
        # float32 like LeRobot's np.mean of float32 pixels, so the running state keeps its dtypes
        batch_mean = (counts @ _VALUES / num_elements).astype(np.float32)
        batch_mean_of_squares = (counts @ _SQUARES / num_elements).astype(np.float32)
        if self._sums is not None:
            exact = counts.astype(object)
            self._sums = [self._sums[0] + exact @ _INTEGERS, self._sums[1] + exact @ (_INTEGERS * _INTEGERS)]
        if self._count == 0:
            self._mean, self._mean_of_squares, self._min, self._max = batch_mean, batch_mean_of_squares, low, high
            self._histograms = [np.zeros(self._num_quantile_bins) for _ in range(vector_length)]
            self._bin_edges = [np.linspace(self._min[i] - 1e-10, self._max[i] + 1e-10, self._num_quantile_bins + 1)
                               for i in range(vector_length)]
        else:
            if vector_length != self._mean.size:
                raise ValueError("The length of new vectors does not match the initialized vector length.")
            changed = np.any(high > self._max) or np.any(low < self._min)
            self._max = np.maximum(self._max, high)
            self._min = np.minimum(self._min, low)
            if changed:
                self._adjust_histograms()
        self._count += num_elements
        self._mean += (batch_mean - self._mean) * (num_elements / self._count)
        self._mean_of_squares += (batch_mean_of_squares - self._mean_of_squares) * (num_elements / self._count)
        for i in range(vector_length):
            # the 256 values weighted by their counts fall in the bins the pixels themselves would
            self._histograms[i] += np.histogram(_VALUES, bins=self._bin_edges[i], weights=counts[i])[0]

    def get_statistics(self) -> dict[str, np.ndarray]:
        stats = super().get_statistics()
        if self._sums is not None:  # mean and std from the exact sums (n * sum x^2 - (sum x)^2 is an integer)
            n, total, squares = self._count, self._sums[0], self._sums[1]
            stats["mean"] = np.array([t / n for t in total], dtype=np.float32)
            stats["std"] = np.array([np.sqrt((n * q - t * t) / (n * n)) for t, q in zip(total, squares)],
                                    dtype=np.float32)
        return stats

    def _adjust_histograms(self) -> None:
        """LeRobot's rebinning (each old bin's count to the new bin holding its centre), vectorised: np.add.at
        adds in the order its loop does, so the result is the same to the last bit."""
        for i in range(len(self._histograms)):
            old_edges, old_hist = self._bin_edges[i], self._histograms[i]
            padding = (self._max[i] - self._min[i]) * 1e-10
            new_edges = np.linspace(self._min[i] - padding, self._max[i] + padding, self._num_quantile_bins + 1)
            filled = old_hist > 0
            centres = ((old_edges[:-1] + old_edges[1:]) / 2)[filled]
            bins = np.clip(np.searchsorted(new_edges, centres) - 1, 0, self._num_quantile_bins - 1)
            new_hist = np.zeros(self._num_quantile_bins)
            np.add.at(new_hist, bins, old_hist[filled])
            self._histograms[i] = new_hist
            self._bin_edges[i] = new_edges


def install() -> bool:
    """Make LeRobot's encoder threads in this process use CountingQuantileStats; False (and LeRobot's own class
    left in place) when the installed LeRobot's class lacks what it relies on."""
    if compute_stats.RunningQuantileStats is CountingQuantileStats:
        return True
    state = vars(_LEROBOTS())
    missing = [name for name in _RELIED_ON if not hasattr(_LEROBOTS, name)] + [s for s in _STATE if s not in state]
    if missing or compute_stats.RunningQuantileStats is not _LEROBOTS:
        log.warning("LeRobot's RunningQuantileStats changed (%s): its own image statistics stay in use",
                    ", ".join(missing) or "replaced by another class")
        return False
    compute_stats.RunningQuantileStats = CountingQuantileStats
    return True


def uninstall() -> None:
    """LeRobot's own class back where install() put this one (benchmarks/record_speed.py measures the writer
    with both)."""
    if compute_stats.RunningQuantileStats is CountingQuantileStats:
        compute_stats.RunningQuantileStats = _LEROBOTS
