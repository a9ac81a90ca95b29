"""Production-terminal realism (roadgrip/sim/production.py): each effect against its closed form, each switched off
alone leaves every other signal as it was, and all of them off is bit for bit the sensor model of before."""

import dataclasses
import math

import numpy as np
import pytest

from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.production import SENSOR_FIELDS, ProductionDraw, ProductionEffects, ecu_speed, sensed_truth
from roadgrip.sim.roads import GradeProfile, MuProfile, Path
from roadgrip.sim.scenario import SAMPLE_PERIOD_S, Scenario
from roadgrip.sim.sensors import SensorModel
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2, kmh_to_mps
from roadgrip.vehicle.params import MIDSIZE_SEDAN, PAPER_SUV

WHEELS = ("fl", "fr", "rl", "rr")
ALL_ON = ProductionEffects.production()
SIGNALS = (
    "speed_mps",
    "accel_lon_mps2",
    "accel_lat_mps2",
    "yaw_rate_radps",
    "steering_wheel_angle_rad",
    *(f"wheel_speed_{w}_radps" for w in WHEELS),
)
# a FWD sedan: accelerates, cruises through a lane change, brakes hard without ABS (the wheels lock)
DRIVE = Scenario(
    "drive",
    Path.lane_changes(900.0, [200.0], [3.5], 40.0),
    MuProfile.uniform(0.8),
    SpeedProfile([0.0, 8.0, 14.0, 17.0, 20.0], [5.0, 25.0, 25.0, 0.0, 0.0]),
    vehicle=MIDSIZE_SEDAN,
    duration_s=20.0,
    abs_enabled=False,
    seed=7,
)


def run(scenario, sensors=SensorModel.noiseless()):
    table = simulate([scenario], sensors)
    return {name: table[name].to_numpy() for name in table.column_names if name not in ("vehicle_id", "run_id")}


@pytest.fixture(scope="module")
def clean():
    return run(DRIVE)


@pytest.fixture(scope="module")
def production():
    return run(DRIVE.replace(effects=ALL_ON))


def test_effects_off_is_the_sensor_model_of_before(clean):
    again = run(DRIVE.replace(effects=ProductionEffects.off()))
    for name in SIGNALS:
        assert np.array_equal(again[name], clean[name]), name
    noisy_before, noisy_now = run(DRIVE, SensorModel()), run(DRIVE.replace(effects=ProductionEffects()), SensorModel())
    for name in (*SIGNALS, "latitude_deg"):
        assert np.array_equal(noisy_before[name], noisy_now[name]), name


@pytest.mark.parametrize("field", SENSOR_FIELDS)
def test_each_effect_changes_only_its_own_signals(clean, field):
    on = dataclasses.replace(ProductionEffects.off(), **{field: getattr(ALL_ON, field)})
    out = run(DRIVE.replace(effects=on), SensorModel())
    base = run(DRIVE, SensorModel())
    speeds = {"speed_mps", *(f"wheel_speed_{w}_radps" for w in WHEELS)}
    own = {
        "speed_from_wheels": {"speed_mps"},
        "wheel_radius_spread": speeds - {"speed_mps"},
        "wheel_speed_resolution_kmh": speeds,
        "time_offset_max_s": set(SIGNALS),
        "accel_mount_max_rad": {"accel_lon_mps2", "accel_lat_mps2"},
        "accel_bias_max_mps2": {"accel_lon_mps2", "accel_lat_mps2"},
        "pitch_gradient_rad_per_mps2": {"accel_lon_mps2"},
    }[field]
    changed = {name for name in SIGNALS if not np.array_equal(out[name], base[name])}
    assert changed == own
    assert np.array_equal(out["latitude_deg"], base["latitude_deg"]) and np.array_equal(out["mu"], base["mu"])


def test_speed_is_the_undriven_wheels_mean_while_driving_fwd(production):
    p = production
    driving = ~p["abs_active"] & (p["t_s"] < 14.0) & (p["t_s"] > 0.5)
    rear_mps = 0.5 * (p["wheel_speed_rl_radps"] + p["wheel_speed_rr_radps"]) * MIDSIZE_SEDAN.wheel_radius_m
    step = kmh_to_mps(ALL_ON.wheel_speed_resolution_kmh)
    assert np.abs(p["speed_mps"] - rear_mps)[driving].max() <= step, "within the CAN resolution"
    front_mps = 0.5 * (p["wheel_speed_fl_radps"] + p["wheel_speed_fr_radps"]) * MIDSIZE_SEDAN.wheel_radius_m
    accelerating = driving & (p["t_s"] < 7.0) & (p["t_s"] > 1.0)
    assert (front_mps - rear_mps)[accelerating].mean() > 0.05, "the driven front wheels slip; the rear ones roll"


