"""The `can-dbc` importer: a raw CAN log decoded with the car's DBC (through cantools) and a mapping file per car,
resampled onto the 10 Hz grid of wire format v1 as a production terminal samples its car's buses.

**Input**: a folder holding a CAN log as CSV with the columns `Time` (s since the Unix epoch), `Bus`, `MessageID`
(decimal), `Message` (payload in hex) and optionally `MessageLength` (the format of the VerifiedCAN and strym
loggers), the car's `.dbc`, and a mapping file (YAML). The path may also be the CSV file itself. The mapping is, in
this order: the option `mapping` (a path); the one `.yaml`/`.yml` file in the folder; or the mapping shipped with
roadgrip whose `dbc` names the folder's DBC file (toyota_rav4_2019.yaml: the Toyota RAV4 2019 of
data/real/toyota_rav4_street).

**Mapping file** (`roadgrip.fleet.importers.can_mapping` reads and checks it; unknown keys are errors):

| key          | meaning                                                                                       |
| ------------ | --------------------------------------------------------------------------------------------- |
| `dbc`        | the DBC file's name it was written for (picks the DBC of a folder of several, and a shipped mapping) |
| `vehicle`    | the vehicle profile (CONTRACTS 3.2): a YAML file beside the mapping, or its fields inline         |
| `vehicle_id` | the samples' vehicle_id unless the option says otherwise (default: the log folder's name)      |
| `bus`        | the bus of every signal that names none (default 0)                                            |
| `max_age_s`  | staleness limit of every signal that names none (default 0.3 s)                               |
| `fields`     | wire field -> `{message, signal, unit, bus, sign, scale, max_age_s}`; a flag may be `false` instead |

`message` is the DBC's message name or frame id; `signal` a signal name, or a list of names that are summed (a coarse
angle and its fraction); `unit` the unit the DBC must state for it, checked against the DBC (a different one is a
`ValueError` naming the field, message and signal; a signal without a unit in the DBC is taken in this one) and
converted to the field's SI unit with `roadgrip.units`; wheel speeds given as a speed at the tyre (km/h, m/s) are
divided by the profile's `wheel_radius_m`, so that wheel speed x radius gives back the car's own figure; `sign: -1`
turns a signal of the car's convention into ISO 8855's; `scale` (default 1) multiplies a signal the DBC leaves in counts into
`unit` (x forward, y left, z up, yaw and steering positive to the
left). A flag (a boolean field: abs_active, acc_active, ...) has no unit and is true where its signal is not 0;
`false` instead of a source means the log does not report it. Every required field of CONTRACTS 3.1 must be mapped;
the optional ones (latitude_deg, longitude_deg, lateral_speed_mps, ...) may be, else they are left empty.

**Resampling**: the grid instants are the multiples of 100 ms since the Unix epoch between the log's first and last
frame. Each field takes at each instant the latest value of its signal at or before it (zero-order hold), as a
terminal that samples its car's buses every 100 ms does: causal (a live terminal cannot interpolate towards a frame
that has not come yet, so a replay sends what it would have sent), and never a value the car did not send. The cost
is a delay of half a frame period on average (5-50 ms at the RAV4's 10-31 Hz), small beside the 100 ms grid. An
instant is kept only where every mapped required signal's latest frame is at most `max_age_s` old (an optional
field's stale value is left absent, NaN, and the instant kept) (default 0.3 s: three grid
periods; a held value older than that would misstate speed by about 1 m/s under firm braking): where the logger
dropped frames, the telemetry has a gap, which `validate_telemetry` reports and the estimators do not bridge. Frames
that do not decode (a payload shorter than its message, bad hex) are left out and counted in a warning.

**Timestamps**: the instants in ms since the Unix epoch, from the log's own `Time`; the option `start_ms` shifts them
so that the first sample has that timestamp. A log whose `Time` counts from its start (before 2001) gets
DEFAULT_START_MS unless `start_ms` is given.

**Options of `load`**:

| option     | default                                  | meaning                                                     |
| ---------- | ---------------------------------------- | ----------------------------------------------------------- |
| vehicle_id | the mapping's `vehicle_id`, else the folder's name | the samples' vehicle_id                           |
| start_ms   | the log's own clock                      | timestamp of the first sample, ms since the epoch           |
| mapping    | sought as above                          | the mapping file to use                                     |
| max_age_s  | the mapping's, per signal                | one staleness limit for every signal, s                     |

**The DBC** is loaded with cantools. Files with value tables (`VAL_`) for signals they do not define, such as the
RAV4's `VAL_ 295 GEAR`, are refused by cantools 45.1 (39.4.13, 41.4.3, 43.0.2, 44.2.1 and 45.0.0 load them), and its
`strict=False` does not tolerate them: the check is unconditional. Such entries, and only they, are dropped before
the file is handed to cantools, with a warning naming them, so that every cantools version allowed reads the file
alike. The result is validated (`validate_telemetry`, with the profile's wheel radius), and its schema metadata
records the mapping, the DBC and how many grid instants were kept.
"""

