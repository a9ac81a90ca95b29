"""Reading and validating a telemetry file (wire format v1, DESIGN 3.1) for offline estimation (`roadgrip estimate`).

`read_telemetry(path)` reads CSV, Parquet, NDJSON/JSONL (one object per line) or JSON (an array of objects) and hands
the table to `validate_telemetry`, which returns a `TelemetryBatch`: the accepted rows in the schema's columns and
types, sorted by (vehicle_id, timestamp_ms); one `Rejection` per refused row; a segment id per accepted row; and
warnings.

Three kinds of problem, three answers:

- a file that cannot be telemetry (unknown extension, missing columns, no rows, a column in the wrong unit):
  `ValueError`;
- a bad row (a missing, non-numeric, NaN or infinite value, a value outside its physical range, an invalid vehicle_id, a
  duplicated (vehicle_id, timestamp_ms)): the row is rejected, named with its column and value, and reading goes on;
- something a user should know about but that leaves the data usable (unsorted input, gaps, ignored columns): a warning.

Row checks, in this order (a row is reported once, with its first fault): the row could be parsed; vehicle_id; the
timestamp; the required columns in schema order (missing, not a number, NaN, infinite; the booleans true/false/1/0); the
optional columns (NaN there means "absent" and becomes null); then the physical ranges of `RANGES`; then duplicates,
keeping the first row in file order. The unit checks (`_unit_problems`) run on the rows that pass the parsing checks and
before the range checks, because a column in the wrong unit would otherwise lose exactly the rows that show it.

Unit checks compare columns with each other instead of trusting magnitudes, since each signal alone is ambiguous (30 is
a plausible speed in m/s and in km/h). All use medians, percentiles or a least-squares fit over many samples, so a few
bad rows can neither trigger nor mask them; each needs enough moving (or turning) samples and is skipped without them,
never guessed. They run vehicle by vehicle (a fleet's terminals need not agree). The limits were set on the paper preset
and 750 random-preset runs (seeds 3, 5, 7, 11, 13), with and without their wheel radius: none raised a false alarm, and
each wrong unit tested (speed in km/h or mph, wheel speeds in rpm or deg/s, yaw rate in deg/s, steering in degrees,
accel_lon in g) was caught wherever the run had the motion that shows it: for speed and wheel speeds any moving run
given its radius (without one, mph also needs some acceleration or wheels over 0.31 m), for yaw rate and steering a
turning run.

1. speed and wheel speeds. With `wheel_radius_m`: the median of speed / (wheel speed x radius) over moving samples is
   about 1 (0.95-1.09 simulated); each pair of a speed unit (m/s, km/h, mph) and a wheel unit (rad/s, rpm, deg/s) has
   its own ratio (1, 3.6, 2.24, 0.105, 0.0175, 0.377, ...), at least a factor 1.6 from any other, matched within a
   factor `UNIT_TOLERANCE`; a ratio matching none is an error outside [0.5, 2] and a warning (check the radius) inside.
   Without a radius: the implied radius speed / wheel speed must lie in `WHEEL_RADIUS_RANGE_M`, 0.15-0.7 m for any road
   vehicle (0.29-0.43 m simulated); a larger one is a speed in km/h (or mph, when both would fit), a 9.55 or 57.3 times
   smaller one wheel speeds in rpm or deg/s.
2. speed and longitudinal acceleration: the least-squares slope of d(speed)/dt on accel_lon between consecutive samples
   driving straight (|r| < 0.05 rad/s, |ay| < 1.5 m/s^2: in a skid d(vx)/dt = ax + vy r is far from ax) is about 1
   (0.97-1.02 simulated), 3.6 for km/h, 2.24 for mph and 9.81 for an accelerometer in g; used only when the fit gives
   the slope within 10 %, which needs a few m/s^2 of acceleration or braking.
3. last resort for speed, when neither 1 nor 2 could be computed: a 99th percentile above 70 m/s (252 km/h) is km/h.
4. yaw rate: ay = v r in steady driving, so p95(|v r|) / p95(|ay|) over samples above 5 m/s is about 1 in rad/s
   (0.57-6.3 simulated when turning, spins included) and 57 times that in deg/s (32 or more); above `YAW_RATIO_LIMIT`
   (12) means degrees, provided the car turns (p95 |ay| >= 0.5 m/s^2) or |yaw rate| has a 99th percentile above 1.5
   rad/s, which at 5 m/s and more would be a lateral acceleration the accelerometer does not show.
5. steering-wheel angle: delta_sw = i_s (L + K v^2) kappa with kappa = r / v, so the median of |delta_sw| / |kappa| over
   samples with |kappa| >= 0.002 1/m is 37-750 m in rad (the high end: the paper's mu 0.1 circle at full lock) and about
   2300-5000 m in degrees; above `STEER_RATIO_LIMIT` (1500) means degrees. So does a 95th percentile of |angle| beyond
   15 rad, past any steering lock.
   Checks 4 and 5 use the speed: unless check 1 or 2 confirmed its unit, their limits are multiplied by 2.24, the
   largest speed error that can pass check 1 unseen (mph on wheels under 0.31 m).
6. timestamp_ms: a median between 1e9 and 1e10 is seconds since the epoch, above 1e14 micro- or nanoseconds.
"""

