"""Writing tables to the file formats the command line speaks: CSV, Parquet, NDJSON (chosen by extension)."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

WRITERS = (".csv", ".parquet", ".ndjson", ".jsonl")


def write_table(table: pa.Table, path: str | Path) -> Path:
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITERS:
        raise ValueError(f"output file must end in one of {list(WRITERS)}, got {path.name!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".csv":
        pacsv.write_csv(table, path)
    elif suffix == ".parquet":
        pq.write_table(table, path)
    else:
        with path.open("w") as f:
            for row in table.to_pylist():
                f.write(json.dumps(row) + "\n")
    return path
