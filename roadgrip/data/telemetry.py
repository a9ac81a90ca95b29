"""Reading and validating a telemetry file (wire format v1, CONTRACTS 3.1) for offline estimation (`roadgrip estimate`).

`read_telemetry(path)` reads CSV, Parquet, NDJSON/JSONL (one object per line) or JSON (an array of objects) with
`roadgrip.data.readers` and hands the table to `validate_telemetry`, which returns a `TelemetryBatch`: the accepted
rows in the schema's columns and types, sorted by (vehicle_id, timestamp_ms); one `Rejection` per refused row; a
segment id per accepted row; and warnings.

Three kinds of problem, three answers:

- a file that cannot be telemetry (unknown extension, missing columns, no rows, a column in the wrong unit):
  `ValueError`;
- a bad row (a missing, non-numeric, NaN or infinite value, a value outside its physical range, an invalid vehicle_id, a
  duplicated (vehicle_id, timestamp_ms)): the row is rejected, named with its column and value, and reading goes on;
- something a user should know about but that leaves the data usable (unsorted input, gaps, ignored columns): a warning.

Row checks, in this order (a row is reported once, with its first fault): the row could be parsed; vehicle_id; the
timestamp; the required columns in schema order (missing, not a number, NaN, infinite; the booleans true/false/1/0); the
optional columns (NaN there means "absent" and becomes null); then the physical ranges of `RANGES`; then duplicates,
keeping the first row in file order. The unit checks (`roadgrip.data.unit_checks`, which describes them) run on the
rows that pass the parsing checks and before the range checks, because a column in the wrong unit would otherwise lose
exactly the rows that show it.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.data.readers import Rejection, read_file
from roadgrip.data.schema import TELEMETRY
from roadgrip.data.unit_checks import WHEEL_COLUMNS, check_units, vehicle_codes

VEHICLE_ID_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")  # CONTRACTS 3.1
BOOL_COLUMNS = ("abs_active", "acc_active", "tcs_active", "esc_active")
TIME_COLUMNS = ("vehicle_id", "timestamp_ms")
SCHEMA = {c.name: c for c in TELEMETRY}

# Physical range of each numeric column, beyond which a row is rejected: wider than any road vehicle's normal driving,
# narrow enough to catch corrupt values. Speed: 360 km/h forward, a fast reverse. Accelerations: 3 g, past any tire's
# grip but leaving room for pothole spikes. Yaw rate: a spin at 170 deg/s. Steering wheel: 2.4 turns, past any lock.
# Wheel speeds: a 0.3 m wheel at 380 km/h; a little backwards.
RANGES = {
    "latitude_deg": (-90.0, 90.0),
    "longitude_deg": (-180.0, 180.0),
    "speed_mps": (-5.0, 100.0),
    "accel_lon_mps2": (-30.0, 30.0),
    "accel_lat_mps2": (-30.0, 30.0),
    "yaw_rate_radps": (-3.0, 3.0),
    "steering_wheel_angle_rad": (-15.0, 15.0),
    **{c: (-10.0, 350.0) for c in WHEEL_COLUMNS},
    "lateral_speed_mps": (-30.0, 30.0),
    # optional channels: GNSS speed as the vehicle speed; its accuracy up to a receiver's "no fix" figure; forces up to
    # 3 g on a 5 t vehicle (a powertrain's drag is a negative drive force); torques past any driver's or EPS motor's
    "gnss_speed_mps": (-5.0, 100.0),
    "gnss_speed_accuracy_mps": (0.0, 50.0),
    "drive_force_n": (-150_000.0, 150_000.0),
    "brake_force_n": (0.0, 150_000.0),
    "steering_torque_nm": (-100.0, 100.0),
    "eps_assist_torque_nm": (-200.0, 200.0),
}

REJECTION_SCHEMA = pa.schema(
    [
        ("row", pa.int64()),
        ("vehicle_id", pa.string()),
        ("timestamp_ms", pa.int64()),
        ("column", pa.string()),
        ("reason", pa.string()),
    ]
)
TELEMETRY_SCHEMA = pa.schema([pa.field(c.name, c.type, nullable=not c.required) for c in TELEMETRY])


@dataclass
class TelemetryBatch:
    """Accepted rows sorted by (vehicle_id, timestamp_ms), in the schema's columns and types, with a segment id per row
    that changes at every new vehicle and at every gap longer than max_gap_s; segments never bridge a gap."""

    table: pa.Table
    rejections: list[Rejection]
    segments: np.ndarray
    warnings: list[str] = field(default_factory=list)
    time_column: str = "timestamp_ms"  # the input's time column: timestamp_ms, or t_s converted to ms from the start

    def rejection_table(self) -> pa.Table:
        """The rejections as a table (row, vehicle_id, timestamp_ms, column, reason), for a CSV report."""
        return pa.Table.from_pylist([vars(r) for r in self.rejections], schema=REJECTION_SCHEMA)


def read_telemetry(path: str | Path, *, max_gap_s: float = 0.25, wheel_radius_m: float | None = None) -> TelemetryBatch:
    """Read and validate a telemetry file; the format comes from the extension (.csv, .parquet, .ndjson, .jsonl, .json).

    Without a vehicle_id column, all rows are one vehicle named after the file's stem."""
    path = Path(path)
    table, rows, rejections = read_file(path)
    return _validate(table, rows, rejections, str(path), max_gap_s, wheel_radius_m)


