"""The UKF kernel: the unscented transform's moments, and the UKF against the EKF where the model is nearly linear."""

import numpy as np
import pytest

from roadgrip.estimators.ekf import ekf_update
from roadgrip.estimators.kalman import M_P, M_X, SAMPLE_COLUMNS, read_sample
from roadgrip.estimators.physics import physics_estimator
from roadgrip.estimators.ukf import N_SIGMA, sigma_points, ukf_predict, ukf_update, weights
from roadgrip.estimators.vehicle_model import (
    MU,
    N_U,
    N_X,
    N_Z,
    FilterTuning,
    pack_model,
    predict_state,
    process_noise,
)
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import PAPER_SUV


def _covariance(seed):
    A = np.random.default_rng(seed).normal(size=(N_X, N_X)) * 0.1
    return A @ A.T + 0.01 * np.eye(N_X)


@pytest.mark.parametrize("alpha", [1.0, 0.5, 0.1])
def test_sigma_points_carry_the_mean_and_covariance_exactly(alpha):
    prm = pack_model(PAPER_SUV, FilterTuning(ukf_alpha=alpha))
    x = np.array([20.0, 0.1, 0.05, 0.003, 0.6])
    P = _covariance(1)
    X = np.empty((N_SIGMA, N_X))
    assert sigma_points(prm, x, P, X)
    wm = np.array([weights(prm, i)[0] for i in range(N_SIGMA)])
    wc = np.array([weights(prm, i)[1] for i in range(N_SIGMA)])
    assert wm.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(wm @ X, x, rtol=1e-12)
    d = X - x
    np.testing.assert_allclose((wc[:, None] * d).T @ d - (wc[0] - wm[0]) * np.outer(d[0], d[0]), P, rtol=1e-9)
    # the last two points along mu's Cholesky column move mu alone (the UKF reads its excitation off them)
    for i in (N_X, 2 * N_X):
        assert (X[i, :MU] == x[:MU]).all() and X[i, MU] != x[MU]


def test_the_unscented_prior_is_the_extended_one_where_the_process_is_linear():
    """With a diagonal P every sigma point moves one state, along which f (bilinear in r and vy) is linear: the
    transform's mean and covariance are then f(x) and F P F' + Q exactly."""
    prm = pack_model(PAPER_SUV)
    x = np.array([18.0, 0.2, 0.15, 0.002, 0.5])
    P = np.diag([0.04, 0.01, 1e-4, 1e-5, 0.09])
    u_prev = np.array([47.0, 47.0, 47.0, 47.0, 0.02, -1.0, 2.5])
    u = np.array([46.6, 46.8, 46.7, 46.9, 0.025, -1.2, 2.7])
    x_ukf, P_ukf = np.empty(N_X), np.empty((N_X, N_X))
    assert ukf_predict(prm, x, P, u_prev, u, 0.1, x_ukf, P_ukf)
    x_ekf, F, Q = np.empty(N_X), np.empty((N_X, N_X)), np.empty((N_X, N_X))
    predict_state(x, u_prev, u, 0.1, prm, x_ekf, F)
    process_noise(prm, 0.1, u_prev, u, P[MU, MU], Q)
    np.testing.assert_allclose(x_ukf, x_ekf, rtol=1e-12)
    np.testing.assert_allclose(P_ukf, F @ P @ F.T + Q, rtol=1e-9, atol=1e-15)


@pytest.fixture(scope="module")
def braking_rows():
    run = simulate(
        [
            Scenario(
                run_id="brake",
                path=Path.straight(600.0),
                mu=MuProfile.uniform(0.45),
                speed=SpeedProfile([0.0, 2.0, 2.3, 10.0], [25.0, 25.0, 0.0, 0.0]),
                duration_s=10.0,
                seed=21,
            )
        ]
    )
    return run.to_pylist()


@pytest.mark.parametrize("k", [10, 28])  # cruising (mu held), ABS braking (mu updated)
def test_one_update_with_a_small_covariance_is_the_ekf_update(braking_rows, k):
    """Shrink the prior's covariance until h is linear over the sigma points' spread: both filters must then make
    the same update, with the same gate decision."""
    estimator = physics_estimator("ekf")
    state = estimator.start(PAPER_SUV)
    for row in braking_rows[:k]:
        estimator.update(state, row)
    prm = state.prm
    x = state.mem[M_X : M_X + N_X].copy()
    P = state.mem[M_P : M_P + N_X * N_X].reshape(N_X, N_X) * 1e-4
    u, z = np.empty(N_U), np.empty(N_Z)
    read_sample(prm, np.array([float(braking_rows[k][c]) for c in SAMPLE_COLUMNS]), u, z)
    x_e, P_e, x_u, P_u = np.empty(N_X), np.empty((N_X, N_X)), np.empty(N_X), np.empty((N_X, N_X))
    ok_e, snr_e = ekf_update(prm, x, P, u, z, x_e, P_e, True)
    ok_u, snr_u = ukf_update(prm, x, P, u, z, x_u, P_u, True)
    assert ok_e and ok_u
    assert snr_u == pytest.approx(snr_e, rel=1e-3)
    assert (snr_e >= FilterTuning().excitation_snr) == (k == 28)
    np.testing.assert_allclose(x_u, x_e, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(P_u, P_e, rtol=1e-3, atol=1e-12)


def test_ukf_and_ekf_agree_on_a_braking_run(braking_rows):
    out = {}
    for name in ("ekf", "ukf"):
        estimator = physics_estimator(name)
        state = estimator.start(PAPER_SUV)
        out[name] = [estimator.update(state, row) for row in braking_rows]
    both = [(e.mu, u.mu) for e, u in zip(out["ekf"], out["ukf"]) if e.excited and u.excited]
    assert len(both) > 20
    # the first excited sample meets the prior's wide spread (0.5 +- 0.8 for the UKF's points): there they differ
    assert np.abs(np.diff(both[5:], axis=1)).max() < 0.04
    assert abs(both[-1][0] - 0.45) < 0.03 and abs(both[-1][1] - 0.45) < 0.03
