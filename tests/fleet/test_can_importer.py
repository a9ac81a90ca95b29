"""The `can-dbc` importer (roadgrip/fleet/importers/can_dbc.py, can_mapping.py): decoding against hand-made frames of a
tiny DBC (scaling, units, sign flips, summed signals, zero-order hold, staleness gaps), mapping checks, the DBC snag,
and the real Toyota RAV4 log of data/real/toyota_rav4_street through the importer and the command line."""

import logging
import math
import struct
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml
from typer.testing import CliRunner

from roadgrip.cli import app
from roadgrip.data.telemetry import TELEMETRY_SCHEMA, read_telemetry, validate_telemetry
from roadgrip.fleet.importers import detect_importer, get_importer
from roadgrip.fleet.importers.can_dbc import (
    CanDbcImporter,
    drop_unused_value_tables,
    latest_values,
    load_dbc,
    shipped_mappings,
)
from roadgrip.fleet.importers.can_mapping import load_mapping
from roadgrip.fleet.replay import replay_file
from roadgrip.units import canonical_unit, to_si

ROOT = Path(__file__).resolve().parents[2]
RAV4 = ROOT / "data" / "real" / "toyota_rav4_street"  # the real log, kept in the repository (README: source, licences)
WHEELS = ("fl", "fr", "rl", "rr")
runner = CliRunner()

T0 = 1_700_000_000.0  # s since the epoch: the tiny log's clock, on a whole 100 ms
RADIUS_M = 0.3

TINY_DBC = """VERSION ""

NS_ :

BS_:

BU_: XXX

BO_ 100 CHASSIS: 8 XXX
 SG_ SPEED : 0|16@1+ (0.01,0) [0|655.35] "kph" XXX
 SG_ YAW : 16|16@1- (0.01,0) [-327.68|327.67] "deg/s" XXX
 SG_ ACC_X : 32|16@1- (0.001,0) [-32|32] "m/s^2" XXX
 SG_ ACC_Y : 48|16@1- (0.001,0) [-32|32] "m/s2" XXX

BO_ 200 WHEELS: 8 XXX
 SG_ WHEEL_FL : 0|16@1+ (0.01,-67.67) [0|250] "kph" XXX
 SG_ WHEEL_FR : 16|16@1+ (0.01,-67.67) [0|250] "kph" XXX
 SG_ WHEEL_RL : 32|16@1+ (0.01,-67.67) [0|250] "kph" XXX
 SG_ WHEEL_RR : 48|16@1+ (0.01,-67.67) [0|250] "kph" XXX

BO_ 300 STEER: 4 XXX
 SG_ ANGLE : 0|16@1- (1.5,0) [-1500|1500] "deg" XXX
 SG_ FRACTION : 16|8@1- (0.1,0) [-0.7|0.7] "deg" XXX
 SG_ CRUISE : 24|1@1+ (1,0) [0|1] "" XXX

VAL_ 999 GEAR 0 "P" 1 "D; or drive" ;
VAL_ 300 CRUISE 0 "off" 1 "on" ;
"""

# A car whose lateral axis points right (SAE-like): yaw rate and lateral acceleration need sign -1, steering not.
TINY_MAPPING = {
    "dbc": "tiny.dbc",
    "vehicle": {"name": "tiny", "wheel_radius_m": RADIUS_M},
    "vehicle_id": "tiny-car",
    "bus": 0,
    "max_age_s": 0.3,
    "fields": {
        "speed_mps": {"message": "CHASSIS", "signal": "SPEED", "unit": "km/h"},
        "yaw_rate_radps": {"message": "CHASSIS", "signal": "YAW", "unit": "deg/s", "sign": -1},
        "accel_lon_mps2": {"message": 100, "signal": "ACC_X", "unit": "m/s^2"},
        "accel_lat_mps2": {"message": "CHASSIS", "signal": "ACC_Y", "unit": "m/s^2", "sign": -1},
        "steering_wheel_angle_rad": {"message": "STEER", "signal": ["ANGLE", "FRACTION"], "unit": "deg"},
        **{
            f"wheel_speed_{w}_radps": {"message": "WHEELS", "signal": f"WHEEL_{w.upper()}", "unit": "km/h"}
            for w in WHEELS
        },
        "acc_active": {"message": "STEER", "signal": "CRUISE", "max_age_s": 1.0},
        "abs_active": False,
    },
}