from __future__ import annotations

import csv
import json
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from roadgrip.data.schema import TELEMETRY, WHEELS
from roadgrip.units import G_MPS2, KMH_PER_MPS

VEHICLE_ID_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")  # DESIGN 3.1
FORMATS = {".csv": "csv", ".parquet": "parquet", ".ndjson": "ndjson", ".jsonl": "ndjson", ".json": "json"}
CSV_NULLS = ["", "null", "NULL", "None", "NA", "N/A"]  # not "NaN": a NaN must be reported as NaN, not as missing
WHEEL_COLUMNS = tuple(f"wheel_speed_{w}_radps" for w in WHEELS)
BOOL_COLUMNS = ("abs_active", "acc_active")
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
}

# Unit factors (value in that unit / value in SI). KMH_PER_MPS and G_MPS2 come from roadgrip.units; these three would
# belong there too.
MPH_PER_MPS = 1.0 / 0.44704
RPM_PER_RADPS = 60.0 / (2.0 * math.pi)
DEG_PER_RAD = 180.0 / math.pi
SPEED_UNITS = {"m/s": 1.0, "km/h": KMH_PER_MPS, "mph": MPH_PER_MPS}
WHEEL_UNITS = {"rad/s": 1.0, "rpm": RPM_PER_RADPS, "deg/s": DEG_PER_RAD}
ACCEL_UNITS = {"m/s^2": 1.0, "g": 1.0 / G_MPS2}
FIXES = {"km/h": "divide by 3.6", "mph": "multiply by 0.44704", "rpm": "multiply by 2 pi / 60",
         "deg/s": "multiply by pi / 180", "g": f"multiply by {G_MPS2}", "deg": "multiply by pi / 180"}
UNIT_TOLERANCE = 1.2  # a ratio matches a unit within this factor; neighbouring units' ratios are >= 1.6 apart
WHEEL_RADIUS_RANGE_M = (0.15, 0.7)  # small city cars to heavy trucks (a 315/80 R22.5 truck tire has 0.54 m)
MIN_SAMPLES = 20  # samples a unit check needs
MOVING_MPS = 5.0  # speed above which yaw rate and steering are compared with lateral motion
MAX_PLAUSIBLE_SPEED_MPS = 70.0  # 252 km/h: a 99th percentile above this is km/h (last resort, see the module doc)
YAW_RATIO_LIMIT = 12.0  # p95(|v r|) / p95(|ay|): 0.57-6.3 simulated in rad/s when turning, x 57 in deg/s
STEER_RATIO_LIMIT = 1500.0  # median |delta_sw| / |kappa| in metres: 37-750 simulated in rad, x 57 in degrees
STEER_MIN_CURVATURE_PER_M = 0.002  # a 500 m radius: below it, sensor bias dominates the steering angle
STEER_LOCK_RAD = 15.0


@dataclass
class Rejection:
    """One rejected input row: its 0-based index among the file's data records (CSV: after the header; NDJSON: among
    the non-blank lines; JSON: in the array; a table: its position), and why."""

    row: int
    vehicle_id: str | None
    timestamp_ms: int | None
    column: str  # the column at fault ("" if the whole row)
    reason: str


REJECTION_SCHEMA = pa.schema([("row", pa.int64()), ("vehicle_id", pa.string()), ("timestamp_ms", pa.int64()),
                              ("column", pa.string()), ("reason", pa.string())])
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
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"unknown telemetry file extension {path.suffix!r} of {path}; "
                         f"expected one of {sorted(FORMATS)}")
    if not path.is_file():
        raise FileNotFoundError(f"telemetry file {path} does not exist")
    if path.stat().st_size == 0:
        raise ValueError(f"telemetry file {path} is empty")
    table, rows, rejections = _READERS[FORMATS[suffix]](path)
    return _validate(table, rows, rejections, str(path), max_gap_s, wheel_radius_m)


