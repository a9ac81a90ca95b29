"""Full-vehicle body dynamics: longitudinal, lateral, yaw, roll and the four wheel spins (paper section 3).

State vector x (SI, ISO 8855 axes: x forward, y left, z up; yaw, steering and roll positive by the right-hand rule, so a
positive roll lowers the right side):

| index | name      | unit  | meaning                                      |
|-------|-----------|-------|----------------------------------------------|
| 0, 1  | X, Y      | m     | CoG position in the road's east/north frame  |
| 2     | psi       | rad   | heading, 0 = east, positive to the left      |
| 3, 4  | vx, vy    | m/s   | CoG velocity in the body frame               |
| 5     | r         | rad/s | yaw rate                                     |
| 6, 7  | phi, phid | rad, rad/s | roll angle and rate of the sprung mass  |
| 8-11  | omega_i   | rad/s | wheel spins, i = 0 fl, 1 fr, 2 rl, 3 rr      |

Inputs: road-wheel steering angle delta (both front wheels), drive torque per wheel, and the road's mu under each wheel.
Brake and rolling-resistance torques act as Coulomb friction on the wheels and are applied by the integrator (sim/integrator.py),
which also needs from this module the stiffness of each wheel's tire force with respect to its spin (`wheel_k`) to integrate the
stiff wheel dynamics semi-implicitly.

`derivatives` is pure: it reads x, the inputs and the previous step's accelerations (for the quasi-static load transfer of
eq. 2, which would otherwise be an algebraic loop) and writes dx/dt and the per-wheel quantities into caller-owned arrays.
"""

from math import atan, cos, sin

import numpy as np
from numba import njit

from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import VehicleParams
from roadgrip.vehicle.tires.kernel import tire_forces

AIR_DENSITY_KGPM3 = 1.225  # ISA sea level
SLIP_SPEED_FLOOR_MPS = 0.5  # denominator floor of eq. 6 and eq. 8 at standstill (see docs/SIMULATOR.md)
SLIP_FD_STEP = 1e-4  # finite-difference step on the slip ratio for d fx / d sigma

# State indices
X, Y, PSI, VX, VY, R, PHI, PHID, W0 = 0, 1, 2, 3, 4, 5, 6, 7, 8
N_STATE = 12

# Packed vehicle parameter vector
(
    P_M,
    P_MS,
    P_IZ,
    P_IX,
    P_LF,
    P_LR,
    P_H,
    P_TF,
    P_TR,
    P_RW,
    P_JW,
    P_KF,
    P_KR,
    P_CROLL,
    P_HRF,
    P_HRR,
    P_AERO,
    P_FRR,
    P_DRIVE_F,
    P_BRAKE_F,
    P_TMAX,
    P_PMAX,
    P_STEER_MAX,
    P_STEER_RATIO,
) = range(24)
N_VP = 24


def pack_vehicle(v: VehicleParams) -> np.ndarray:
    """The vehicle as the flat float vector the compiled kernels read (indices P_*)."""
    vp = np.zeros(N_VP)
    vp[P_M] = v.mass_kg
    vp[P_MS] = v.sprung_mass_kg
    vp[P_IZ] = v.yaw_inertia_kgm2
    vp[P_IX] = v.roll_inertia_kgm2
    vp[P_LF] = v.cg_to_front_axle_m
    vp[P_LR] = v.cg_to_rear_axle_m
    vp[P_H] = v.cg_height_m
    vp[P_TF] = v.track_front_m
    vp[P_TR] = v.track_rear_m
    vp[P_RW] = v.wheel_radius_m
    vp[P_JW] = v.wheel_inertia_kgm2
    vp[P_KF] = v.roll_stiffness_front_nmprad
    vp[P_KR] = v.roll_stiffness_rear_nmprad
    vp[P_CROLL] = v.roll_damping_nmsprad
    vp[P_HRF] = v.roll_center_height_front_m
    vp[P_HRR] = v.roll_center_height_rear_m
    vp[P_AERO] = 0.5 * AIR_DENSITY_KGPM3 * v.drag_coefficient * v.frontal_area_m2  # F = P_AERO vx |vx|
    vp[P_FRR] = v.rolling_resistance
    vp[P_DRIVE_F] = v.drive_split[0]
    vp[P_BRAKE_F] = v.brake_front_share
    vp[P_TMAX] = v.max_drive_torque_nm
    vp[P_PMAX] = v.max_power_w
    vp[P_STEER_MAX] = v.max_steer_rad
    vp[P_STEER_RATIO] = v.steering_ratio
    return vp