def validate_telemetry(
    table: pa.Table, *, source: str = "input", max_gap_s: float = 0.25, wheel_radius_m: float | None = None
) -> TelemetryBatch:
    """Validate a table of telemetry (the columns of a file: wire-format names, `t_s` allowed in place of timestamp_ms,
    vehicle_id optional); `source` names the input in messages and, without vehicle_id, names the vehicle."""
    return _validate(table, np.arange(table.num_rows), [], source, max_gap_s, wheel_radius_m)


# ------------------------------------------------------------------------------------------------- column parsing


class _Faults:
    """The first fault of each row: column and reason (None while the row is clean)."""

    def __init__(self, n: int):
        self.column = np.full(n, None, dtype=object)
        self.reason = np.full(n, None, dtype=object)

    @property
    def clean(self) -> np.ndarray:
        return np.equal(self.reason, None)

    def add(self, mask: np.ndarray, column: str, reason) -> None:
        """Record `reason(i)` (or a fixed string) for the rows of `mask` that have no fault yet."""
        for i in np.flatnonzero(mask & self.clean):
            self.column[i] = column
            self.reason[i] = reason if isinstance(reason, str) else reason(i)


def _plain(arr) -> pa.Array:
    arr = arr.combine_chunks() if isinstance(arr, pa.ChunkedArray) else arr
    return arr.dictionary_decode() if pa.types.is_dictionary(arr.type) else arr


def _is_string(t: pa.DataType) -> bool:
    return pa.types.is_string(t) or pa.types.is_large_string(t)


def _strings(arr: pa.Array) -> tuple[np.ndarray, np.ndarray]:
    """(the distinct values as Python objects, each row's index into them or -1 for null), to parse each value once."""
    enc = pc.dictionary_encode(arr)
    return np.array(enc.dictionary.to_pylist() + [None], dtype=object), enc.indices.fill_null(-1).to_numpy()


def _numbers(arr, name: str, faults: _Faults, required: bool) -> np.ndarray:
    """float64 values of a numeric column; missing and unparsable values are faults (required) or NaN (optional)."""
    arr = _plain(arr)
    n = len(arr)
    if pa.types.is_null(arr.type):
        values, missing, text = np.full(n, np.nan), np.ones(n, bool), None
    elif pa.types.is_integer(arr.type) or pa.types.is_floating(arr.type) or pa.types.is_decimal(arr.type):
        values = pc.cast(arr, pa.float64()).fill_null(np.nan).to_numpy(zero_copy_only=False)
        missing, text = arr.is_null().to_numpy(zero_copy_only=False), None
    elif _is_string(arr.type):
        uniq, idx = _strings(arr)
        parsed = np.array([_float_or_none(u) for u in uniq], dtype=object)
        missing = np.array([u is None or not u.strip() for u in uniq])[idx]
        bad = np.equal(parsed, None)[idx] & ~missing
        values = np.where(missing | bad, np.nan, parsed[idx]).astype(np.float64)
        text = uniq[idx]
        faults.add(bad, name, lambda i: f"{name} value {text[i]!r} is not a number")
    else:
        raise ValueError(f"column {name} has type {arr.type}, expected numbers")
    if required:
        faults.add(missing, name, f"missing value in {name}")
        faults.add(np.isnan(values) & ~missing, name, f"NaN in {name}")
        faults.add(np.isinf(values), name, lambda i: f"infinite value in {name} ({values[i]})")
    return values


def _float_or_none(s):
    try:
        return float(s)
    except (TypeError, ValueError):
        return None


_TRUE, _FALSE = {"true", "1", "1.0"}, {"false", "0", "0.0"}