def validate_telemetry(table: pa.Table, *, source: str = "input", max_gap_s: float = 0.25,
                       wheel_radius_m: float | None = None) -> TelemetryBatch:
    """Validate a table of telemetry (the columns of a file: wire-format names, `t_s` allowed in place of timestamp_ms,
    vehicle_id optional); `source` names the input in messages and, without vehicle_id, names the vehicle."""
    return _validate(table, np.arange(table.num_rows), [], source, max_gap_s, wheel_radius_m)


# ---------------------------------------------------------------------------------------------------------- readers

def _read_csv(path: Path):
    """Arrow's reader; where it cannot (a row with the wrong number of fields, which it does not place; a value that
    does not fit the type Arrow inferred from the first block), Python's csv module, every value a string."""
    invalid = []
    try:
        table = pacsv.read_csv(
            path,
            parse_options=pacsv.ParseOptions(invalid_row_handler=lambda row: invalid.append(row) or "skip"),
            convert_options=pacsv.ConvertOptions(column_types={"vehicle_id": pa.string()}, null_values=CSV_NULLS,
                                                 strings_can_be_null=True),
        )
        if not invalid:
            return table, np.arange(table.num_rows), []
    except pa.ArrowInvalid:
        pass
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        header = [h.strip() for h in next(reader, [])]
        records, rejections = [], []
        for i, fields in enumerate(reader):
            if len(fields) != len(header):
                rejections.append(Rejection(i, None, None, "", f"row has {len(fields)} fields, the header has "
                                                                 f"{len(header)}"))
            else:
                values = [None if v.strip() in CSV_NULLS else v for v in fields]
                records.append((i, dict(zip(header, values, strict=True))))
    return _records_table(records, rejections, header)


def _read_parquet(path: Path):
    try:
        table = pq.read_table(path)
    except pa.ArrowInvalid as e:
        raise ValueError(f"cannot read {path} as Parquet: {e}") from None
    return table, np.arange(table.num_rows), []


def _read_ndjson(path: Path):
    records, rejections = [], []
    with open(path, encoding="utf-8") as f:
        lines = (line for line in f if line.strip())
        for i, line in enumerate(lines):
            try:
                obj = json.loads(line)
            except json.JSONDecodeError as e:
                rejections.append(Rejection(i, None, None, "", f"not valid JSON: {e.msg} at character {e.pos}"))
                continue
            if isinstance(obj, dict):
                records.append((i, obj))
            else:
                rejections.append(Rejection(i, None, None, "", f"not a JSON object but {type(obj).__name__}"))
    return _records_table(records, rejections)


def _read_json(path: Path):
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        hint = " (one object per line is NDJSON: name the file .ndjson or .jsonl)" if e.msg == "Extra data" else ""
        raise ValueError(f"cannot read {path} as JSON: {e.msg} at line {e.lineno}{hint}") from None
    if not isinstance(data, list):
        raise ValueError(f"{path} must hold a JSON array of objects, got a JSON {type(data).__name__}")
    records, rejections = [], []
    for i, obj in enumerate(data):
        if isinstance(obj, dict):
            records.append((i, obj))
        else:
            rejections.append(Rejection(i, None, None, "", f"not a JSON object but {type(obj).__name__}"))
    return _records_table(records, rejections)


def _records_table(records, rejections, names=None):
    """A table from (row, dict) records; a column whose values Arrow cannot type together becomes strings, which the
    validation then parses value by value (so that one bad value rejects one row, not the file)."""
    if names is None:
        names = list(dict.fromkeys(k for _, rec in records for k in rec))
    columns = {}
    for name in names:
        values = [rec.get(name) for _, rec in records]
        try:
            columns[name] = pa.array(values)
        except (pa.ArrowInvalid, pa.ArrowTypeError):
            columns[name] = pa.array([None if v is None else str(v) for v in values], pa.string())
    return pa.table(columns), np.array([i for i, _ in records], dtype=np.int64), rejections


_READERS = {"csv": _read_csv, "parquet": _read_parquet, "ndjson": _read_ndjson, "json": _read_json}


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


def _booleans(arr, name: str, faults: _Faults) -> np.ndarray:
    """Booleans from bool, 0/1 numbers, or the strings true/false/1/0 (any case); anything else is a fault."""
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
        bad = np.array([x not in _TRUE and x not in _FALSE for x in low])[idx] & ~missing
        text = uniq[idx]
    elif pa.types.is_null(arr.type):
        values, bad, text = np.zeros(n, bool), np.zeros(n, bool), None
    else:
        raise ValueError(f"column {name} has type {arr.type}, expected booleans (true/false or 1/0)")
    faults.add(missing, name, f"missing value in {name}")
    faults.add(bad, name, lambda i: f"{name} value {text[i]!r} is not a boolean (true/false or 1/0)")
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