@njit(cache=True)
def wheel_position(vp, i):
    """(x, y) of wheel i's contact point relative to the CoG: left wheels at +track/2."""
    if i < 2:
        return vp[P_LF], (0.5 if i == 0 else -0.5) * vp[P_TF]
    return -vp[P_LR], (0.5 if i == 2 else -0.5) * vp[P_TR]


@njit(cache=True)
def slip_ratio(wheel_speed_mps, hub_speed_mps):
    """Eq. 6, sigma = (R w - v) / max(R w, v), with a floor on the denominator so that it is 0, not 0/0, at standstill."""
    den = max(abs(wheel_speed_mps), abs(hub_speed_mps), SLIP_SPEED_FLOOR_MPS)
    return (wheel_speed_mps - hub_speed_mps) / den


@njit(cache=True)
def slip_ratio_per_spin(wheel_speed_mps, hub_speed_mps, radius_m):
    """d sigma / d omega of eq. 6 (per rad/s), on the branch that `slip_ratio` takes."""
    a, b = abs(wheel_speed_mps), abs(hub_speed_mps)
    if a >= b and a >= SLIP_SPEED_FLOOR_MPS:
        return radius_m * hub_speed_mps / (wheel_speed_mps * wheel_speed_mps) * (1.0 if wheel_speed_mps > 0 else -1.0)
    return radius_m / max(b, SLIP_SPEED_FLOOR_MPS)


@njit(cache=True)
def wheel_loads(vp, ax, ay, phi, phid, fz_out):
    """Vertical loads on a level road (`wheel_loads_on_grade` with a zero grade)."""
    wheel_loads_on_grade(vp, ax, ay, phi, phid, 0.0, fz_out)


@njit(cache=True)
def wheel_loads_on_grade(vp, ax, ay, phi, phid, grade_rad, fz_out):
    """Vertical loads, eq. 2: static share, longitudinal transfer m a_x h / (2 L), and per axle the lateral transfer through
    the roll centre (m_axle a_y h_rc / d) plus the elastic one through the roll stiffness and damping ((K phi + C phid) / d).

    The paper prints the lateral terms over 2 d and both with the CoG height, which halves them and counts the roll moment
    twice; the form here balances the roll moment exactly (sum of Fz y = -(m_s a_y e + m a_y h_ra) in steady state).

    On a grade the loads carry the weight's component normal to the road, m g cos(grade); the weight's component along
    the road acts at the CoG and makes no moment about it, so the longitudinal transfer stays m a_x h / L with a_x the
    specific force of the tire (and drag) forces, which is what `derivatives` passes."""
    m, lf, lr, h = vp[P_M], vp[P_LF], vp[P_LR], vp[P_H]
    wheelbase = lf + lr
    k_total = vp[P_KF] + vp[P_KR]
    weight_normal = m * G_MPS2 * cos(grade_rad)
    static_f = weight_normal * lr / (2.0 * wheelbase)
    static_r = weight_normal * lf / (2.0 * wheelbase)
    lon = m * ax * h / (2.0 * wheelbase)
    roll_moment_f = vp[P_KF] * phi + vp[P_CROLL] * vp[P_KF] / k_total * phid
    roll_moment_r = vp[P_KR] * phi + vp[P_CROLL] * vp[P_KR] / k_total * phid
    lat_f = (m * lr / wheelbase * ay * vp[P_HRF] + roll_moment_f) / vp[P_TF]
    lat_r = (m * lf / wheelbase * ay * vp[P_HRR] + roll_moment_r) / vp[P_TR]
    fz_out[0] = max(static_f - lon - lat_f, 0.0)
    fz_out[1] = max(static_f - lon + lat_f, 0.0)
    fz_out[2] = max(static_r + lon - lat_r, 0.0)
    fz_out[3] = max(static_r + lon + lat_r, 0.0)