from __future__ import annotations

import bisect
import logging
import math
import re
from pathlib import Path

import cantools
import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import yaml

from roadgrip.data.telemetry import TELEMETRY_SCHEMA, validate_telemetry
from roadgrip.fleet.importers.can_mapping import (
    BOOL_FIELDS,
    REQUIRED_FIELDS,
    WHEEL_FIELDS,
    CanMapping,
    SignalSource,
    check_against_dbc,
    load_mapping,
)
from roadgrip.fleet.importers.wire import check_options, check_start_ms, check_vehicle_id, csv_header
from roadgrip.units import to_si
from roadgrip.vehicle.params import VehicleParams

logger = logging.getLogger(__name__)

CAN_COLUMNS = ("Time", "Bus", "MessageID", "Message")
OPTIONS = ("vehicle_id", "start_ms", "mapping", "max_age_s")
PERIOD_MS = 100  # wire format v1: one sample every 100 ms (CONTRACTS 3.1)
DEFAULT_START_MS = 1_704_067_200_000  # 2024-01-01T00:00:00Z, for a log whose clock counts from its start
RELATIVE_CLOCK_S = 1e9  # a Time below this (2001-09-09) counts from the log's start, not from the epoch
SHIPPED_MAPPINGS = Path(__file__).parent  # the mappings shipped with roadgrip, beside this file