def chassis(k: int) -> str:
    """CHASSIS frame k: speed 36.00 + 0.36 k km/h (10 + 0.1 k m/s), yaw rate -5.73 deg/s, ax 1.5, ay -2.0 m/s^2."""
    return struct.pack("<Hhhh", 3600 + 36 * k, -573, 1500, -2000).hex()


def wheels(kmh: float) -> str:
    raw = round((kmh + 67.67) / 0.01)
    return struct.pack("<HHHH", raw, raw + 1, raw + 2, raw + 3).hex()  # fr, rl, rr 0.01 km/h faster each


def steer(angle_raw: int, fraction_raw: int, cruise: int) -> str:
    return struct.pack("<hbB", angle_raw, fraction_raw, cruise).hex()


def tiny_frames() -> list[tuple[float, int, int, str]]:
    """(time s after T0, bus, id, hex) of the tiny log: CHASSIS every 50 ms from 0.01 s; WHEELS every 50 ms from
    0.02 s; STEER every 100 ms from 0.03 s with frames 4-7 (0.43-0.73 s) lost; a CHASSIS frame on bus 1 (ignored)."""
    frames = [(0.01 + 0.05 * k, 0, 100, chassis(k)) for k in range(21)]
    frames += [(0.02 + 0.05 * k, 0, 200, wheels(36.0)) for k in range(21)]
    frames += [
        (0.03 + 0.1 * k, 0, 300, steer(2 if k < 5 else -2, 3, int(k >= 2))) for k in range(11) if k not in (4, 5, 6, 7)
    ]
    frames.append((0.26, 1, 100, chassis(100)))
    return sorted(frames)


def write_log(folder: Path, frames=None, mapping=TINY_MAPPING, dbc=TINY_DBC) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["Time,Bus,MessageID,Message,MessageLength"]
    lines += [
        f"{T0 + t:.6f},{bus},{fid},{payload},{len(payload) // 2}"
        for t, bus, fid, payload in (frames if frames is not None else tiny_frames())
    ]
    (folder / "can.csv").write_text("\n".join(lines) + "\n")
    (folder / "tiny.dbc").write_text(dbc)
    if mapping is not None:
        (folder / "mapping.yaml").write_text(yaml.safe_dump(mapping, sort_keys=False))
    return folder


@pytest.fixture
def tiny(tmp_path):
    return write_log(tmp_path / "tiny")


# ------------------------------------------------------------------------------------------- the tiny log


def test_tiny_log_decodes_scales_converts_and_flips(tiny):
    table = CanDbcImporter().load(tiny)
    assert table.schema.equals(TELEMETRY_SCHEMA)
    rows = {r["timestamp_ms"]: r for r in table.to_pylist()}
    t0_ms = round(T0 * 1000)
    # first instant: 0.1 s, when every signal has a frame (STEER's first is at 0.03 s)
    assert min(rows) == t0_ms + 100
    r = rows[t0_ms + 100]  # latest CHASSIS at 0.06 s (k = 1), WHEELS at 0.07 s, STEER at 0.03 s (k = 0)
    assert r["vehicle_id"] == "tiny-car"
    assert r["speed_mps"] == pytest.approx(36.36 / 3.6)
    assert r["yaw_rate_radps"] == pytest.approx(5.73 * math.pi / 180)  # -5.73 deg/s in the car's sign, flipped
    assert r["accel_lon_mps2"] == pytest.approx(1.5)
    assert r["accel_lat_mps2"] == pytest.approx(2.0)  # -2.0 flipped
    assert r["steering_wheel_angle_rad"] == pytest.approx(math.radians(2 * 1.5 + 0.3))  # ANGLE + FRACTION
    for i, w in enumerate(WHEELS):  # km/h at the tyre / 3.6 / radius
        assert r[f"wheel_speed_{w}_radps"] == pytest.approx((36.0 + 0.01 * i) / 3.6 / RADIUS_M)
    assert r["abs_active"] is False and r["acc_active"] is False
    assert r["latitude_deg"] is None and r["longitude_deg"] is None and r["lateral_speed_mps"] is None
    # zero-order hold: at 0.3 s the latest CHASSIS frame is k = 5 (0.26 s), not the interpolation towards k = 6
    assert rows[t0_ms + 300]["speed_mps"] == pytest.approx((36.0 + 0.36 * 5) / 3.6)
    assert rows[t0_ms + 300]["acc_active"] is True  # STEER k = 2 (0.23 s) turned it on
    # the last instant, 1.0 s, holds k = 19 (0.96 s); the bus-1 CHASSIS frame (k = 100, 72 km/h) is not this bus's
    assert max(r["speed_mps"] for r in rows.values()) == pytest.approx((36.0 + 0.36 * 19) / 3.6)


