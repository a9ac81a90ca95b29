"""Latency percentiles of the service's health: exact over the recent window, within one bin over the whole run."""

import numpy as np
import pytest

from roadgrip.cloud.pipeline.latency import LatencyRecorder


def test_percentiles_since_start_lie_within_one_bin_above_the_exact_ones():
    rng = np.random.default_rng(0)
    values = rng.lognormal(np.log(900.0), 0.4, 50_000)
    recorder = LatencyRecorder(window=1_000, bin_ms=10.0)
    for chunk in np.array_split(values, 37):
        recorder.add(chunk)
    total = recorder.since_start()
    assert total["n"] == 50_000 and total["over_max"] == 0
    for key, q in (("p50_ms", 50), ("p99_ms", 99)):
        exact = np.percentile(values, q)
        assert exact - 0.1 <= total[key] <= exact + 10.0 + 0.1
    recent = recorder.recent()  # the last 1,000 only
    assert recent["n"] == 1_000
    assert recent["p50_ms"] == pytest.approx(np.percentile(values[-1_000:], 50))


def test_the_whole_run_is_remembered_while_the_window_forgets():
    recorder = LatencyRecorder(window=100, bin_ms=10.0)
    recorder.add(np.full(900, 5_000.0))  # a slow start ...
    recorder.add(np.full(100, 50.0))  # ... then fast
    assert recorder.recent()["p99_ms"] == 50.0
    assert recorder.since_start()["p50_ms"] == 5_010.0  # the upper edge of the bin holding 5,000 ms


def test_beyond_the_histogram_and_before_zero():
    recorder = LatencyRecorder(bin_ms=10.0, max_ms=1_000.0)
    recorder.add(np.array([-20.0, 5_000.0, 7_000.0]))
    total = recorder.since_start()
    assert total["over_max"] == 2 and total["p99_ms"] == 1_000.0 and total["n"] == 3
    assert recorder.recent()["n"] == 3
    assert LatencyRecorder().since_start() == {"p50_ms": None, "p99_ms": None, "n": 0, "over_max": 0}


def test_arguments_are_checked():
    with pytest.raises(ValueError, match="bin_ms"):
        LatencyRecorder(bin_ms=0)