def _validate(table: pa.Table, rows: np.ndarray, rejections: list[Rejection], source: str, max_gap_s: float,
              wheel_radius_m: float | None) -> TelemetryBatch:
    _check_options(max_gap_s, wheel_radius_m)
    names = [n.strip() for n in table.column_names]
    table = table.rename_columns(names)
    doubled = sorted(n for n, k in Counter(names).items() if k > 1)
    if doubled:
        raise ValueError(f"{source} has column(s) {doubled} more than once")
    if table.num_rows == 0:
        if rejections:
            raise ValueError(f"{source} has no valid rows of telemetry: all {len(rejections)} were rejected "
                             f"({_summary(rejections)})")
        raise ValueError(f"{source} has no rows of telemetry")
    missing = [c.name for c in TELEMETRY if c.required and c.name not in TIME_COLUMNS and c.name not in names]
    if "timestamp_ms" not in names and "t_s" not in names:
        missing.insert(0, "timestamp_ms (or t_s, seconds from the start)")
    if missing:
        raise ValueError(f"{source} is missing required telemetry column(s): {', '.join(missing)} (DESIGN 3.1); "
                         f"its columns are {names[:40]}{' ...' if len(names) > 40 else ''}")

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
            values[col.name] = _booleans(table.column(col.name), col.name, faults)
        else:
            values[col.name] = _numbers(table.column(col.name), col.name, faults, col.required)
    used = set(SCHEMA) | {time_column}
    extras = [c for c in names if c not in used]
    if extras:
        warnings.append(f"ignored {len(extras)} column(s) that are not telemetry (wire format v1): {', '.join(extras)}")

    errors, unit_warnings = _unit_problems(values, vehicle, ts, ts_raw, time_column, faults.clean, max_gap_s,
                                           wheel_radius_m)
    if errors:
        raise ValueError(f"implausible units in {source}: " + "; ".join(errors))
    warnings += unit_warnings

    for name, (low, high) in RANGES.items():
        v = values[name]
        unit = SCHEMA[name].unit
        faults.add(~np.isnan(v) & ((v < low) | (v > high)), name,
                   lambda i, v=v, name=name, low=low, high=high, unit=unit:
                   f"{name} {v[i]:.6g} outside [{low:g}, {high:g}] {unit}")

    # Stable sort by (vehicle_id, timestamp): duplicates end up next to each other, the first in file order first.
    ok = np.flatnonzero(faults.clean)
    codes = _codes(vehicle[ok])
    order = ok[np.lexsort((ts[ok], codes))]
    by_vehicle = ok[np.argsort(codes, kind="stable")]
    same = vehicle[by_vehicle[1:]] == vehicle[by_vehicle[:-1]]
    unsorted = sorted(set(vehicle[by_vehicle[1:]][same & (np.diff(ts[by_vehicle]) < 0)]))
    if unsorted:
        warnings.append(f"input was not sorted by timestamp for {len(unsorted)} vehicle(s) ({_few(unsorted)}); "
                        "sorted it (stable)")
    if order.size:
        dup = np.zeros(order.size, bool)
        dup[1:] = (vehicle[order[1:]] == vehicle[order[:-1]]) & (ts[order[1:]] == ts[order[:-1]])
        mask = np.zeros(n, bool)
        mask[order[dup]] = True
        faults.add(mask, time_column,
                   lambda i: f"duplicate timestamp {ts[i]} for vehicle {vehicle[i]} (kept the first)")
        order = order[~dup]

    total = n + len(rejections)  # the rows of the table and the records that could not become rows
    rejections = sorted(rejections + [
        Rejection(int(rows[i]), vehicle[i], int(ts[i]) if np.isfinite(ts_raw[i]) else None, faults.column[i],
                  faults.reason[i])
        for i in np.flatnonzero(~faults.clean)], key=lambda r: r.row)
    if not order.size:
        raise ValueError(f"{source} has no valid rows of telemetry: all {total} were rejected ({_summary(rejections)})")
    if rejections:
        warnings.append(f"rejected {len(rejections)} of {total} rows ({_summary(rejections)})")

    out = _output_table(vehicle, ts, values, order)
    segments, gap_warnings = _segments(vehicle[order], ts[order], max_gap_s, time_column)
    return TelemetryBatch(out, rejections, segments, warnings + gap_warnings, time_column)


def _check_options(max_gap_s, wheel_radius_m) -> None:
    if isinstance(max_gap_s, bool) or not isinstance(max_gap_s, (int, float)) or not (
            math.isfinite(max_gap_s) and max_gap_s > 0):
        raise ValueError(f"max_gap_s must be a finite number of seconds > 0, got {max_gap_s!r}")
    if wheel_radius_m is not None and (isinstance(wheel_radius_m, bool) or not isinstance(wheel_radius_m, (int, float))
                                       or not 0.1 < wheel_radius_m <= 1.5):
        raise ValueError(f"wheel_radius_m must be None or in (0.1, 1.5] m (as VehicleParams), got {wheel_radius_m!r}")