def test_staleness_leaves_gaps_where_a_signal_is_too_old(tiny):
    ts = CanDbcImporter().load(tiny)["timestamp_ms"].to_pylist()
    t0_ms = round(T0 * 1000)
    # STEER frames 4-7 lost: its latest frame is 0.33 s until 0.83 s, so 0.7 s (0.37 s old) and 0.8 s (0.47 s) go;
    # 0.6 s (0.27 s old) stays. The log ends at 1.03 s: last instant 1.0 s.
    assert [t - t0_ms for t in ts] == [100, 200, 300, 400, 500, 600, 900, 1000]
    rows = {r["timestamp_ms"] - t0_ms: r for r in CanDbcImporter().load(tiny).to_pylist()}
    assert rows[600]["steering_wheel_angle_rad"] == pytest.approx(math.radians(3.3))  # held from 0.33 s
    assert rows[900]["steering_wheel_angle_rad"] == pytest.approx(math.radians(-2 * 1.5 + 0.3))  # 0.83 s
    # a longer limit keeps them: every instant from 0.1 to 1.0 s
    looser = CanDbcImporter().load(tiny, max_age_s=0.5)["timestamp_ms"].to_pylist()
    assert [t - t0_ms for t in looser] == list(range(100, 1001, 100))


def test_latest_values_is_a_zero_order_hold_with_an_age_limit():
    t = np.array([0.0, 100.0, 250.0, 900.0])
    x = np.array([1.0, 2.0, 3.0, 4.0])
    held, fresh = latest_values(t, x, np.array([-50.0, 0.0, 99.0, 100.0, 300.0, 600.0, 1000.0]), 300.0)
    np.testing.assert_array_equal(held, [np.nan, 1.0, 1.0, 2.0, 3.0, 3.0, 4.0])
    np.testing.assert_array_equal(fresh, [False, True, True, True, True, False, True])  # 600: 350 ms old


def test_start_ms_and_vehicle_id_options(tiny):
    table = CanDbcImporter().load(tiny, start_ms=0, vehicle_id="other")
    assert table["timestamp_ms"].to_pylist()[:3] == [0, 100, 200]
    assert set(table["vehicle_id"].to_pylist()) == {"other"}
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['speed'\]"):
        CanDbcImporter().load(tiny, speed=1)


def test_frames_that_do_not_decode_are_left_out_with_a_warning(tmp_path, caplog):
    frames = tiny_frames() + [(0.155, 0, 100, "0102"), (0.156, 0, 100, "zz")]  # too short; not hex
    folder = write_log(tmp_path / "bad", frames)
    with caplog.at_level(logging.WARNING, logger="roadgrip.fleet.importers.can_dbc"):
        table = CanDbcImporter().load(folder)
    assert "2 of 23 frames of CHASSIS (id 100, bus 0) did not decode" in caplog.text
    assert table.num_rows == 8


def test_unused_value_tables_are_dropped_and_named(tmp_path, caplog):
    text, dropped = drop_unused_value_tables(TINY_DBC)
    assert dropped == ["VAL_ 999 GEAR"]
    assert 'VAL_ 300 CRUISE 0 "off" 1 "on" ;' in text and "GEAR" not in text
    (tmp_path / "tiny.dbc").write_text(TINY_DBC)
    with caplog.at_level(logging.WARNING, logger="roadgrip.fleet.importers.can_dbc"):
        db = load_dbc(tmp_path / "tiny.dbc")
    assert "VAL_ 999 GEAR" in caplog.text
    assert db.get_message_by_name("STEER").get_signal_by_name("CRUISE").choices[1] == "on"