class CanDbcImporter:
    """Raw CAN logs with their DBC and a mapping file per car (see the module docstring)."""

    name = "can-dbc"

    def __init__(self):
        self.last_profile_: VehicleParams | None = None  # the vehicle of the log loaded last

    def detect(self, path: Path) -> bool:
        found = _log_files(Path(path))
        return found is not None and bool(found[1]) and bool(found[2])

    def profile(self, path: str | Path | None = None, mapping: str | Path | None = None) -> VehicleParams:
        """The vehicle of the log at `path` (its mapping's profile), or of the log loaded last (optional importer
        method: `roadgrip fleet --replay` registers the vehicle with it)."""
        if path is None:
            if self.last_profile_ is None:
                raise ValueError("can-dbc knows the vehicle only of a log: load one first or pass its path")
            return self.last_profile_
        folder, _, dbcs = _checked_files(Path(path))
        return _resolve(folder, dbcs, mapping)[0].profile

    def load(self, path: Path, **options) -> pa.Table:
        check_options(self.name, options, OPTIONS)
        folder, csvs, dbcs = _checked_files(Path(path))
        if len(csvs) != 1:
            raise ValueError(f"{folder} holds {len(csvs)} CAN logs ({[c.name for c in csvs]}): pass one of them")
        mapping, dbc_path = _resolve(folder, dbcs, options.get("mapping"))
        max_age_s = options.get("max_age_s")
        if max_age_s is not None and (
            isinstance(max_age_s, bool)
            or not isinstance(max_age_s, (int, float))
            or not (math.isfinite(max_age_s) and max_age_s > 0)
        ):
            raise ValueError(f"max_age_s must be a number of seconds > 0, got {max_age_s!r}")
        vehicle_id = check_vehicle_id(options.get("vehicle_id") or mapping.vehicle_id or folder.name)
        start_ms = options.get("start_ms")
        if start_ms is not None:
            start_ms = check_start_ms(start_ms)

        db = load_dbc(dbc_path)
        messages = check_against_dbc(mapping, db, dbc_path.name)
        frames = read_can_csv(csvs[0])
        series = decode(frames, messages, source_name=csvs[0].name)
        table, kept, total = to_wire(series, mapping, vehicle_id=vehicle_id, start_ms=start_ms, max_age_s=max_age_s)
        batch = validate_telemetry(table, source=str(folder), wheel_radius_m=mapping.profile.wheel_radius_m)
        for warning in batch.warnings:
            logger.warning("%s: %s", folder, warning)
        self.last_profile_ = mapping.profile
        age = _ages(mapping, max_age_s)
        return batch.table.replace_schema_metadata(
            {
                "roadgrip.importer": self.name,
                "roadgrip.mapping": mapping.path.name,
                "roadgrip.dbc": dbc_path.name,
                "roadgrip.vehicle": mapping.profile.name,
                "roadgrip.resampling": f"latest value at each 100 ms instant (zero-order hold), signals at most {age}: "
                f"{kept} of {total} instants kept",
            }
        )


def _ages(mapping: CanMapping, max_age_s: float | None) -> str:
    """The staleness limits in words: '0.3 s old (acc_active 1.5 s)'."""
    if max_age_s is not None:
        return f"{max_age_s:g} s old"
    ages = [s.max_age_s for s in mapping.sources]
    usual = max(set(ages), key=ages.count)
    others = [f"{s.field} {s.max_age_s:g} s" for s in mapping.sources if s.max_age_s != usual]
    return f"{usual:g} s old" + (f" ({', '.join(others)})" if others else "")


# ------------------------------------------------------------------------------------------------ finding files


def _log_files(path: Path) -> tuple[Path, list[Path], list[Path]] | None:
    """(folder, CAN CSV files, DBC files) of a log folder or of a CAN CSV file in one; None if `path` is neither."""
    if path.is_file():
        if path.suffix.lower() != ".csv" or not _is_can_csv(path):
            return None
        folder, csvs = path.parent, [path]
    elif path.is_dir():
        folder = path
        csvs = [p for p in sorted(path.iterdir()) if p.suffix.lower() == ".csv" and p.is_file() and _is_can_csv(p)]
    else:
        return None
    dbcs = [p for p in sorted(folder.iterdir()) if p.suffix.lower() == ".dbc" and p.is_file()]
    return folder, csvs, dbcs


def _checked_files(path: Path) -> tuple[Path, list[Path], list[Path]]:
    found = _log_files(path)
    if found is None or not found[1] or not found[2]:
        raise ValueError(
            f"{path} is not a raw CAN log: expected a folder holding a CSV file with the columns "
            f"{list(CAN_COLUMNS)} and the car's .dbc file (or that CSV file itself)"
        )
    return found


