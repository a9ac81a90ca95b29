import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from telemetry_samples import T0_MS, drive, rows_of, table_of, with_column, write

from roadgrip.data.schema import TELEMETRY_COLUMNS
from roadgrip.data.telemetry import read_telemetry, validate_telemetry
from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import PAPER_SUV

# -------------------------------------------------------------------------------------------- columns and rows


def test_t_s_becomes_timestamp_ms_and_the_file_stem_names_the_vehicle(tmp_path, clean):
    t_s = np.arange(clean.num_rows) * 0.1 + 0.0004  # round(t_s * 1000) drops the 0.4 ms
    table = clean.drop(["vehicle_id", "timestamp_ms"]).append_column("t_s", pa.array(t_s))
    batch = read_telemetry(write(table, tmp_path / "my car 7.csv", "csv"))
    assert batch.time_column == "t_s"
    assert batch.table["timestamp_ms"].to_pylist() == [round(x * 1000) for x in t_s]
    assert set(batch.table["vehicle_id"].to_pylist()) == {"my_car_7"}
    assert any("no vehicle_id column" in w and "my_car_7" in w for w in batch.warnings)


def test_missing_columns_are_all_named(clean):
    with pytest.raises(ValueError) as err:
        validate_telemetry(clean.drop(["speed_mps", "yaw_rate_radps", "wheel_speed_rr_radps"]))
    for name in ("speed_mps", "yaw_rate_radps", "wheel_speed_rr_radps"):
        assert name in str(err.value)
    with pytest.raises(ValueError, match=r"timestamp_ms \(or t_s"):
        validate_telemetry(clean.drop(["timestamp_ms"]))


def test_optional_columns_may_be_absent_and_extras_are_ignored_with_one_warning(clean):
    table = clean.drop(["latitude_deg", "longitude_deg", "lateral_speed_mps"])
    table = table.append_column("mu", pa.array(np.full(table.num_rows, 0.8))).append_column(
        "run_id", pa.array(["r1"] * table.num_rows)
    )
    batch = validate_telemetry(table)
    assert batch.table.column_names == list(TELEMETRY_COLUMNS)
    assert batch.table["latitude_deg"].null_count == table.num_rows
    assert batch.table["lateral_speed_mps"].null_count == table.num_rows
    extras = [w for w in batch.warnings if "ignored" in w]
    assert len(extras) == 1 and "mu" in extras[0] and "run_id" in extras[0]


