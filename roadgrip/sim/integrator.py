"""The compiled time loop: vehicle dynamics, driver and controllers, over a batch of runs in parallel.

Why compiled (numba) rather than vectorised over runs with numpy: the wheel dynamics are stiff (time constants down to
about a millisecond), so a run needs some 40,000 steps of 1 ms; numpy pays its per-call overhead on every one of the ~200
small operations of a step whatever the batch size, while a compiled loop runs one step of one run in about a microsecond and
`prange` spreads the independent runs over the cores. See docs/SIMULATOR.md for the measurement.

Integration (1 ms): explicit Euler for the body states, whose fastest mode at the speed floor is ~500 1/s; the wheel spins
semi-implicitly, (J + dt k) d omega = dt (T_drive - R F_x - T_friction), with k = R dF_x/d omega from the tire model (the
secant to zero slip instead, when the tangent step would cross zero slip: on a saturated low-mu curve it would flip the
slip's sign every step) and the brake and rolling-resistance torques as Coulomb friction that can stop a wheel but never turn it backwards. The driver and
path follower run at 100 Hz, ABS and traction control at every step. Samples are taken every 100 ms.

Load transfer (eq. 2) is quasi-static in the accelerations, which depend on the loads: an algebraic loop. Closing it with
the previous step's accelerations oscillates (the loop gain exceeds one at high slip), so the accelerations that set the
loads follow the body's through a 50 ms first-order lag, which stands for the pitch and heave response of the suspension
that the model does not carry as states.
"""

import math

import numpy as np
from numba import njit, prange

from roadgrip.sim.driver import (
    BRAKE_RISE_S,
    ESC_CUT_SIDESLIP_RAD,
    LOOKAHEAD_MIN_M,
    LOOKAHEAD_TIME_S,
    STEER_LAG_S,
    TCS_CUT_SLIP,
    YAW_BUILD_UP_S,
    YAW_MAX_SHARE,
    abs_step,
    pure_pursuit,
    speed_control,
    speed_reference,
    steer_input,
    traction_control,
)
from roadgrip.sim.roads import grade_at, mu_at, point_at_station, project_on_path
from roadgrip.units import G_MPS2
from roadgrip.vehicle.dynamics import (
    N_STATE,
    P_AERO,
    P_BRAKE_F,
    P_DRIVE_F,
    P_FRR,
    P_JW,
    P_LF,
    P_LR,
    P_M,
    P_PMAX,
    P_RW,
    P_STEER_MAX,
    P_TMAX,
    PHI,
    PSI,
    VX,
    VY,
    W0,
    R,
    X,
    Y,
    derivatives,
    wheel_position,
)

STEP_S = 0.001
CONTROL_EVERY = 10  # steps between driver updates (100 Hz)
LOAD_TRANSFER_LAG_S = 0.05  # first-order lag of the accelerations that drive the load transfer of eq. 2 (see below)

