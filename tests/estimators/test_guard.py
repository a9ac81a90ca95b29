"""The physics guard: every estimator's output is physical and never below what the car's acceleration proves."""

from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from roadgrip.data.schema import CHANNEL_NAMES, TELEMETRY_COLUMNS
from roadgrip.estimators.guard import (
    PRIOR_MU,
    PRIOR_UPPER_MU,
    GuardSettings,
    apply_bound,
    apply_bound_scalar,
    drag_per_mass,
    tire_force_bound,
)
from roadgrip.estimators.learned import estimator_names, load_estimator
from roadgrip.fleet.importers import get_importer
from roadgrip.units import G_MPS2
from roadgrip.vehicle.dynamics import AIR_DENSITY_KGPM3
from roadgrip.vehicle.params import PAPER_SUV

ESTIMATORS = estimator_names()
UNCALIBRATED_SIGMA_MPS2 = 0.3  # docs/PRODUCTION.md, "The physics guard": an uncalibrated production sensor's allowance


def test_bound_takes_drag_out_and_nothing_else():
    """A car decelerating at mu g + D/m with every wheel at its limit gets the bound mu (less the margin)."""
    mu, v = 0.1, 30.0
    ax = -(mu * G_MPS2 + drag_per_mass(PAPER_SUV) * v * v)
    bound = tire_force_bound(PAPER_SUV, ax, 0.0, v, GuardSettings(k_sigma=0.0))
    assert bound == pytest.approx(mu, abs=1e-12)
    margin = tire_force_bound(PAPER_SUV, ax, 0.0, v)
    assert margin == pytest.approx(mu - 0.6 / G_MPS2, abs=1e-12)
    assert tire_force_bound(PAPER_SUV, 0.05, 0.0, 0.0) == 0.0  # never negative


def test_bound_holds_on_simulated_runs_at_the_limit():
    """On the paper's decreasing road (every wheel at its limit on the 0.1 section) the guard's bound never exceeds
    the true mu under the wheels, nor on random runs with every production effect on (accelerometers tilted up to 2
    degrees, 0.34 m/s^2, and offset up to 0.2 m/s^2: within the guard's allowance; with half of it the bound exceeded
    the truth by up to 0.02 there)."""
    import pyarrow.compute as pc

    from roadgrip.sim.presets import paper_scenarios, random_scenarios
    from roadgrip.sim.simulate import simulate

    scenarios = [s for s in paper_scenarios() if s.condition == "decreasing"] + random_scenarios(8, seed=5)
    table = simulate(scenarios)
    for s in scenarios:
        run = table.filter(pc.equal(table["run_id"], s.run_id))
        bound = tire_force_bound(
            s.vehicle, run["accel_lon_mps2"].to_numpy(), run["accel_lat_mps2"].to_numpy(), run["speed_mps"].to_numpy()
        )
        mu_max = np.max([run[f"mu_{w}"].to_numpy() for w in ("fl", "fr", "rl", "rr")], axis=0)
        assert (bound <= mu_max + 1e-9).all(), s.run_id


def test_apply_bound_raises_what_is_below_and_widens_what_is_contradicted():
    mu, lower, upper, excited = apply_bound(
        [0.3, 0.1, 0.9], [0.2, 0.05, 0.8], [0.6, 0.15, 1.0], [True, True, True], [0.4, 0.5, 0.2]
    )
    assert mu.tolist() == [0.4, PRIOR_MU, 0.9]  # raised; contradicted: back to the prior, not a low number
    assert lower.tolist() == [0.4, 0.5, 0.8]
    assert upper.tolist() == [0.6, PRIOR_UPPER_MU, 1.0]
    assert excited.tolist() == [True, False, True]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.floats(-1.0, 2.0), st.just(float("nan"))), min_size=4, max_size=4), st.booleans())
def test_the_streaming_guard_is_the_batch_guard(values, excited):
    mu, lower, upper, bound = values
    bound = 0.0 if np.isnan(bound) else abs(bound)
    expected = [float(v[0]) for v in apply_bound([mu], [lower], [upper], [excited], [bound])[:3]]
    got = apply_bound_scalar(mu, lower, upper, excited, bound)
    assert list(got[:3]) == expected
    assert got[3] == bool(apply_bound([mu], [lower], [upper], [excited], [bound])[3][0])