def _booleans(arr, name: str, faults: _Faults, required: bool = True) -> np.ndarray:
    """Booleans from bool, 0/1 numbers, or the strings true/false/1/0 (any case); anything else is a fault. A missing
    value is a fault in a required column; in an optional one it is "absent": the result is then float, 1.0 / 0.0 with
    NaN where absent (as an absent optional column is)."""
    arr = _plain(arr)
    n = len(arr)
    missing = arr.is_null().to_numpy(zero_copy_only=False)
    if pa.types.is_boolean(arr.type):
        values, bad, text = arr.fill_null(False).to_numpy(zero_copy_only=False), np.zeros(n, bool), None
    elif pa.types.is_integer(arr.type) or pa.types.is_floating(arr.type):
        raw = pc.cast(arr, pa.float64()).fill_null(0.0).to_numpy(zero_copy_only=False)
        values, bad, text = raw == 1.0, ~np.isin(raw, (0.0, 1.0)) & ~missing, raw
    elif _is_string(arr.type):
        uniq, idx = _strings(arr)
        low = [None if u is None else u.strip().lower() for u in uniq]
        values = np.array([x in _TRUE for x in low])[idx]
        if not required:  # a blank cell of an optional column is an absent value, as a CSV writes one
            missing = missing | np.array([x == "" for x in low])[idx]
        bad = np.array([x not in _TRUE and x not in _FALSE for x in low])[idx] & ~missing
        text = uniq[idx]
    elif pa.types.is_null(arr.type):
        values, bad, text = np.zeros(n, bool), np.zeros(n, bool), None
    else:
        raise ValueError(f"column {name} has type {arr.type}, expected booleans (true/false or 1/0)")
    faults.add(bad, name, lambda i: f"{name} value {text[i]!r} is not a boolean (true/false or 1/0)")
    if not required:
        return np.where(missing, np.nan, values.astype(np.float64))
    faults.add(missing, name, f"missing value in {name}")
    return values.astype(bool)


def _timestamps(table: pa.Table, faults: _Faults) -> tuple[np.ndarray, np.ndarray, str]:
    """(int64 ms, float ms for the unit check, the column used): timestamp_ms, else round(t_s * 1000)."""
    name = "timestamp_ms" if "timestamp_ms" in table.column_names else "t_s"
    arr = _plain(table.column(name))
    if pa.types.is_timestamp(arr.type) and name == "timestamp_ms":
        arr = pc.cast(pc.cast(arr, pa.timestamp("ms", arr.type.tz)), pa.int64())
    if pa.types.is_integer(arr.type):
        ms = pc.cast(arr, pa.int64()).fill_null(0).to_numpy(zero_copy_only=False)
        missing = arr.is_null().to_numpy(zero_copy_only=False)
        faults.add(missing, name, f"missing value in {name}")
        return ms, np.where(missing, np.nan, ms.astype(np.float64)), name
    if _is_string(arr.type):
        uniq, idx = _strings(arr)
        parsed, text = np.array([_int_or_float(u) for u in uniq], dtype=object)[idx], uniq[idx]
        faults.add(np.equal(text, None), name, f"missing value in {name}")
        faults.add(np.equal(parsed, None), name, lambda i: f"{name} value {text[i]!r} is not a number")
        values = np.array([np.nan if p is None else float(p) for p in parsed], dtype=np.float64)
    else:
        values = _numbers(arr, name, faults, required=True)
    if name == "t_s":
        values = values * 1000.0
    finite = np.isfinite(values)
    faults.add(~finite, name, lambda i: f"{name} value {values[i]} is not finite")
    values = np.where(finite, values, np.nan)
    if name == "timestamp_ms":
        fractional = finite & (values != np.round(values))
        faults.add(fractional, name, lambda i: f"timestamp_ms {values[i]!r} is not a whole number of milliseconds")
    return np.where(finite, np.round(values), 0).astype(np.int64), values, name


def _int_or_float(s):
    if s is None:
        return None
    try:
        return int(s)
    except ValueError:
        return _float_or_none(s)


def _vehicle_ids(table: pa.Table, source: str, faults: _Faults, warnings: list[str]) -> np.ndarray:
    if "vehicle_id" not in table.column_names:
        stem = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(source).stem)[:64] or "vehicle"
        warnings.append(f"no vehicle_id column: all rows are one vehicle, {stem!r} (from the name of {source})")
        return np.full(table.num_rows, stem, dtype=object)
    arr = _plain(table.column("vehicle_id"))
    if not _is_string(arr.type):
        arr = pc.cast(arr, pa.string())
    uniq, idx = _strings(arr)
    ids = uniq[idx]
    valid = np.array([u is not None and VEHICLE_ID_RE.fullmatch(u) is not None for u in uniq])[idx]
    faults.add(np.equal(ids, None), "vehicle_id", "missing value in vehicle_id")
    faults.add(~valid, "vehicle_id", lambda i: f"vehicle_id {ids[i]!r} does not match {VEHICLE_ID_RE.pattern}")
    return ids


