"""simulate(): scenarios in, a table of telemetry (wire format v1) and ground truth out (CONTRACTS 3.3)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pyarrow as pa

from roadgrip.data.schema import CHANNEL_NAMES, DATASET_SCHEMA, WHEELS
from roadgrip.sim.integrator import CHANNELS, run_batch
from roadgrip.sim.scenario import SAMPLE_PERIOD_S, Scenario, pack
from roadgrip.sim.sensors import SensorModel

DEFAULT_START_EPOCH_MS = 1_767_225_600_000  # 2026-01-01T00:00:00Z
BATCH_RUNS = 64  # runs integrated per compiled call: large enough to keep both cores busy, small enough for progress


def simulate_truth(scenarios: Sequence[Scenario], progress: Callable[[int], None] | None = None) -> list[np.ndarray]:
    """Integrate the scenarios; returns per run an array (samples, channels) of the true signals (integrator.CHANNELS)."""
    results: list[np.ndarray | None] = [None] * len(scenarios)
    by_length: dict[int, list[int]] = {}
    for i, s in enumerate(scenarios):
        by_length.setdefault(s.n_samples, []).append(i)
    for n_samples, indices in by_length.items():
        for start in range(0, len(indices), BATCH_RUNS):
            chunk = indices[start : start + BATCH_RUNS]
            out = run_batch(pack([scenarios[i] for i in chunk]), n_samples, SAMPLE_PERIOD_S)
            for j, i in enumerate(chunk):
                results[i] = out[j]
            if progress is not None:
                progress(len(chunk))
    return results


def simulate(
    scenarios: Sequence[Scenario],
    sensors: SensorModel = SensorModel(),
    start_epoch_ms: int = DEFAULT_START_EPOCH_MS,
    progress: Callable[[int], None] | None = None,
) -> pa.Table:
    """Simulate the scenarios and measure them with the sensor model (each run's noise seeded by its scenario's seed)."""
    if not scenarios:
        raise ValueError("simulate() needs at least one scenario")
    ids = [s.run_id for s in scenarios]
    if len(set(ids)) != len(ids):
        raise ValueError(
            f"scenario run_id values must be unique, got duplicates {sorted({i for i in ids if ids.count(i) > 1})}"
        )
    truths = simulate_truth(scenarios, progress)
    index = {name: k for k, name in enumerate(CHANNELS)}
    tables = []
    for scenario, truth in zip(scenarios, truths):
        signal = {name: truth[:, k] for name, k in index.items()}
        rng = np.random.default_rng(scenario.seed)
        measured = sensors.measure(
            signal,
            scenario.vehicle.steering_ratio,
            SAMPLE_PERIOD_S,
            rng,
            effects=scenario.effects,
            vehicle=scenario.vehicle,
            tire=scenario.tire,
        )
        n = truth.shape[0]
        for name in CHANNEL_NAMES:  # an optional channel not sent (off, a GNSS outage) is null, as on the wire
            measured[name] = pa.array(measured[name], pa.float64(), mask=np.isnan(measured[name]))
        columns = {
            "vehicle_id": [f"sim-{scenario.run_id}"] * n,
            "timestamp_ms": start_epoch_ms + np.round(signal["t_s"] * 1000.0).astype(np.int64),
            **measured,
            "abs_active": signal["abs_active"] > 0.5,
            "acc_active": signal["acc_active"] > 0.5,
            "tcs_active": signal["tcs_active"] > 0.5,
            "esc_active": signal["esc_active"] > 0.5,
            "run_id": [scenario.run_id] * n,
            "condition": [scenario.condition] * n,
            "road": [scenario.road] * n,
            "manoeuvre": [scenario.manoeuvre] * n,
            "experiment": np.full(n, scenario.experiment, dtype=np.int64),
            "vehicle": [scenario.vehicle.name] * n,
            "tire_model": [scenario.tire.name] * n,
            "t_s": signal["t_s"],
            "x_m": signal["x_m"],
            "y_m": signal["y_m"],
            "heading_rad": signal["heading_rad"],
            "vx_true_mps": signal["vx_mps"],
            "vy_true_mps": signal["vy_mps"],
            "ax_true_mps2": signal["ax_mps2"],
            "ay_true_mps2": signal["ay_mps2"],
            "yaw_rate_true_radps": signal["yaw_rate_radps"],
            "roll_true_rad": signal["roll_rad"],
            "steer_true_rad": signal["steer_rad"],
            "mu": signal["mu"],
        }
        for w in WHEELS:
            columns[f"mu_{w}"] = signal[f"mu_{w}"]
            columns[f"slip_ratio_{w}"] = signal[f"slip_ratio_{w}"]
            columns[f"slip_angle_{w}_rad"] = signal[f"slip_angle_{w}_rad"]
            columns[f"fz_{w}_n"] = signal[f"fz_{w}_n"]
            columns[f"fx_{w}_n"] = signal[f"fx_{w}_n"]
            columns[f"fy_{w}_n"] = signal[f"fy_{w}_n"]
        tables.append(pa.table(columns, schema=DATASET_SCHEMA))
    return pa.concat_tables(tables)
