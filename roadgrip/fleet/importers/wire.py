"""The `wire` importer: any file already in wire format v1 (CONTRACTS 3.1): CSV, Parquet, NDJSON/JSONL or JSON.

It reads the file with `roadgrip.data.telemetry.read_telemetry` (`roadgrip.data.readers`, then `validate_telemetry`),
so that a replay sends exactly what `roadgrip estimate` would accept: rows that fail a check are left out (logged
with their count and first reason), a column in a wrong unit is a `ValueError`.

Options of `load`:

| option         | default                       | meaning                                                          |
| -------------- | ----------------------------- | ---------------------------------------------------------------- |
| vehicle_id     | the file's (or the file stem) | replaces the vehicle_id of every row (a one-vehicle file only)   |
| start_ms       | the file's timestamps         | shifts all timestamps so that the earliest one is start_ms; a file in `t_s` otherwise starts at 0 ms |
| max_gap_s      | 0.25                          | as `validate_telemetry`                                          |
| wheel_radius_m | None                          | the vehicle's, for the unit check of the wheel speeds            |
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from roadgrip.data.readers import FORMATS
from roadgrip.data.telemetry import VEHICLE_ID_RE, read_telemetry

logger = logging.getLogger(__name__)

OPTIONS = ("vehicle_id", "start_ms", "max_gap_s", "wheel_radius_m")
_SIGNATURE = {"speed_mps", "accel_lon_mps2"}  # with a time column: enough to call a file wire format


class WireImporter:
    """Wire-format v1 files (see the module docstring)."""

    name = "wire"

    def detect(self, path: Path) -> bool:
        path = Path(path)
        if not path.is_file() or path.suffix.lower() not in FORMATS:
            return False
        names = _column_names(path)
        return _SIGNATURE <= names and bool({"timestamp_ms", "t_s"} & names)

    def load(self, path: Path, **options) -> pa.Table:
        check_options(self.name, options, OPTIONS)
        path = Path(path)
        batch = read_telemetry(
            path, max_gap_s=options.get("max_gap_s", 0.25), wheel_radius_m=options.get("wheel_radius_m")
        )
        for warning in batch.warnings:
            logger.warning("%s: %s", path, warning)
        out = batch.table
        if options.get("vehicle_id") is not None:
            out = with_vehicle_id(out, options["vehicle_id"], str(path))
        if options.get("start_ms") is not None:
            out = shifted_to(out, options["start_ms"])
        return out


def check_options(importer: str, options: dict, allowed: tuple[str, ...]) -> None:
    """`ValueError` naming an option that `importer` does not know."""
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ValueError(f"unknown option(s) {unknown} for importer {importer!r}; allowed: {list(allowed)}")


def check_vehicle_id(vehicle_id) -> str:
    if not isinstance(vehicle_id, str) or VEHICLE_ID_RE.fullmatch(vehicle_id) is None:
        raise ValueError(f"vehicle_id must match {VEHICLE_ID_RE.pattern}, got {vehicle_id!r}")
    return vehicle_id


def check_start_ms(start_ms) -> int:
    if isinstance(start_ms, bool) or not isinstance(start_ms, int) or start_ms < 0:
        raise ValueError(f"start_ms must be a whole number of ms since the Unix epoch, >= 0, got {start_ms!r}")
    return start_ms


def with_vehicle_id(table: pa.Table, vehicle_id: str, source: str) -> pa.Table:
    """`table` with every row under `vehicle_id`; a table of several vehicles is a `ValueError` (their samples would
    collide)."""
    check_vehicle_id(vehicle_id)
    present = pc.unique(table["vehicle_id"]).to_pylist()
    if len(present) > 1:
        raise ValueError(
            f"vehicle_id={vehicle_id!r} cannot rename {source}: it holds {len(present)} vehicles "
            f"({', '.join(map(str, present[:5]))}{' ...' if len(present) > 5 else ''})"
        )
    index = table.schema.get_field_index("vehicle_id")
    return table.set_column(index, table.schema.field(index), pa.array([vehicle_id] * table.num_rows, pa.string()))


def shifted_to(table: pa.Table, start_ms: int) -> pa.Table:
    """`table` with all timestamps moved by one amount, so that the earliest is `start_ms` (the vehicles keep their
    timing relative to each other)."""
    check_start_ms(start_ms)
    if table.num_rows == 0:
        return table
    shift = start_ms - pc.min(table["timestamp_ms"]).as_py()
    index = table.schema.get_field_index("timestamp_ms")
    return table.set_column(
        index, table.schema.field(index), pc.add(table["timestamp_ms"], pa.scalar(shift, pa.int64()))
    )


def csv_header(line: str) -> set[str]:
    """The column names in the header line of a CSV file (quoted or not)."""
    return {h.strip() for h in next(csv.reader([line]), [])}


def _column_names(path: Path) -> set[str]:
    """The column names of a telemetry file, from its header (CSV), schema (Parquet) or first record (JSON)."""
    kind = FORMATS[path.suffix.lower()]
    if kind == "parquet":
        try:
            return set(pq.read_schema(path).names)
        except (pa.ArrowInvalid, OSError):
            return set()
    with open(path, encoding="utf-8-sig") as f:
        if kind == "csv":
            return csv_header(f.readline())
        if kind == "ndjson":
            first = next((line for line in f if line.strip()), "")
        else:  # a JSON array: the first object, read without parsing the whole file
            text = f.read(1 << 16).lstrip()
            if not text.startswith("["):
                return set()
            first = text[1 : text.find("}") + 1] if "}" in text else ""
    try:
        obj = json.loads(first)
    except json.JSONDecodeError:
        return set()
    return set(obj) if isinstance(obj, dict) else set()