def _is_can_csv(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8-sig") as f:
            return set(CAN_COLUMNS) <= csv_header(f.readline())
    except (OSError, UnicodeDecodeError):
        return False


def _resolve(folder: Path, dbcs: list[Path], option) -> tuple[CanMapping, Path]:
    """(mapping, DBC file) of a log folder: see the module docstring for the order in which mappings are sought."""
    if option is not None:
        mapping = load_mapping(option)
    else:
        local = [p for p in sorted(folder.iterdir()) if p.suffix.lower() in (".yaml", ".yml") and p.is_file()]
        if len(local) > 1:
            raise ValueError(
                f"{folder} holds {len(local)} YAML files ({[p.name for p in local]}); pass the CAN "
                "mapping as the option `mapping`"
            )
        if local:
            mapping = load_mapping(local[0])
        else:
            shipped = {name: path for name, path in shipped_mappings().items() if name in {d.name for d in dbcs}}
            if len(shipped) != 1:
                raise ValueError(
                    f"no CAN mapping for {folder}: put a mapping file (YAML, see roadgrip.fleet.importers.can_dbc) "
                    f"beside the log or pass the option `mapping`; roadgrip ships mappings for the DBC files "
                    f"{sorted(shipped_mappings())}, and this folder has {[d.name for d in dbcs]}"
                )
            mapping = load_mapping(next(iter(shipped.values())))
    if mapping.dbc is not None:
        named = [d for d in dbcs if d.name == mapping.dbc]
        if named:
            return mapping, named[0]
    if len(dbcs) != 1:
        raise ValueError(
            f"{folder} holds {len(dbcs)} DBC files ({[d.name for d in dbcs]}) and the mapping "
            f"{mapping.path.name} names {mapping.dbc!r}: which one decodes the log?"
        )
    return mapping, dbcs[0]


def shipped_mappings() -> dict[str, Path]:
    """The CAN mappings shipped with roadgrip, by the name of the DBC file each is for."""
    found = {}
    for path in sorted(SHIPPED_MAPPINGS.glob("*.yaml")):
        try:
            data = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError):
            continue
        if isinstance(data, dict) and "fields" in data and isinstance(data.get("dbc"), str):
            found[data["dbc"]] = path
    return found


# ----------------------------------------------------------------------------------------------------- reading

_VAL = re.compile(r'^[ \t]*VAL_[ \t]+(\d+)[ \t]+(\w+)(?:\s+-?\d+\s+"[^"]*")*\s*;[ \t]*\r?\n?', re.MULTILINE)
_MESSAGE = re.compile(r"^[ \t]*BO_[ \t]+(\d+)[ \t]+\w+[ \t]*:", re.MULTILINE)
_SIGNAL = re.compile(r"^[ \t]*SG_[ \t]+(\w+)", re.MULTILINE)


def load_dbc(path: str | Path):
    """The DBC at `path` as a cantools database. Value tables for signals that the file does not define are dropped
    first, with a warning naming them (cantools refuses them, whatever `strict` says)."""
    path = Path(path)
    text = path.read_text(encoding="cp1252")  # the DBC format's customary encoding, as cantools reads it
    text, dropped = drop_unused_value_tables(text)
    if dropped:
        logger.warning(
            "%s: dropped %d value table(s) for signals it does not define: %s",
            path.name,
            len(dropped),
            ", ".join(dropped),
        )
    try:
        return cantools.database.load_string(text, database_format="dbc")
    except Exception as err:  # noqa: BLE001 - cantools raises its own errors, and others from its parser
        raise ValueError(f"cannot load the DBC {path}: {type(err).__name__}: {err}") from None


def drop_unused_value_tables(text: str) -> tuple[str, list[str]]:
    """(`text` without the `VAL_ <frame id> <signal>` entries whose signal is not in that frame's message, the
    entries dropped as 'VAL_ 295 GEAR')."""
    defined: set[tuple[int, str]] = set()
    messages = list(_MESSAGE.finditer(text))
    starts = [m.start() for m in messages]
    for m in _SIGNAL.finditer(text):
        owner = bisect.bisect_right(starts, m.start()) - 1  # the last message that begins before this signal
        if owner >= 0:
            defined.add((int(messages[owner].group(1)), m.group(1)))
    dropped = []

    def keep(m: re.Match) -> str:
        if (int(m.group(1)), m.group(2)) in defined:
            return m.group(0)
        dropped.append(f"VAL_ {m.group(1)} {m.group(2)}")
        return ""

    return _VAL.sub(keep, text), dropped