# --------------------------------------------------------------------------------------------------- validation


def _validate(
    table: pa.Table,
    rows: np.ndarray,
    rejections: list[Rejection],
    source: str,
    max_gap_s: float,
    wheel_radius_m: float | None,
) -> TelemetryBatch:
    _check_options(max_gap_s, wheel_radius_m)
    names = [n.strip() for n in table.column_names]
    table = table.rename_columns(names)
    doubled = sorted(n for n, k in Counter(names).items() if k > 1)
    if doubled:
        raise ValueError(f"{source} has column(s) {doubled} more than once")
    if table.num_rows == 0:
        if rejections:
            raise ValueError(
                f"{source} has no valid rows of telemetry: all {len(rejections)} were rejected ({_summary(rejections)})"
            )
        raise ValueError(f"{source} has no rows of telemetry")
    missing = [c.name for c in TELEMETRY if c.required and c.name not in TIME_COLUMNS and c.name not in names]
    if "timestamp_ms" not in names and "t_s" not in names:
        missing.insert(0, "timestamp_ms (or t_s, seconds from the start)")
    if missing:
        raise ValueError(
            f"{source} is missing required telemetry column(s): {', '.join(missing)} (CONTRACTS 3.1); "
            f"its columns are {names[:40]}{' ...' if len(names) > 40 else ''}"
        )

    n = table.num_rows
    faults = _Faults(n)
    warnings: list[str] = []
    vehicle = _vehicle_ids(table, source, faults, warnings)
    ts, ts_raw, time_column = _timestamps(table, faults)
    values = {}
    for col in TELEMETRY:
        if col.name in TIME_COLUMNS:
            continue
        if col.name not in names:
            values[col.name] = np.full(n, np.nan)  # an absent optional column
        elif col.name in BOOL_COLUMNS:
            values[col.name] = _booleans(table.column(col.name), col.name, faults, col.required)
        else:
            values[col.name] = _numbers(table.column(col.name), col.name, faults, col.required)
    used = set(SCHEMA) | {time_column}
    extras = [c for c in names if c not in used]
    if extras:
        warnings.append(f"ignored {len(extras)} column(s) that are not telemetry (wire format v1): {', '.join(extras)}")

    errors, unit_warnings = check_units(
        values, vehicle, ts, ts_raw, time_column, faults.clean, max_gap_s, wheel_radius_m
    )
    if errors:
        raise ValueError(f"implausible units in {source}: " + "; ".join(errors))
    warnings += unit_warnings

    for name, (low, high) in RANGES.items():
        v = values[name]
        unit = SCHEMA[name].unit
        faults.add(
            ~np.isnan(v) & ((v < low) | (v > high)),
            name,
            lambda i, v=v, name=name, low=low, high=high, unit=unit: (
                f"{name} {v[i]:.6g} outside [{low:g}, {high:g}] {unit}"
            ),
        )

    # Stable sort by (vehicle_id, timestamp): duplicates end up next to each other, the first in file order first.
    ok = np.flatnonzero(faults.clean)
    codes = vehicle_codes(vehicle[ok])
    order = ok[np.lexsort((ts[ok], codes))]
    by_vehicle = ok[np.argsort(codes, kind="stable")]
    same = vehicle[by_vehicle[1:]] == vehicle[by_vehicle[:-1]]
    unsorted = sorted(set(vehicle[by_vehicle[1:]][same & (np.diff(ts[by_vehicle]) < 0)]))
    if unsorted:
        warnings.append(
            f"input was not sorted by timestamp for {len(unsorted)} vehicle(s) ({_few(unsorted)}); sorted it (stable)"
        )
    if order.size:
        dup = np.zeros(order.size, bool)
        dup[1:] = (vehicle[order[1:]] == vehicle[order[:-1]]) & (ts[order[1:]] == ts[order[:-1]])
        mask = np.zeros(n, bool)
        mask[order[dup]] = True
        faults.add(
            mask, time_column, lambda i: f"duplicate timestamp {ts[i]} for vehicle {vehicle[i]} (kept the first)"
        )
        order = order[~dup]

    total = n + len(rejections)  # the rows of the table and the records that could not become rows
    rejections = sorted(
        rejections
        + [
            Rejection(
                int(rows[i]),
                vehicle[i],
                int(ts[i]) if np.isfinite(ts_raw[i]) else None,
                faults.column[i],
                faults.reason[i],
            )
            for i in np.flatnonzero(~faults.clean)
        ],
        key=lambda r: r.row,
    )
    if not order.size:
        raise ValueError(f"{source} has no valid rows of telemetry: all {total} were rejected ({_summary(rejections)})")
    if rejections:
        warnings.append(f"rejected {len(rejections)} of {total} rows ({_summary(rejections)})")

    out = _output_table(vehicle, ts, values, order)
    segments, gap_warnings = _segments(vehicle[order], ts[order], max_gap_s, time_column)
    return TelemetryBatch(out, rejections, segments, warnings + gap_warnings, time_column)


