"""Importers of recorded logs (roadgrip/fleet/importers): the registry and its entry points, the wire importer, and the
BMW M8 log: clock alignment, resampling, units and signs, the profile, and what the EKF makes of it."""

import logging
import math
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pytest
from typer.testing import CliRunner

import roadgrip.fleet.importers as registry
from roadgrip.cli import app
from roadgrip.data.schema import WHEELS
from roadgrip.data.tables import write_table
from roadgrip.data.telemetry import TELEMETRY_SCHEMA, read_telemetry, validate_telemetry
from roadgrip.fleet.importers import (
    ENTRY_POINT_GROUP,
    Importer,
    detect_importer,
    get_importer,
    importers,
    load_entry_points,
    register_importer,
)
from roadgrip.fleet.importers.bmw_m8 import (
    DEFAULT_START_MS,
    FAST_FILE,
    SLOW_FILE,
    BmwM8Importer,
    estimate_clock_offset,
    grid_means,
    m8_profile,
)
from roadgrip.fleet.importers.wire import WireImporter
from roadgrip.vehicle.params import VehicleParams

ROOT = Path(__file__).resolve().parents[2]
LOG = ROOT / "data" / "real" / "bmw_m8_braking"  # the real log, kept in the repository (its README: source, licence)
WHEEL_COLUMNS = [f"wheel_speed_{w}_radps" for w in WHEELS]
runner = CliRunner()


@pytest.fixture(scope="module")
def m8():
    """The real log, imported with the defaults."""
    return BmwM8Importer().load(LOG)


# --------------------------------------------------------------------------------------------------- registry


@pytest.fixture
def fresh_registry(monkeypatch):
    """The registry as after import (built-ins only), restored after the test."""
    monkeypatch.setattr(registry, "_REGISTRY", {k: v for k, v in registry._REGISTRY.items() if k in ("wire", "bmw-m8")})
    monkeypatch.setattr(registry, "_FAILED", {})
    monkeypatch.setattr(registry, "_entry_points_loaded", False)
    monkeypatch.setattr(registry, "entry_points", lambda group: [])
    return registry


class TextLogImporter:
    """A toy third-party format: `.txtlog` files of `t_s speed` lines."""

    name = "txtlog"

    def detect(self, path):
        return Path(path).suffix == ".txtlog"

    def load(self, path, vehicle_id="txt", start_ms=0):
        rows = [line.split() for line in Path(path).read_text().splitlines() if line.strip()]
        n = len(rows)
        speed = [float(r[1]) for r in rows]
        return pa.table(
            {
                "vehicle_id": [vehicle_id] * n,
                "timestamp_ms": [start_ms + round(float(r[0]) * 1000) for r in rows],
                "speed_mps": speed,
                "accel_lon_mps2": [0.0] * n,
                "accel_lat_mps2": [0.0] * n,
                "yaw_rate_radps": [0.0] * n,
                "steering_wheel_angle_rad": [0.0] * n,
                **{c: [v / 0.3 for v in speed] for c in WHEEL_COLUMNS},
                "abs_active": [False] * n,
                "acc_active": [False] * n,
            }
        )


def test_builtin_importers_are_registered(fresh_registry):
    assert list(importers()) == ["wire", "bmw-m8"]
    assert isinstance(get_importer("wire"), WireImporter) and isinstance(get_importer("bmw-m8"), BmwM8Importer)
    assert all(isinstance(i, Importer) for i in importers().values())


def test_unknown_importer_names_the_known_ones(fresh_registry):
    with pytest.raises(ValueError, match=r"importer must be one of \['bmw-m8', 'wire'\], got 'csv2'"):
        get_importer("csv2")


def test_register_checks_what_it_is_given(fresh_registry):
    with pytest.raises(TypeError, match="importer object, got the class"):
        register_importer(TextLogImporter)

    class Nameless:
        def detect(self, path):
            return False

        def load(self, path):
            return None

    with pytest.raises(TypeError, match="name"):
        register_importer(Nameless())

    class NoLoad:
        name = "noload"

        def detect(self, path):
            return False

    with pytest.raises(TypeError, match="lacks the method.*load"):
        register_importer(NoLoad())


def test_register_refuses_a_taken_name_unless_replacing(fresh_registry):
    first = register_importer(TextLogImporter())
    assert get_importer("txtlog") is first
    with pytest.raises(ValueError, match="already registered"):
        register_importer(TextLogImporter())
    second = register_importer(TextLogImporter(), replace=True)
    assert get_importer("txtlog") is second
    assert register_importer(second) is second  # the same object again is no conflict