def _codes(ids: np.ndarray) -> np.ndarray:
    """Integer codes of vehicle ids in their lexicographic order."""
    _, inverse = np.unique(ids.astype(str), return_inverse=True)
    return inverse.reshape(-1)


def _few(items, k: int = 5) -> str:
    items = list(items)
    return ", ".join(map(str, items[:k])) + (f" and {len(items) - k} more" if len(items) > k else "")


def _summary(rejections: list[Rejection]) -> str:
    counts = Counter(r.column or "(row)" for r in rejections)
    return ", ".join(f"{k}: {v}" for k, v in counts.most_common(8)) + (
        f"; e.g. row {rejections[0].row}: {rejections[0].reason}" if rejections else "")


def _output_table(vehicle, ts, values, order) -> pa.Table:
    columns = []
    for col in TELEMETRY:
        if col.name == "vehicle_id":
            columns.append(pa.array(vehicle[order].tolist(), pa.string()))
        elif col.name == "timestamp_ms":
            columns.append(pa.array(ts[order], pa.int64()))
        elif col.name in BOOL_COLUMNS:
            columns.append(pa.array(values[col.name][order], pa.bool_()))
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
        warnings.append(f"{int(gap.sum())} gap(s) longer than max_gap_s={max_gap_s:g} s split the data into "
                        f"{int(segments[-1]) + 1} segments: {', '.join(details)}{more}")
    steps = dt_ms[~new_vehicle]
    if steps.size and np.median(steps) > max_gap_s * 1000.0:
        warnings.append(f"the median sampling interval, {np.median(steps) / 1000:.3g} s, exceeds max_gap_s="
                        f"{max_gap_s:g} s: nearly every sample is its own segment (check the unit of {time_column})")
    return segments.astype(np.int64), warnings


# ---------------------------------------------------------------------------------------------------- unit checks

SI_UNITS = {"speed_mps": "m/s", "accel_lon_mps2": "m/s^2", "yaw_rate_radps": "rad/s", "steering_wheel_angle_rad": "rad",
            "timestamp_ms": "milliseconds", **{c: "rad/s" for c in WHEEL_COLUMNS}}
UNIT_NAMES = {"deg/s": "degrees per second", "deg": "degrees"}


def _match(ratio: float, candidates: dict) -> object | None:
    """The key whose expected ratio lies within a factor UNIT_TOLERANCE of `ratio`, else None."""
    for key, expected in candidates.items():
        if ratio > 0 and expected / UNIT_TOLERANCE <= ratio <= expected * UNIT_TOLERANCE:
            return key
    return None


class _UnitReport:
    """Columns found in a wrong unit (one message per unit and evidence), other errors, and warnings."""

    def __init__(self):
        self.found: dict[tuple[str, str], list[str]] = {}  # (unit, evidence) -> columns
        self.errors: list[str] = []
        self.warnings: list[str] = []

    def wrong_unit(self, column: str, unit: str, evidence: str) -> None:
        self.found.setdefault((unit, evidence), []).append(column)

    def messages(self) -> list[str]:
        out = []
        for (unit, evidence), cols in self.found.items():
            subject = f"column {cols[0]} looks" if len(cols) == 1 else f"columns {', '.join(cols)} look"
            out.append(f"{subject} like {UNIT_NAMES.get(unit, unit)}, not {SI_UNITS[cols[0]]}: {evidence}; "
                       f"convert {'it' if len(cols) == 1 else 'them'} ({FIXES[unit]})")
        return out + self.errors


def _unit_problems(values, vehicle, ts, ts_raw, time_column, ok, max_gap_s, radius):
    """(errors, warnings) of the unit checks of the module docstring over the rows `ok` that parsed, vehicle by vehicle
    (a fleet's terminals need not agree: one sending km/h among many sending m/s must not hide in a pooled median)."""
    errors, warnings = [], []
    if time_column == "timestamp_ms" and ok.any():
        median = float(np.median(ts_raw[ok]))
        unit = ("seconds" if 1e9 <= median < 1e10 else "microseconds" if 1e14 <= median < 1e17
                else "nanoseconds" if median >= 1e17 else None)
        if unit:
            errors.append(f"column timestamp_ms looks like {unit} since the epoch, not milliseconds (median "
                          f"{median:.4g}, where milliseconds now are about 1.7e12); convert it")
    rows = np.flatnonzero(ok)
    codes = _codes(vehicle[rows])
    by_vehicle = rows[np.argsort(codes, kind="stable")]
    groups = np.split(by_vehicle, np.flatnonzero(np.diff(np.sort(codes))) + 1) if rows.size else []
    for group in groups:
        if group.size < MIN_SAMPLES:
            continue
        report = _UnitReport()
        v = {k: a[group] for k, a in values.items()}
        speed = _check_speed_and_wheels(v, vehicle[group], ts[group], max_gap_s, radius, report)
        if speed is not None:
            _check_yaw_and_steering(v, *speed, report)
        prefix = f"vehicle {vehicle[group[0]]}: " if len(groups) > 1 else ""
        errors += [prefix + m for m in report.messages()]
        warnings += [prefix + w for w in report.warnings]
    return _capped(errors), _capped(warnings)


