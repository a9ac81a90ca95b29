"""The EKF kernel against a textbook Kalman step written with numpy (a second implementation) and closed forms."""

import numpy as np
import pytest

from roadgrip.estimators.ekf import ekf_step, ekf_update
from roadgrip.estimators.kalman import (
    M_P,
    M_SNR,
    M_T,
    M_U,
    M_X,
    N_OUT,
    SAMPLE_COLUMNS,
    cholesky,
    cholesky_solve,
    matmul,
    matmul_bt,
    read_sample,
)
from roadgrip.estimators.physics import physics_estimator
from roadgrip.estimators.vehicle_model import (
    MU,
    N_U,
    N_X,
    N_Z,
    FilterTuning,
    loads_from_accel,
    measure,
    measurement_noise,
    pack_model,
    predict_state,
    process_noise,
)
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import PAPER_SUV

PRM = pack_model(PAPER_SUV)


@pytest.fixture(scope="module")
def rows():
    """ABS braking from 30 to 12 m/s on mu 0.5, then a steady 12 m/s."""
    run = simulate(
        [
            Scenario(
                run_id="brake-cruise",
                path=Path.straight(1200.0),
                mu=MuProfile.uniform(0.5),
                speed=SpeedProfile([0.0, 2.0, 2.3, 30.0], [30.0, 30.0, 12.0, 12.0]),
                duration_s=30.0,
                seed=3,
            )
        ]
    )
    return run.to_pylist()


def _state_before(rows, k):
    """The EKF's memory after samples 0 .. k-1."""
    estimator = physics_estimator("ekf")
    state = estimator.start(PAPER_SUV)
    for row in rows[:k]:
        estimator.update(state, row)
    return state.mem.copy()


def _textbook_step(mem, row, zero_mu_gain=False):
    """x-, P- by the kernel's f, F, Q; then the update as printed in the books, with numpy's inverse:
    K = P H' (H P H' + R)^-1, x+ = x- + K (z - h), P+ = (I - K H) P- (the short form: equal to Joseph's for the optimal K),
    or for a held mu the Joseph form with mu's row of K zeroed."""
    smp = np.array([float(row[c]) for c in SAMPLE_COLUMNS])
    u, z = np.empty(N_U), np.empty(N_Z)
    read_sample(PRM, smp, u, z)
    x, P = mem[M_X : M_X + N_X], mem[M_P : M_P + N_X * N_X].reshape(N_X, N_X)
    dt = (smp[0] - mem[M_T]) / 1000.0
    x_prior, F, Q = np.empty(N_X), np.empty((N_X, N_X)), np.empty((N_X, N_X))
    predict_state(x, mem[M_U : M_U + N_U], u, dt, PRM, x_prior, F)
    process_noise(PRM, dt, mem[M_U : M_U + N_U], u, P[MU, MU], Q)
    P_prior = F @ P @ F.T + Q
    fz, zp, H, G, Rm = np.empty(4), np.empty(N_Z), np.empty((N_Z, N_X)), np.empty((N_Z, 4)), np.empty((N_Z, N_Z))
    loads_from_accel(PRM, u[5], u[6], fz)
    measure(x_prior, u, PRM, fz, zp, H, G)
    measurement_noise(PRM, x_prior, G, Rm)
    K = P_prior @ H.T @ np.linalg.inv(H @ P_prior @ H.T + Rm)
    if zero_mu_gain:
        K[MU, :] = 0.0
        A = np.eye(N_X) - K @ H
        return x_prior + K @ (z - zp), A @ P_prior @ A.T + K @ Rm @ K.T
    return x_prior + K @ (z - zp), (np.eye(N_X) - K @ H) @ P_prior


def _kernel_step(mem, row):
    mem = mem.copy()
    ekf_step(mem, PRM, np.array([float(row[c]) for c in SAMPLE_COLUMNS]), np.zeros(N_OUT))
    return mem


def test_an_excited_step_is_the_textbook_kalman_step(rows):
    k = 24  # ABS braking
    mem = _state_before(rows, k)
    after = _kernel_step(mem, rows[k])
    assert after[M_SNR] >= FilterTuning().excitation_snr
    x, P = _textbook_step(mem, rows[k])
    np.testing.assert_allclose(after[M_X : M_X + N_X], x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(after[M_P : M_P + N_X * N_X].reshape(N_X, N_X), P, rtol=1e-6, atol=1e-12)
    assert abs(x[MU] - mem[M_X + MU]) > 1e-4, "mu was updated"


def test_a_step_that_does_not_excite_mu_holds_it_with_the_joseph_covariance(rows):
    k = 200  # steady 12 m/s
    mem = _state_before(rows, k)
    after = _kernel_step(mem, rows[k])
    assert after[M_SNR] < FilterTuning().excitation_snr
    x, P = _textbook_step(mem, rows[k], zero_mu_gain=True)
    np.testing.assert_allclose(after[M_X : M_X + N_X], x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(after[M_P : M_P + N_X * N_X].reshape(N_X, N_X), P, rtol=1e-6, atol=1e-12)
    assert after[M_X + MU] == mem[M_X + MU]


def test_held_mu_variance_grows_by_the_random_walk_exactly(rows):
    """Closed form: with mu held, P_mumu(k) = P_mumu(k0) + (k - k0) sigma_walk^2 dt, until sigma reaches mu_std_max."""
    tuning = FilterTuning()
    estimator = physics_estimator("ekf")
    state = estimator.start(PAPER_SUV)
    variances, excited = [], []
    for row in rows:
        excited.append(estimator.update(state, row).excited)
        variances.append(state.mem[M_P + N_X * MU + MU])
    first = max(np.flatnonzero(excited)) + 1
    q = tuning.mu_walk_std_per_sqrt_s**2 * 0.1
    held = np.asarray(variances[first:])
    below = held < tuning.mu_std_max**2 - q
    steps = np.diff(held)[below[:-1]]
    assert steps.size > 50
    np.testing.assert_allclose(steps, q, rtol=1e-9)


def test_an_update_that_would_break_the_covariance_is_rejected_and_leaves_the_prior():
    x = np.array([20.0, 0.0, 0.0, 0.0, 0.5])
    P = np.diag([0.01, 0.01, 0.01, 1e-4, 0.1])
    P[0, 0] = np.nan
    u = np.array([52.0, 52.0, 52.0, 52.0, 0.0, 0.0, 0.0])
    z = np.array([0.0, 0.0, 0.0, 20.0])
    x_post, P_post = np.empty(N_X), np.empty((N_X, N_X))
    accepted, _ = ekf_update(PRM, x, P, u, z, x_post, P_post, True)
    assert not accepted and (x_post == x).all()


def test_small_linear_algebra_matches_numpy():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 5))
    S = A @ A.T + 5 * np.eye(5)
    L = np.empty((5, 5))
    assert cholesky(S, L)
    np.testing.assert_allclose(L, np.linalg.cholesky(S), rtol=1e-12)
    B = rng.normal(size=(5, 3))
    X = B.copy()
    cholesky_solve(L, X)
    np.testing.assert_allclose(X, np.linalg.solve(S, B), rtol=1e-10)
    C = np.empty((5, 3))
    matmul(A, B, C)
    np.testing.assert_allclose(C, A @ B, rtol=1e-12)
    D = np.empty((5, 5))
    matmul_bt(A, S, D)
    np.testing.assert_allclose(D, A @ S.T, rtol=1e-12)
    assert not cholesky(-S, L) and not cholesky(np.full((5, 5), np.nan), L)