def test_speed_under_locked_wheels_falls_at_most_the_reference_deceleration(production, clean):
    p = production
    braking = (p["t_s"] > 14.5) & (p["vx_true_mps"] > 1.0)
    wheels = np.column_stack([p[f"wheel_speed_{w}_radps"] for w in WHEELS]) * MIDSIZE_SEDAN.wheel_radius_m
    assert (wheels[braking].min(axis=1) < 0.5).mean() > 0.7, "no ABS: the wheels lock"
    drop = -np.diff(p["speed_mps"])[braking[1:]] / SAMPLE_PERIOD_S
    assert drop.max() <= ALL_ON.reference_decel_max_mps2 + 0.1
    assert (p["speed_mps"] >= wheels.max(axis=1) - 0.01)[braking].all()
    error = (p["speed_mps"] - p["vx_true_mps"])[braking]
    assert np.abs(error).max() < 1.5, "the accelerometer carries the reference over the locked wheels"


def test_ecu_speed_for_each_layout():
    n = 6
    wheels = np.tile([10.4, 10.6, 10.0, 10.2], (n, 1))
    none = np.zeros(n, dtype=bool)
    assert ecu_speed(wheels, none, 1.0, 0.1, 12.0) == pytest.approx(10.1), "fwd: the rear wheels"
    assert ecu_speed(wheels, none, 0.0, 0.1, 12.0) == pytest.approx(10.5), "rwd: the front wheels"
    assert ecu_speed(wheels, none, 0.5, 0.1, 12.0) == pytest.approx(10.3), "awd cruising: all four"
    rising = wheels + np.arange(n)[:, None] * 0.2  # 2 m/s^2
    assert ecu_speed(rising, none, 0.5, 0.1, 12.0)[1:] == pytest.approx(rising[1:].min(axis=1)), "awd: the slowest"
    locked = np.vstack([wheels[:1], np.zeros((n - 1, 4))])
    speed = ecu_speed(locked, np.ones(n, dtype=bool), 1.0, 0.1, 12.0)
    assert speed == pytest.approx(np.maximum(10.6 - 1.2 * np.arange(n), 0.0)), "fastest wheel, falling at 12 m/s^2"
    aided = ecu_speed(locked, np.ones(n, dtype=bool), 1.0, 0.1, 12.0, np.full(n, -4.0))
    assert aided == pytest.approx(10.6 - 0.4 * np.arange(n)), "with an accelerometer: as fast as it says"
    assert ecu_speed(locked, np.ones(n, dtype=bool), 1.0, 0.1, 12.0, np.full(n, -30.0)) == pytest.approx(speed)


def test_accelerometer_reads_mounting_pitch_bias_and_grade_in_closed_form():
    t = np.arange(0.0, 2.0, 0.1)
    ax = np.linspace(-3.0, 3.0, t.size)
    truth = {
        "t_s": t,
        "ax_mps2": ax,
        "ay_mps2": np.full(t.size, 1.0),
        "roll_rad": np.full(t.size, 0.01),
        "grade_rad": np.full(t.size, 0.05),
        "yaw_rate_radps": np.zeros(t.size),
        "steer_rad": np.zeros(t.size),
        "vx_mps": np.full(t.size, 10.0),
        "brake_active": np.zeros(t.size),
        **{f"omega_{w}_radps": np.full(t.size, 30.0) for w in WHEELS},
    }
    draw = ProductionDraw(np.zeros(4), np.zeros(3), math.radians(1.0), math.radians(-0.5), np.array([0.1, -0.2]))
    effects = ProductionEffects(accel_mount_max_rad=0.1, accel_bias_max_mps2=0.2, pitch_gradient_rad_per_mps2=0.003)
    seen = sensed_truth(truth, effects, draw)
    theta = math.radians(1.0) + 0.003 * ax
    assert seen["ax_mps2"] == pytest.approx(ax * np.cos(theta) + G_MPS2 * math.cos(0.05) * np.sin(theta) + 0.1)
    assert seen["roll_rad"] == pytest.approx(0.01 - math.radians(0.5)) and seen["ay_mps2"] == pytest.approx(0.8)


def test_accelerometer_offset_against_dspeed_dt_has_the_configured_size():
    """Cruising on a level road: accel_lon - d(speed)/dt is the run's g sin(mounting) + bias, within the ranges."""
    effects = ProductionEffects(
        accel_mount_max_rad=ALL_ON.accel_mount_max_rad, accel_bias_max_mps2=0.2, speed_from_wheels=True
    )
    cruise = Scenario(
        "cruise",
        Path.straight(600.0),
        MuProfile.uniform(0.8),
        SpeedProfile([0.0], [20.0]),
        vehicle=MIDSIZE_SEDAN,
        duration_s=4.0,
        effects=effects,
    )
    table = simulate([cruise.replace(run_id=f"c{k}", seed=k) for k in range(24)], SensorModel.noiseless())
    offsets = []
    for k in range(24):
        rows = np.flatnonzero(np.array(table["run_id"].to_pylist()) == f"c{k}")[10:]
        dvdt = np.gradient(table["speed_mps"].to_numpy()[rows], SAMPLE_PERIOD_S)
        offsets.append((table["accel_lon_mps2"].to_numpy()[rows] - dvdt).mean())
    limit = G_MPS2 * math.sin(effects.accel_mount_max_rad) + effects.accel_bias_max_mps2
    assert np.abs(offsets).max() <= limit + 0.03
    expected_sd = math.sqrt((G_MPS2 * math.sin(effects.accel_mount_max_rad)) ** 2 / 3 + 0.2**2 / 3)  # two uniforms
    assert np.std(offsets) == pytest.approx(expected_sd, rel=0.4)