def _random_telemetry(draw, n):
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    speed = np.abs(np.cumsum(rng.normal(0.0, draw(st.floats(0.0, 3.0)), n))) + draw(st.floats(0.0, 40.0))
    ax = rng.normal(0.0, draw(st.floats(0.0, 12.0)), n)
    ay = rng.normal(0.0, draw(st.floats(0.0, 12.0)), n)
    wheel = speed / PAPER_SUV.wheel_radius_m
    slip = rng.normal(0.0, draw(st.floats(0.0, 0.5)), (4, n))
    cols = {
        "vehicle_id": ["v"] * n,
        "timestamp_ms": np.arange(n, dtype=np.int64) * 100 + 1_700_000_000_000,
        "latitude_deg": np.full(n, 38.0),
        "longitude_deg": np.full(n, 114.5),
        "speed_mps": speed,
        "accel_lon_mps2": ax,
        "accel_lat_mps2": ay,
        "yaw_rate_radps": rng.normal(0.0, 0.3, n),
        "steering_wheel_angle_rad": rng.normal(0.0, 1.0, n),
        "abs_active": rng.random(n) < draw(st.floats(0.0, 1.0)),
        "acc_active": np.zeros(n, dtype=bool),
        "tcs_active": rng.random(n) < 0.1,
        "esc_active": rng.random(n) < 0.1,
        "lateral_speed_mps": np.zeros(n),
    }
    for k, w in enumerate(("fl", "fr", "rl", "rr")):
        cols[f"wheel_speed_{w}_radps"] = np.maximum(wheel * (1.0 + slip[k]), 0.0)
    # the optional channels (CONTRACTS 3.1): each absent (null) or sent with arbitrary errors
    channels = {
        "gnss_speed_mps": np.abs(speed + rng.normal(0.0, 2.0, n)),
        "gnss_speed_accuracy_mps": rng.uniform(0.01, 3.0, n),
        "drive_force_n": rng.uniform(0.0, 15_000.0, n),
        "brake_force_n": rng.uniform(0.0, 30_000.0, n),
        "steering_torque_nm": rng.normal(0.0, 5.0, n),
        "eps_assist_torque_nm": rng.normal(0.0, 10.0, n),
    }
    for name in CHANNEL_NAMES:
        cols[name] = channels[name] if draw(st.booleans()) else np.full(n, np.nan)
    return pa.table({c: cols[c] for c in TELEMETRY_COLUMNS})


@pytest.fixture(scope="module")
def estimators():
    return {name: load_estimator(name) for name in ESTIMATORS}


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
@pytest.mark.slow
def test_every_estimator_is_physical_on_any_telemetry(estimators, data):
    """0 <= mu_lower <= mu <= mu_upper and nothing below the tire-force bound, batch and streaming, for any drive."""
    table = _random_telemetry(data.draw, 40)
    rows = table.to_pylist()
    for name, estimator in estimators.items():
        out = estimator.estimate_batch(table, np.zeros(table.num_rows, dtype=np.int64), PAPER_SUV)
        idx = np.searchsorted(table["timestamp_ms"].to_numpy(), out["timestamp_ms"].to_numpy())
        bound = tire_force_bound(
            PAPER_SUV,
            table["accel_lon_mps2"].to_numpy()[idx],
            table["accel_lat_mps2"].to_numpy()[idx],
            table["speed_mps"].to_numpy()[idx],
        )
        mu, lower, upper = (out[c].to_numpy() for c in ("mu", "mu_lower", "mu_upper"))
        assert (lower >= 0.0).all(), name
        assert (lower <= mu).all() and (mu <= upper).all(), name
        assert (lower >= bound - 1e-12).all(), name
        assert out["mu_proven"].to_numpy() == pytest.approx(bound, abs=1e-12), name  # the bound goes out as such
        state = estimator.start(PAPER_SUV)
        streamed = [e for e in (estimator.update(state, r) for r in rows) if e is not None]
        assert all(0.0 <= e.mu_lower <= e.mu <= e.mu_upper for e in streamed), name
        # the streaming guard computes the bound from the profile's constants kept in the state: the same bound
        at = {r["timestamp_ms"]: r for r in rows}
        stream_bound = tire_force_bound(
            PAPER_SUV,
            *(
                np.array([at[e.timestamp_ms][c] for e in streamed])
                for c in ("accel_lon_mps2", "accel_lat_mps2", "speed_mps")
            ),
        )
        assert all(e.mu_lower >= b - 1e-9 for e, b in zip(streamed, stream_bound)), name
        assert [e.mu_proven for e in streamed] == pytest.approx(list(stream_bound), abs=1e-9), name


