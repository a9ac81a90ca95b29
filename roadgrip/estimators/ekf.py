"""Extended Kalman filter with mu as a state (as the paper's ref 8), on the vehicle + Dugoff model of vehicle_model.py.

One step per 100 ms sample (symbols as in filterpy / Simon, Optimal State Estimation, ch. 13):

    prior      x- = f(x+, u)               F = df/dx at x+
               P- = F P+ F' + Q
    update     y  = z - h(x-, u)           H = dh/dx at x-
               S  = H P- H' + R            R: sensor noise + wheel-speed noise through the slips (sigma_w^2 G G')
               K  = P- H' S^-1             mu's row of K zeroed unless the sample excites mu (below)
               x+ = x- + K y
               P+ = (I - K H) P- (I - K H)' + K R K'     Joseph form: symmetric PSD for any K, the zeroed row included

Excitation gate: mu is updated only where the measurements depend on it, mu_snr = |R^-1/2 dh/dmu| >= excitation_snr,
at speeds of at least min_speed_mps and not on a segment's first sample; elsewhere mu is held at its value as a
consider parameter (its row of K zeroed; the Joseph form keeps P exact for that gain) while its variance grows by the
random walk. Without the gate, Dugoff's kink at lambda = 1 (dF/dmu jumps from 0 to F_z (1 - lambda)) lets a small
tangent and a large prior variance turn a velocity error of a few cm/s into a jump of mu by 0.3 (docs/ESTIMATORS.md).

An update whose S or P+ is not positive definite, or not finite, is rejected (x+ = x-, P+ = P-, counted in the state).
The Jacobians are analytic (vehicle_model.measure); tests/estimators/test_vehicle_model.py checks them against finite
differences, tests/estimators/test_ekf.py this update against a textbook one.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from roadgrip.estimators.kalman import (
    M_P,
    M_U,
    M_X,
    REJECT,
    STEP,
    KalmanEstimator,
    accept_posterior,
    begin,
    cholesky,
    cholesky_solve,
    finish_step,
    matmul,
    matmul_bt,
    output,
)
from roadgrip.estimators.vehicle_model import (
    MU,
    N_U,
    N_X,
    N_Z,
    T_MIN_SPEED,
    T_SNR,
    U_AX,
    U_AY,
    VX,
    loads_from_accel,
    measure,
    measurement_noise,
    mu_snr,
    predict_state,
    process_noise,
)


@njit(cache=True)
def ekf_update(prm, x_prior, P_prior, u, z, x_post, P_post, mu_allowed):
    """Measurement update of the EKF. Returns (accepted, mu_snr); on rejection x_post, P_post are the prior. mu may be
    updated only if `mu_allowed` (not on a segment's first sample) and the sample excites it; mu_snr is 0 where it may
    not."""
    fz = np.empty(4)
    zp = np.empty(N_Z)
    H = np.empty((N_Z, N_X))
    G = np.empty((N_Z, 4))
    Rm = np.empty((N_Z, N_Z))
    loads_from_accel(prm, u[U_AX], u[U_AY], fz)
    measure(x_prior, u, prm, fz, zp, H, G)  # z^ = h(x-), H = dh/dx
    measurement_noise(prm, x_prior, G, Rm)
    snr = mu_snr(H[:, MU], Rm) if x_prior[VX] >= prm[T_MIN_SPEED] else 0.0
    if not mu_allowed:
        snr = 0.0
    mu_updated = snr >= prm[T_SNR]  # excited: otherwise mu is held (its row of K zeroed)
    x_post[:] = x_prior
    P_post[:, :] = P_prior
    # S = H P- H' + R
    HP = np.empty((N_Z, N_X))
    matmul(H, P_prior, HP)
    S = np.empty((N_Z, N_Z))
    matmul_bt(HP, H, S)
    S += Rm
    L = np.empty((N_Z, N_Z))
    if not cholesky(S, L):
        return False, snr
    # K = P- H' S^-1, from S K' = H P-
    Kt = HP.copy()
    cholesky_solve(L, Kt)
    K = Kt.T.copy()
    if not mu_updated:
        K[MU, :] = 0.0
    # x+ = x- + K (z - h(x-))
    x_new = x_prior.copy()
    for i in range(N_X):
        for j in range(N_Z):
            x_new[i] += K[i, j] * (z[j] - zp[j])
    # P+ = (I - K H) P- (I - K H)' + K R K'
    IKH = np.empty((N_X, N_X))
    matmul(K, H, IKH)
    IKH *= -1.0
    for i in range(N_X):
        IKH[i, i] += 1.0
    A = np.empty((N_X, N_X))
    matmul(IKH, P_prior, A)
    P_new = np.empty((N_X, N_X))
    matmul_bt(A, IKH, P_new)
    KR = np.empty((N_X, N_Z))
    matmul(K, Rm, KR)
    KRK = np.empty((N_X, N_X))
    matmul_bt(KR, K, KRK)
    P_new += KRK
    return accept_posterior(x_new, P_new, x_post, P_post), snr


@njit(cache=True)
def ekf_step(mem, prm, smp, out):
    """One sample: prior (unless the filter starts on it), update, commit, output."""
    u = np.empty(N_U)
    z = np.empty(N_Z)
    decision, dt = begin(mem, prm, smp, u, z)
    if decision == REJECT:
        output(mem, prm, False, out)
        return
    x = mem[M_X : M_X + N_X].copy()
    P = mem[M_P : M_P + N_X * N_X].reshape(N_X, N_X).copy()
    if decision == STEP:
        # x- = f(x+), P- = F P+ F' + Q
        x_prior = np.empty(N_X)
        F = np.empty((N_X, N_X))
        predict_state(x, mem[M_U : M_U + N_U], u, dt, prm, x_prior, F)
        FP = np.empty((N_X, N_X))
        matmul(F, P, FP)
        P_prior = np.empty((N_X, N_X))
        matmul_bt(FP, F, P_prior)
        Q = np.empty((N_X, N_X))
        process_noise(prm, dt, mem[M_U : M_U + N_U], u, P[MU, MU], Q)
        P_prior += Q
    else:
        x_prior, P_prior = x, P
    x_post = np.empty(N_X)
    P_post = np.empty((N_X, N_X))
    # at a (re)start mu is held: the first sample is spent on the speeds
    accepted, snr = ekf_update(prm, x_prior, P_prior, u, z, x_post, P_post, decision == STEP)
    finish_step(mem, prm, smp, u, z, x_post, P_post, accepted, snr, out)


class EKFEstimator(KalmanEstimator):
    """mu from an extended Kalman filter on a vehicle + Dugoff tire model (docs/ESTIMATORS.md)."""

    name = "ekf"
    step_kernel = staticmethod(ekf_step)