def test_unit_spellings_of_dbc_files_convert_to_si():
    assert canonical_unit("kph") == canonical_unit(" KM/H ") == "km/h" and canonical_unit("m/s2") == "m/s^2"
    assert to_si(36.0, "kph") == (pytest.approx(10.0), "m/s")
    assert to_si(180.0, "deg/s") == (pytest.approx(math.pi), "rad/s")
    assert to_si(1.0, "g") == (pytest.approx(9.80665), "m/s^2")
    with pytest.raises(ValueError, match="unknown unit 'furlong'"):
        canonical_unit("furlong")


# ---------------------------------------------------------------------------------------------- detection


def test_detects_a_can_folder_and_its_csv(tiny, tmp_path):
    importer = CanDbcImporter()
    assert importer.detect(tiny) and importer.detect(tiny / "can.csv")
    assert detect_importer(tiny).name == "can-dbc"
    assert not importer.detect(tiny / "tiny.dbc")
    assert not importer.detect(ROOT / "data" / "real" / "bmw_m8_braking")
    no_dbc = tmp_path / "no_dbc"
    no_dbc.mkdir()
    (no_dbc / "can.csv").write_text((tiny / "can.csv").read_text())
    assert not importer.detect(no_dbc)
    with pytest.raises(ValueError, match="not a raw CAN log"):
        importer.load(no_dbc)


def test_mapping_passed_explicitly_and_missing(tmp_path):
    folder = write_log(tmp_path / "log", mapping=None)
    with pytest.raises(ValueError, match="no CAN mapping for .*pass the option `mapping`"):
        CanDbcImporter().load(folder)
    elsewhere = tmp_path / "tiny_mapping.yaml"
    elsewhere.write_text(yaml.safe_dump(TINY_MAPPING))
    assert CanDbcImporter().load(folder, mapping=elsewhere).num_rows == 8


# ------------------------------------------------------------------------------------------- bad mappings


def bad_mapping(tmp_path, **field_changes) -> Path:
    mapping = yaml.safe_load(yaml.safe_dump(TINY_MAPPING))
    for field, change in field_changes.items():
        old = mapping["fields"].get(field, {})
        mapping["fields"][field] = {**old, **change} if isinstance(change, dict) and isinstance(old, dict) else change
    return write_log(tmp_path / "log", mapping=mapping)


def test_unknown_signal_is_named(tmp_path):
    folder = bad_mapping(tmp_path, speed_mps={"signal": "VEHICLE_SPEED"})
    with pytest.raises(
        ValueError,
        match=r"field speed_mps: signal 'VEHICLE_SPEED' is not in message CHASSIS of "
        r"tiny.dbc; its signals: \['SPEED', 'YAW', 'ACC_X', 'ACC_Y'\]",
    ):
        CanDbcImporter().load(folder)


def test_unknown_message_is_named(tmp_path):
    folder = bad_mapping(tmp_path, yaw_rate_radps={"message": "KINEMATICS"})
    with pytest.raises(ValueError, match="field yaw_rate_radps: message 'KINEMATICS' is not in tiny.dbc"):
        CanDbcImporter().load(folder)


def test_wrong_unit_is_named(tmp_path):
    folder = bad_mapping(tmp_path, speed_mps={"unit": "mph"})
    with pytest.raises(
        ValueError,
        match=r"field speed_mps: signal CHASSIS.SPEED has unit 'kph' in tiny.dbc, but the "
        r"mapping expects 'mph'",
    ):
        CanDbcImporter().load(folder)
    folder = bad_mapping(tmp_path, yaw_rate_radps={"unit": "rad/s"})
    with pytest.raises(ValueError, match="signal CHASSIS.YAW has unit 'deg/s'"):
        CanDbcImporter().load(folder)


