"""`roadgrip bench estimate`: streaming throughput and per-update latency of the estimators, on one core.

Each estimator is fed a stream of wire-format samples (dicts, as the cloud hands them over) of one simulated vehicle,
the paper preset's run `paper-decreasing-circular-e2` repeated end to end (it starts and ends at standstill, so the
repeats join smoothly; timestamps keep counting). `update` is timed call by call after a warm-up (which also
triggers numba's compilation or cache load); torch is held to one thread while timing, so that the numbers are per core.
The batch path (`estimate_batch` over the run) is timed too. With channel sets (issue 26: what each channel costs), the
run is simulated with every optional channel (CONTRACTS 3.1: GNSS speed, drive and brake force, steering torques; the
simulator's error models) and each set streams the channels the physics benchmark's set of that name keeps
(physics_benchmark.CHANNEL_SETS: base, gnss, forces, steering, all), the others null, as a car that does not send them.
"""

from __future__ import annotations

import time

import numpy as np

from roadgrip.estimators.base import Estimator
from roadgrip.evaluation.physics_benchmark import CHANNEL_SETS, blank_channels

BENCH_RUN = "paper-decreasing-circular-e2"
WARMUP_UPDATES = 200
DEFAULT_NAMES = ("pmf", "ekf", "ukf", "default")


def bench_estimator_by_name(name: str) -> Estimator:
    """'fusion' (ekf + the default model), or anything `load_estimator` takes, as the cloud runs it (guarded)."""
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.estimators.physics import physics_estimator

    if name == "fusion":
        from roadgrip.estimators.fusion import FusionEstimator

        return FusionEstimator(physics_estimator("ekf"), load_estimator("default"))
    return load_estimator(name)


# the physics benchmark's channel sets that blank channels of one simulated run (gnss-degraded simulates another)
BENCH_CHANNEL_SETS = tuple(name for name in CHANNEL_SETS if name != "gnss-degraded")


def stream_samples(n_updates: int, channel_set: str | None = None):
    """(samples as dicts, the run's table, its vehicle): n_updates samples of the bench run, repeated; with a channel
    set (BENCH_CHANNEL_SETS), the optional channels it keeps, the others null."""
    import dataclasses

    from roadgrip.sim.presets import paper_scenarios
    from roadgrip.sim.simulate import simulate

    if channel_set is not None and channel_set not in BENCH_CHANNEL_SETS:
        raise ValueError(f"unknown channel set {channel_set!r}: use one of {', '.join(BENCH_CHANNEL_SETS)}")
    scenario = next(s for s in paper_scenarios() if s.run_id == BENCH_RUN)
    if channel_set is not None:
        scenario = dataclasses.replace(scenario, effects=scenario.effects.with_channels())
    table = simulate([scenario])
    if channel_set is not None:
        table = blank_channels(table, CHANNEL_SETS[channel_set])
    rows = table.select(
        [
            c
            for c in table.column_names
            if c not in ("run_id", "condition", "road", "manoeuvre", "vehicle", "tire_model")
        ]
    ).to_pylist()
    span_ms = int(rows[-1]["timestamp_ms"] - rows[0]["timestamp_ms"]) + 100
    samples = []
    for k in range(n_updates):
        sample = dict(rows[k % len(rows)])
        sample["timestamp_ms"] += (k // len(rows)) * span_ms
        samples.append(sample)
    return samples, table, scenario.vehicle


def bench_estimators(names=DEFAULT_NAMES, n_updates: int = 20000, channel_sets: tuple[str, ...] = ()) -> list[dict]:
    """For each estimator name: streaming updates per second on one core, per-update latency (median and 99th
    percentile, microseconds), and batch rows per second. `n_updates` timed updates each (at least 100); with
    `channel_sets`, each estimator once per set (rows `<name> [<set>]`), else on the run without channels."""
    if n_updates < 100:
        raise ValueError(f"n_updates must be at least 100, got {n_updates!r}")
    import torch

    streams = [(c, stream_samples(n_updates + WARMUP_UPDATES, c)) for c in channel_sets or (None,)]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    results = []
    try:
        for channel_set, (samples, table, vehicle) in streams:
            for name in names:
                label = name if channel_set is None else f"{name} [{channel_set}]"
                results.append(_bench_one(name, label, samples, table, vehicle, n_updates))
    finally:
        torch.set_num_threads(threads)
    return results


def _bench_one(name: str, label: str, samples: list[dict], table, vehicle, n_updates: int) -> dict:
    """One estimator's streaming and batch timings over a stream (its first WARMUP_UPDATES samples untimed), as the
    row `label`."""
    estimator = bench_estimator_by_name(name)
    state = estimator.start(vehicle)
    for sample in samples[:WARMUP_UPDATES]:
        estimator.update(state, sample)
    latencies = np.empty(n_updates)
    clock = time.perf_counter_ns
    start = clock()
    for k, sample in enumerate(samples[WARMUP_UPDATES:]):
        t0 = clock()
        estimator.update(state, sample)
        latencies[k] = clock() - t0
    total_s = (clock() - start) / 1e9
    segments = np.zeros(table.num_rows, dtype=np.int64)
    estimator.estimate_batch(table, segments, vehicle)  # warm
    t0 = time.perf_counter()
    repeats = 5
    for _ in range(repeats):
        estimator.estimate_batch(table, segments, vehicle)
    batch_s = (time.perf_counter() - t0) / repeats
    return {
        "estimator": label,
        "updates": n_updates,
        "updates_per_s": n_updates / total_s,
        "latency_median_us": float(np.median(latencies)) / 1e3,
        "latency_p99_us": float(np.percentile(latencies, 99)) / 1e3,
        "batch_rows_per_s": table.num_rows / batch_s,
        "threads": 1,
    }


def format_bench(results: list[dict]) -> str:
    """The results as a Markdown table."""
    lines = [
        "| estimator | updates/s (1 core) | latency median (us) | latency p99 (us) | batch rows/s |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for r in results:
        lines.append(
            f"| {r['estimator']} | {r['updates_per_s']:,.0f} | {r['latency_median_us']:.1f} | "
            f"{r['latency_p99_us']:.1f} | {r['batch_rows_per_s']:,.0f} |"
        )
    return "\n".join(lines)
