"""Acceptance of the physics estimators (issue 5), for the EKF and the UKF alike: convergence when braking, no drift and a
widening interval when cruising, a wrong mass, numerical safety on the presets, the interface (streaming == batch, state
save/restore, reset, bad samples)."""

import json

import numpy as np
import pytest

from roadgrip.estimators.base import ESTIMATE_SCHEMA
from roadgrip.estimators.kalman import M_P, SAMPLE_COLUMNS
from roadgrip.estimators.physics import PHYSICS_ESTIMATORS, physics_estimator
from roadgrip.estimators.vehicle_model import N_X
from roadgrip.sim.driver import SpeedProfile, SteerInput
from roadgrip.sim.presets import paper_scenarios, random_scenarios
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import PAPER_SUV

NAMES = sorted(PHYSICS_ESTIMATORS)
BRAKING_MUS = (0.3, 0.6, 0.9)


def _runs(table):
    ids = table["run_id"].to_numpy(zero_copy_only=False)
    return {run_id: table.filter(ids == run_id) for run_id in dict.fromkeys(ids)}


@pytest.fixture(scope="module")
def runs():
    """Hard braking with ABS from 25 m/s at three mu; a steady cruise after an ABS stop; a curve and a sine steer."""
    scenarios = [
        Scenario(
            run_id=f"brake-{mu}",
            path=Path.straight(600.0),
            mu=MuProfile.uniform(mu),
            speed=SpeedProfile([0.0, 2.0, 2.3, 10.0], [25.0, 25.0, 0.0, 0.0]),
            duration_s=10.0,
            seed=11,
        )
        for mu in BRAKING_MUS
    ]
    scenarios += [
        Scenario(
            run_id="cruise",
            path=Path.straight(1500.0),
            mu=MuProfile.uniform(0.6),
            speed=SpeedProfile([0.0, 2.0, 2.3, 60.0], [30.0, 30.0, 12.0, 12.0]),
            duration_s=60.0,
            seed=12,
        ),
        Scenario(
            run_id="curve",
            path=Path.circle(80.0, 800.0),
            mu=MuProfile.uniform(0.8),
            speed=SpeedProfile([0.0, 30.0], [8.0, 17.0]),
            duration_s=30.0,
            seed=13,
        ),
        Scenario(
            run_id="sine",
            path=Path.straight(1500.0),
            mu=MuProfile.uniform(0.7),
            speed=SpeedProfile([0.0, 40.0], [20.0, 20.0]),
            steer=SteerInput(3.0, 37.0, 0.04, 0.5, 0.0),
            duration_s=40.0,
            seed=14,
        ),
    ]
    return _runs(simulate(scenarios))


def _batch(name, run, vehicle=PAPER_SUV):
    out = physics_estimator(name).estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), vehicle)
    return {c: out[c].to_numpy(zero_copy_only=False) for c in out.column_names}


def _braking_window(run):
    """(t_s, start of braking, samples from 2 s after it while the car still moves above 5 m/s)."""
    t = run["t_s"].to_numpy()
    t_brake = t[np.argmax(run["ax_true_mps2"].to_numpy() < -1.0)]
    return t, t_brake, (t >= t_brake + 2.0) & (run["vx_true_mps"].to_numpy() > 5.0)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("mu", BRAKING_MUS)
def test_braking_converges_within_2_s_to_005(runs, name, mu):
    run = runs[f"brake-{mu}"]
    est = _batch(name, run)
    t, t_brake, window = _braking_window(run)
    assert window.sum() >= 3  # at mu 0.9 the car stops 2.8 s after the brakes go on
    error = np.abs(est["mu"] - run["mu"].to_numpy())
    assert error[window].max() <= 0.05
    assert est["excited"][window].all()
    assert (est["mu_lower"][window] <= mu).all() and (mu <= est["mu_upper"][window]).all()
    assert not est["excited"][t < t_brake].any(), "cruising before the brakes: nothing to judge mu by"


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("mu", BRAKING_MUS)
def test_a_20_percent_heavier_profile_still_converges_to_01(runs, name, mu):
    run = runs[f"brake-{mu}"]
    est = _batch(name, run, PAPER_SUV.replace(mass_kg=1.2 * PAPER_SUV.mass_kg))
    _, _, window = _braking_window(run)
    assert np.abs(est["mu"] - run["mu"].to_numpy())[window].max() <= 0.1


