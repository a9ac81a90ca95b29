"""The grid filter: wide and honest without excitation, tight at the limit, self-calibrating, restartable."""

import numpy as np
import pytest

from roadgrip.estimators.pmf import CALIBRATION, N_MEM_V3, N_MEM_V4, PMFEstimator
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import PAPER_SUV

FWD = PAPER_SUV.replace(drive="fwd", front_drive_share=1.0)


def _samples(
    speed_mps,
    accel_lon_mps2,
    *,
    abs_active=None,
    accel_bias=0.0,
    radius_ratio=(1.0, 1.0, 1.0, 1.0),
    front_slip=None,
    seed=0,
    vehicle=FWD,
):
    """Straight-line telemetry: the wheels roll at the speed (times their radius ratio, plus the front's slip), the
    accelerometer reads the acceleration plus its bias and 0.05 m/s^2 noise."""
    rng = np.random.default_rng(seed)
    n = len(speed_mps)
    front_slip = np.zeros(n) if front_slip is None else front_slip
    abs_active = np.zeros(n, dtype=bool) if abs_active is None else abs_active
    out = []
    for k in range(n):
        omega = speed_mps[k] / vehicle.wheel_radius_m
        wheels = [omega * radius_ratio[i] * (1.0 + (front_slip[k] if i < 2 else 0.0)) for i in range(4)]
        out.append(
            {
                "vehicle_id": "t",
                "timestamp_ms": 1_700_000_000_000 + 100 * k,
                "speed_mps": float(speed_mps[k]),
                "accel_lon_mps2": float(accel_lon_mps2[k] + accel_bias + rng.normal(0.0, 0.05)),
                "accel_lat_mps2": float(rng.normal(0.0, 0.05)),
                "yaw_rate_radps": 0.0,
                "steering_wheel_angle_rad": 0.0,
                "wheel_speed_fl_radps": wheels[0],
                "wheel_speed_fr_radps": wheels[1],
                "wheel_speed_rl_radps": wheels[2],
                "wheel_speed_rr_radps": wheels[3],
                "abs_active": bool(abs_active[k]),
            }
        )
    return out


def _run(samples, vehicle=FWD, estimator=None, state=None):
    estimator = estimator or PMFEstimator()
    state = state or estimator.start(vehicle)
    return [estimator.update(state, s) for s in samples], estimator, state


def test_calm_driving_is_a_wide_interval_never_a_low_number():
    n = 600  # a minute at 25 m/s with the speed wandering by 0.05 g
    t = np.arange(n) * 0.1
    ax = 0.5 * np.sin(2 * np.pi * t / 20.0)
    speed = 25.0 + np.cumsum(ax) * 0.1
    estimates, _, _ = _run(_samples(speed, ax, accel_bias=-0.6))
    mu = np.array([e.mu for e in estimates])
    upper = np.array([e.mu_upper for e in estimates])
    assert mu.min() >= 0.6 and upper.min() >= 1.0
    assert not any(e.excited for e in estimates)


def test_where_nothing_is_proven_the_interval_holds_ice_and_the_best_dry_asphalt():
    """A minute at a steady 25 m/s proves nothing about mu: the interval reaches both ends of what roads have, ice
    (0.05) and the best dry asphalt (the guard's PRIOR_UPPER_MU, 1.2), however long the grid's walk has run."""
    n = 600
    estimates, _, _ = _run(_samples(np.full(n, 25.0), np.zeros(n)))
    assert max(e.mu_lower for e in estimates) <= 0.05
    assert min(e.mu_upper for e in estimates) >= 1.19