def _check_options(max_gap_s, wheel_radius_m) -> None:
    if (
        isinstance(max_gap_s, bool)
        or not isinstance(max_gap_s, (int, float))
        or not (math.isfinite(max_gap_s) and max_gap_s > 0)
    ):
        raise ValueError(f"max_gap_s must be a finite number of seconds > 0, got {max_gap_s!r}")
    if wheel_radius_m is not None and (
        isinstance(wheel_radius_m, bool)
        or not isinstance(wheel_radius_m, (int, float))
        or not 0.1 < wheel_radius_m <= 1.5
    ):
        raise ValueError(f"wheel_radius_m must be None or in (0.1, 1.5] m (as VehicleParams), got {wheel_radius_m!r}")


def _few(items, k: int = 5) -> str:
    items = list(items)
    return ", ".join(map(str, items[:k])) + (f" and {len(items) - k} more" if len(items) > k else "")


def _summary(rejections: list[Rejection]) -> str:
    counts = Counter(r.column or "(row)" for r in rejections)
    return ", ".join(f"{k}: {v}" for k, v in counts.most_common(8)) + (
        f"; e.g. row {rejections[0].row}: {rejections[0].reason}" if rejections else ""
    )


def _output_table(vehicle, ts, values, order) -> pa.Table:
    columns = []
    for col in TELEMETRY:
        if col.name == "vehicle_id":
            columns.append(pa.array(vehicle[order].tolist(), pa.string()))
        elif col.name == "timestamp_ms":
            columns.append(pa.array(ts[order], pa.int64()))
        elif col.name in BOOL_COLUMNS and col.required:
            columns.append(pa.array(values[col.name][order], pa.bool_()))
        elif col.name in BOOL_COLUMNS:  # optional: NaN is absent
            v = values[col.name][order]
            columns.append(pa.array(v == 1.0, pa.bool_(), mask=np.isnan(v)))
        else:
            v = values[col.name][order]
            columns.append(pa.array(v, pa.float64(), mask=np.isnan(v) if not col.required else None))
    return pa.Table.from_arrays(columns, schema=TELEMETRY_SCHEMA)


def _segments(vehicle: np.ndarray, ts: np.ndarray, max_gap_s: float, time_column: str) -> tuple[np.ndarray, list[str]]:
    """A new segment at every new vehicle and after every gap longer than max_gap_s."""
    n = ts.size
    new_vehicle = np.ones(n, bool)
    new_vehicle[1:] = vehicle[1:] != vehicle[:-1]
    dt_ms = np.zeros(n, np.int64)
    dt_ms[1:] = np.diff(ts)
    gap = ~new_vehicle & (dt_ms > max_gap_s * 1000.0)
    segments = np.cumsum(new_vehicle | gap) - 1
    warnings = []
    if gap.any():
        vehicles = list(dict.fromkeys(vehicle[gap]))
        details = []
        for v in vehicles[:5]:
            g = np.flatnonzero(gap & (vehicle == v))
            longest = g[np.argmax(dt_ms[g])]
            details.append(f"{v}: {g.size} (longest {dt_ms[longest] / 1000:.3g} s, before timestamp {ts[longest]})")
        more = f" and {len(vehicles) - 5} more vehicles" if len(vehicles) > 5 else ""
        warnings.append(
            f"{int(gap.sum())} gap(s) longer than max_gap_s={max_gap_s:g} s split the data into "
            f"{int(segments[-1]) + 1} segments: {', '.join(details)}{more}"
        )
    steps = dt_ms[~new_vehicle]
    if steps.size and np.median(steps) > max_gap_s * 1000.0:
        warnings.append(
            f"the median sampling interval, {np.median(steps) / 1000:.3g} s, exceeds max_gap_s="
            f"{max_gap_s:g} s: nearly every sample is its own segment (check the unit of {time_column})"
        )
    return segments.astype(np.int64), warnings