def test_tcs_and_esc_flags_are_optional_booleans(tmp_path, clean):
    n = clean.num_rows
    absent = validate_telemetry(clean.drop([c for c in ("tcs_active", "esc_active") if c in clean.column_names]))
    assert absent.table["tcs_active"].null_count == n and absent.table["esc_active"].null_count == n
    assert absent.rejections == []
    flags = [True, None, False] * (n // 3) + [False] * (n % 3)
    table = clean.drop([c for c in ("tcs_active", "esc_active") if c in clean.column_names])
    table = table.append_column("tcs_active", pa.array(flags, pa.bool_())).append_column(
        "esc_active", pa.array(["1", "0", ""] * (n // 3) + ["0"] * (n % 3))
    )
    batch = read_telemetry(write(table, tmp_path / "flags.parquet", "parquet"))
    assert batch.rejections == []
    assert batch.table["tcs_active"].to_pylist()[:3] == [True, None, False], "a missing value is absent, not a fault"
    assert batch.table["esc_active"].to_pylist()[:3] == [True, False, None]
    bad = table.set_column(table.column_names.index("tcs_active"), "tcs_active", pa.array(["maybe"] + ["1"] * (n - 1)))
    assert [(r.row, r.column) for r in validate_telemetry(bad).rejections] == [(0, "tcs_active")]


def test_nan_and_infinite_values_reject_their_rows_naming_the_column(clean):
    speed = clean["speed_mps"].to_numpy().copy()
    yaw = clean["yaw_rate_radps"].to_numpy().copy()
    speed[3], yaw[7], yaw[8] = np.nan, np.inf, -np.inf
    lat = clean["latitude_deg"].to_numpy().copy()
    lat[9] = np.nan  # an optional column: NaN means absent
    table = with_column(with_column(with_column(clean, "speed_mps", speed), "yaw_rate_radps", yaw), "latitude_deg", lat)
    batch = validate_telemetry(table)
    assert [(r.row, r.column) for r in batch.rejections] == [
        (3, "speed_mps"),
        (7, "yaw_rate_radps"),
        (8, "yaw_rate_radps"),
    ]
    assert batch.rejections[0].reason == "NaN in speed_mps"
    assert batch.rejections[1].reason == "infinite value in yaw_rate_radps (inf)"
    assert batch.rejections[0].vehicle_id == "v1" and batch.rejections[0].timestamp_ms == T0_MS + 300
    assert batch.table.num_rows == clean.num_rows - 3
    assert batch.table["latitude_deg"].null_count == 1
    assert any("rejected 3 of 200 rows" in w for w in batch.warnings)


def test_booleans_accept_bool_01_and_true_false_text_only(tmp_path):
    n = 8
    columns = drive(n=n)
    columns["abs_active"] = [True, False, 1, 0, "true", "FALSE", "1", "maybe"]
    columns["acc_active"] = [0, 1, 0, 1, 0, 1, 2, 0]
    path = tmp_path / "bools.json"
    records = [{k: (v[i].item() if isinstance(v, np.ndarray) else v[i]) for k, v in columns.items()} for i in range(n)]
    path.write_text(json.dumps(records))
    batch = read_telemetry(path)
    assert [(r.row, r.column) for r in batch.rejections] == [(6, "acc_active"), (7, "abs_active")]
    assert "'maybe'" in batch.rejections[1].reason
    assert batch.table["abs_active"].to_pylist() == [True, False, True, False, True, False]
    assert batch.table["acc_active"].to_pylist() == [False, True, False, True, False, True]


def test_values_outside_physical_ranges_reject_the_row():
    columns = drive()
    columns["speed_mps"][10] = 150.0
    columns["yaw_rate_radps"][11] = -3.5
    columns["wheel_speed_fl_radps"][12] = 400.0
    columns["latitude_deg"][13] = 95.0
    columns["longitude_deg"][14] = -181.0
    columns["accel_lat_mps2"][15] = 31.0
    batch = validate_telemetry(table_of(columns))
    assert [(r.row, r.column) for r in batch.rejections] == [
        (10, "speed_mps"),
        (11, "yaw_rate_radps"),
        (12, "wheel_speed_fl_radps"),
        (13, "latitude_deg"),
        (14, "longitude_deg"),
        (15, "accel_lat_mps2"),
    ]
    assert batch.rejections[0].reason == "speed_mps 150 outside [-5, 100] m/s"
    assert batch.rejections[1].reason == "yaw_rate_radps -3.5 outside [-3, 3] rad/s"


def test_bad_vehicle_ids_are_rejected():
    columns = drive(n=40)
    columns["vehicle_id"][1] = "bad id!"
    columns["vehicle_id"][2] = "x" * 65
    columns["vehicle_id"][3] = ""
    columns["vehicle_id"][4] = None
    columns["vehicle_id"][5] = "v1\n"
    columns["vehicle_id"][6] = "car-7.b_2"  # valid: a second vehicle
    batch = validate_telemetry(table_of(columns))
    assert [(r.row, r.column) for r in batch.rejections] == [(i, "vehicle_id") for i in range(1, 6)]
    assert batch.rejections[0].reason == "vehicle_id 'bad id!' does not match ^[A-Za-z0-9_.-]{1,64}$"
    assert batch.rejections[3].reason == "missing value in vehicle_id"
    assert batch.table["vehicle_id"].to_pylist().count("car-7.b_2") == 1


# ------------------------------------------------------------------------------ order, duplicates, segments


def test_duplicates_keep_the_first_and_unsorted_input_is_sorted_with_a_warning(clean):
    rows = rows_of(clean.slice(0, 50))
    dup = dict(rows[10], speed_mps=99.0)  # same vehicle and timestamp as row 10, later in the file
    shuffled = rows[25:] + rows[:25] + [dup]
    batch = validate_telemetry(pa.Table.from_pylist(shuffled, schema=clean.schema))
    assert [(r.row, r.column, r.reason) for r in batch.rejections] == [
        (50, "timestamp_ms", f"duplicate timestamp {T0_MS + 1000} for vehicle v1 (kept the first)")
    ]
    assert batch.table["timestamp_ms"].to_pylist() == [T0_MS + 100 * i for i in range(50)]
    assert batch.table["speed_mps"][10].as_py() == rows[10]["speed_mps"]
    assert any("not sorted by timestamp" in w and "v1" in w for w in batch.warnings)
    assert batch.segments.tolist() == [0] * 50


def test_gaps_split_segments_and_are_counted():
    columns = drive(n=100)
    keep = np.r_[0:30, 50:70, 71:100]  # a 2.1 s gap after sample 29 and a 0.2 s one after 69 (under 0.25 s)
    table = table_of(columns).take(pa.array(keep))
    batch = validate_telemetry(table)
    assert batch.segments.tolist() == [0] * 30 + [1] * 49
    gaps = [w for w in batch.warnings if "gap" in w]
    assert len(gaps) == 1 and gaps[0].startswith("1 gap(s) longer than max_gap_s=0.25 s")
    assert "v1: 1 (longest 2.1 s" in gaps[0]
    assert validate_telemetry(table, max_gap_s=0.15).segments.max() == 2
    assert validate_telemetry(table, max_gap_s=5.0).segments.max() == 0
    with pytest.raises(ValueError, match="max_gap_s"):
        validate_telemetry(table, max_gap_s=0.0)


def test_interleaved_vehicles_get_their_own_segments():
    a, b = drive(n=60, vehicle_id="b-car", seed=1), drive(n=60, vehicle_id="a-car", seed=2, start_ms=T0_MS + 50)
    rows = []
    for i in range(60):  # b then a, sample by sample: each vehicle is in order, the file is not sorted by vehicle
        rows.append({k: (v[i].item() if isinstance(v, np.ndarray) else v[i]) for k, v in a.items()})
        rows.append({k: (v[i].item() if isinstance(v, np.ndarray) else v[i]) for k, v in b.items()})
    batch = validate_telemetry(pa.Table.from_pylist(rows))
    assert batch.table["vehicle_id"].to_pylist() == ["a-car"] * 60 + ["b-car"] * 60
    assert batch.segments.tolist() == [0] * 60 + [1] * 60
    assert batch.table["timestamp_ms"].to_pylist()[:2] == [T0_MS + 50, T0_MS + 150]
    assert not any("sorted" in w for w in batch.warnings), "interleaving is normal, not unsorted"


def test_rejection_table_has_one_row_per_rejection():
    columns = drive(n=40)
    columns["speed_mps"][2] = np.nan
    columns["vehicle_id"][5] = "no spaces"
    batch = validate_telemetry(table_of(columns))
    report = batch.rejection_table()
    assert report.schema.names == ["row", "vehicle_id", "timestamp_ms", "column", "reason"]
    assert report.to_pylist() == [
        {
            "row": 2,
            "vehicle_id": "v1",
            "timestamp_ms": T0_MS + 200,
            "column": "speed_mps",
            "reason": "NaN in speed_mps",
        },
        {
            "row": 5,
            "vehicle_id": "no spaces",
            "timestamp_ms": T0_MS + 500,
            "column": "vehicle_id",
            "reason": "vehicle_id 'no spaces' does not match ^[A-Za-z0-9_.-]{1,64}$",
        },
    ]
    empty = validate_telemetry(table_of(drive(n=40))).rejection_table()
    assert empty.num_rows == 0 and empty.schema == report.schema


def test_no_valid_rows_is_an_error():
    columns = drive(n=30)
    columns["speed_mps"] = np.full(30, np.nan)
    with pytest.raises(ValueError, match=r"no valid rows.*all 30 were rejected.*speed_mps: 30"):
        validate_telemetry(table_of(columns))


# ------------------------------------------------------------------------------------------- simulated data


@pytest.fixture(scope="module")
def two_paper_runs():
    return simulate(paper_scenarios()[:2])


def test_a_clean_simulated_run_passes_with_no_rejections(two_paper_runs, tmp_path):
    pq.write_table(two_paper_runs, tmp_path / "sim.parquet")
    for batch in (
        validate_telemetry(two_paper_runs, wheel_radius_m=PAPER_SUV.wheel_radius_m),
        read_telemetry(tmp_path / "sim.parquet", wheel_radius_m=PAPER_SUV.wheel_radius_m),
        validate_telemetry(two_paper_runs),
    ):
        assert batch.rejections == []
        assert batch.table.num_rows == two_paper_runs.num_rows
        assert batch.table.schema.names == list(TELEMETRY_COLUMNS)
        assert batch.segments.max() == 1, "two vehicles, no gaps"
        assert len(batch.warnings) == 1 and "mu" in batch.warnings[0] and "run_id" in batch.warnings[0]