@njit(cache=True)
def derivatives(
    x,
    delta,
    drive_torque,
    mu,
    vp,
    tp,
    ax_prev,
    ay_prev,
    dx,
    fz,
    sigma,
    alpha,
    fx,
    fy,
    wheel_k,
    wheel_k_secant,
    hub_speed,
    grade_rad=0.0,
):
    """dx/dt of the body and the wheels' tire torques. Returns (a_x, a_y): the specific force of the tire and drag forces
    on the body (force / m, body frame), which is the CoG acceleration on a level road and what a level accelerometer reads
    on any road.

    `grade_rad` is the road's longitudinal grade under the car (positive uphill): the weight's component along the road,
    -g sin(grade), enters dv_x/dt but not a_x, and the loads carry m g cos(grade). The road is taken as a plane tilted
    about the body's y axis (no cross slope); the mu of the road is the adhesion coefficient as before (force / normal
    load), so the label keeps its meaning.

    Writes dx (N_STATE), and per wheel: fz (load, N), sigma (eq. 6), alpha (eq. 8, rad), fx/fy (tire force in the wheel
    frame, N), wheel_k and wheel_k_secant (N m s/rad, >= 0: the tangent and secant growth of the tire torque with the
    spin, for the implicit wheel step) and hub_speed (m/s along the wheel's heading)."""
    vx, vy, r, phi, phid = x[VX], x[VY], x[R], x[PHI], x[PHID]
    radius = vp[P_RW]
    wheel_loads_on_grade(vp, ax_prev, ay_prev, phi, phid, grade_rad, fz)
    fx_body = 0.0
    fy_body = 0.0
    yaw_moment = 0.0
    for i in range(4):
        xi, yi = wheel_position(vp, i)
        steer = delta if i < 2 else 0.0
        c, s = cos(steer), sin(steer)
        vwx = vx - r * yi  # hub velocity in the body frame
        vwy = vy + r * xi
        v_long = vwx * c + vwy * s  # hub speed along the wheel's heading (v_i of eq. 6)
        alpha[i] = steer - atan(vwy / max(vwx, SLIP_SPEED_FLOOR_MPS))  # eq. 8
        wheel_speed = radius * x[W0 + i]
        sigma[i] = slip_ratio(wheel_speed, v_long)  # eq. 6
        tpi = tp[0] if i < 2 else tp[1]
        fx[i], fy[i] = tire_forces(tpi, sigma[i], alpha[i], fz[i], mu[i])
        fx_step, _ = tire_forces(tpi, sigma[i] + SLIP_FD_STEP, alpha[i], fz[i], mu[i])
        # stiffnesses for the implicit wheel step: the tangent, and the secant to zero slip (the integrator takes the
        # secant when a tangent step would jump across the steep part of a saturated curve to the other side of zero)
        per_spin = radius * slip_ratio_per_spin(wheel_speed, v_long, radius)
        wheel_k[i] = max((fx_step - fx[i]) / SLIP_FD_STEP, 0.0) * per_spin
        secant = fx[i] / sigma[i] if abs(sigma[i]) > SLIP_FD_STEP else 0.0
        wheel_k_secant[i] = max(secant, wheel_k[i] / per_spin) * per_spin
        hub_speed[i] = v_long
        fxb = fx[i] * c - fy[i] * s  # eq. 1: wheel frame to body frame
        fyb = fx[i] * s + fy[i] * c
        fx_body += fxb
        fy_body += fyb
        yaw_moment += xi * fyb - yi * fxb
        dx[W0 + i] = (drive_torque[i] - radius * fx[i]) / vp[P_JW]
    m = vp[P_M]
    ax = (fx_body - vp[P_AERO] * vx * abs(vx)) / m  # eq. 1, m a_x = sum of longitudinal forces
    ay = fy_body / m  # eq. 1, m a_y = sum of lateral forces
    psi = x[PSI]
    dx[X] = vx * cos(psi) - vy * sin(psi)
    dx[Y] = vx * sin(psi) + vy * cos(psi)
    dx[PSI] = r
    dx[VX] = ax + r * vy - G_MPS2 * sin(grade_rad)  # the weight's component along the road
    dx[VY] = ay - r * vx
    dx[R] = yaw_moment / vp[P_IZ]
    roll_arm = vp[P_H] - (vp[P_HRF] + (vp[P_HRR] - vp[P_HRF]) * vp[P_LF] / (vp[P_LF] + vp[P_LR]))
    ms = vp[P_MS]
    dx[PHI] = phid
    dx[PHID] = (
        ms * ay * roll_arm + ms * G_MPS2 * roll_arm * sin(phi) - (vp[P_KF] + vp[P_KR]) * phi - vp[P_CROLL] * phid
    ) / vp[P_IX]
    return ax, ay