# Recorded channels, one row per sample
CHANNELS = (
    [
        "t_s",
        "x_m",
        "y_m",
        "heading_rad",
        "vx_mps",
        "vy_mps",
        "yaw_rate_radps",
        "roll_rad",
        "ax_mps2",
        "ay_mps2",
        "steer_rad",
        "station_m",
        "mu",
        "abs_active",
        "acc_active",
        "v_ref_mps",
    ]
    + [f"omega_{w}_radps" for w in ("fl", "fr", "rl", "rr")]
    + [f"mu_{w}" for w in ("fl", "fr", "rl", "rr")]
    + [f"slip_ratio_{w}" for w in ("fl", "fr", "rl", "rr")]
    + [f"slip_angle_{w}_rad" for w in ("fl", "fr", "rl", "rr")]
    + [f"fz_{w}_n" for w in ("fl", "fr", "rl", "rr")]
    + [f"fx_{w}_n" for w in ("fl", "fr", "rl", "rr")]
    + [f"fy_{w}_n" for w in ("fl", "fr", "rl", "rr")]
    + ["grade_rad", "brake_active", "tcs_active", "esc_active"]
)
N_CH = len(CHANNELS)
(
    C_T,
    C_X,
    C_Y,
    C_PSI,
    C_VX,
    C_VY,
    C_R,
    C_PHI,
    C_AX,
    C_AY,
    C_STEER,
    C_STATION,
    C_MU,
    C_ABS,
    C_ACC,
    C_VREF,
    C_OMEGA,
    C_MUW,
    C_SIG,
    C_ALPHA,
    C_FZ,
    C_FX,
    C_FY,
    C_GRADE,
    C_BRAKE,
    C_TCS,
    C_ESC,
) = list(range(16)) + [16 + 4 * k for k in range(7)] + [44, 45, 46, 47]
# ax_mps2 is the specific force of the tire and drag forces (what a level accelerometer reads; dv_x/dt - r v_y + g sin(grade));
# brake_active: the driver asked for brake torque at the sample (the brake-light switch); tcs_active / esc_active: during
# the 100 ms before the sample, traction control cut drive torque that the driver asked for, triggered by a driven
# wheel's slip (TCS) or by the body's sideslip beyond the kinematic atan(l_r r / v_x) (the engine intervention of ESC).