def _capped(messages: list[str], k: int = 10) -> list[str]:
    return messages[:k] + ([f"... and {len(messages) - k} more like these"] if len(messages) > k else [])


def _check_speed_and_wheels(v, vehicle, ts, max_gap_s, radius, report: _UnitReport) -> tuple[float, bool] | None:
    """Checks 1-3 of the module docstring. Returns (the factor of the speed column's unit, whether a check confirmed
    it), the factor being 1 when nothing says otherwise; or None when the speed's unit is wrong but cannot be told."""
    speed = v["speed_mps"]
    implied = _implied_radii(speed, v, report)
    speed_unit, evidence, wheel_units = None, "", {}
    if radius is not None:
        speed_unit, evidence, wheel_units = _units_from_radius(implied, radius, report)

    slope = _speed_slope(v, vehicle, ts, max_gap_s)  # 2: d(speed)/dt against accel_lon
    if slope is not None:
        match = _match(slope, {(s, a): fs / fa for s, fs in SPEED_UNITS.items() for a, fa in ACCEL_UNITS.items()})
        if speed_unit is None and match is not None:
            speed_unit = match[0]
            evidence = (f"its rate of change is {slope:.3g} times accel_lon_mps2 (least-squares slope; 1 "
                        f"expected, {SPEED_UNITS[speed_unit]:.3g} for {speed_unit})")
        elif speed_unit is not None and match is not None and match[0] != speed_unit:
            report.errors.append(f"{evidence}, but the rate of change of speed_mps is {slope:.3g} times "
                                 f"accel_lon_mps2, which says {match[0]}: check wheel_radius_m={radius:g} m and the "
                                 "units of speed_mps and the wheel speeds")
            return None
        accel_unit = _match(slope / SPEED_UNITS[speed_unit or "m/s"], {u: 1 / f for u, f in ACCEL_UNITS.items()})
        if accel_unit == "g":
            report.wrong_unit("accel_lon_mps2", "g", f"the rate of change of speed is {slope:.3g} times it "
                                                     f"(least-squares slope; 1 expected, {G_MPS2:.3g} for g)")
        elif accel_unit is None:
            report.warnings.append(f"the rate of change of speed_mps is {slope:.3g} times accel_lon_mps2 "
                                   "(least-squares slope, 1 expected): check the sign and unit of accel_lon_mps2")

    lo, hi = WHEEL_RADIUS_RANGE_M
    confirmed = speed_unit is not None
    if not confirmed and radius is None and implied:  # 1, without a radius: too large an implied radius
        r = float(np.median(list(implied.values())))
        fits = {u: r / SPEED_UNITS[u] for u in ("km/h", "mph") if lo <= r / SPEED_UNITS[u] <= hi}
        text = f"speed_mps / wheel speed implies a wheel radius of {r:.3g} m ({lo}-{hi} m expected; " + " or ".join(
            f"{x:.2g} m if it is {u}" for u, x in fits.items()) + ")"
        if r > hi and len(fits) == 1:
            speed_unit, evidence, confirmed = next(iter(fits)), text, True
        elif r > hi and fits:
            report.errors.append(f"column speed_mps looks like {' or '.join(fits)}, not m/s: {text}; convert it")
            return None
    if not confirmed and not implied and slope is None:  # 3: the last resort
        p99 = float(np.percentile(np.abs(speed), 99))
        if p99 > MAX_PLAUSIBLE_SPEED_MPS:
            speed_unit = "km/h"
            evidence = (f"its 99th percentile is {p99:.4g}, above {MAX_PLAUSIBLE_SPEED_MPS:g} m/s "
                        f"({MAX_PLAUSIBLE_SPEED_MPS * KMH_PER_MPS:.0f} km/h), and neither wheel speeds nor "
                        "accelerations could be compared with it")
    if speed_unit not in (None, "m/s"):
        report.wrong_unit("speed_mps", speed_unit, evidence)
    speed_factor = SPEED_UNITS[speed_unit or "m/s"]

    found: dict[str, dict[str, float]] = {}  # the wheels' units, given the speed's: unit -> {column: ratio}
    unexplained = {}
    for col, r in implied.items():
        if radius is not None:
            unit = wheel_units.get(col)
            if unit is not None and unit[0] == (speed_unit or "m/s") and unit[1] != "rad/s":
                found.setdefault(unit[1], {})[col] = r / radius
            continue
        r = r / speed_factor
        if not lo <= r <= hi:
            unit = next((u for u, f in WHEEL_UNITS.items() if lo <= r * f <= hi), None)
            if unit is None:
                unexplained[col] = r
            else:
                found.setdefault(unit, {})[col] = r
    for unit, ratios in found.items():
        x = float(np.median(list(ratios.values())))
        if radius is not None:
            evidence = (f"speed_mps / (wheel speed x wheel_radius_m) over moving samples is {x:.3g} (1 expected; "
                        f"{speed_factor / WHEEL_UNITS[unit]:.3g} for {unit})")
        else:
            evidence = (f"speed / wheel speed implies a wheel radius of {x:.2g} m ({lo}-{hi} m expected; "
                        f"{x * WHEEL_UNITS[unit]:.2g} m for {unit}{'' if confirmed else ', if speed_mps is m/s'})")
        for col in ratios:
            report.wrong_unit(col, unit, evidence)
    if unexplained:
        r = float(np.median(list(unexplained.values()))) * speed_factor
        combos = [f"speed in {s} with wheel speeds in {w}" for s, fs in SPEED_UNITS.items()
                  for w, fw in WHEEL_UNITS.items() if (s, w) != ("m/s", "rad/s") and lo <= r * fw / fs <= hi
                  and (not confirmed or s == (speed_unit or "m/s"))]
        report.errors.append(
            f"speed_mps / wheel speed implies a wheel radius of {r:.3g} m ({lo}-{hi} m expected for a road vehicle) "
            f"for {', '.join(unexplained)}: check the units of speed_mps and the wheel speeds"
            + (f" ({' or '.join(combos)} would explain it)" if combos else ""))
        if not confirmed:
            return None  # the speed itself may be wrong: leave the checks that use it alone
    return speed_factor, confirmed


