"""pmf's wheel kinematics against rigid-body geometry: in a turn the wheels roll at different speeds with no slip at
all (each at the yaw rate times its distance to the instantaneous centre of rotation), and that is no evidence of
friction; slip is read only above the speed where the wheel-speed resolution lets it speak (SLIP_MIN_SPEED_MPS).

The samples here are built from the geometry alone (no simulator, none of pmf's code): a car of the profile turning
steadily about a centre C at lateral distance R, every wheel rolling without longitudinal slip."""

import math

import numpy as np
import pytest

from roadgrip.estimators.pmf import SLIP_MIN_SPEED_MPS, PMFEstimator, pack, wheel_kinematics
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV

RWD_SEDAN = MIDSIZE_SEDAN.replace(drive="rwd", front_drive_share=0.0)
START_MS = 1_700_000_000_000


def _wheel_positions(vehicle):
    """Contact points (x forward, y left) of fl, fr, rl, rr relative to the CoG."""
    a, b = vehicle.cg_to_front_axle_m, vehicle.cg_to_rear_axle_m
    tf, tr = vehicle.track_front_m, vehicle.track_rear_m
    return np.array([[a, tf / 2], [a, -tf / 2], [-b, tr / 2], [-b, -tr / 2]])


def steady_turn(vehicle, radius_m: float, speed_mps: float, left: bool = True, slip_angles: bool = True):
    """A rigid car turning steadily: (yaw rate, road-wheel steer, a_x, a_y, rolling speed of each wheel in m/s).

    The centre of rotation C lies at y = +-R. Its x: on the rear axle's line for a kinematic turn (no slip angles);
    with slip angles, ahead of it by R alpha_r, where the rear tires' slip angle alpha_r = a_y / (g C_alpha_r) makes
    the rear axle's lateral force m a_y a / L on its load m g a / L. The CoG moves at speed_mps along the body's x
    axis (v_x = r C_y); the specific force is the centripetal acceleration r^2 C. A rear wheel rolls along the body's
    x axis: r (C_y - y_i). A front wheel is steered Ackermann-true, its heading its hub velocity's direction plus the
    front slip angle alpha_f = a_y / (g C_alpha_f), so it rolls at r |P_i - C| cos(alpha_f). The steering wheel reads
    the front axle centre's heading."""
    side = 1.0 if left else -1.0
    r = side * speed_mps / radius_m
    a_y = r * speed_mps
    alpha_r = a_y / (G_MPS2 * vehicle.tire_rear.cornering_stiffness_per_load_per_rad) if slip_angles else 0.0
    alpha_f = a_y / (G_MPS2 * vehicle.tire_front.cornering_stiffness_per_load_per_rad) if slip_angles else 0.0
    centre = np.array([-vehicle.cg_to_rear_axle_m + side * radius_m * alpha_r, side * radius_m])
    a_x = r * r * centre[0]
    rolling = np.empty(4)
    for i, p in enumerate(_wheel_positions(vehicle)):
        d = p - centre
        if i >= 2:
            rolling[i] = -r * d[1]  # the hub velocity's x component, r (C_y - y_i)
        else:
            rolling[i] = abs(r) * math.hypot(*d) * math.cos(alpha_f)
    axle = np.array([vehicle.cg_to_front_axle_m, 0.0]) - centre
    steer = math.atan2(r * axle[0], -r * axle[1]) + alpha_f  # direction of the hub velocity r z x (P - C)
    return r, steer, a_x, a_y, rolling


def turn_samples(vehicle, radius_m, speed_mps, n, *, left=True, seed=0, abs_active=False):
    """n samples (10 Hz) of the steady turn as a terminal sends them: the accelerometer with 0.05 m/s^2 noise."""
    rng = np.random.default_rng(seed)
    r, steer, a_x, a_y, rolling = steady_turn(vehicle, radius_m, speed_mps, left)
    out = []
    for k in range(n):
        wheels = rolling / vehicle.wheel_radius_m
        out.append(
            {
                "vehicle_id": "t",
                "timestamp_ms": START_MS + 100 * k,
                "speed_mps": speed_mps,
                "accel_lon_mps2": a_x + rng.normal(0.0, 0.05),
                "accel_lat_mps2": a_y + rng.normal(0.0, 0.05),
                "yaw_rate_radps": r,
                "steering_wheel_angle_rad": steer * vehicle.steering_ratio,
                "wheel_speed_fl_radps": wheels[0],
                "wheel_speed_fr_radps": wheels[1],
                "wheel_speed_rl_radps": wheels[2],
                "wheel_speed_rr_radps": wheels[3],
                "abs_active": abs_active,
            }
        )
    return out


@pytest.mark.parametrize("vehicle", [PAPER_SUV, MIDSIZE_SEDAN, COMPACT_HATCHBACK], ids=lambda v: v.name)
@pytest.mark.parametrize("radius_m", [8.0, 10.0, 25.0, 60.0])
@pytest.mark.parametrize("left", [True, False], ids=["left", "right"])
def test_kinematic_wheel_speeds_are_the_yaw_rate_times_the_distance_to_the_centre(vehicle, radius_m, left):
    """A kinematic turn (the centre on the rear axle's line, no lateral force): each wheel rolls at |r| times its
    distance to the centre. The rear wheels exactly; the front wheels, steered here Ackermann-true but projected by pmf
    on their common steer angle (the front axle centre's heading), within 1 - cos of the difference (the SUV at
    R = 8 m: 2.2 degrees, 7.4e-4), below the slip noise floor SLIP_SIGMA0 = 0.0015."""
    v = 6.0
    r, steer, _, _, _ = steady_turn(vehicle, radius_m, v, left, slip_angles=False)
    side = 1.0 if left else -1.0
    centre = np.array([-vehicle.cg_to_rear_axle_m, side * radius_m])
    distance = np.hypot(*(_wheel_positions(vehicle) - centre).T)
    gain, offset = np.empty(4), np.empty(4)
    wheel_kinematics(pack(vehicle), r, steer, 0.0, gain, offset)
    kinematic = gain * v + offset
    np.testing.assert_allclose(kinematic[2:], abs(r) * distance[2:], rtol=1e-12)
    np.testing.assert_allclose(kinematic[:2], abs(r) * distance[:2], rtol=1e-3)
    # what the correction takes out: the inner wheels turn slower than the outer by track / R
    inner, outer = (0, 1) if left else (1, 0)
    assert distance[outer] / distance[inner] - 1.0 > 0.9 * vehicle.track_front_m / radius_m


