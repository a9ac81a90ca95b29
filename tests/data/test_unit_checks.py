import math

import pyarrow as pa
import pyarrow.compute as pc
import pytest
from telemetry_samples import RADIUS_M, WHEEL_COLUMNS, drive, table_of, with_column

from roadgrip.data.telemetry import validate_telemetry
from roadgrip.sim.presets import paper_scenarios, random_scenarios
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.simulate import simulate


def scaled(table: pa.Table, names, factor: float) -> pa.Table:
    for name in names:
        table = table.set_column(table.column_names.index(name), name, pc.multiply(table[name], factor))
    return table


@pytest.mark.parametrize("radius", [RADIUS_M, None])
def test_speed_in_kmh_is_detected(clean, radius):
    with pytest.raises(ValueError, match=r"column speed_mps looks like km/h, not m/s: .*divide by 3\.6"):
        validate_telemetry(scaled(clean, ["speed_mps"], 3.6), wheel_radius_m=radius)


def test_speed_in_kmh_without_radius_or_acceleration_is_still_caught():
    steady = table_of(drive(accel_mps2=0.0, v0_mps=25.0))
    with pytest.raises(ValueError, match=r"speed_mps looks like km/h or mph, not m/s: .*wheel radius of 1\.26 m"):
        validate_telemetry(scaled(steady, ["speed_mps"], 3.6))
    with pytest.raises(ValueError, match="column speed_mps looks like km/h"):
        validate_telemetry(scaled(steady, ["speed_mps"], 3.6), wheel_radius_m=RADIUS_M)


@pytest.mark.parametrize("radius", [RADIUS_M, None])
def test_yaw_rate_in_degrees_per_second_is_detected(clean, radius):
    with pytest.raises(
        ValueError,
        match=r"column yaw_rate_radps looks like degrees per second, not rad/s: .*"
        r"99th percentile of \|yaw rate\| \d+.*convert it",
    ):
        validate_telemetry(scaled(clean, ["yaw_rate_radps"], 180.0 / math.pi), wheel_radius_m=radius)


@pytest.mark.parametrize("radius", [RADIUS_M, None])
@pytest.mark.parametrize(("factor", "unit"), [(60.0 / (2.0 * math.pi), "rpm"), (180.0 / math.pi, "degrees per second")])
def test_wheel_speeds_in_rpm_or_degrees_are_detected(clean, radius, factor, unit):
    with pytest.raises(
        ValueError,
        match=f"columns wheel_speed_fl_radps, wheel_speed_fr_radps, wheel_speed_rl_radps, "
        f"wheel_speed_rr_radps look like {unit}, not rad/s",
    ):
        validate_telemetry(scaled(clean, WHEEL_COLUMNS, factor), wheel_radius_m=radius)


def test_units_are_checked_vehicle_by_vehicle():
    fine, kmh = table_of(drive(vehicle_id="fine")), table_of(drive(vehicle_id="kmh", seed=1))
    fleet = pa.concat_tables([fine, scaled(kmh, ["speed_mps"], 3.6)])
    with pytest.raises(ValueError, match=r"vehicle kmh: column speed_mps looks like km/h") as err:
        validate_telemetry(fleet, wheel_radius_m=RADIUS_M)
    assert "vehicle fine" not in str(err.value)


def test_steering_in_degrees_accel_in_g_and_timestamps_in_seconds_are_detected(clean):
    with pytest.raises(ValueError, match="column steering_wheel_angle_rad looks like degrees, not rad"):
        validate_telemetry(scaled(clean, ["steering_wheel_angle_rad"], 180.0 / math.pi))
    with pytest.raises(ValueError, match=r"column accel_lon_mps2 looks like g, not m/s\^2"):
        validate_telemetry(scaled(clean, ["accel_lon_mps2"], 1.0 / 9.80665))
    seconds = with_column(clean, "timestamp_ms", (clean["timestamp_ms"].to_numpy() / 1000.0))
    with pytest.raises(ValueError, match="column timestamp_ms looks like seconds since the epoch"):
        validate_telemetry(seconds)


def test_a_wheel_radius_that_does_not_fit_is_an_error_or_a_warning(clean):
    with pytest.raises(ValueError, match="no unit of speed .* explains it"):
        validate_telemetry(clean, wheel_radius_m=0.745)  # ratio 0.47
    with pytest.raises(
        ValueError,
        match=r"0\.234 for speed in mph, wheel speeds in rpm\), but the rate of change of "
        r"speed_mps is 1\.\d+ times accel_lon_mps2, which says m/s",
    ):
        validate_telemetry(clean, wheel_radius_m=1.4)  # ratio 0.25, as mph and rpm would give
    batch = validate_telemetry(clean, wheel_radius_m=0.5)  # ratio 0.7: a wrong profile, not a wrong unit
    assert any("check wheel_radius_m=0.5 m" in w for w in batch.warnings)
    with pytest.raises(ValueError, match="wheel_radius_m"):
        validate_telemetry(clean, wheel_radius_m=0.0)


def test_a_parked_car_passes_without_unit_checks():
    columns = drive(n=100, accel_mps2=0.0, v0_mps=0.0)
    batch = validate_telemetry(table_of(columns))
    assert batch.rejections == []
    assert any("too few moving samples" in w and "units not verified" in w for w in batch.warnings)


def test_unit_checks_do_not_fire_on_the_paper_and_random_runs():
    scenarios = paper_scenarios() + random_scenarios(runs=20, seed=3, effects=ProductionEffects.off())
    table = simulate(scenarios)
    run_ids = table["run_id"]
    for scenario in scenarios:
        run = table.filter(pc.equal(run_ids, scenario.run_id))
        for radius in (scenario.vehicle.wheel_radius_m, None):
            batch = validate_telemetry(run, source=scenario.run_id, wheel_radius_m=radius)  # raises on a unit error
            assert not any("check" in w or "units not verified" in w for w in batch.warnings), batch.warnings
            if scenario.run_id.startswith("paper"):
                assert batch.rejections == []


def test_unit_checks_pass_production_terminal_runs():
    """With production-terminal realism (speed from the wheels, accelerometer mounting, bias and pitch, road grade) no
    run is refused. The speed-vs-acceleration slope still warns on a few cruising runs whose accelerations are mostly
    the grade (the accelerometer reads g sin(grade) that d(speed)/dt does not): 2 of these 20 runs, 4 of 80."""
    scenarios = random_scenarios(runs=20, seed=3)
    table = simulate(scenarios)
    run_ids = table["run_id"]
    warned = 0
    for scenario in scenarios:
        run = table.filter(pc.equal(run_ids, scenario.run_id))
        batch = validate_telemetry(run, source=scenario.run_id, wheel_radius_m=scenario.vehicle.wheel_radius_m)
        warned += any("check" in w or "units not verified" in w for w in batch.warnings)
    assert warned <= 2
