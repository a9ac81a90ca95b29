"""Feature set `production` (roadgrip/features/production.py): closed forms on kinematic wheel speeds, no use of the
reported speed, batch and stream alike."""

import numpy as np
import pyarrow as pa
import pytest

from roadgrip.features.production import SPEED_FLOOR_MPS
from roadgrip.features.windows import feature_columns, feature_matrix, features_from_columns, vehicle_profile
from roadgrip.sim.presets import generalization_scenarios
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import PAPER_SUV

NAMES = feature_columns("production")
PROFILE = vehicle_profile(PAPER_SUV)
R = PAPER_SUV.wheel_radius_m


def telemetry(v_fl, v_fr, v_rl, v_rr, ax=0.0, ay=0.0, yaw=0.0, steer=0.0, dt_s=0.1, **extra) -> pa.Table:
    """A table of wheel rolling speeds (m/s, arrays or numbers) and body signals, sampled every dt_s."""
    n = max(np.size(x) for x in (v_fl, v_fr, v_rl, v_rr, ax, ay, yaw, steer))
    full = lambda x: np.broadcast_to(np.asarray(x, dtype=np.float64), (n,)).copy()
    cols = {
        "timestamp_ms": (np.arange(n) * dt_s * 1000).astype(np.int64),
        "accel_lon_mps2": full(ax),
        "accel_lat_mps2": full(ay),
        "yaw_rate_radps": full(yaw),
        "steering_wheel_angle_rad": full(steer),
        "abs_active": np.zeros(n, dtype=bool),
    }
    for w, v in zip(("fl", "fr", "rl", "rr"), (v_fl, v_fr, v_rl, v_rr)):
        cols[f"wheel_speed_{w}_radps"] = full(v) / R
    return pa.table(cols | extra)


def features(table, **kwargs) -> dict:
    x = feature_matrix(table, "production", profile=PROFILE, **kwargs)
    return {name: x[:, k].astype(np.float64) for k, name in enumerate(NAMES)}


def test_front_tires_one_percent_larger_give_the_normalised_axle_difference():
    # at 25 m/s a front tire of radius 1.01 r spins at v / (1.01 r): the sensor, scaled by r, reports v / 1.01
    v = 25.0
    f = features(telemetry(v / 1.01, v / 1.01, v, v))
    expected = (v / 1.01 - v) / ((v / 1.01 + v) / 2)
    assert f["axle_slip"] == pytest.approx(expected, abs=1e-6)
    assert f["side_slip_front"] == pytest.approx(0.0, abs=1e-6) and f["side_slip_rear"] == pytest.approx(0.0, abs=1e-6)
    assert f["wheel_speed_mps"] == pytest.approx((v / 1.01 + v) / 2, rel=1e-6)


def test_a_kinematic_turn_reads_no_slip():
    """Rear axle rolling at v without sideslip, yaw rate r: each wheel centre moves at |(v - r y, r x)|; the yaw
    corrections take the turn out of the left/right and front/rear differences."""
    v, r = 20.0, 0.2  # 0.41 g of centripetal acceleration
    a, tf, tr = PAPER_SUV.wheelbase_m, PAPER_SUV.track_front_m, PAPER_SUV.track_rear_m
    speed = lambda x, y: np.hypot(v - r * y, r * x)
    table = telemetry(
        speed(a, tf / 2),
        speed(a, -tf / 2),
        speed(0, tr / 2),
        speed(0, -tr / 2),
        ay=r * v,
        yaw=r,
        steer=PAPER_SUV.steering_ratio * np.arctan(a * r / v),
    )
    f = features(table)
    for name in ("axle_slip", "side_slip_front", "side_slip_rear"):
        assert f[name] == pytest.approx(0.0, abs=2e-4), name
    assert f["centripetal_g"] == pytest.approx(r * v / G_MPS2, rel=1e-3)
    assert f["understeer_g"] == pytest.approx(0.0, abs=2e-3)  # Ackermann steering: the yaw rate it asks for
    assert f["utilization_g"] == pytest.approx(r * v / G_MPS2, rel=1e-6)


def test_wheel_speed_rates_against_the_accelerometer():
    """Braking at 5 m/s^2 with the rear wheels following the body and the front wheels decelerating 1 m/s^2 more:
    0 and -1 / g; the first sample has no previous one: 0."""
    t = np.arange(20) * 0.1
    body = 30.0 - 5.0 * t
    f = features(telemetry(body - t, body - t, body, body, ax=-5.0))
    assert f["wheel_accel_rear_g"] == pytest.approx(np.zeros(20), abs=1e-6)
    assert f["wheel_accel_front_g"][1:] == pytest.approx(np.full(19, -1.0 / G_MPS2), abs=1e-6)
    assert f["wheel_accel_front_g"][0] == 0.0
    # a new segment restarts the differences; so does a gap in time
    seg = features(telemetry(body - t, body - t, body, body, ax=-5.0), segments=np.repeat([0, 1], 10))
    assert seg["wheel_accel_front_g"][10] == 0.0 and seg["wheel_accel_front_g"][11] != 0.0


def test_standstill_is_finite_and_the_ratios_are_bounded():
    f = features(telemetry(np.zeros(5), np.zeros(5), 0.0, 0.0, yaw=0.01))
    assert all(np.isfinite(f[n]).all() for n in NAMES)
    assert f["side_slip_front"] == pytest.approx(np.full(5, 0.01 * PAPER_SUV.track_front_m / SPEED_FLOOR_MPS))


def test_the_reported_speed_is_not_read_and_absent_or_null_flags_read_zero():
    table = telemetry(20.0, 20.1, 20.2, 20.3)
    assert "speed_mps" not in table.column_names  # the set needs no speed signal at all
    f = features(table)
    assert (f["tcs_active"] == 0).all() and (f["esc_active"] == 0).all()
    flagged = telemetry(
        20.0, 20.1, 20.2, 20.3, tcs_active=pa.array([None], pa.bool_()), esc_active=pa.array([True], pa.bool_())
    )
    g = features(flagged)
    assert g["tcs_active"][0] == 0.0 and g["esc_active"][0] == 1.0
    with pytest.raises(ValueError, match="needs column"):
        feature_matrix(table.drop_columns(["timestamp_ms"]), "production", profile=PROFILE)
    with pytest.raises(ValueError, match="profile"):
        feature_matrix(table, "production", PAPER_SUV.wheel_radius_m, PAPER_SUV.steering_ratio)


def test_batch_and_stream_give_the_same_features():
    """A held-out run with every production effect on, as one batch and sample by sample with the previous sample."""
    scenario = generalization_scenarios("test", 0, runs=2)[1]
    table = simulate([scenario])
    profile = vehicle_profile(scenario.vehicle)
    batch = feature_matrix(table, "production", profile=profile)
    previous = None
    for k, sample in enumerate(table.to_pylist()):
        data = {c: np.asarray([float(v)]) for c, v in sample.items() if isinstance(v, (int, float, bool))}
        row = features_from_columns(data, "production", profile=profile, previous=previous)
        np.testing.assert_allclose(row[0], batch[k], rtol=1e-6, atol=1e-6, err_msg=f"sample {k}")
        previous = sample
    assert np.isfinite(batch).all() and np.abs(batch[:, NAMES.index("wheel_accel_front_g")]).max() > 0