@pytest.mark.parametrize("vehicle", [PAPER_SUV, MIDSIZE_SEDAN, RWD_SEDAN, COMPACT_HATCHBACK], ids=lambda v: v.name)
@pytest.mark.parametrize("left", [True, False], ids=["left", "right"])
def test_a_tight_turn_without_slip_is_no_evidence_of_low_friction(vehicle, left):
    """20 s around a 10 m circle at 7 m/s (a_y 0.5 g, on a dry road) with every wheel rolling freely: the inner
    and outer wheels differ by 15-17 %, the front axle runs 3 % faster than the rear, and none of it is slip. The
    estimate stays dry: the interval reaches above 0.9, the median above 0.6 (the bound proves 0.5). Before the
    kinematics, the spread read as a wheel past its peak: mu 0.5-0.7, the upper end below 0.8."""
    estimates = _run(turn_samples(vehicle, 10.0, 7.0, 200, left=left), vehicle)
    assert min(e.mu_upper for e in estimates) >= 0.9
    assert min(e.mu for e in estimates) >= 0.6


def test_the_radius_calibration_is_not_bent_by_gentle_curves():
    """Three minutes around an 80 m circle at 15 m/s, all tires equal: gentle enough to count as straight driving
    (the calibration's gate admits radii from 20 wheelbases), yet the outer wheels turn 2 % faster. The left/right
    radius ratios learned stay at 0 (before: -0.02, the track over the radius)."""
    estimator = PMFEstimator()
    state = estimator.start(MIDSIZE_SEDAN)
    for sample in turn_samples(MIDSIZE_SEDAN, 80.0, 15.0, 1800):
        estimator.update(state, sample)
    calibration = estimator.calibration(state)
    assert calibration["radius_ratio_weight_s"] > 150.0  # it did learn
    assert calibration["radius_ratio_left_right_front"] == pytest.approx(0.0, abs=0.001)
    assert calibration["radius_ratio_left_right_rear"] == pytest.approx(0.0, abs=0.001)


def _straight(
    speed_mps, n, *, wheel_scale=(1.0, 1.0, 1.0, 1.0), accel_lon_mps2=0.0, abs_active=False, vehicle=MIDSIZE_SEDAN
):
    out = []
    for k in range(n):
        v = max(speed_mps + accel_lon_mps2 * 0.1 * k, 0.0)
        wheels = [v * s / vehicle.wheel_radius_m for s in wheel_scale]
        out.append(
            {
                "vehicle_id": "t",
                "timestamp_ms": START_MS + 100 * k,
                "speed_mps": v,
                "accel_lon_mps2": accel_lon_mps2,
                "accel_lat_mps2": 0.0,
                "yaw_rate_radps": 0.0,
                "steering_wheel_angle_rad": 0.0,
                "wheel_speed_fl_radps": wheels[0],
                "wheel_speed_fr_radps": wheels[1],
                "wheel_speed_rl_radps": wheels[2],
                "wheel_speed_rr_radps": wheels[3],
                "abs_active": abs_active,
            }
        )
    return out


def _run(samples, vehicle=MIDSIZE_SEDAN):
    estimator = PMFEstimator()
    state = estimator.start(vehicle)
    return [estimator.update(state, s) for s in samples]


def test_below_the_slip_speed_a_wheel_off_the_others_is_no_evidence():
    """At 4.5 m/s a wheel reading 20 % slow (0.9 m/s: two counts of a 48-tooth tone wheel in a 100 ms sample)
    proves nothing; a front wheel 30 % fast at 8 m/s while the car pulls at 0.15 g is past its peak: mu 0.15-0.2."""
    assert SLIP_MIN_SPEED_MPS == pytest.approx(5.0)
    slow = _run(_straight(4.5, 50, wheel_scale=(1.0, 1.0, 0.8, 1.0), accel_lon_mps2=0.0))
    assert min(e.mu_upper for e in slow) >= 1.0
    fast = _run(_straight(8.0, 50, wheel_scale=(1.3, 1.0, 1.0, 1.0), accel_lon_mps2=0.15 * G_MPS2))
    assert fast[-1].mu_upper < 0.3


def test_below_the_slip_speed_the_controllers_still_speak():
    """ABS acting at 4.5 m/s to a stop on ice (0.9 of mu 0.15 on the front axle): the flag is evidence at any speed."""
    front_load_share = (MIDSIZE_SEDAN.cg_to_rear_axle_m + MIDSIZE_SEDAN.cg_height_m * 0.1) / MIDSIZE_SEDAN.wheelbase_m
    decel = 0.9 * 0.15 * front_load_share / MIDSIZE_SEDAN.brake_front_share * G_MPS2
    estimates = _run(_straight(4.5, 30, accel_lon_mps2=-decel, abs_active=True))
    assert estimates[-1].mu_upper < 0.3
    assert estimates[-1].mu_lower <= 0.15 <= estimates[-1].mu_upper