@pytest.mark.parametrize(
    "change, message",
    [
        (
            {"yaw_rate_radps": {"unit": "km/h"}},
            "field yaw_rate_radps: unit 'km/h' does not convert to the field's rad/s",
        ),
        ({"speed_mps": {"unit": "furlong/fortnight"}}, "field speed_mps: unknown unit 'furlong/fortnight'"),
        ({"speed_mps": {"sign": 2}}, "field speed_mps: sign must be 1 or -1, got 2"),
        ({"speed_mps": {"factor": 2}}, r"field speed_mps: unknown key\(s\) \['factor'\]"),
        ({"speed_mps": {"scale": 0}}, "field speed_mps: scale must be a number > 0, got 0"),
        ({"speed_mps": False}, "only the flags .* may be a constant"),
        ({"speed_mps": {"unit": None}}, "field speed_mps needs `unit`"),
        ({"acc_active": {"unit": "km/h"}}, "field acc_active is a flag"),
        ({"speed_kmh": {"message": "CHASSIS", "signal": "SPEED", "unit": "km/h"}}, "'speed_kmh' is not a field"),
    ],
)
def test_bad_mapping_entries_are_named(tmp_path, change, message):
    with pytest.raises(ValueError, match=message):
        CanDbcImporter().load(bad_mapping(tmp_path, **change))


def test_mapping_needs_every_required_field_and_no_unknown_keys(tmp_path):
    mapping = yaml.safe_load(yaml.safe_dump(TINY_MAPPING))
    del mapping["fields"]["abs_active"]
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mapping))
    with pytest.raises(ValueError, match=r"lacks the required wire field\(s\) \['abs_active'\]"):
        load_mapping(tmp_path / "m.yaml")
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({**TINY_MAPPING, "cars": 1}))
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['cars'\]"):
        load_mapping(tmp_path / "m.yaml")


def test_flag_signal_with_a_unit_in_the_dbc_is_refused(tmp_path):
    folder = write_log(tmp_path / "log", dbc=TINY_DBC.replace('[0|1] ""', '[0|1] "deg"'))
    with pytest.raises(ValueError, match="signal STEER.CRUISE has unit 'deg' in tiny.dbc, but the field is a flag"):
        CanDbcImporter().load(folder)


# ------------------------------------------------------------------------------------------- the real RAV4


@pytest.fixture(scope="module")
def rav4():
    importer = CanDbcImporter()
    return importer, importer.load(RAV4)


def test_rav4_mapping_is_shipped_and_found_by_its_dbc():
    assert shipped_mappings()["toyota_rav4_2019.dbc"].name == "toyota_rav4_2019.yaml"
    assert detect_importer(RAV4).name == "can-dbc" and get_importer("can-dbc").detect(RAV4 / "can_messages.csv")
    assert (RAV4 / "LICENSES.txt").is_file() and (RAV4 / "README.md").is_file()


def test_rav4_imports_to_115_s_of_10_hz_samples(rav4):
    importer, table = rav4
    ts = np.asarray(table["timestamp_ms"])
    assert (ts[-1] - ts[0]) / 1000 == pytest.approx(115.2)
    assert ts[0] == 1_580_765_471_700  # the log's own clock (2020-02-03), on a whole 100 ms
    assert np.all(ts % 100 == 0) and np.all(np.diff(ts) >= 100) and np.median(np.diff(ts)) == 100
    assert table.num_rows == 1031  # of 1,153 instants: the others fall in the logger's dropouts (signal > 0.3 s old)
    batch = validate_telemetry(table, wheel_radius_m=importer.profile().wheel_radius_m)
    assert batch.table.num_rows == table.num_rows and not batch.rejections
    meta = table.schema.metadata
    assert meta[b"roadgrip.importer"] == b"can-dbc" and b"1031 of 1153" in meta[b"roadgrip.resampling"]


def test_rav4_speed_is_the_mean_wheel_speed_times_the_radius(rav4):
    importer, table = rav4
    col = {c: np.asarray(table[c], dtype=float) for c in table.column_names if c != "vehicle_id"}
    radius = importer.profile().wheel_radius_m
    wheels = np.mean([col[f"wheel_speed_{w}_radps"] for w in WHEELS], axis=0) * radius
    moving = col["speed_mps"] > 1.0
    ratio = np.median(col["speed_mps"][moving] / wheels[moving])
    assert ratio == pytest.approx(0.997, abs=0.003) and abs(ratio - 1) < 0.01
    assert col["speed_mps"].max() == pytest.approx(13.0, abs=0.05)  # 46.8 km/h