@njit(cache=True)
def simulate_one(
    vp,
    tp,
    path,
    n_path,
    mu_tab,
    n_mu,
    mu_mode,
    grade_tab,
    n_grade,
    speed,
    n_speed,
    steer_row,
    abs_on,
    tcs_on,
    n_sub,
    n_samples,
    out,
):
    dt = STEP_S
    x = np.zeros(N_STATE)
    dx = np.zeros(N_STATE)
    fz, sigma, alpha = np.zeros(4), np.zeros(4), np.zeros(4)
    fx, fy, wheel_k = np.zeros(4), np.zeros(4), np.zeros(4)
    wheel_k_secant, hub_speed = np.zeros(4), np.zeros(4)
    mu_w, drive_t, brake_demand, brake_t = np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4)
    drive_now = np.zeros(4)
    abs_mode = np.zeros(4, dtype=np.int64)
    radius, mass = vp[P_RW], vp[P_M]
    wheelbase = vp[P_LF] + vp[P_LR]
    brake_rate = 1.2 * mass * G_MPS2 * radius * 0.5 / BRAKE_RISE_S  # N m/s per wheel: full braking in BRAKE_RISE_S
    # initial state: at the path's start, heading along it, at the profile's initial speed, wheels rolling freely
    x[X], x[Y] = path[0, 0], path[0, 1]
    x[PSI] = math.atan2(path[1, 1] - path[0, 1], path[1, 0] - path[0, 0])
    x[VX] = speed[0, 1]
    for i in range(4):
        x[W0 + i] = speed[0, 1] / radius
    ax_prev, ay_prev = 0.0, 0.0
    delta, delta_cmd, accel_cmd, integral, tcs_factor = 0.0, 0.0, 0.0, 0.0, 1.0
    seg, sp_k, station, v_ref, acc = 0, 0, 0.0, speed[0, 1], False
    abs_window, tcs_window, esc_window, tcs_cause, esc_cause = False, False, False, False, False
    grade = grade_at(grade_tab, n_grade, 0.0)
    yaw_limit = 0.0  # N m: how far the front brakes may differ (grows while braking)
    for step in range(n_samples * n_sub):
        t = step * dt
        if step % CONTROL_EVERY == 0:
            seg, station, _ = project_on_path(path, n_path, seg, x[X], x[Y])
            grade = grade_at(grade_tab, n_grade, station)
            v_ref, slope, acc, sp_k = speed_reference(speed, n_speed, t, sp_k)
            accel_cmd, integral = speed_control(v_ref, slope, acc, x[VX], integral, CONTROL_EVERY * dt)
            open_loop, steer_angle = steer_input(steer_row, t)
            if open_loop:
                delta_cmd = steer_angle
            else:
                lookahead = max(LOOKAHEAD_MIN_M, LOOKAHEAD_TIME_S * x[VX])
                tx, ty = point_at_station(path, n_path, seg, station + lookahead)
                delta_cmd = pure_pursuit(x[X], x[Y], x[PSI], tx, ty, wheelbase)
            force = mass * accel_cmd + vp[P_AERO] * x[VX] * abs(x[VX]) + vp[P_FRR] * mass * G_MPS2
            force += (
                mass * G_MPS2 * math.sin(grade)
            )  # the driver feels the grade: feed-forward of the weight's component
            if force >= 0.0:
                force = min(force, vp[P_TMAX] / radius, vp[P_PMAX] / max(x[VX], 1.0))
                for i in range(4):
                    share = vp[P_DRIVE_F] if i < 2 else 1.0 - vp[P_DRIVE_F]
                    drive_t[i] = 0.5 * force * radius * share
                    brake_demand[i] = 0.0
            else:
                force = min(-force, 1.2 * mass * G_MPS2)
                for i in range(4):
                    share = vp[P_BRAKE_F] if i < 2 else 1.0 - vp[P_BRAKE_F]
                    drive_t[i] = 0.0
                    brake_demand[i] = 0.5 * force * radius * share
        for i in range(4):
            xi, yi = wheel_position(vp, i)
            mu_w[i] = mu_at(mu_tab, n_mu, mu_mode, station + xi, 1 if yi > 0 else 2)
        for i in range(4):
            drive_now[i] = drive_t[i] * tcs_factor
        ax, ay = derivatives(
            x,
            delta,
            drive_now,
            mu_w,
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
            grade,
        )
        if step % n_sub == 0:
            row = out[step // n_sub]
            row[C_T], row[C_X], row[C_Y], row[C_PSI] = t, x[X], x[Y], x[PSI]
            row[C_VX], row[C_VY], row[C_R], row[C_PHI] = x[VX], x[VY], x[R], x[PHI]
            row[C_AX], row[C_AY], row[C_STEER], row[C_STATION] = ax, ay, delta, station
            row[C_MU] = mu_at(mu_tab, n_mu, mu_mode, station, 1) * 0.5 + mu_at(mu_tab, n_mu, mu_mode, station, 2) * 0.5
            row[C_ABS], row[C_ACC], row[C_VREF] = 1.0 if abs_window else 0.0, 1.0 if acc else 0.0, v_ref
            for i in range(4):
                row[C_OMEGA + i], row[C_MUW + i], row[C_SIG + i] = x[W0 + i], mu_w[i], sigma[i]
                row[C_ALPHA + i], row[C_FZ + i], row[C_FX + i], row[C_FY + i] = alpha[i], fz[i], fx[i], fy[i]
            row[C_GRADE] = grade
            row[C_BRAKE] = 1.0 if brake_demand[0] + brake_demand[1] + brake_demand[2] + brake_demand[3] > 0.0 else 0.0
            row[C_TCS], row[C_ESC] = 1.0 if tcs_window else 0.0, 1.0 if esc_window else 0.0
            abs_window, tcs_window, esc_window = False, False, False
        # ABS and traction control, every step
        driven_slip = 0.0
        for i in range(4):
            share = vp[P_DRIVE_F] if i < 2 else 1.0 - vp[P_DRIVE_F]
            if share > 0.0:
                driven_slip = max(driven_slip, sigma[i])
            abs_mode[i], brake_t[i], intervening = abs_step(
                abs_mode[i], brake_t[i], brake_demand[i], sigma[i], x[VX], abs_on, brake_rate, dt
            )
            abs_window = abs_window or intervening
        if abs_on:
            # rear axle select-low, front axle yaw-moment build-up delay, as production ABS does on split mu
            brake_t[2] = brake_t[3] = min(brake_t[2], brake_t[3])
            full_brake = brake_rate * BRAKE_RISE_S
            yaw_limit = (
                min(yaw_limit + dt * full_brake / YAW_BUILD_UP_S, YAW_MAX_SHARE * full_brake)
                if brake_demand[0] > 0.0
                else 0.0
            )
            low = min(brake_t[0], brake_t[1])
            brake_t[0] = min(brake_t[0], low + yaw_limit)
            brake_t[1] = min(brake_t[1], low + yaw_limit)
        if tcs_on:
            # the body's sideslip beyond the kinematic one (the rear axle rolling without a slip angle: v_y = l_r r),
            # as a production ESC compares it against its reference model: a slow tight turn is no skid
            speed_floor = max(abs(x[VX]), 1.0)
            sideslip = math.atan2(x[VY], speed_floor) - math.atan2(vp[P_LR] * x[R], speed_floor)
            tcs_factor = traction_control(tcs_factor, driven_slip, sideslip, dt)
            # which half of the controller cut the torque, until it is fully restored
            tcs_cause = tcs_factor < 1.0 and (tcs_cause or driven_slip > TCS_CUT_SLIP)
            esc_cause = tcs_factor < 1.0 and (esc_cause or abs(sideslip) > ESC_CUT_SIDESLIP_RAD)
            demanded = drive_t[0] + drive_t[1] + drive_t[2] + drive_t[3] > 0.0
            tcs_window = tcs_window or (demanded and tcs_cause)
            esc_window = esc_window or (demanded and esc_cause)
        # body: explicit Euler
        for j in range(W0):
            x[j] += dt * dx[j]
        # wheels: semi-implicit, brake and rolling resistance as Coulomb friction
        for i in range(4):
            torque = drive_now[i] - radius * fx[i]
            den = vp[P_JW] + dt * wheel_k[i]
            free = x[W0 + i] + dt * torque / den
            if (radius * free - hub_speed[i]) * (radius * x[W0 + i] - hub_speed[i]) < 0.0:  # would cross zero slip
                den = vp[P_JW] + dt * wheel_k_secant[i]
                free = x[W0 + i] + dt * torque / den
            friction = dt * (brake_t[i] + vp[P_FRR] * fz[i] * radius) / den
            if abs(free) <= friction:
                x[W0 + i] = 0.0
            else:
                x[W0 + i] = free - friction * (1.0 if free > 0.0 else -1.0)
        # steering actuator
        delta += dt * (delta_cmd - delta) / STEER_LAG_S
        delta = min(max(delta, -vp[P_STEER_MAX]), vp[P_STEER_MAX])
        # load-transfer accelerations lag the body's by the suspension's pitch/heave response
        ax_prev += dt * (ax - ax_prev) / LOAD_TRANSFER_LAG_S
        ay_prev += dt * (ay - ay_prev) / LOAD_TRANSFER_LAG_S
    return out


@njit(parallel=True, cache=True)
def simulate_batch(
    vp, tp, path, n_path, mu_tab, n_mu, mu_mode, grade, n_grade, speed, n_speed, steer, flags, n_sub, n_samples, out
):
    for k in prange(vp.shape[0]):
        simulate_one(
            vp[k],
            tp[k],
            path[k],
            n_path[k],
            mu_tab[k],
            n_mu[k],
            mu_mode[k],
            grade[k],
            n_grade[k],
            speed[k],
            n_speed[k],
            steer[k],
            flags[k, 0] != 0,
            flags[k, 1] != 0,
            n_sub,
            n_samples,
            out[k],
        )
    return out


def run_batch(packed, n_samples: int, sample_period_s: float) -> np.ndarray:
    """Integrate every run of a packed batch; returns the recorded channels, shape (runs, n_samples, N_CH)."""
    n_sub = round(sample_period_s / STEP_S)
    out = np.zeros((packed.vp.shape[0], n_samples, N_CH))
    return simulate_batch(
        packed.vp,
        packed.tp,
        packed.path,
        packed.n_path,
        packed.mu,
        packed.n_mu,
        packed.mu_mode,
        packed.grade,
        packed.n_grade,
        packed.speed,
        packed.n_speed,
        packed.steer,
        packed.flags,
        n_sub,
        n_samples,
        out,
    )