def test_detection_picks_the_importer_of_the_file(fresh_registry, tmp_path):
    register_importer(TextLogImporter())
    (tmp_path / "a.txtlog").write_text("0 1\n0.1 1.2\n")
    (tmp_path / "notes.txt").write_text("hello")
    assert detect_importer(tmp_path / "a.txtlog").name == "txtlog"
    with pytest.raises(ValueError, match="no importer recognises"):
        detect_importer(tmp_path / "notes.txt")
    with pytest.raises(FileNotFoundError):
        detect_importer(tmp_path / "missing.csv")


PLUGIN = """
from pathlib import Path


class TextLogImporter:
    name = "txtlog"

    def detect(self, path):
        return Path(path).suffix == ".txtlog"

    def load(self, path, **options):
        return "loaded " + Path(path).name


instance = TextLogImporter()
misnamed = TextLogImporter()
misnamed.name = "other"
"""


def _entry_points(tmp_path, monkeypatch, specs):
    """A fake plug-in module on sys.path and `entry_points` answering with real EntryPoint objects for it."""
    (tmp_path / "roadgrip_fake_plugin.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    eps = [EntryPoint(name, value, ENTRY_POINT_GROUP) for name, value in specs]

    def fake(group):
        return eps if group == ENTRY_POINT_GROUP else []

    monkeypatch.setattr(registry, "entry_points", fake)


@pytest.mark.parametrize("target", ["roadgrip_fake_plugin:TextLogImporter", "roadgrip_fake_plugin:instance"])
def test_an_entry_point_registers_a_third_party_importer(fresh_registry, tmp_path, monkeypatch, target):
    """Both forms: the entry point names a class (instantiated) or an importer object."""
    _entry_points(tmp_path, monkeypatch, [("txtlog", target)])
    assert list(importers()) == ["wire", "bmw-m8", "txtlog"]  # loaded lazily, on the first question
    (tmp_path / "run.txtlog").write_text("0 1\n")
    found = detect_importer(tmp_path / "run.txtlog")
    assert found is get_importer("txtlog") and found.load(tmp_path / "run.txtlog") == "loaded run.txtlog"
    assert load_entry_points() == []  # already there: nothing new


def test_a_broken_entry_point_is_skipped_and_explained(fresh_registry, tmp_path, monkeypatch, caplog):
    _entry_points(
        tmp_path,
        monkeypatch,
        [
            ("gone", "roadgrip_no_such_module:Importer"),
            ("other2", "roadgrip_fake_plugin:misnamed"),
            ("txtlog", "roadgrip_fake_plugin:instance"),
        ],
    )
    with caplog.at_level(logging.WARNING, logger="roadgrip.fleet.importers"):
        names = list(importers())
    assert names == ["wire", "bmw-m8", "txtlog"]
    assert "gone" in caplog.text and "other2" in caplog.text
    with pytest.raises(ValueError, match="'gone' is not available: .*ModuleNotFoundError"):
        get_importer("gone")
    with pytest.raises(ValueError, match="named 'other', not 'other2'"):
        get_importer("other2")


def test_entry_points_cannot_replace_a_builtin(fresh_registry, tmp_path, monkeypatch):
    _entry_points(tmp_path, monkeypatch, [("wire", "roadgrip_fake_plugin:instance")])
    assert isinstance(get_importer("wire"), WireImporter)


# ------------------------------------------------------------------------------------------------ wire importer


@pytest.mark.parametrize("suffix", [".csv", ".parquet", ".ndjson", ".jsonl"])
def test_wire_importer_reads_back_what_was_written(m8, tmp_path, suffix):
    path = write_table(m8, tmp_path / f"m8{suffix}")
    assert detect_importer(path).name == "wire"
    back = WireImporter().load(path)
    assert back.select(TELEMETRY_SCHEMA.names).equals(m8.select(TELEMETRY_SCHEMA.names))


def test_wire_importer_options(m8, tmp_path):
    path = write_table(m8, tmp_path / "m8.parquet")
    out = WireImporter().load(path, vehicle_id="car-7", start_ms=5_000, wheel_radius_m=0.345)
    assert set(out["vehicle_id"].to_pylist()) == {"car-7"}
    assert out["timestamp_ms"].to_pylist()[:2] == [5_000, 5_100]
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['speed'\]"):
        WireImporter().load(path, speed=2)
    with pytest.raises(ValueError, match="vehicle_id must match"):
        WireImporter().load(path, vehicle_id="a b")
    with pytest.raises(ValueError, match="start_ms"):
        WireImporter().load(path, start_ms=-1)


def test_wire_importer_refuses_to_merge_vehicles(m8, tmp_path):
    two = pa.concat_tables([m8, m8.set_column(0, m8.schema.field(0), pa.array(["other"] * m8.num_rows))])
    path = write_table(two, tmp_path / "two.parquet")
    assert WireImporter().load(path).num_rows == 2 * m8.num_rows
    with pytest.raises(ValueError, match="holds 2 vehicles"):
        WireImporter().load(path, vehicle_id="one")


def test_wire_detection_needs_wire_columns(tmp_path):
    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    (tmp_path / "y.json").write_text('[{"t_s": 0, "speed_mps": 1, "accel_lon_mps2": 0}]')
    (tmp_path / "z.ndjson").write_text('{"timestamp_ms": 0, "speed_mps": 1, "accel_lon_mps2": 0}\n')
    assert not WireImporter().detect(tmp_path / "x.csv")
    assert WireImporter().detect(tmp_path / "y.json") and WireImporter().detect(tmp_path / "z.ndjson")
    assert not WireImporter().detect(tmp_path)


# ------------------------------------------------------------------------------------ synthetic BMW-style logs


def _synthetic_log(
    folder: Path, *, offset_s: float, seed: int = 0, vibration_hz: float = 0.0, radius_m: float = 0.345
) -> dict:
    """A log folder in the BMW M8 layout with a known truth: accelerate at 4 m/s^2 for 4 s, coast, brake at
    9 m/s^2 to a stop, each change of acceleration a 0.2 s ramp (as brake pressure and engine torque build up), at
    940 Hz (fast) and 94 Hz (slow), speed quantised to 5 mm/s like the real one; the slow clock runs `offset_s`
    behind (time = car_time + offset_s). Returns the truth as functions of the fast clock."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    fine = np.arange(0.0, 12.0, 1e-4)
    steps = np.select([fine < 1.0, fine < 5.0, fine < 7.0, fine < 8.65], [0.0, 4.0, -0.5, -9.0], 0.0)
    accel_fine = np.convolve(steps, np.ones(2000) / 2000, "same")  # 0.2 s ramps
    speed_fine = np.maximum(np.cumsum(accel_fine) * 1e-4, 0.0)

    def accel(t):
        return np.interp(t, fine, accel_fine)

    def speed(t):
        return np.interp(t, fine, speed_fine)

    t_fast = np.arange(0.0, 10.0, 1 / 940)
    v = np.round(speed(t_fast) / 0.005) * 0.005
    wheel = speed(t_fast) / radius_m + 0.3 * np.sin(2 * np.pi * vibration_hz * t_fast + 0.7)
    fast = {
        "time": t_fast,
        "steering": np.full(t_fast.size, 0.001),
        "throttle": np.zeros(t_fast.size),
        "brake": np.zeros(t_fast.size),
        "Velocity_X": v,
        "Velocity_Y": np.zeros(t_fast.size),
        **{f"v_wheel_{w}": wheel + rng.normal(0, 0.05, t_fast.size) for w in WHEELS},
    }
    t_slow = np.arange(-3.0, 14.0, 1 / 94)  # car_time
    on_fast = t_slow + offset_s
    s = np.cumsum(speed(on_fast)) / 94
    slow = {
        "car_time": t_slow,
        "Acceleration_X": accel(on_fast) + rng.normal(0, 0.1, t_slow.size),
        "Acceleration_Y": rng.normal(0, 0.05, t_slow.size),
        "Acceleration_Z": np.zeros(t_slow.size),
        "Yaw_Velocity": rng.normal(0, 0.001, t_slow.size),
        "Roll_Velocity": np.zeros(t_slow.size),
        "Pitch_Velocity": np.zeros(t_slow.size),
        "Roll": np.zeros(t_slow.size),
        "Pitch": np.zeros(t_slow.size),
        "Yaw": np.full(t_slow.size, math.pi / 4),
        "Rel_pos_x": s * math.cos(math.pi / 4),
        "Rel_pos_y": s * math.sin(math.pi / 4),
    }
    pacsv.write_csv(pa.table(fast), folder / FAST_FILE)
    pacsv.write_csv(pa.table(slow), folder / SLOW_FILE)
    return {"speed": speed, "accel": accel}


@pytest.mark.parametrize("offset_s", [0.0, 0.237, -0.412])
def test_clock_alignment_recovers_a_known_offset(tmp_path, offset_s):
    _synthetic_log(tmp_path, offset_s=offset_s)
    fast = pacsv.read_csv(tmp_path / FAST_FILE)
    slow = pacsv.read_csv(tmp_path / SLOW_FILE)
    found, corr = estimate_clock_offset(
        fast["time"].to_numpy(),
        fast["Velocity_X"].to_numpy(),
        slow["car_time"].to_numpy(),
        slow["Acceleration_X"].to_numpy(),
    )
    assert found == pytest.approx(offset_s, abs=0.002)  # the grid is 5 ms, the slow log's period 10.6 ms
    assert corr > 0.9
    table = BmwM8Importer().load(tmp_path)
    assert float(table.schema.metadata[b"roadgrip.clock_offset_s"]) == pytest.approx(offset_s, abs=0.002)


def test_aligned_import_puts_acceleration_and_speed_on_one_clock(tmp_path):
    """With a 0.3 s offset injected, the imported accel_lon matches d(speed)/dt; imported with the offset ignored
    (clock_offset_s=0) it lags by three samples and matches far worse."""
    _synthetic_log(tmp_path, offset_s=0.3)

    def mismatch(table):
        v, a = table["speed_mps"].to_numpy(), table["accel_lon_mps2"].to_numpy()
        dv = np.gradient(v, 0.1)
        return float(np.sqrt(np.mean((dv - a)[5:-5] ** 2)))

    aligned = mismatch(BmwM8Importer().load(tmp_path))
    naive = mismatch(BmwM8Importer().load(tmp_path, clock_offset_s=0.0))
    assert aligned < 1.0 and naive > 2 * aligned


def test_alignment_needs_motion(tmp_path):
    t = np.arange(0, 5, 0.001)
    rng = np.random.default_rng(1)
    with pytest.raises(ValueError, match="cannot align the clocks"):
        estimate_clock_offset(t, np.zeros(t.size), t[::10], rng.normal(0, 0.1, t[::10].size))


def test_grid_means_average_each_bin():
    t = np.array([0.00, 0.04, 0.09, 0.10, 0.15, 0.31])
    x = np.array([1.0, 2.0, 6.0, 10.0, 20.0, 7.0])
    out = grid_means(t, x, 0.0, 0.1, 4)
    assert out[:2] == pytest.approx([3.0, 15.0]) and np.isnan(out[2]) and out[3] == pytest.approx(7.0)


def test_resampling_averages_instead_of_picking(tmp_path):
    """A 50 Hz vibration of the wheel speed (0.3 rad/s) fills each 100 ms bin with five whole periods: the bin mean
    cancels it, where picking one sample per 100 ms keeps an error of 0.3 sin(phase) in every sample (50 Hz aliases
    to 0 Hz at 10 Hz sampling)."""
    truth = _synthetic_log(tmp_path, offset_s=0.0, vibration_hz=50.0)
    table = BmwM8Importer().load(tmp_path, clock_offset_s=0.0)
    k = (table["timestamp_ms"].to_numpy() - DEFAULT_START_MS) // 100  # bin k covers [0.1 k, 0.1 k + 0.1) s
    fine = np.arange(0.0, 10.0, 1e-5)
    expected = grid_means(fine, truth["speed"](fine) / 0.345, 0.0, 0.1, int(k.max()) + 1)[k]
    fast = pacsv.read_csv(tmp_path / FAST_FILE)
    t_fast = fast["time"].to_numpy()
    centre = np.searchsorted(t_fast, 0.1 * k + 0.05)  # one sample per bin: the pick that aliases
    for c, w in zip(WHEEL_COLUMNS, WHEELS, strict=True):
        assert np.abs(table[c].to_numpy() - expected).max() < 0.05  # the noise of 94 samples, not the vibration
        picked = fast[f"v_wheel_{w}"].to_numpy()[centre]
        assert np.median(np.abs(picked - expected)) > 0.1


def test_import_options_and_errors(tmp_path):
    _synthetic_log(tmp_path / "log", offset_s=0.0)
    table = BmwM8Importer().load(
        tmp_path / "log",
        vehicle_id="m8-2",
        start_ms=1_000,
        origin_lat_deg=57.7,
        origin_lon_deg=11.97,
        clock_offset_s=0.0,
        steering_full_scale_rad=10.0,
    )
    assert set(table["vehicle_id"].to_pylist()) == {"m8-2"} and table["timestamp_ms"][0].as_py() == 1_000
    assert table["latitude_deg"][0].as_py() == pytest.approx(57.7, abs=1e-3)
    assert table["steering_wheel_angle_rad"].to_numpy() == pytest.approx(0.01)
    assert table.schema.metadata[b"roadgrip.clock_offset_method"] == b"given"
    with pytest.raises(ValueError, match="unknown option"):
        BmwM8Importer().load(tmp_path / "log", origin=(1, 2))
    with pytest.raises(ValueError, match="origin_lat_deg must be a number in"):
        BmwM8Importer().load(tmp_path / "log", origin_lat_deg=91)
    with pytest.raises(ValueError, match="not a BMW M8 log"):
        BmwM8Importer().load(tmp_path)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / FAST_FILE).write_text("time,steering\n0,0\n")
    (tmp_path / "bad" / SLOW_FILE).write_text((tmp_path / "log" / SLOW_FILE).read_text())
    assert not BmwM8Importer().detect(tmp_path / "bad")
    with pytest.raises(ValueError, match=r"lacks the column\(s\) \['Velocity_X'"):
        BmwM8Importer().load(tmp_path / "bad")


# -------------------------------------------------------------------------------------------------- the real log


def test_m8_profile_loads_with_the_recordings_values():
    p = m8_profile()
    assert isinstance(p, VehicleParams) and p.name == "bmw-m8" and p.drive == "awd"
    assert (p.mass_kg, p.wheelbase_m, p.cg_to_front_axle_m, p.steering_ratio) == (2074.4, 2.827, 1.331, 14.3)
    assert p.cg_to_rear_axle_m == pytest.approx(1.496)
    assert 0.34 <= p.wheel_radius_m <= 0.355


def test_detects_the_log_folder_and_its_files():
    assert detect_importer(LOG).name == "bmw-m8"
    assert detect_importer(LOG / FAST_FILE).name == "bmw-m8"
    assert not WireImporter().detect(LOG / SLOW_FILE)


def test_real_log_gives_clean_10_hz_wire_telemetry(m8):
    ts = m8["timestamp_ms"].to_numpy()
    assert m8.schema.equals(TELEMETRY_SCHEMA)
    assert ts[0] == DEFAULT_START_MS and set(np.diff(ts)) == {100}
    assert 90 <= m8.num_rows <= 96  # 9.6 s of fast signals
    batch = validate_telemetry(m8, wheel_radius_m=m8_profile().wheel_radius_m)
    assert batch.rejections == [] and batch.warnings == []  # no rejection, no unit warning
    assert batch.table.num_rows == m8.num_rows and set(batch.segments) == {0}
    assert not any(m8["abs_active"].to_pylist()) and not any(m8["acc_active"].to_pylist())


def test_real_log_clocks_agree_as_its_readme_says(m8):
    """The README: slow_signals' car_time is 'the same clock as time'. The cross-correlation agrees within 10 ms (the
    slow logger's period)."""
    assert abs(float(m8.schema.metadata[b"roadgrip.clock_offset_s"])) < 0.01


def test_real_log_speed_agrees_with_wheel_speed_times_radius(m8):
    v = m8["speed_mps"].to_numpy()
    ax = m8["accel_lon_mps2"].to_numpy()
    gentle = (v > 5.0) & (np.abs(ax) < 3.0)  # rolling: coasting, not braking or launching hard
    assert gentle.sum() >= 15
    radius = m8_profile().wheel_radius_m
    for c in WHEEL_COLUMNS:
        ratio = v[gentle] / (m8[c].to_numpy()[gentle] * radius)
        assert np.median(ratio) == pytest.approx(1.0, abs=0.01)
        assert np.abs(ratio - 1.0).max() < 0.03


def test_real_log_braking_is_negative_accel_lon_and_matches_the_speed(m8):
    v = m8["speed_mps"].to_numpy()
    ax = m8["accel_lon_mps2"].to_numpy()
    dv = np.gradient(v, 0.1)
    braking = dv < -5.0
    assert braking.sum() >= 8  # the stop from 19 m/s at about 1.2 g
    assert (ax[braking] < -5.0).all() and ax.min() < -10.0
    assert np.median(np.abs(ax[braking] - dv[braking])) < 1.0
    assert ax.max() > 4.0 and v.max() == pytest.approx(21.8, abs=0.3)  # the launch, the top speed


def test_real_log_positions_follow_the_speed(m8):
    import pymap3d

    lat, lon = m8["latitude_deg"].to_numpy(), m8["longitude_deg"].to_numpy()
    e, n, _ = pymap3d.geodetic2enu(lat, lon, 0.0, 48.7665, 11.4326, 0.0)
    path_m = np.sum(np.hypot(np.diff(e), np.diff(n)))
    travelled_m = np.sum(m8["speed_mps"].to_numpy()) * 0.1
    assert path_m == pytest.approx(travelled_m, rel=0.05) and 90 < path_m < 110
    heading = math.atan2(n[-1] - n[0], e[-1] - e[0])
    assert heading == pytest.approx(1.0, abs=0.1)  # the log's Yaw, about 1.05 rad


def test_real_log_lateral_signals_agree_in_sign(m8):
    """Steering, yaw rate and lateral acceleration tell one story: the path curvature (yaw rate / speed) follows the
    steering-wheel angle (positive left for both) with the slope of kinematic steering, 1 / (i_s L), or a little
    less (understeer); and ay = v r. The track is nearly straight, but these small signals still correlate."""
    v, r = m8["speed_mps"].to_numpy(), m8["yaw_rate_radps"].to_numpy()
    sw, ay = m8["steering_wheel_angle_rad"].to_numpy(), m8["accel_lat_mps2"].to_numpy()
    moving = v > 8.0
    kappa = r[moving] / v[moving]
    assert np.corrcoef(sw[moving], kappa)[0, 1] > 0.95
    slope = np.polyfit(sw[moving], kappa, 1)[0]
    p = m8_profile()
    assert 1.0 <= 1.0 / (slope * p.steering_ratio * p.wheelbase_m) <= 1.3  # 1: no understeer
    assert np.corrcoef(ay[v > 5.0], (v * r)[v > 5.0])[0, 1] > 0.8


def test_ekf_runs_on_the_real_log(m8):
    """The EKF with the M8's profile gives a finite estimate inside its interval for every sample. What it estimates
    on this dry road is reported (docs), not asserted: there is no friction ground truth. Two things follow from
    physics alone: the braking at over 1 g is excited (utilization >= 0.5 for any mu <= 2, CONTRACTS 4), and where it
    judges a sample excited its interval cannot lie below the friction the tyres were seen to use (|a| / g, less
    0.1 for accelerometer error and pitch)."""
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.units import G_MPS2

    batch = validate_telemetry(m8, wheel_radius_m=m8_profile().wheel_radius_m)
    est = load_estimator("ekf").estimate_batch(batch.table, batch.segments, m8_profile())
    assert est["timestamp_ms"].to_pylist() == m8["timestamp_ms"].to_pylist()
    mu, lo, hi = (est[c].to_numpy() for c in ("mu", "mu_lower", "mu_upper"))
    assert np.isfinite(mu).all() and np.isfinite(lo).all() and np.isfinite(hi).all()
    assert (lo <= mu).all() and (mu <= hi).all()
    excited = est["excited"].to_numpy(zero_copy_only=False)
    used = np.hypot(m8["accel_lon_mps2"].to_numpy(), m8["accel_lat_mps2"].to_numpy()) / G_MPS2
    assert excited[used > 1.0].any()
    assert (hi[excited] >= used[excited] - 0.1).all()


def test_cli_import_log_writes_a_wire_file(tmp_path):
    out = tmp_path / "m8.csv"
    result = runner.invoke(
        app, ["import-log", str(LOG), "--out", str(out), "--vehicle-id", "m8-cli", "--start-ms", "1700000000000"]
    )
    assert result.exit_code == 0, result.output
    assert "bmw-m8" in result.output and "clock_offset_s" in result.output
    batch = read_telemetry(out, wheel_radius_m=m8_profile().wheel_radius_m)
    assert batch.rejections == [] and batch.warnings == []
    assert set(batch.table["vehicle_id"].to_pylist()) == {"m8-cli"}
    assert batch.table["timestamp_ms"][0].as_py() == 1_700_000_000_000


def test_cli_import_log_errors_are_friendly(tmp_path):
    result = runner.invoke(app, ["import-log", str(LOG), "--out", str(tmp_path / "m8.xlsx")])
    assert result.exit_code == 2 and "--out must end in one of" in result.output
    result = runner.invoke(app, ["import-log", str(LOG), "--out", str(tmp_path / "m8.csv"), "--importer", "nope"])
    assert result.exit_code == 2 and "importer must be one of" in result.output
    result = runner.invoke(app, ["import-log", str(tmp_path), "--out", str(tmp_path / "m8.csv")])
    assert result.exit_code == 2 and "no importer recognises" in result.output
    assert not (tmp_path / "m8.csv").exists()
