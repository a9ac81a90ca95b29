"""A synthetic drive in wire format v1 and file writers, shared by the telemetry reader and unit-check tests."""

import json

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from roadgrip.data.schema import WHEELS

T0_MS = 1_700_000_000_000
RADIUS_M = 0.35
WHEEL_COLUMNS = [f"wheel_speed_{w}_radps" for w in WHEELS]


def drive(
    n=200, vehicle_id="v1", start_ms=T0_MS, dt_ms=100, seed=0, accel_mps2=1.5, curve_per_m=0.005, v0_mps=8.0
) -> dict:
    """A consistent synthetic drive in SI units: accelerate then brake (a = dv/dt), straight then on a curve of
    curvature `curve_per_m` (r = v kappa, ay = v r, steering wheel = 16 x 2.9 m x kappa), wheels rolling (v / R)."""
    rng = np.random.default_rng(seed)
    t_s = np.arange(n) * dt_ms / 1000.0
    a = np.where(t_s < t_s[-1] / 2, accel_mps2, -accel_mps2)
    v = v0_mps + np.concatenate([[0.0], np.cumsum(a[:-1]) * dt_ms / 1000.0])
    kappa = np.where(t_s > 0.4 * t_s[-1], curve_per_m, 0.0)
    r = v * kappa

    def noisy(x, sigma):
        return x + rng.normal(0.0, sigma, n)

    return {
        "vehicle_id": [vehicle_id] * n,
        "timestamp_ms": start_ms + np.arange(n, dtype=np.int64) * dt_ms,
        "latitude_deg": 38.04 + 1e-5 * np.arange(n),
        "longitude_deg": np.full(n, 114.51),
        "speed_mps": noisy(v, 0.02),
        "accel_lon_mps2": noisy(a, 0.03),
        "accel_lat_mps2": noisy(v * r, 0.03),
        "yaw_rate_radps": noisy(r, 0.001),
        "steering_wheel_angle_rad": noisy(16.0 * 2.9 * kappa, 0.003),
        **{c: noisy(v / RADIUS_M, 0.02) for c in WHEEL_COLUMNS},
        "abs_active": [False] * n,
        "acc_active": [True] * (n // 2) + [False] * (n - n // 2),
        "lateral_speed_mps": noisy(np.zeros(n), 0.01),
    }


def table_of(columns: dict) -> pa.Table:
    return pa.table(columns)


def with_column(table: pa.Table, name: str, values) -> pa.Table:
    return table.set_column(table.column_names.index(name), name, pa.array(values))


def rows_of(table: pa.Table) -> list[dict]:
    return table.to_pylist()


def write(table: pa.Table, path, fmt: str):
    if fmt == "csv":
        pacsv.write_csv(table, path)
    elif fmt == "parquet":
        pq.write_table(table, path)
    elif fmt in ("ndjson", "jsonl"):
        path.write_text("".join(json.dumps(r) + "\n" for r in rows_of(table)))
    else:
        path.write_text(json.dumps(rows_of(table)))
    return path