def _moving_threshold(x: np.ndarray) -> float:
    """|x| above which a sample counts as moving: a fifth of the 95th percentile, the same samples whatever the unit
    (the slowest samples are where sensors misbehave: wheel-speed drop-out, quantisation, creeping at a stop), and at
    least 1 in the file's unit, so that a parked car's noise is never taken for motion."""
    return max(0.2 * float(np.percentile(np.abs(x), 95)), 1.0)


def _implied_radii(speed: np.ndarray, v: dict, report: _UnitReport) -> dict[str, float]:
    """Per wheel column, the median of speed / wheel speed over samples where both clearly move (file units)."""
    implied = {}
    for col in WHEEL_COLUMNS:
        w = v[col]
        moving = (np.abs(speed) >= _moving_threshold(speed)) & (np.abs(w) >= _moving_threshold(w)) & (
            np.sign(speed) == np.sign(w))
        if moving.sum() >= MIN_SAMPLES:
            implied[col] = float(np.median(speed[moving] / w[moving]))
    unchecked = [c for c in WHEEL_COLUMNS if c not in implied]
    if unchecked:
        report.warnings.append(f"too few moving samples to compare {', '.join(unchecked)} with speed_mps (units not "
                               "verified)")
    return implied


def _units_from_radius(implied: dict[str, float], radius: float, report: _UnitReport):
    """Check 1 with a radius: (speed unit or None, its evidence, wheel column -> (speed unit, wheel unit) or None)."""
    pairs = {(s, w): fs / fw for s, fs in SPEED_UNITS.items() for w, fw in WHEEL_UNITS.items()}
    units = {}
    for col, r in implied.items():
        q = r / radius
        units[col] = _match(q, pairs)
        if units[col] is None:
            text = f"speed_mps / ({col} x wheel_radius_m) over moving samples has median {q:.3g}, about 1 expected"
            if 0.5 <= q <= 2.0:
                report.warnings.append(f"{text}: check wheel_radius_m={radius:g} m")
            else:
                report.errors.append(f"{text}, and no unit of speed (m/s, km/h, mph) and wheel speed (rad/s, rpm, "
                                     f"deg/s) explains it: check these columns and wheel_radius_m={radius:g} m")
    votes = Counter(u for u in units.values() if u is not None).most_common(1)
    if not votes or votes[0][1] < len(implied) // 2 + 1:
        return None, "", units
    pair = votes[0][0]
    q = float(np.median([implied[c] / radius for c, u in units.items() if u == pair]))
    return pair[0], (f"speed_mps / (wheel speed x wheel_radius_m) over moving samples is {q:.3g} (1 expected; "
                     f"{pairs[pair]:.3g} for speed in {pair[0]}, wheel speeds in {pair[1]})"), units