@pytest.mark.parametrize("name", NAMES)
def test_steady_cruise_holds_the_estimate_and_widens_the_interval(runs, name):
    run = runs["cruise"]  # ABS braking from 30 to 12 m/s, then 54 s at 12 m/s
    est = _batch(name, run)
    t = run["t_s"].to_numpy()
    assert est["mu"][0] == 0.5 and not est["excited"][0]  # the prior: nothing known yet
    width = est["mu_upper"] - est["mu_lower"]
    braked = np.flatnonzero(run["abs_active"].to_numpy(zero_copy_only=False))[-1]
    assert abs(est["mu"][braked] - 0.6) <= 0.05 and width[braked] < 0.1, "the ABS stop fixed mu"
    cruise = t > t[np.flatnonzero(run["ax_true_mps2"].to_numpy() < -1.0)[-1]] + 1.0  # the speed has settled
    assert not est["excited"][cruise].any()
    assert np.ptp(est["mu"][cruise]) <= 0.02, "no drift while nothing is observable"
    assert (np.diff(width[cruise]) >= -1e-12).all() and width[-1] > 10.0 * width[braked] and width[-1] > 1.0


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("run_id", ["curve", "sine"])
def test_the_filter_estimates_the_lateral_speed_that_the_terminal_does_not_send(runs, name, run_id):
    run = runs[run_id]
    estimator = physics_estimator(name)
    state = estimator.start(PAPER_SUV)
    error = []
    for row in run.to_pylist():
        row.pop("lateral_speed_mps")
        estimator.update(state, row)
        error.append(estimator.diagnostics(state)["vy_mps"] - row["vy_true_mps"])
    assert np.sqrt(np.mean(np.square(error[30:]))) < 0.08
    if run_id == "sine":
        assert np.abs(run["vy_true_mps"].to_numpy()).max() > 0.8  # the sine steer makes the car slide sideways


@pytest.fixture(scope="module")
def preset_runs():
    scenarios = paper_scenarios() + random_scenarios(40, seed=5)
    table = simulate(scenarios)
    vehicles = {s.run_id: s.vehicle for s in scenarios}
    return [(run, vehicles[run_id]) for run_id, run in _runs(table).items()]


@pytest.mark.parametrize("name", NAMES)
def test_no_nan_and_covariance_symmetric_positive_definite_on_the_presets(preset_runs, name):
    """Every run of the paper preset and 40 of the random one (its vehicles, Dugoff, Magic Formula and Burckhardt
    tires, split mu, all its manoeuvres), sample by sample."""
    estimator = physics_estimator(name)
    for run, vehicle in preset_runs:
        state = estimator.start(vehicle)
        for row in run.to_pylist():
            estimate = estimator.update(state, row)
            P = state.mem[M_P : M_P + N_X * N_X].reshape(N_X, N_X)
            assert (
                np.isfinite(state.mem).all() and np.isfinite([estimate.mu, estimate.mu_lower, estimate.mu_upper]).all()
            )
            assert (P == P.T).all()
            np.linalg.cholesky(P)  # raises unless positive definite
            assert 0.05 <= estimate.mu <= 1.5 and 0.0 <= estimate.mu_lower <= estimate.mu <= estimate.mu_upper <= 1.5
        diagnostics = estimator.diagnostics(state)
        assert diagnostics["rejected"] == 0 and diagnostics["restarts"] == 0, run["run_id"][0]


