import json

import numpy as np
import pyarrow as pa
import pytest
from telemetry_samples import RADIUS_M, rows_of, write

from roadgrip.data.schema import TELEMETRY_COLUMNS
from roadgrip.data.telemetry import TelemetryBatch, read_telemetry


@pytest.mark.parametrize("fmt", ["csv", "parquet", "ndjson", "jsonl", "json"])
def test_each_format_reads_to_the_same_table(tmp_path, clean, fmt):
    batch = read_telemetry(write(clean, tmp_path / f"drive.{fmt}", fmt), wheel_radius_m=RADIUS_M)
    assert isinstance(batch, TelemetryBatch)
    assert batch.table.column_names == list(TELEMETRY_COLUMNS)
    assert batch.table.schema.field("timestamp_ms").type == pa.int64()
    assert batch.table.schema.field("abs_active").type == pa.bool_()
    assert batch.rejections == []
    assert batch.table.num_rows == clean.num_rows
    assert batch.table["timestamp_ms"].to_pylist() == clean["timestamp_ms"].to_pylist()
    np.testing.assert_allclose(batch.table["speed_mps"].to_numpy(), clean["speed_mps"].to_numpy(), rtol=1e-12)
    assert batch.table["acc_active"].to_pylist() == clean["acc_active"].to_pylist()
    assert batch.segments.tolist() == [0] * clean.num_rows
    assert batch.warnings == []


def test_unknown_extension_and_missing_or_empty_files(tmp_path, clean):
    with pytest.raises(ValueError, match=r"unknown telemetry file extension '\.xlsx'"):
        read_telemetry(tmp_path / "drive.xlsx")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_telemetry(tmp_path / "absent.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(ValueError, match="is empty"):
        read_telemetry(tmp_path / "empty.csv")
    (tmp_path / "header.csv").write_text(",".join(clean.column_names) + "\n")
    with pytest.raises(ValueError, match="no rows"):
        read_telemetry(tmp_path / "header.csv")
    (tmp_path / "empty.json").write_text("[]")
    with pytest.raises(ValueError, match="no rows"):
        read_telemetry(tmp_path / "empty.json")
    (tmp_path / "object.json").write_text('{"speed_mps": 1}')
    with pytest.raises(ValueError, match="JSON array of objects"):
        read_telemetry(tmp_path / "object.json")
    write(clean.slice(0, 3), tmp_path / "lines.json", "ndjson")
    with pytest.raises(ValueError, match="NDJSON"):
        read_telemetry(tmp_path / "lines.json")


def test_nan_inf_missing_and_text_in_a_csv_file(tmp_path, clean):
    path = write(clean.slice(0, 40), tmp_path / "drive.csv", "csv")
    lines = path.read_text().splitlines()
    header = [h.strip('"') for h in lines[0].split(",")]
    speed, accel, abs_col = header.index("speed_mps"), header.index("accel_lon_mps2"), header.index("abs_active")
    edits = {1: (speed, "nan"), 2: (accel, "inf"), 3: (speed, ""), 4: (speed, "fast"), 5: (abs_col, "yes")}
    for row, (col, value) in edits.items():
        fields = lines[row + 1].split(",")
        fields[col] = value
        lines[row + 1] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    batch = read_telemetry(path)
    assert [(r.row, r.column, r.reason) for r in batch.rejections] == [
        (1, "speed_mps", "NaN in speed_mps"),
        (2, "accel_lon_mps2", "infinite value in accel_lon_mps2 (inf)"),
        (3, "speed_mps", "missing value in speed_mps"),
        (4, "speed_mps", "speed_mps value 'fast' is not a number"),
        (5, "abs_active", "abs_active value 'yes' is not a boolean (true/false or 1/0)"),
    ]
    assert batch.table.num_rows == 35


def test_a_malformed_csv_row_or_json_line_is_rejected_and_the_rest_read(tmp_path, clean):
    path = write(clean.slice(0, 30), tmp_path / "drive.csv", "csv")
    lines = path.read_text().splitlines()
    lines[3] = "v1,1700000000200"  # data row 2: two fields
    path.write_text("\n".join(lines) + "\n")
    batch = read_telemetry(path)
    assert [(r.row, r.column) for r in batch.rejections] == [(2, "")]
    assert "2 fields" in batch.rejections[0].reason
    assert batch.table.num_rows == 29

    records = rows_of(clean.slice(0, 30))
    text = [json.dumps(r) for r in records]
    text[4] = text[4][:-5]  # truncated
    text[6] = "[1, 2]"
    (tmp_path / "drive.ndjson").write_text("\n".join(text[:10]) + "\n\n" + "\n".join(text[10:]) + "\n")
    batch = read_telemetry(tmp_path / "drive.ndjson")
    assert [(r.row, r.column) for r in batch.rejections] == [(4, ""), (6, "")]
    assert "not valid JSON" in batch.rejections[0].reason and "not a JSON object" in batch.rejections[1].reason
    assert batch.table.num_rows == 28