def _check_yaw_and_steering(v, speed_factor: float, confirmed: bool, report: _UnitReport) -> None:
    """Checks 4 and 5 of the module docstring. Both use the speed; unless a check confirmed its unit, their limits are
    raised by the largest error that can pass unnoticed (mph read as m/s: with wheels under 0.31 m, the implied radius
    stays plausible)."""
    margin = 1.0 if confirmed else MPH_PER_MPS
    sw95 = float(np.percentile(np.abs(v["steering_wheel_angle_rad"]), 95))
    v_mps = v["speed_mps"] / speed_factor
    moving = v_mps > MOVING_MPS
    steer_evidence = None
    if moving.sum() >= MIN_SAMPLES:
        r, ay, speed = v["yaw_rate_radps"][moving], v["accel_lat_mps2"][moving], v_mps[moving]
        ay95 = float(np.percentile(np.abs(ay), 95))
        vr95 = float(np.percentile(np.abs(speed * r), 95))
        r99 = float(np.percentile(np.abs(r), 99))
        yaw_factor = 1.0
        if ay95 > 0 and vr95 / ay95 > YAW_RATIO_LIMIT * margin and (ay95 >= 0.5 or r99 > 1.5):
            yaw_factor = DEG_PER_RAD
            report.wrong_unit("yaw_rate_radps", "deg/s",
                              f"speed x yaw rate is {vr95 / ay95:.3g} times the lateral acceleration (95th percentiles "
                              f"above {MOVING_MPS:g} m/s; about 1 expected, as ay = v r; 99th percentile of |yaw rate| "
                              f"{r99:.3g})")
        kappa = r / yaw_factor / speed  # path curvature, 1/m
        curving = np.abs(kappa) >= STEER_MIN_CURVATURE_PER_M
        if curving.sum() >= MIN_SAMPLES:
            ratio = float(np.median(np.abs(v["steering_wheel_angle_rad"][moving][curving]) / np.abs(kappa[curving])))
            if ratio > STEER_RATIO_LIMIT * margin:
                steer_evidence = (f"the median of |angle| / path curvature (yaw rate / speed) is {ratio:.4g} m "
                                  "(steering ratio x wheelbase, more when understeering: 37-750 m in rad)")
    if steer_evidence is None and sw95 > STEER_LOCK_RAD:
        steer_evidence = f"its 95th percentile of |angle| is {sw95:.4g}, past any steering lock (about 15 rad)"
    if steer_evidence:
        report.wrong_unit("steering_wheel_angle_rad", "deg", steer_evidence)


def _speed_slope(v: dict, vehicle, ts, max_gap_s) -> float | None:
    """Least-squares slope of d(speed)/dt on accel_lon between consecutive samples of a vehicle that move (see
    `_moving_threshold`) straight, or None unless it is positive and known within 10 % (enough samples and enough
    acceleration).

    In the body frame d(vx)/dt = ax + vy r: the samples keep |r| < 0.05 rad/s and |ay| < 1.5 m/s^2 at both ends, where
    vy r is negligible (in a skid it is not: a spinning car's vx falls at several g with ax near zero)."""
    order = np.lexsort((ts, _codes(vehicle)))
    s, a, t, veh = v["speed_mps"][order], v["accel_lon_mps2"][order], ts[order], vehicle[order]
    straight = (np.abs(v["yaw_rate_radps"][order]) < 0.05) & (np.abs(v["accel_lat_mps2"][order]) < 1.5)
    dt = np.diff(t) / 1000.0
    fast = np.abs(s) >= _moving_threshold(s)
    moving = fast[1:] & fast[:-1]
    pair = (veh[1:] == veh[:-1]) & (dt > 0) & (dt <= max_gap_s) & moving & straight[1:] & straight[:-1]
    if pair.sum() < 30:
        return None
    x = 0.5 * (a[1:] + a[:-1])[pair]
    y = np.diff(s)[pair] / dt[pair]
    xc, yc = x - x.mean(), y - y.mean()
    sxx = float(np.sum(xc * xc))
    if sxx <= 0:
        return None
    slope = float(np.sum(xc * yc) / sxx)  # b = Sxy / Sxx
    se = math.sqrt(float(np.sum((yc - slope * xc) ** 2)) / (x.size - 2) / sxx)  # se(b) = sqrt(s^2 / Sxx)
    return slope if slope > 0 and se < 0.1 * slope else None
