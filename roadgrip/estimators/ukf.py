"""Unscented Kalman filter with mu as a state (as the paper's refs 11 and 12), on the model of vehicle_model.py.

Scaled unscented transform (Wan and van der Merwe 2000) with alpha = tuning.ukf_alpha (default 1), beta = 2, kappa = 0:
2n + 1 = 11 sigma points X_0 = x, X_i = x +- gamma L_i (L L' = P, gamma = alpha sqrt(n)); for alpha = 1 the weights are
Wm_0 = 0, Wc_0 = 2, W_i = 1 / (2n), all non-negative, so the sample covariances are positive semi-definite by
construction. (A smaller alpha gives Wm_0 < 0; docs/ESTIMATORS.md compares the spreads.)

    prior      X_i = sigma points of (x+, P+);  X-_i = f(X_i, u)
               x- = sum Wm_i X-_i,  P- = sum Wc_i (X-_i - x-)(X-_i - x-)' + Q
    update     X_i = sigma points of (x-, P-);  Z_i = h(X_i, u)
               z^ = sum Wm_i Z_i,   S = sum Wc_i (Z_i - z^)(Z_i - z^)' + R,   Pxz = sum Wc_i (X_i - x-)(Z_i - z^)'
               K  = Pxz S^-1         mu's row of K zeroed unless the sample excites mu (below)
               x+ = x- + K (z - z^)
               P+ = P- - K Pxz' - Pxz K' + K S K'     valid for any K (= P- - K S K' for the optimal one)

Excitation, as in the EKF but read off the transform itself: mu is the last state, so the last column of the Cholesky
factor has a single entry and the two sigma points along it differ from x only in mu; (Z_+ - Z_-) / (X_+ - X_-) is the
transform's own dh/dmu (a divided difference over +- gamma sigma_mu), and mu_snr = |R^-1/2 dh/dmu|. Not excited, mu is
held as a consider parameter: the transform is redone with mu's spread removed (averaging h over a spread that
straddles the tire's saturation would pull vx, since E[h] then differs from h at the mean), and mu's row of K is zeroed.
An update whose S or P+ is not positive definite, or not finite, is rejected (x+ = x-, P+ = P-).
"""

from __future__ import annotations