def test_rolling_radius_spread_shows_as_per_wheel_ratios_at_free_rolling():
    effects = ProductionEffects(wheel_radius_spread=0.02)
    cruise = Scenario(
        "cruise",
        Path.straight(600.0),
        MuProfile.uniform(0.8),
        SpeedProfile([0.0], [20.0]),
        vehicle=PAPER_SUV,
        duration_s=4.0,
        effects=effects,
        seed=3,
    )
    p = run(cruise)
    nominal = p["vx_true_mps"][10:] / PAPER_SUV.wheel_radius_m
    ratios = np.array([(p[f"wheel_speed_{w}_radps"][10:] / nominal) for w in WHEELS])
    assert ratios.std(axis=1).max() < 2e-3, "a constant ratio per wheel and run"
    mean = ratios.mean(axis=1)
    assert ((mean > 1 / 1.02 - 2e-3) & (mean < 1 / 0.98 + 2e-3)).all() and np.ptp(mean) > 2e-3
    base = run(cruise.replace(effects=ProductionEffects.off()))
    assert np.abs(base["wheel_speed_fl_radps"][10:] / nominal - 1.0).max() < 2e-3


def test_wheel_speeds_and_speed_are_quantised_to_the_can_resolution(production):
    step_mps = kmh_to_mps(0.01)
    for name in ("speed_mps", *(f"wheel_speed_{w}_radps" for w in WHEELS)):
        v = production[name] * (1.0 if name == "speed_mps" else MIDSIZE_SEDAN.wheel_radius_m)
        counts = v / step_mps
        assert np.abs(counts - np.round(counts)).max() < 1e-6, name
        assert np.unique(np.round(np.diff(np.unique(counts)), 6)).min() >= 1.0 - 1e-6


def test_time_offsets_shift_a_step_signal():
    t = np.arange(0.0, 3.0, 0.1)
    step = (t >= 1.0).astype(float)
    truth = {
        "t_s": t,
        "ax_mps2": step,
        "ay_mps2": step,
        "roll_rad": 0 * t,
        "grade_rad": 0 * t,
        "yaw_rate_radps": step,
        "steer_rad": step,
        "vx_mps": step,
        "brake_active": 0 * t,
        **{f"omega_{w}_radps": step for w in WHEELS},
    }
    draw = ProductionDraw(np.zeros(4), np.array([0.05, -0.05, 0.1]), 0.0, 0.0, np.zeros(2))
    seen = sensed_truth(truth, ProductionEffects(time_offset_max_s=0.1), draw)
    k = int(np.flatnonzero(t >= 1.0)[0])
    assert seen["omega_fl_radps"][k - 1] == pytest.approx(0.5), "wheels 50 ms ahead: half way up at 0.9 s"
    assert seen["yaw_rate_radps"][k] == pytest.approx(0.5) and seen["ax_mps2"][k] == pytest.approx(0.5), "IMU late"
    assert seen["steer_rad"][k - 1] == pytest.approx(1.0), "steering 100 ms ahead: up a sample early"
    assert seen["ay_mps2"][k + 1] == 1.0 and seen["steer_rad"][0] == 0.0


def test_same_seed_same_production_data():
    scenario = DRIVE.replace(effects=ALL_ON, grade=GradeProfile([0.0, 300.0], [0.03, -0.03]))
    a, b = simulate([scenario]), simulate([scenario])
    assert a.equals(b)
    c = simulate([scenario.replace(seed=8)])
    assert not np.array_equal(a["speed_mps"].to_numpy(), c["speed_mps"].to_numpy())


def test_effects_reject_bad_values():
    with pytest.raises(ValueError, match=r"ProductionEffects.wheel_radius_spread must be in \[0.0, 0.2\], got 0.5"):
        ProductionEffects(wheel_radius_spread=0.5)
    with pytest.raises(TypeError, match="speed_from_wheels must be a bool"):
        ProductionEffects(speed_from_wheels=1)
    with pytest.raises(ValueError, match="production effects need the vehicle"):
        SensorModel().measure({"t_s": np.zeros(2)}, 16.0, 0.1, np.random.default_rng(0), effects=ALL_ON)