def read_can_csv(path: str | Path) -> dict[str, np.ndarray]:
    """The frames of a CAN CSV log: `time_s` (float64), `bus`, `frame_id` (int64) and `payload` (hex strings), in
    file order; rows without a finite Time are left out."""
    path = Path(path)
    types = {"Time": pa.float64(), "Bus": pa.int64(), "MessageID": pa.int64(), "Message": pa.string()}
    try:
        table = pacsv.read_csv(
            path, convert_options=pacsv.ConvertOptions(include_columns=list(CAN_COLUMNS), column_types=types)
        )
    except (pa.ArrowInvalid, KeyError) as err:
        raise ValueError(f"cannot read the CAN log {path}: {err}") from None
    time_s = table["Time"].to_numpy(zero_copy_only=False).astype(np.float64)
    ok = np.isfinite(time_s)
    if table.num_rows and not ok.all():
        logger.warning("%s: left out %d rows without a finite Time", path.name, int((~ok).sum()))
    if not ok.any():
        raise ValueError(f"the CAN log {path} has no frames")
    return {
        "time_s": time_s[ok],
        "bus": table["Bus"].fill_null(-1).to_numpy(zero_copy_only=False)[ok],
        "frame_id": table["MessageID"].fill_null(-1).to_numpy(zero_copy_only=False)[ok],
        "payload": np.asarray(table["Message"].fill_null("").to_pylist(), dtype=object)[ok],
    }


def decode(
    frames: dict[str, np.ndarray], messages: dict[SignalSource, object], *, source_name: str = "log"
) -> dict[SignalSource, tuple[np.ndarray, np.ndarray]]:
    """(times in s, values in the DBC's units, summed over the source's signals, sorted by time) of each source, from
    the frames on its bus with its message's frame id. Frames that do not decode are left out, with a warning."""
    by_key: dict[tuple[int, int], list[SignalSource]] = {}
    for source, message in messages.items():
        by_key.setdefault((source.bus, message.frame_id), []).append(source)
    out = {}
    for (bus, frame_id), sources in by_key.items():
        message = messages[sources[0]]
        rows = np.flatnonzero((frames["bus"] == bus) & (frames["frame_id"] == frame_id))
        rows = rows[np.argsort(frames["time_s"][rows], kind="stable")]
        good, values, failures = [], {s: [] for s in sources}, []
        for i in rows:
            try:
                decoded = message.decode(bytes.fromhex(frames["payload"][i]), decode_choices=False)
            except (ValueError, cantools.database.errors.Error) as err:
                failures.append(err)
                continue
            good.append(i)
            for s in sources:
                values[s].append(sum(float(decoded[name]) for name in s.signals))
        if failures:
            logger.warning(
                "%s: %d of %d frames of %s (id %d, bus %d) did not decode and were left out (first: %s)",
                source_name,
                len(failures),
                rows.size,
                message.name,
                frame_id,
                bus,
                failures[0],
            )
        if not good:
            raise ValueError(
                f"{source_name} has no decodable frame of {message.name} (id {frame_id}) on bus {bus}, "
                f"which the mapping needs for {[s.field for s in sources]}"
            )
        t = frames["time_s"][np.asarray(good)]
        for s in sources:
            out[s] = (t, np.asarray(values[s], np.float64))
    return out


# -------------------------------------------------------------------------------------------------- resampling


def latest_values(
    t_ms: np.ndarray, values: np.ndarray, grid_ms: np.ndarray, max_age_ms: float
) -> tuple[np.ndarray, np.ndarray]:
    """(value, fresh) at each grid instant: the latest of `values` (at sorted times `t_ms`) at or before it
    (zero-order hold; NaN before the first), and whether that value is at most `max_age_ms` old."""
    i = np.searchsorted(t_ms, grid_ms, side="right") - 1
    has = i >= 0
    j = np.maximum(i, 0)
    held = np.where(has, values[j], np.nan)
    fresh = has & (grid_ms - t_ms[j] <= max_age_ms + 1e-6)
    return held, fresh