from math import sqrt

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
    symmetrize,
)
from roadgrip.estimators.vehicle_model import (
    MU,
    N_U,
    N_X,
    N_Z,
    T_MIN_SPEED,
    T_SNR,
    T_UKF_ALPHA,
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

UKF_BETA, UKF_KAPPA = 2.0, 0.0  # beta = 2 is optimal for Gaussian priors; kappa = 0 (alpha sets the spread)
N_SIGMA = 2 * N_X + 1
if MU != N_X - 1:
    raise ImportError("ukf.py reads the excitation off the last Cholesky column: mu must be the last state")


@njit(cache=True)
def ut_parameters(prm):
    """(gamma, Wm_0, Wc_0, W_i) of the scaled unscented transform for alpha = tuning.ukf_alpha."""
    alpha = prm[T_UKF_ALPHA]
    lam = alpha * alpha * (N_X + UKF_KAPPA) - N_X
    wm0 = lam / (N_X + lam)
    return sqrt(N_X + lam), wm0, wm0 + 1.0 - alpha * alpha + UKF_BETA, 1.0 / (2.0 * (N_X + lam))


@njit(cache=True)
def sigma_points(prm, x, P, X):
    """X[0] = x, X[1 + i] = x + gamma L[:, i], X[1 + n + i] = x - gamma L[:, i]. False unless P is positive definite."""
    gamma = ut_parameters(prm)[0]
    L = np.empty((N_X, N_X))
    if not cholesky(P, L):
        return False
    for j in range(N_X):
        X[0, j] = x[j]
    for i in range(N_X):
        for j in range(N_X):
            X[1 + i, j] = x[j] + gamma * L[j, i]
            X[1 + N_X + i, j] = x[j] - gamma * L[j, i]
    return True


@njit(cache=True)
def weights(prm, i):
    """(Wm_i, Wc_i) of sigma point i."""
    _, wm0, wc0, wi = ut_parameters(prm)
    return (wm0, wc0) if i == 0 else (wi, wi)


@njit(cache=True)
def ukf_predict(prm, x, P, u_prev, u, dt, x_prior, P_prior):
    """Prior by the unscented transform of the process. False (prior not formed) unless P is positive definite."""
    X = np.empty((N_SIGMA, N_X))
    if not sigma_points(prm, x, P, X):
        return False
    Xp = np.empty((N_SIGMA, N_X))
    F = np.empty((N_X, N_X))  # unused here: f's Jacobian
    for i in range(N_SIGMA):
        predict_state(X[i], u_prev, u, dt, prm, Xp[i], F)  # X-_i = f(X_i)
    # x- = sum Wm_i X-_i
    for j in range(N_X):
        x_prior[j] = 0.0
    for i in range(N_SIGMA):
        wm, _ = weights(prm, i)
        for j in range(N_X):
            x_prior[j] += wm * Xp[i, j]
    # P- = sum Wc_i (X-_i - x-)(X-_i - x-)' + Q
    process_noise(prm, dt, u_prev, u, P[MU, MU], P_prior)
    for i in range(N_SIGMA):
        _, wc = weights(prm, i)
        for a in range(N_X):
            for b in range(N_X):
                P_prior[a, b] += wc * (Xp[i, a] - x_prior[a]) * (Xp[i, b] - x_prior[b])
    symmetrize(P_prior)
    return True


@njit(cache=True)
def unscented_measurement(prm, x, P, u, fz, X, Z, zh, S, Pxz, G0):
    """The transform of the measurement for (x, P): sigma points X, Z_i = h(X_i), z^ = sum Wm_i Z_i,
    S = sum Wc_i (Z_i - z^)(Z_i - z^)' (without R), Pxz = sum Wc_i (X_i - x)(Z_i - z^)', and G0, the wheel-spin
    Jacobian at the mean. False unless P is positive definite."""
    if not sigma_points(prm, x, P, X):
        return False
    H = np.empty((N_Z, N_X))  # unused: the transform needs no Jacobian
    G = np.empty((N_Z, 4))
    for i in range(N_SIGMA):
        measure(X[i], u, prm, fz, Z[i], H, G)  # Z_i = h(X_i)
        if i == 0:
            G0[:, :] = G
    zh[:] = 0.0
    for i in range(N_SIGMA):
        wm, _ = weights(prm, i)
        for j in range(N_Z):
            zh[j] += wm * Z[i, j]
    S[:, :] = 0.0
    Pxz[:, :] = 0.0
    for i in range(N_SIGMA):
        _, wc = weights(prm, i)
        for a in range(N_Z):
            da = Z[i, a] - zh[a]
            for b in range(N_Z):
                S[a, b] += wc * da * (Z[i, b] - zh[b])
            for b in range(N_X):
                Pxz[b, a] += wc * (X[i, b] - x[b]) * da
    symmetrize(S)
    return True


@njit(cache=True)
def ukf_update(prm, x_prior, P_prior, u, z, x_post, P_post, mu_allowed):
    """Measurement update by the unscented transform. Returns (accepted, mu_snr); on rejection the posterior is the
    prior.

    Not excited (mu_snr below its threshold), mu is held as a consider parameter: the transform is redone with mu at
    its mean (its spread straddles the kink of Dugoff's saturation, and averaging h over it would bias vx), the mu row
    of Pxz comes from the regression of mu on the other states, P_mu,o P_oo^-1 Pxz_o, and mu's row of K is zeroed."""
    x_post[:] = x_prior
    P_post[:, :] = P_prior
    fz = np.empty(4)
    loads_from_accel(prm, u[U_AX], u[U_AY], fz)
    X = np.empty((N_SIGMA, N_X))
    Z = np.empty((N_SIGMA, N_Z))
    zh = np.empty(N_Z)
    S = np.empty((N_Z, N_Z))
    Pxz = np.empty((N_X, N_Z))
    G0 = np.empty((N_Z, 4))
    if not unscented_measurement(prm, x_prior, P_prior, u, fz, X, Z, zh, S, Pxz, G0):
        return False, 0.0
    Rm = np.empty((N_Z, N_Z))
    measurement_noise(prm, x_prior, G0, Rm)
    # the transform's dh/dmu from the two points along mu (the last Cholesky column has only its mu entry)
    snr = 0.0
    if x_prior[VX] >= prm[T_MIN_SPEED]:
        h_mu = np.empty(N_Z)
        step = X[1 + MU, MU] - X[1 + N_X + MU, MU]
        for j in range(N_Z):
            h_mu[j] = (Z[1 + MU, j] - Z[1 + N_X + MU, j]) / step
        snr = mu_snr(h_mu, Rm)
    if not mu_allowed:
        snr = 0.0
    mu_updated = snr >= prm[T_SNR]  # excited
    if not mu_updated:
        no = N_X - 1  # the states other than mu
        P_held = P_prior.copy()
        for j in range(N_X):
            P_held[MU, j] = 0.0
            P_held[j, MU] = 0.0
        P_held[MU, MU] = 1e-12 * max(P_prior[MU, MU], 1e-12)  # a point, but a positive definite one
        if not unscented_measurement(prm, x_prior, P_held, u, fz, X, Z, zh, S, Pxz, G0):
            return False, snr
        # Pxz_mu = P_mu,o P_oo^-1 Pxz_o
        Loo = np.empty((no, no))
        if not cholesky(P_prior[:no, :no].copy(), Loo):
            return False, snr
        A = Pxz[:no, :].copy()
        cholesky_solve(Loo, A)
        for j in range(N_Z):
            acc = 0.0
            for k in range(no):
                acc += P_prior[MU, k] * A[k, j]
            Pxz[MU, j] = acc
    S += Rm  # S = sum Wc_i (Z_i - z^)(Z_i - z^)' + R
    L = np.empty((N_Z, N_Z))
    if not cholesky(S, L):
        return False, snr
    # K = Pxz S^-1, from S K' = Pxz'
    Kt = Pxz.T.copy()
    cholesky_solve(L, Kt)
    K = Kt.T.copy()
    if not mu_updated:
        K[MU, :] = 0.0
    # x+ = x- + K (z - z^)
    x_new = x_prior.copy()
    for i in range(N_X):
        for j in range(N_Z):
            x_new[i] += K[i, j] * (z[j] - zh[j])
    # P+ = P- - K Pxz' - Pxz K' + K S K'
    KS = np.empty((N_X, N_Z))
    matmul(K, S, KS)
    P_new = np.empty((N_X, N_X))
    matmul_bt(KS, K, P_new)
    KPxz = np.empty((N_X, N_X))
    matmul_bt(K, Pxz, KPxz)
    for a in range(N_X):
        for b in range(N_X):
            P_new[a, b] += P_prior[a, b] - KPxz[a, b] - KPxz[b, a]
    return accept_posterior(x_new, P_new, x_post, P_post), snr


@njit(cache=True)
def ukf_step(mem, prm, smp, out):
    """One sample: prior (unless the filter starts on it), update, commit, output."""
    u = np.empty(N_U)
    z = np.empty(N_Z)
    decision, dt = begin(mem, prm, smp, u, z)
    if decision == REJECT:
        output(mem, prm, False, out)
        return
    x = mem[M_X : M_X + N_X].copy()
    P = mem[M_P : M_P + N_X * N_X].reshape(N_X, N_X).copy()
    x_prior, P_prior = x, P
    if decision == STEP:
        x_prior = np.empty(N_X)
        P_prior = np.empty((N_X, N_X))
        if not ukf_predict(prm, x, P, mem[M_U : M_U + N_U], u, dt, x_prior, P_prior):
            x_prior[:] = np.nan  # cannot happen with a committed (positive definite) P; commit() restarts
            P_prior[:, :] = np.nan
    x_post = np.empty(N_X)
    P_post = np.empty((N_X, N_X))
    # at a (re)start mu is held: the first sample is spent on the speeds
    accepted, snr = ukf_update(prm, x_prior, P_prior, u, z, x_post, P_post, decision == STEP)
    finish_step(mem, prm, smp, u, z, x_post, P_post, accepted, snr, out)


class UKFEstimator(KalmanEstimator):
    """mu from an unscented Kalman filter on a vehicle + Dugoff tire model (docs/ESTIMATORS.md)."""

    name = "ukf"
    step_kernel = staticmethod(ukf_step)
