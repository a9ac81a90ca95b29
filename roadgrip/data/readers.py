"""Reading a telemetry file into a table: CSV, Parquet, NDJSON/JSONL (one object per line) or JSON (an array of
objects), the format chosen by the extension.

`read_file` returns the table as the file has it (wire-format names, values not yet checked: a column Arrow cannot type
as one stays strings, parsed value by value in `roadgrip.data.telemetry`), each table row's index among the file's
records, and one `Rejection` per record that could not become a row (a CSV row with the wrong number of fields, an
NDJSON line that is not a JSON object). A file that cannot be telemetry at all (an unknown extension, no bytes, not
Parquet or not a JSON array where the extension says so) raises `ValueError`; a missing one, `FileNotFoundError`.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

FORMATS = {".csv": "csv", ".parquet": "parquet", ".ndjson": "ndjson", ".jsonl": "ndjson", ".json": "json"}
CSV_NULLS = ["", "null", "NULL", "None", "NA", "N/A"]  # not "NaN": a NaN must be reported as NaN, not as missing


@dataclass
class Rejection:
    """One rejected input row: its 0-based index among the file's data records (CSV: after the header; NDJSON: among
    the non-blank lines; JSON: in the array; a table: its position), and why."""

    row: int
    vehicle_id: str | None
    timestamp_ms: int | None
    column: str  # the column at fault ("" if the whole row)
    reason: str


def read_file(path: Path) -> tuple[pa.Table, np.ndarray, list[Rejection]]:
    """(the table, each of its rows' index among the file's records, the records rejected) of a telemetry file."""
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(
            f"unknown telemetry file extension {path.suffix!r} of {path}; expected one of {sorted(FORMATS)}"
        )
    if not path.is_file():
        raise FileNotFoundError(f"telemetry file {path} does not exist")
    if path.stat().st_size == 0:
        raise ValueError(f"telemetry file {path} is empty")
    return _READERS[FORMATS[suffix]](path)


def _read_csv(path: Path):
    """Arrow's reader; where it cannot (a row with the wrong number of fields, which it does not place; a value that
    does not fit the type Arrow inferred from the first block), Python's csv module, every value a string."""
    invalid = []
    try:
        table = pacsv.read_csv(
            path,
            parse_options=pacsv.ParseOptions(invalid_row_handler=lambda row: invalid.append(row) or "skip"),
            convert_options=pacsv.ConvertOptions(
                column_types={"vehicle_id": pa.string()}, null_values=CSV_NULLS, strings_can_be_null=True
            ),
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
                rejections.append(
                    Rejection(i, None, None, "", f"row has {len(fields)} fields, the header has {len(header)}")
                )
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
        raise ValueError(f"{path} must hold a JSON array of objects, got a JSON {type(data).__name__}")  # noqa: TRY004 (bad file content, not a bad argument)
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