def test_rav4_signs_agree_with_each_other(rav4):
    """ISO 8855 signs as measured (docs/FLEET.md): steering with path curvature, lateral acceleration with v r."""
    _, table = rav4
    v, r, ay, sw = (
        np.asarray(table[c]) for c in ("speed_mps", "yaw_rate_radps", "accel_lat_mps2", "steering_wheel_angle_rad")
    )
    moving = v > 3.0
    assert np.corrcoef(sw[moving], r[moving] / v[moving])[0, 1] > 0.7
    slope = np.polyfit(v[moving] * r[moving], ay[moving], 1)[0]
    assert 0.5 < slope < 1.5
    assert np.percentile(np.abs(r), 99) < 0.02 and np.abs(sw).max() < math.radians(5)  # nearly straight streets


def test_rav4_flags(rav4):
    _, table = rav4
    ts = np.asarray(table["timestamp_ms"])
    acc = np.asarray(table["acc_active"])
    assert not np.asarray(table["abs_active"]).any()  # not in the log: "not reported"
    engaged = ts[np.argmax(acc)] - ts[0]
    assert 7000 <= engaged <= 7500 and acc[ts - ts[0] >= 7500].all()  # the radar cruise control from 7.3 s on


def test_rav4_steering_torques_are_mapped_and_the_channels_it_lacks_are_null(rav4):
    _, table = rav4
    driver = np.asarray(table["steering_torque_nm"], dtype=float)
    eps = np.asarray(table["eps_assist_torque_nm"], dtype=float)
    assert np.isfinite(driver).mean() > 0.99 and np.isfinite(eps).mean() > 0.99  # optional: stale values null
    assert 0.3 < np.nanpercentile(np.abs(driver), 99) < 5.0  # nominal 0.01 N m a count: hands-on steering
    for name in ("gnss_speed_mps", "gnss_speed_accuracy_mps", "drive_force_n", "brake_force_n"):
        assert table[name].null_count == table.num_rows, name  # not in the log: not sent, never zero


def test_rav4_profile(rav4):
    importer, _ = rav4
    profile = importer.profile()
    assert profile.name == "toyota-rav4-2019" and profile.drive == "fwd"
    assert profile.wheelbase_m == pytest.approx(2.69) and 1600 <= profile.mass_kg <= 1700
    assert profile.wheel_radius_m == pytest.approx(0.355)
    assert CanDbcImporter().profile(RAV4) == profile
    with pytest.raises(ValueError, match="load one first"):
        CanDbcImporter().profile()


def test_rav4_replays_with_its_profile():
    importer = get_importer("can-dbc")
    rows = replay_file(RAV4, importer, start_ms=0)
    assert len(rows) == 1031 and rows[0]["timestamp_ms"] == 0 and "latitude_deg" not in rows[0]
    assert importer.profile().name == "toyota-rav4-2019"


def test_import_log_cli_round_trip_and_estimate(tmp_path):
    out = tmp_path / "rav4.csv"
    result = runner.invoke(app, ["import-log", str(RAV4), "--out", str(out)])
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())  # rich wraps lines at the terminal's width
    assert "wrote 1031 samples of 1 vehicle(s) (toyota-rav4-2019), 115.2 s" in said and "importer can-dbc" in said
    assert "dbc: toyota_rav4_2019.dbc" in said and "1031 of 1153 instants kept" in said
    batch = read_telemetry(out, wheel_radius_m=0.355)
    assert batch.table.num_rows == 1031 and not batch.rejections
    explicit = tmp_path / "rav4.parquet"
    result = runner.invoke(
        app,
        [
            "import-log",
            str(RAV4),
            "--importer",
            "can-dbc",
            "--out",
            str(explicit),
            "--vehicle-id",
            "rav4-a",
            "--start-ms",
            "0",
        ],
    )
    assert result.exit_code == 0, result.output
    table = pq.read_table(explicit)
    assert table["timestamp_ms"][0].as_py() == 0 and table["vehicle_id"][0].as_py() == "rav4-a"

    estimates = tmp_path / "e.csv"
    profile = ROOT / "roadgrip" / "fleet" / "importers" / "toyota_rav4_2019_profile.yaml"
    result = runner.invoke(
        app, ["estimate", "--input", str(out), "--model", "ekf", "--out", str(estimates), "--vehicle", str(profile)]
    )
    assert result.exit_code == 0, result.output
    assert "wrote 1031 estimates" in " ".join(result.output.split())