@pytest.mark.parametrize("name", NAMES)
def test_streaming_gives_the_batch_numbers_with_a_restart_and_a_saved_state(runs, name):
    run = runs["sine"]
    segments = np.repeat([0, 1], [250, run.num_rows - 250])
    estimator = physics_estimator(name)
    batch = estimator.estimate_batch(run, segments, PAPER_SUV)
    assert batch.schema == ESTIMATE_SCHEMA and batch.num_rows == run.num_rows
    state = estimator.start(PAPER_SUV)
    streamed = []
    for k, row in enumerate(run.to_pylist()):
        if k == 123:  # a service restarting mid-stream: save, throw away, restore
            state = estimator.state_from_dict(json.loads(json.dumps(estimator.state_to_dict(state))))
        if k == 250:
            estimator.reset(state)
        streamed.append(estimator.update(state, row).to_dict())
    assert streamed == batch.to_pylist()
    assert streamed[250]["mu"] == 0.5 and not streamed[250]["excited"], "after a reset the filter starts afresh"


@pytest.mark.parametrize("name", NAMES)
def test_bad_samples_are_rejected_and_counted_not_propagated(runs, name):
    rows = runs["brake-0.6"].to_pylist()
    estimator = physics_estimator(name)
    state = estimator.start(PAPER_SUV)
    before = [estimator.update(state, row) for row in rows[:25]][-1]
    nan_row = dict(rows[25], accel_lon_mps2=float("nan"))
    held = estimator.update(state, nan_row)
    assert (held.mu, held.mu_lower, held.mu_upper, held.excited) == (before.mu, before.mu_lower, before.mu_upper, False)
    assert held.timestamp_ms == rows[25]["timestamp_ms"]
    assert estimator.update(state, dict(rows[26], speed_mps=None)).mu == before.mu
    assert estimator.update(state, rows[24]).mu == before.mu  # time going backwards
    assert estimator.diagnostics(state)["rejected"] == 3
    later = [estimator.update(state, row) for row in rows[27:60]]
    assert np.isfinite([e.mu for e in later]).all() and abs(later[-1].mu - 0.6) < 0.05
    gap = dict(rows[60], timestamp_ms=rows[60]["timestamp_ms"] + 5000)  # 5 s of silence: start afresh
    assert estimator.update(state, gap).mu == 0.5 and estimator.diagnostics(state)["restarts"] == 1
    with pytest.raises(ValueError, match="yaw_rate_radps"):
        estimator.update(state, {k: v for k, v in rows[61].items() if k != "yaw_rate_radps"})
    fresh = estimator.start(PAPER_SUV)
    assert estimator.update(fresh, nan_row) is None, "nothing to say before a first good sample"


@pytest.mark.parametrize("name", NAMES)
def test_batch_refuses_tables_it_cannot_use(runs, name):
    run = runs["curve"]
    estimator = physics_estimator(name)
    with pytest.raises(ValueError, match="steering_wheel_angle_rad"):
        estimator.estimate_batch(run.drop_columns(["steering_wheel_angle_rad"]), np.zeros(run.num_rows), PAPER_SUV)
    with pytest.raises(ValueError, match="segments"):
        estimator.estimate_batch(run, np.zeros(3), PAPER_SUV)
    state = estimator.start(PAPER_SUV)
    with pytest.raises(ValueError, match="state of estimator"):
        physics_estimator("ukf" if name == "ekf" else "ekf").state_from_dict(estimator.state_to_dict(state))


def test_the_registry_names_the_filters_and_refuses_others():
    assert set(PHYSICS_ESTIMATORS) == {"ekf", "ukf"}
    for name in NAMES:
        assert physics_estimator(name).name == name
    with pytest.raises(ValueError, match="physics estimator name must be one of"):
        physics_estimator("kalman")
    assert len(SAMPLE_COLUMNS) == 10