def to_wire(
    series: dict[SignalSource, tuple[np.ndarray, np.ndarray]],
    mapping: CanMapping,
    *,
    vehicle_id: str,
    start_ms: int | None,
    max_age_s: float | None = None,
) -> tuple[pa.Table, int, int]:
    """(wire-format rows in TELEMETRY_SCHEMA, not yet validated; grid instants kept; grid instants in all) of the
    decoded signals: resampled, converted to SI and ISO 8855 as the module docstring says."""
    first_s = min(t[0] for t, _ in series.values())
    last_s = max(t[-1] for t, _ in series.values())
    grid_ms = (
        np.arange(math.ceil(first_s * 1000 / PERIOD_MS), math.floor(last_s * 1000 / PERIOD_MS) + 1, dtype=np.int64)
        * PERIOD_MS
    )
    fresh = np.ones(grid_ms.size, bool)
    held = {}
    for source, (t_s, values) in series.items():
        age_s = max_age_s if max_age_s is not None else source.max_age_s
        t_ms = np.round(t_s * 1e6) / 1e3  # to the microsecond: a frame stamped on a grid instant is at it, not after
        held[source], ok = latest_values(t_ms, values, grid_ms.astype(np.float64), age_s * 1000.0)
        if source.field in REQUIRED_FIELDS:
            fresh &= ok
        else:  # an optional field's stale value is absent (not sent); the instant stays
            held[source] = np.where(ok, held[source], np.nan)
    k = np.flatnonzero(fresh)
    if not k.size:
        raise ValueError(
            "no 100 ms instant of the log has every mapped signal fresh (at most "
            f"{max_age_s or max(s.max_age_s for s in series):g} s old); the fields' frames do not overlap"
        )
    if grid_ms.size - k.size:
        logger.info(
            "kept %d of %d grid instants: at the others a signal's latest frame was too old", k.size, grid_ms.size
        )
    timestamps = grid_ms[k]
    if start_ms is not None:
        timestamps = timestamps - timestamps[0] + start_ms
    elif first_s < RELATIVE_CLOCK_S:
        logger.warning(
            "the log's Time counts from its start, not from the Unix epoch: timestamps start at %d ms "
            "(pass start_ms to choose)",
            DEFAULT_START_MS,
        )
        timestamps = timestamps - timestamps[0] + DEFAULT_START_MS

    columns = {
        "vehicle_id": pa.array([vehicle_id] * k.size, pa.string()),
        "timestamp_ms": pa.array(timestamps, pa.int64()),
    }
    for source, values in held.items():
        columns[source.field] = to_field(source, values[k], mapping.profile.wheel_radius_m)
    for field, value in mapping.constants.items():
        columns[field] = np.full(k.size, value, bool)
    arrays = [columns[f.name] if f.name in columns else pa.nulls(k.size, f.type) for f in TELEMETRY_SCHEMA]
    return (
        pa.Table.from_arrays([pa.array(a, f.type) for a, f in zip(arrays, TELEMETRY_SCHEMA)], schema=TELEMETRY_SCHEMA),
        int(k.size),
        int(grid_ms.size),
    )


def to_field(source: SignalSource, values: np.ndarray, wheel_radius_m: float) -> np.ndarray:
    """A source's held values (DBC units) in its field's unit and ISO 8855 sign."""
    if source.field in BOOL_FIELDS:
        return values != 0
    if source.field in ("latitude_deg", "longitude_deg"):
        return source.sign * values  # degrees, as the mapping's unit must be
    si, si_unit = to_si(values * source.scale, source.unit)
    if source.field in WHEEL_FIELDS and si_unit == "m/s":
        si = si / wheel_radius_m  # speed at the tyre -> wheel angular speed, rad/s
    return source.sign * si