def log_accelerometer_sigma(table: pa.Table) -> float:
    """The accelerometer's noise and bias (1 sigma, m/s^2) as a log shows them: the RMS of its longitudinal reading
    less the rate of change of the reference speed, wherever the car moves (above 1 m/s)."""
    t_s = table["timestamp_ms"].to_numpy() / 1000.0
    speed = table["speed_mps"].to_numpy()
    residual = table["accel_lon_mps2"].to_numpy() - np.gradient(speed, t_s)
    return float(np.sqrt(np.mean(np.square(residual[speed > 1.0]))))


@pytest.mark.parametrize("name", ESTIMATORS)
def test_bmw_m8_braking_log_never_below_what_the_car_proves(name, estimators):
    """A real car braking at 1.2-1.4 g on dry asphalt. Coulomb's law at the tires: mu g >= |a_road_x|, the road's
    force along the car per mass (the accelerometer's reading with the air's drag taken out). The reading carries
    noise and bias: two sigma of them come off, the larger of the log's own (measured against the reference speed,
    0.25 m/s^2) and the documented allowance of a sensor nobody has calibrated yet (docs/PRODUCTION.md: 0.3 m/s^2),
    which is all an estimator reading the log can know. The guard's drag does not enter this bound, so the estimates
    could fall below it (without the guard each of the four estimators does: on 11-47 of 87-96 samples)."""
    importer = get_importer("bmw-m8")
    table = importer.load(Path(__file__).parents[2] / "data/real/bmw_m8_braking")
    vehicle = importer.profile()
    sigma = log_accelerometer_sigma(table)
    assert 0.05 < sigma < 0.5  # a real sensor's scatter, not a broken log (0.25 m/s^2)
    speed = table["speed_mps"].to_numpy()
    drag = 0.5 * AIR_DENSITY_KGPM3 * vehicle.drag_coefficient * vehicle.frontal_area_m2 / vehicle.mass_kg * speed**2
    road_x = table["accel_lon_mps2"].to_numpy() + drag
    proven = np.maximum(np.abs(road_x) - 2.0 * max(sigma, UNCALIBRATED_SIGMA_MPS2), 0.0) / G_MPS2
    assert (proven > 0.8).sum() >= 10  # the hard braking is in the log
    out = estimators[name].estimate_batch(table, np.zeros(table.num_rows, dtype=np.int64), vehicle)
    idx = np.searchsorted(table["timestamp_ms"].to_numpy(), out["timestamp_ms"].to_numpy())
    assert out.num_rows > 80 and (proven[idx] > 0.8).sum() >= 10
    assert (out["mu_lower"].to_numpy() >= proven[idx]).all()


@pytest.mark.parametrize("name", ("pmf", "default"))
def test_rav4_street_drive_reads_as_no_slippery_road(name, estimators):
    """A production RAV4's street drive (speed from the wheels, accelerometer 0.38 m/s^2 off d(speed)/dt): nothing
    below the bound, no mu_upper below 0.4, so no pass of it can be slippery by the warning engine's rule (median
    mu_upper of a pass's excited estimates below 0.4). The EKF and UKF fail this (docs/PRODUCTION.md)."""
    importer = get_importer("can-dbc")
    log = Path(__file__).parents[2] / "data/real/toyota_rav4_street"
    table = importer.load(log)
    vehicle = importer.profile(log)
    # the optional channels its DBC carries (STEER_TORQUE_SENSOR: driver and EPS torque) are in the estimator's input,
    # the others (GNSS speed, drive and brake force) absent
    for channel in ("steering_torque_nm", "eps_assist_torque_nm"):
        assert table[channel].null_count < 0.2 * table.num_rows
    for channel in ("gnss_speed_mps", "drive_force_n", "brake_force_n"):
        assert channel not in table.column_names or table[channel].null_count == table.num_rows
    out = estimators[name].estimate_batch(table, np.zeros(table.num_rows, dtype=np.int64), vehicle)
    assert out.num_rows > 900
    idx = np.searchsorted(table["timestamp_ms"].to_numpy(), out["timestamp_ms"].to_numpy())
    bound = tire_force_bound(
        vehicle,
        table["accel_lon_mps2"].to_numpy()[idx],
        table["accel_lat_mps2"].to_numpy()[idx],
        table["speed_mps"].to_numpy()[idx],
    )
    assert (out["mu_lower"].to_numpy() >= bound - 1e-12).all()
    assert out["mu_upper"].to_numpy().min() >= 0.4
