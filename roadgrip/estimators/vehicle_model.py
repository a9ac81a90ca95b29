"""The vehicle and tire model that the Kalman filters (ekf.py, ukf.py) share: process, measurement, noise, excitation.

State x (SI, ISO 8855 body axes: x forward, y left, z up; yaw positive to the left):

| index | name | unit  | meaning                                   | process model                         |
|-------|------|-------|-------------------------------------------|---------------------------------------|
| 0     | vx   | m/s   | longitudinal speed of the CoG (body axes) | d vx/dt = a_x + r vy (a_x measured)    |
| 1     | vy   | m/s   | lateral speed of the CoG (not sent)       | d vy/dt = a_y - r vx (a_y measured)    |
| 2     | r    | rad/s | yaw rate                                  | random walk (yaw acceleration noise)   |
| 3     | s    | -     | scale error of the reported speed         | random walk (slow)                     |
| 4     | mu   | -     | road adhesion coefficient                 | random walk, clipped to [0.05, 1.5]    |

Inputs u of a sample: the four wheel spins (rad/s; fl, fr, rl, rr), the road-wheel angle delta = steering-wheel angle /
steering ratio (rad), and the measured accelerations a_x, a_y (m/s^2; the lateral one as the rolled accelerometer reads
it). Measurements z: a_x, a_y (as read), yaw rate, speed.

Process: kinematic, driven by the measured accelerations (trapezoid over the step). The tire model is in the
measurement: slip ratios from the wheel spins and the state's speeds (paper eq. 6), slip angles (eq. 8), Dugoff forces
(eq. 3-7) on loads from eq. 2 with the measured accelerations, summed in the body frame (eq. 1):

    h_ax = (sum_i Fx_i cos d_i - Fy_i sin d_i - c_aero vx |vx|) / m
    h_ay = a_y + g sin(phi_ss(a_y)),  a_y = sum_i (Fx_i sin d_i + Fy_i cos d_i) / m,  phi_ss = k_phi a_y
    h_r  = r,  h_v = (1 + s) vx

mu enters only through the Dugoff forces, and only where a tire is saturated (lambda < 1, eq. 5): that is what makes it
observable, and `mu_snr` measures it. Why this split (and not the tire forces in the process) is argued in
docs/ESTIMATORS.md: at 10 Hz the sampled wheel spins do not represent a 100 ms interval (ABS cycles faster), and the
force's slope with vx (C_x F_z / v) makes a force-driven process stiff at low speed.

Everything here is a numba kernel over a flat parameter vector (`pack_model`), so that one filter update costs a few
microseconds.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from math import atan, cos, sin, sqrt, tan

import numpy as np
from numba import njit

from roadgrip.units import G_MPS2
from roadgrip.validation import bounded, check_bounds, from_mapping
from roadgrip.vehicle.dynamics import (
    N_VP,
    P_AERO,
    P_M,
    P_RW,
    SLIP_SPEED_FLOOR_MPS,
    pack_vehicle,
    slip_ratio,
    slip_ratio_per_spin,
    wheel_loads,
    wheel_position,
)
from roadgrip.vehicle.params import VehicleParams
from roadgrip.vehicle.tires.base import MAX_SLIP_ANGLE_RAD, TP_CX, TP_CY, TP_LEN
from roadgrip.vehicle.tires.dugoff import DugoffTire

# State, input and measurement layouts
VX, VY, R, SCALE, MU = 0, 1, 2, 3, 4
N_X = 5
U_W0, U_DELTA, U_AX, U_AY = 0, 4, 5, 6  # U_W0 .. U_W0 + 3: wheel spins fl, fr, rl, rr
N_U = 7
Z_AX, Z_AY, Z_R, Z_V = 0, 1, 2, 3
N_Z = 4
STATE_NAMES = ("vx_mps", "vy_mps", "yaw_rate_radps", "speed_scale_error", "mu")

MU_MIN, MU_MAX = 0.05, 1.5  # the state's range: below 0.05 is no road surface (polished ice is about 0.05)
INTERVAL_Z = 1.6448536269514722  # the 95 % quantile of the normal: mu +- z sigma is a 90 % interval
INTERVAL_RANGE = (0.0, 1.5)  # CONTRACTS 3.4 bounds of the reported interval


@dataclass(frozen=True)
class FilterTuning:
    """Noise and thresholds of the filters (SI; 1-sigma values). The reasoning behind each is in docs/ESTIMATORS.md."""

    mu_initial: float = field(default=0.5, metadata=bounded(MU_MIN, MU_MAX, doc="prior mean: mid-range, not a guess"))
    mu_initial_std: float = field(default=0.4, metadata=bounded(0.01, 2.0))
    mu_walk_std_per_sqrt_s: float = field(default=0.05, metadata=bounded(0.0, 2.0))
    mu_std_max: float = field(default=0.4, metadata=bounded(0.01, 2.0, doc="the random walk stops widening here"))
    accel_input_std_mps2: float = field(default=0.3, metadata=bounded(0.0, 20.0))
    yaw_accel_std_radps2: float = field(default=2.0, metadata=bounded(0.0, 100.0))
    ax_std_mps2: float = field(default=0.3, metadata=bounded(0.001, 20.0))
    ay_std_mps2: float = field(default=0.3, metadata=bounded(0.001, 20.0))
    yaw_rate_std_radps: float = field(default=0.005, metadata=bounded(1e-5, 1.0))
    speed_std_mps: float = field(default=0.05, metadata=bounded(1e-4, 10.0))
    speed_std_share: float = field(default=0.002, metadata=bounded(0.0, 1.0))
    speed_scale_initial_std: float = field(default=0.01, metadata=bounded(1e-5, 0.5))
    speed_scale_walk_per_sqrt_s: float = field(default=1e-4, metadata=bounded(0.0, 0.1))
    wheel_speed_std_radps: float = field(default=0.02, metadata=bounded(0.0, 10.0))
    vy_initial_std_mps: float = field(default=0.5, metadata=bounded(0.001, 20.0))
    yaw_rate_initial_std_radps: float = field(default=0.02, metadata=bounded(1e-4, 5.0))
    min_speed_mps: float = field(default=5.0, metadata=bounded(0.0, 30.0, doc="below it mu is not updated"))
    excitation_snr: float = field(default=6.0, metadata=bounded(0.0, 1e4))
    max_step_s: float = field(default=0.5, metadata=bounded(0.01, 60.0, doc="a longer step restarts the filter"))
    ukf_alpha: float = field(default=1.0, metadata=bounded(1e-3, 1.0, doc="UKF sigma-point spread (ukf.py)"))

    def __post_init__(self):
        check_bounds(self)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> FilterTuning:
        return from_mapping(cls, data)


# Packed parameter vector: vehicle (dynamics.P_*), the two Dugoff rows, derived constants, then the tuning
PM_TP_FRONT = N_VP
PM_TP_REAR = PM_TP_FRONT + TP_LEN
PM_ROLL_PER_AY = PM_TP_REAR + TP_LEN  # steady-state roll angle per lateral acceleration, rad per m/s^2
PM_TUNING = PM_ROLL_PER_AY + 1
(
    T_MU0,
    T_MU0_STD,
    T_MU_WALK,
    T_MU_STD_MAX,
    T_ACC_IN,
    T_YAW_ACC,
    T_AX,
    T_AY,
    T_YAW,
    T_SPEED,
    T_SPEED_SHARE,
    T_SCALE0,
    T_SCALE_WALK,
    T_WHEEL,
    T_VY0,
    T_R0,
    T_MIN_SPEED,
    T_SNR,
    T_MAX_STEP,
    T_UKF_ALPHA,
) = range(PM_TUNING, PM_TUNING + 20)
N_PM = PM_TUNING + 20


def roll_per_lateral_accel(vehicle: VehicleParams) -> float:
    """Steady-state roll per lateral acceleration (rad per m/s^2), from the roll equation of vehicle/dynamics.py with
    phi'' = phi' = 0: (K_f + K_r) phi = m_s a_y e + m_s g e sin(phi) ~ m_s e (a_y + g phi), e the CoG height over the
    roll axis at the CoG."""
    lf, lr = vehicle.cg_to_front_axle_m, vehicle.cg_to_rear_axle_m
    hrf, hrr = vehicle.roll_center_height_front_m, vehicle.roll_center_height_rear_m
    arm_m = vehicle.cg_height_m - (hrf + (hrr - hrf) * lf / (lf + lr))
    ms_e = vehicle.sprung_mass_kg * arm_m
    stiffness = vehicle.roll_stiffness_front_nmprad + vehicle.roll_stiffness_rear_nmprad - ms_e * G_MPS2
    if stiffness <= 0.0:
        raise ValueError(
            f"vehicle {vehicle.name!r}: roll stiffness {stiffness + ms_e * G_MPS2:.0f} N m/rad does not "
            f"hold the sprung mass's roll moment m_s g e = {ms_e * G_MPS2:.0f} N m/rad"
        )
    return ms_e / stiffness


def pack_model(vehicle: VehicleParams, tuning: FilterTuning = FilterTuning()) -> np.ndarray:
    """The vehicle profile, its Dugoff tire rows and the tuning as the flat vector the kernels read (PM_*, T_*)."""
    if not isinstance(vehicle, VehicleParams):
        raise TypeError(f"vehicle must be a VehicleParams, got {type(vehicle).__name__}")
    if not isinstance(tuning, FilterTuning):
        raise TypeError(f"tuning must be a FilterTuning, got {type(tuning).__name__}")
    prm = np.zeros(N_PM)
    prm[:N_VP] = pack_vehicle(vehicle)
    prm[PM_TP_FRONT : PM_TP_FRONT + TP_LEN] = DugoffTire().row(vehicle.tire_front)
    prm[PM_TP_REAR : PM_TP_REAR + TP_LEN] = DugoffTire().row(vehicle.tire_rear)
    prm[PM_ROLL_PER_AY] = roll_per_lateral_accel(vehicle)
    t = tuning
    prm[PM_TUNING:] = [
        t.mu_initial,
        t.mu_initial_std,
        t.mu_walk_std_per_sqrt_s,
        t.mu_std_max,
        t.accel_input_std_mps2,
        t.yaw_accel_std_radps2,
        t.ax_std_mps2,
        t.ay_std_mps2,
        t.yaw_rate_std_radps,
        t.speed_std_mps,
        t.speed_std_share,
        t.speed_scale_initial_std,
        t.speed_scale_walk_per_sqrt_s,
        t.wheel_speed_std_radps,
        t.vy_initial_std_mps,
        t.yaw_rate_initial_std_radps,
        t.min_speed_mps,
        t.excitation_snr,
        t.max_step_s,
        t.ukf_alpha,
    ]
    return prm


# ------------------------------------------------------------------------------------------------------ tire model


@njit(cache=True)
def dugoff_partials(tp, sigma, alpha_rad, fz_n, mu, out):
    """Dugoff forces (as tires/dugoff.py: eq. 3-5, 7) and their partial derivatives, written to
    out = [fx, fy, dfx/dsigma, dfx/dalpha, dfx/dmu, dfy/dsigma, dfy/dalpha, dfy/dmu]."""
    for k in range(8):
        out[k] = 0.0
    cx = tp[TP_CX] * fz_n
    cy = tp[TP_CY] * fz_n
    q = 1.0 + sigma  # 1 + sigma, eq. 3-4 (floored as in dugoff_forces)
    dq = 1.0
    if q < 1e-9:
        q, dq = 1e-9, 0.0
    a = alpha_rad
    da = 1.0
    if a > MAX_SLIP_ANGLE_RAD or a < -MAX_SLIP_ANGLE_RAD:
        a, da = min(max(a, -MAX_SLIP_ANGLE_RAD), MAX_SLIP_ANGLE_RAD), 0.0
    ta = tan(a)
    fxl = cx * sigma  # C_x sigma
    fyl = cy * ta  # C_y tan(alpha)
    dfyl = cy * (1.0 + ta * ta) * da  # d(C_y tan alpha)/d alpha
    d = sqrt(fxl * fxl + fyl * fyl)
    if d == 0.0 or fz_n <= 0.0:
        return
    lam = mu * fz_n * q / (2.0 * d)  # eq. 7
    if lam >= 1.0:  # linear region, f = 1: F = F_lin / (1 + sigma)
        out[0] = fxl / q
        out[1] = fyl / q
        out[2] = cx / q - fxl * dq / (q * q)
        out[5] = -fyl * dq / (q * q)
        out[6] = dfyl / q
        return
    # saturated, f = (2 - lambda) lambda: F = F_lin k with k = A (2 - lambda) / (2 D), A = mu F_z
    big_a = mu * fz_n
    k = big_a * (2.0 - lam) / (2.0 * d)
    dk_dd = -(big_a / (d * d)) * (1.0 - lam)  # dk/dD
    dk_dq = -big_a * big_a / (4.0 * d * d)  # dk/dq
    dk_dmu = fz_n * (1.0 - lam) / d  # dk/dmu: zero at lambda = 1, so F is C1 across the region boundary
    dd_ds = fxl * cx / d  # dD/dsigma
    dd_da = fyl * dfyl / d  # dD/dalpha
    dk_ds = dk_dd * dd_ds + dk_dq * dq
    dk_da = dk_dd * dd_da
    out[0] = fxl * k
    out[1] = fyl * k
    out[2] = cx * k + fxl * dk_ds
    out[3] = fxl * dk_da
    out[4] = fxl * dk_dmu
    out[5] = fyl * dk_ds
    out[6] = dfyl * k + fyl * dk_da
    out[7] = fyl * dk_dmu


@njit(cache=True)
def slip_ratio_per_hub_speed(wheel_speed_mps, hub_speed_mps):
    """d sigma / d v of eq. 6 on the branch that `slip_ratio` takes (v: the hub's speed along the wheel)."""
    a, b = abs(wheel_speed_mps), abs(hub_speed_mps)
    if a >= b and a >= SLIP_SPEED_FLOOR_MPS:
        return -1.0 / a
    if b >= SLIP_SPEED_FLOOR_MPS:
        return -wheel_speed_mps * (1.0 if hub_speed_mps > 0 else -1.0) / (hub_speed_mps * hub_speed_mps)
    return -1.0 / SLIP_SPEED_FLOOR_MPS


# ---------------------------------------------------------------------------------------------- vehicle kernels


@njit(cache=True)
def lateral_accel_from_sensor(prm, ay_sensor_mps2):
    """The CoG's lateral acceleration from the rolled accelerometer's reading a_y (1 + g k_phi) (small roll angle)."""
    return ay_sensor_mps2 / (1.0 + G_MPS2 * prm[PM_ROLL_PER_AY])


@njit(cache=True)
def loads_from_accel(prm, ax_mps2, ay_sensor_mps2, fz):
    """Eq. 2 loads with the measured accelerations and the steady-state roll angle they imply (roll rate 0)."""
    ay = lateral_accel_from_sensor(prm, ay_sensor_mps2)
    wheel_loads(prm, ax_mps2, ay, prm[PM_ROLL_PER_AY] * ay, 0.0, fz)


@njit(cache=True)
def predict_state(x, u_prev, u, dt, prm, x_out, F):
    """x_out = f(x): one step of the kinematic process (trapezoid of the measured accelerations), F = df/dx."""
    ax = 0.5 * (u_prev[U_AX] + u[U_AX])
    ay = lateral_accel_from_sensor(prm, 0.5 * (u_prev[U_AY] + u[U_AY]))
    vx, vy, r = x[VX], x[VY], x[R]
    x_out[VX] = vx + dt * (ax + r * vy)  # vx' = a_x + r vy
    x_out[VY] = vy + dt * (ay - r * vx)  # vy' = a_y - r vx
    x_out[R] = r
    x_out[SCALE] = x[SCALE]
    x_out[MU] = x[MU]
    for i in range(N_X):
        for j in range(N_X):
            F[i, j] = 1.0 if i == j else 0.0
    F[VX, VY] = dt * r
    F[VX, R] = dt * vy
    F[VY, VX] = -dt * r
    F[VY, R] = -dt * vx


@njit(cache=True)
def process_noise(prm, dt, u_prev, u, p_mumu, Q):
    """Q of one step. On vx and vy: the acceleration input's noise, plus the trapezoid's error where the measured
    acceleration changed between the samples by da: the change may have come anywhere in the step, so the mean
    acceleration is uncertain by |da| / sqrt(12) (uniform timing). On r: yaw-acceleration noise. On mu: the random walk,
    whose growth stops where the mu variance reaches mu_std_max^2 (P_mumu never grows past it by Q)."""
    for i in range(N_X):
        for j in range(N_X):
            Q[i, j] = 0.0
    base = prm[T_ACC_IN] * prm[T_ACC_IN]
    dax = u[U_AX] - u_prev[U_AX]
    day = lateral_accel_from_sensor(prm, u[U_AY] - u_prev[U_AY])
    Q[VX, VX] = (base + dax * dax / 12.0) * dt * dt
    Q[VY, VY] = (base + day * day / 12.0) * dt * dt
    yaw = prm[T_YAW_ACC] * dt
    Q[R, R] = yaw * yaw
    Q[SCALE, SCALE] = prm[T_SCALE_WALK] * prm[T_SCALE_WALK] * dt
    walk = prm[T_MU_WALK] * prm[T_MU_WALK] * dt
    Q[MU, MU] = min(walk, max(prm[T_MU_STD_MAX] * prm[T_MU_STD_MAX] - p_mumu, 0.0))


@njit(cache=True)
def measure(x, u, prm, fz, z, H, G):
    """z = h(x, u) with H = dh/dx and G = dh/d(wheel spins) (N_Z x 4), for the loads fz (from `loads_from_accel`)."""
    vx, vy, r = x[VX], x[VY], x[R]
    mu = x[MU]
    dmu = 1.0
    if mu < MU_MIN or mu > MU_MAX:  # sigma points of the UKF may stray outside; the road does not
        mu, dmu = min(max(mu, MU_MIN), MU_MAX), 0.0
    radius = prm[P_RW]
    part = np.empty(8)
    for i in range(N_Z):
        z[i] = 0.0
        for j in range(N_X):
            H[i, j] = 0.0
        for j in range(4):
            G[i, j] = 0.0
    for i in range(4):
        xi, yi = wheel_position(prm, i)
        steer = u[U_DELTA] if i < 2 else 0.0
        c, s = cos(steer), sin(steer)
        vwx = vx - r * yi  # hub velocity in the body frame
        vwy = vy + r * xi
        v_long = vwx * c + vwy * s  # hub speed along the wheel (v of eq. 6)
        dvl_dvx, dvl_dvy, dvl_dr = c, s, -yi * c + xi * s
        den = max(vwx, SLIP_SPEED_FLOOR_MPS)
        ratio = vwy / den
        alpha = steer - atan(ratio)  # eq. 8
        dal = -1.0 / (1.0 + ratio * ratio)  # d alpha / d ratio
        dratio_dvx = -vwy / (den * den) if vwx > SLIP_SPEED_FLOOR_MPS else 0.0
        dal_dvx = dal * dratio_dvx
        dal_dvy = dal / den
        dal_dr = dal * (xi / den - yi * dratio_dvx)
        wheel_speed = radius * u[U_W0 + i]
        sigma = slip_ratio(wheel_speed, v_long)  # eq. 6
        ds_dvl = slip_ratio_per_hub_speed(wheel_speed, v_long)
        ds_dw = slip_ratio_per_spin(wheel_speed, v_long, radius)
        tp = prm[PM_TP_FRONT : PM_TP_FRONT + TP_LEN] if i < 2 else prm[PM_TP_REAR : PM_TP_REAR + TP_LEN]
        dugoff_partials(tp, sigma, alpha, fz[i], mu, part)
        fx, fy = part[0], part[1]
        # wheel frame to body frame (eq. 1), and the same rotation of each partial derivative
        fxb = fx * c - fy * s
        fyb = fx * s + fy * c
        z[Z_AX] += fxb
        z[Z_AY] += fyb
        for j in range(3):
            dvl = dvl_dvx if j == 0 else (dvl_dvy if j == 1 else dvl_dr)
            dal_j = dal_dvx if j == 0 else (dal_dvy if j == 1 else dal_dr)
            dfx = part[2] * ds_dvl * dvl + part[3] * dal_j
            dfy = part[5] * ds_dvl * dvl + part[6] * dal_j
            H[Z_AX, j] += dfx * c - dfy * s
            H[Z_AY, j] += dfx * s + dfy * c
        H[Z_AX, MU] += (part[4] * c - part[7] * s) * dmu
        H[Z_AY, MU] += (part[4] * s + part[7] * c) * dmu
        G[Z_AX, i] = (part[2] * c - part[5] * s) * ds_dw
        G[Z_AY, i] = (part[2] * s + part[5] * c) * ds_dw
    m = prm[P_M]
    aero = prm[P_AERO]
    # h_ax = (sum Fx_body - c_aero vx |vx|) / m
    z[Z_AX] = (z[Z_AX] - aero * vx * abs(vx)) / m
    H[Z_AX, VX] -= 2.0 * aero * abs(vx)
    # h_ay = a_y + g sin(k_phi a_y): the accelerometer rolls with the body (sensors.py)
    ay = z[Z_AY] / m
    k_phi = prm[PM_ROLL_PER_AY]
    z[Z_AY] = ay + G_MPS2 * sin(k_phi * ay)
    gain = 1.0 + G_MPS2 * k_phi * cos(k_phi * ay)
    for j in range(N_X):
        H[Z_AX, j] /= m
        H[Z_AY, j] *= gain / m
    for j in range(4):
        G[Z_AX, j] /= m
        G[Z_AY, j] *= gain / m
    z[Z_R] = r
    H[Z_R, R] = 1.0
    z[Z_V] = (1.0 + x[SCALE]) * vx
    H[Z_V, VX] = 1.0 + x[SCALE]
    H[Z_V, SCALE] = vx


@njit(cache=True)
def measurement_noise(prm, x, G, Rm):
    """R of one sample: the sensors' noise (with the model error they absorb, see the docs), the speed's error growing
    with speed (a scale error), and the wheel-speed noise carried through the slip ratios: R += sigma_w^2 G G'."""
    for i in range(N_Z):
        for j in range(N_Z):
            Rm[i, j] = 0.0
    Rm[Z_AX, Z_AX] = prm[T_AX] * prm[T_AX]
    Rm[Z_AY, Z_AY] = prm[T_AY] * prm[T_AY]
    Rm[Z_R, Z_R] = prm[T_YAW] * prm[T_YAW]
    sv = prm[T_SPEED] + prm[T_SPEED_SHARE] * abs(x[VX])
    Rm[Z_V, Z_V] = sv * sv
    w2 = prm[T_WHEEL] * prm[T_WHEEL]
    for i in range(2):
        for j in range(2):
            acc = 0.0
            for k in range(4):
                acc += G[i, k] * G[j, k]
            Rm[i, j] += w2 * acc


@njit(cache=True)
def mu_snr(h_mu, Rm):
    """How strongly the measurements depend on mu: sqrt(sum_j (dh_j/dmu)^2 / R_jj), per unit of mu. Its inverse is the
    1-sigma error with which this one sample alone would fix mu."""
    acc = 0.0
    for j in range(N_Z):
        acc += h_mu[j] * h_mu[j] / Rm[j, j]
    return sqrt(acc)


@njit(cache=True)
def initial_state(prm, u, speed_mps, yaw_rate_radps, x, P):
    """The state at a segment's first sample: vx the mean hub speed of the four wheels (R omega: they roll with a few
    per cent of slip at most, while the reported speed may be off by its scale error, and at low speed a vx off by
    0.1 m/s reads as a saturating slip), vy 0, r measured, no speed scale error, mu the prior; P diagonal."""
    radius = prm[P_RW]
    wheels = 0.0
    for i in range(4):
        wheels += 0.25 * radius * u[U_W0 + i]
    x[VX] = wheels
    x[VY] = 0.0
    x[R] = yaw_rate_radps
    x[SCALE] = 0.0
    x[MU] = prm[T_MU0]
    for i in range(N_X):
        for j in range(N_X):
            P[i, j] = 0.0
    sv = 2.0 * prm[T_SPEED] + prm[T_SCALE0] * abs(speed_mps) + abs(speed_mps - wheels)
    P[VX, VX] = sv * sv
    P[SCALE, SCALE] = prm[T_SCALE0] * prm[T_SCALE0]
    P[VY, VY] = prm[T_VY0] * prm[T_VY0]
    P[R, R] = prm[T_R0] * prm[T_R0]
    P[MU, MU] = prm[T_MU0_STD] * prm[T_MU0_STD]