def test_the_accelerometer_bias_is_the_sensors_not_the_roads_grade():
    """Half an hour over roads that climb and descend 2 % in turn (two minutes each), a sensor bias of +0.4 m/s^2:
    a_x - dv/dt is the bias plus g sin(grade), whose grade part is tire force. The calibrated bias is the sensor's
    within 0.1 m/s^2 whichever road the car is on, not the last road's grade (0.2 m/s^2 off) as a one-minute
    average makes it."""
    n = 18_000
    t = np.arange(n) * 0.1
    grade = np.where((t // 120) % 2 == 0, 0.02, -0.02)
    ax = 0.3 * np.sin(2 * np.pi * t / 30.0)  # the wheels' acceleration; the accelerometer adds gravity's part
    speed = 20.0 + np.cumsum(ax) * 0.1
    _, _, state = _run(_samples(speed, ax + G_MPS2 * np.sin(grade), accel_bias=0.4)[: n // 2])
    first = state.mem[CALIBRATION["accel_bias_mps2"]]
    _run(_samples(speed, ax + G_MPS2 * np.sin(grade), accel_bias=0.4)[n // 2 + 600 :], state=state)
    assert abs(first - 0.4) < 0.1 and abs(state.mem[CALIBRATION["accel_bias_mps2"]] - 0.4) < 0.1


def test_abs_braking_on_ice_is_tight_and_low():
    """ABS holding the front tires (the profile's brake split saturates them first) at 0.9 of mu 0.15: the estimate
    brackets 0.15 tightly, its upper end well below 0.4."""
    n = 40
    u = 0.1  # the vehicle's deceleration in g, then scaled so that the front axle's force per load is 0.9 mu
    front_load_share = (FWD.cg_to_rear_axle_m + FWD.cg_height_m * u) / FWD.wheelbase_m
    decel = 0.9 * 0.15 * front_load_share / FWD.brake_front_share * G_MPS2
    speed = 20.0 - decel * np.arange(n) * 0.1
    estimates, _, _ = _run(_samples(speed, np.full(n, -decel), abs_active=np.ones(n, dtype=bool)))
    last = estimates[-1]
    assert last.excited
    assert last.mu_lower <= 0.15 <= last.mu_upper
    assert last.mu == pytest.approx(0.15, abs=0.03)
    assert last.mu_upper < 0.25


def _pulling_drive(mu: float):
    """A FWD car driven gently for 80 s (its acceleration swinging between 0 and 0.06 g), then pulling at 0.13 g for
    10 s, on a road of `mu`, its front wheels slipping as the brush model says (stiffness as the profile's); the
    accelerometer reads the road's force less drag, which is also what the speed follows."""
    from roadgrip.estimators.guard import drag_per_mass

    c = FWD.tire_front.longitudinal_stiffness_per_load
    n = 900
    k = np.arange(n)
    road = np.where(k < PULL_START, 0.03 + 0.03 * np.sin(k * 2 * np.pi / 150), 0.13) * G_MPS2
    speed = np.empty(n)
    speed[0] = 15.0
    for i in range(1, n):
        speed[i] = speed[i - 1] + (road[i - 1] - drag_per_mass(FWD) * speed[i - 1] ** 2) * 0.1
    fz_front = FWD.mass_kg * (G_MPS2 * FWD.cg_to_rear_axle_m - road * FWD.cg_height_m) / FWD.wheelbase_m
    f = FWD.mass_kg * road / fz_front  # the front axle's force per load: 0.26 in the pull
    slip = 3 * mu / c * (1 - np.cbrt(1 - np.clip(f / mu, 0.0, 1.0)))
    return _samples(speed, road - drag_per_mass(FWD) * speed**2, front_slip=slip)


PULL_START = 800


def test_slip_growing_faster_than_force_reads_as_low_friction():
    """On mu 0.3 the pull works the front axle at 0.88 of mu and its slip is 1.7 times the tire's line, 1.5 times
    the line calibrated on this road (whose gentle driving, at up to a third of mu, already bends the brush curve):
    within 5 s the posterior moves from the prior's 0.8 below 0.5, with 0.3 inside; on mu 0.9 the same pull (0.29 of
    mu) reads high. What slip cannot tell: at one force level a soft tire on a good road slips like a stiff one near
    its limit, so held longer the low-mu posterior widens back (docs/PRODUCTION.md)."""
    low, _, _ = _run(_pulling_drive(0.3))
    high, _, _ = _run(_pulling_drive(0.9))
    at = PULL_START + 50
    assert min(e.mu for e in low[PULL_START:at]) < 0.5 and low[at].mu_lower <= 0.3 <= low[at].mu_upper
    assert high[at].mu > 0.7 and high[at].mu_upper >= 0.9
    assert all(e.mu_upper >= 0.9 for e in high)


def worn_tire_drive(n: int):
    """A FWD car driven gently (0 to 0.09 g) for n samples on a worn tire (half the profile's slip stiffness), the
    front left tire 2 % fuller than the others (each front wheel +1 % on the rear axle's mean, 2 % left against
    right), the accelerometer 0.6 m/s^2 off; also results/trials/production/calibration_convergence.py's. Returns (samples, stiffness)."""
    from roadgrip.estimators.guard import drag_per_mass

    road = (0.04 + 0.05 * np.sin(np.arange(n) * 2 * np.pi / 200)) * G_MPS2
    speed = np.empty(n)
    speed[0] = 20.0
    for i in range(1, n):
        speed[i] = speed[i - 1] + (road[i - 1] - drag_per_mass(FWD) * speed[i - 1] ** 2) * 0.1
    fz_front = FWD.mass_kg * (G_MPS2 * FWD.cg_to_rear_axle_m - road * FWD.cg_height_m) / FWD.wheelbase_m
    c = 0.5 * FWD.tire_front.longitudinal_stiffness_per_load
    slip = 3 * 0.9 / c * (1 - np.cbrt(1 - FWD.mass_kg * road / fz_front / 0.9))
    samples = _samples(
        speed,
        road - drag_per_mass(FWD) * speed**2,
        accel_bias=-0.6,
        radius_ratio=(1.02, 1.0, 1.0, 1.0),
        front_slip=slip,
    )
    return samples, c


def test_self_calibration_converges_on_ordinary_driving():
    """Five minutes of gentle driving on a worn tire with mismatched radii and a biased accelerometer: the bias, the
    radius ratios and the tire's stiffness are learned."""
    samples, c = worn_tire_drive(3000)
    _, estimator, state = _run(samples)
    cal = estimator.calibration(state)
    assert cal["accel_bias_mps2"] == pytest.approx(-0.6, abs=0.05)
    assert cal["radius_ratio_left_right_front"] == pytest.approx(0.02, abs=0.002)
    assert cal["radius_ratio_left_right_rear"] == pytest.approx(0.0, abs=0.002)
    assert cal["slip_offset_front_rear"] == pytest.approx(0.01, abs=0.002)
    assert 1.0 / cal["slip_slope"] == pytest.approx(c, rel=0.1)


def test_the_slip_line_is_the_tires_when_the_force_varies_less_than_the_accelerometers_noise():
    """Steady driving: the force per load swings by +-0.01 g around 0.03 g while the accelerometer reads it with
    0.1 m/s^2 of white noise (a production sensor's, ACCEL_NOISE_MPS2), as large as the swing. Regressed sample by
    sample, the noise in the regressor flattens the slope to a third (the tire read three times as stiff as it is,
    and its slip at any real force then reads as low friction); on the force and slip filtered over
    SLIP_LINE_FILTER_S the noise's variance is a twentieth, and the slope is the tire's to within the 10 % that is
    left (0.012^2 / (0.012^2 + 0.0039^2) of it) and the wheels' noise."""
    from roadgrip.estimators.guard import drag_per_mass

    n = 6000
    k = np.arange(n)
    road = (0.03 + 0.01 * np.sin(k * 2 * np.pi / 200)) * G_MPS2
    speed = np.empty(n)
    speed[0] = 25.0
    for i in range(1, n):
        speed[i] = speed[i - 1] + (road[i - 1] - drag_per_mass(FWD) * speed[i - 1] ** 2) * 0.1
    fz_front = FWD.mass_kg * (G_MPS2 * FWD.cg_to_rear_axle_m - road * FWD.cg_height_m) / FWD.wheelbase_m
    c = FWD.tire_front.longitudinal_stiffness_per_load
    noise = np.random.default_rng(3).normal(0.0, 0.1, n)
    _, estimator, state = _run(
        _samples(speed, road - drag_per_mass(FWD) * speed**2 + noise, front_slip=FWD.mass_kg * road / fz_front / c)
    )
    assert 1.0 / estimator.calibration(state)["slip_slope"] == pytest.approx(c, rel=0.2)


def test_a_state_saved_before_the_slip_lines_filter_loads_with_it_empty():
    """A checkpoint of the layout before the slip line's filter (N_MEM_V3 numbers): everything kept, the filter empty
    (it fills again in SLIP_LINE_FILTER_S of steady driving) and the blocks appended since as a new car's."""
    estimator = PMFEstimator()
    samples, _ = worn_tire_drive(600)
    _, _, state = _run(samples, estimator=estimator)
    saved = estimator.state_to_dict(state)
    saved["memory"] = saved["memory"][:N_MEM_V3]
    loaded = estimator.state_from_dict(saved)
    assert np.array_equal(loaded.mem[:N_MEM_V3], state.mem[:N_MEM_V3])
    fresh = estimator.start(FWD)  # the blocks appended since, as a new car holds them
    assert np.array_equal(loaded.mem[N_MEM_V3:], fresh.mem[N_MEM_V3:])
    assert not np.array_equal(state.mem[N_MEM_V3:], fresh.mem[N_MEM_V3:])


def test_a_state_saved_before_the_front_rear_radius_ratio_loads_with_it_unlearned():
    """A checkpoint of the layout before the braking term (N_MEM_V4 numbers) of an all-wheel-drive car: everything
    kept, its front/rear radius ratio and braking line as a new car's (learned again in calm driving and gentle
    stops)."""
    estimator = PMFEstimator()
    samples, _ = worn_tire_drive(600)
    _, _, state = _run(samples, vehicle=PAPER_SUV, estimator=estimator)
    saved = estimator.state_to_dict(state)
    saved["memory"] = saved["memory"][:N_MEM_V4]
    loaded = estimator.state_from_dict(saved)
    assert np.array_equal(loaded.mem[:N_MEM_V4], state.mem[:N_MEM_V4])
    fresh = estimator.start(PAPER_SUV)
    assert np.array_equal(loaded.mem[N_MEM_V4:], fresh.mem[N_MEM_V4:])
    assert not np.array_equal(state.mem[N_MEM_V4:], fresh.mem[N_MEM_V4:])


def test_controller_flags_the_wire_leaves_empty_are_taken_as_not_acting():
    """The wire parser gives an optional field the vehicle does not send as None: the same estimates and calibration
    as without the field (self-calibration used to stall on None)."""
    samples, _ = worn_tire_drive(600)
    absent, estimator, state_absent = _run(samples)
    empty, _, state_empty = _run([{**s, "tcs_active": None, "esc_active": None} for s in samples])
    assert [(e.mu, e.mu_lower, e.mu_upper) for e in empty] == [(e.mu, e.mu_lower, e.mu_upper) for e in absent]
    assert estimator.calibration(state_empty) == estimator.calibration(state_absent)


def test_state_round_trip_continues_identically():
    n = 200
    ax = np.where(np.arange(n) < 100, 0.0, -3.0)
    speed = 25.0 + np.cumsum(ax) * 0.1
    samples = _samples(speed, ax)
    whole, estimator, _ = _run(samples)
    first, _, state = _run(samples[:120], estimator=estimator)
    restored = estimator.state_from_dict(estimator.state_to_dict(state))
    rest, _, _ = _run(samples[120:], estimator=estimator, state=restored)
    assert [e.mu for e in first + rest] == [e.mu for e in whole]
    assert [e.mu_upper for e in first + rest] == [e.mu_upper for e in whole]


def test_batch_equals_streaming():
    import pyarrow as pa

    n = 150
    ax = np.where(np.arange(n) < 60, 0.5, -5.0)
    speed = np.maximum(20.0 + np.cumsum(ax) * 0.1, 0.0)
    samples = _samples(speed, ax)
    streamed, estimator, _ = _run(samples)
    batch = estimator.estimate_batch(pa.Table.from_pylist(samples), np.zeros(n, dtype=np.int64), FWD)
    assert batch["mu"].to_pylist() == [e.mu for e in streamed]


@pytest.mark.parametrize("mu_low, u", [(0.6, 0.54), (0.3, 0.27), (0.9, 0.8)])
def test_the_demand_likelihood_is_its_generative_models(mu_low, u):
    """The bound's likelihood models the driver's demand d as exponential (mean DEMAND_G) whatever the road, the tires
    transmitting u = d below mu and saturating, u / mu uniform in [ETA_LIMIT, 1], when d >= mu. Its density of u,
    written out here from that model, sets the odds of a mu whose band holds u against a mu far above it; pmf's
    likelihood (noise made negligible) must give the same odds (before the saturation's exp(-(mu - u) / DEMAND_G) was
    left out, overstating them by a fifth to a half, which pulled a dry road's estimate to just above its utilisation)."""
    from roadgrip.estimators import pmf

    d, eta = pmf.DEMAND_G, pmf.ETA_LIMIT

    def density(mu):
        below = np.exp(-u / d) / d if u < mu else 0.0
        saturated = np.exp(-mu / d) / ((1.0 - eta) * mu) if eta * mu <= u <= mu else 0.0
        return below + saturated

    mu_high = 1.4
    expected = density(mu_low) / density(mu_high)
    got = pmf._demand_likelihood(mu_low, u, 1e-6) / pmf._demand_likelihood(mu_high, u, 1e-6)
    assert got == pytest.approx(expected, rel=0.03)
