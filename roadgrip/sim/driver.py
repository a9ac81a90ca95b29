"""The driver and the vehicle's controllers: what they want (profiles) and how they act (compiled control laws).

- Speed: a piecewise-linear speed profile (time, speed, and whether adaptive cruise control holds the segment) tracked by
  a feed-forward + PI controller whose demanded acceleration becomes drive torque (engine torque and power limits, drive
  split) or brake torque (front/rear brake split). Under ACC the demand is limited to ISO 15622 comfort values.
- Path: pure pursuit on the road's polyline (Coulter 1992), or an open-loop steering input (sine steer, constant steer).
- ABS: per wheel, release brake torque when the slip ratio falls below -0.12, hold, and re-apply above -0.08; the rear
  axle is controlled select-low (both rear wheels get the lower of their two torques) and the difference between the
  front brakes grows slowly and stays below 15 % of a full brake (yaw-moment build-up delay), as production systems do
  on split mu.
- Traction and stability control: cut drive torque while a driven wheel's slip exceeds 0.05 or the body's sideslip angle
  beyond the kinematic one, atan(v_y / v_x) - atan(l_r r / v_x), exceeds 3 degrees (the engine-intervention half of
  ESC), restore it below 0.02 and 2 degrees. The kinematic sideslip is what the car has without a skid (the rear axle
  rolling without a slip angle): 8 degrees in a 10 m radius turn at any low speed, where a raw 3-degree threshold fired
  without a skid; a production ESC compares against its reference model the same way.
At the friction limit nothing here can make the car follow its profile: the tires saturate and the car slides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from roadgrip.units import G_MPS2
from roadgrip.validation import bounded, check_bounds

SPEED_MAX_MPS = 70.0
SPEED_KP_PER_S = 1.0  # PI gains on the speed error: a 1 m/s error asks 1 m/s^2
SPEED_KI_PER_S2 = 0.2
SPEED_INTEGRAL_LIMIT_MPS2 = 1.5  # anti-windup: the integral term never asks more than this
DRIVER_ACCEL_LIMITS_MPS2 = (-1.2 * G_MPS2, 1.0 * G_MPS2)  # a driver may floor either pedal
ACC_ACCEL_LIMITS_MPS2 = (-3.5, 2.0)  # ISO 15622 ACC comfort limits
STANDSTILL_HOLD_MPS2 = -2.0  # brake demand that holds the car once stopped at a zero reference speed
STEER_LAG_S = 0.1  # steering actuator: first-order lag
LOOKAHEAD_TIME_S = 1.2  # pure pursuit look-ahead distance = max(LOOKAHEAD_MIN_M, LOOKAHEAD_TIME_S * speed)
LOOKAHEAD_MIN_M = 8.0
ABS_RELEASE_SLIP = -0.12
ABS_REAPPLY_SLIP = -0.08
YAW_BUILD_UP_S = 1.5  # s for the front brakes' allowed difference to reach a full brake's torque ...
YAW_MAX_SHARE = 0.15  # ... capped at this share of it
ABS_MIN_SPEED_MPS = 2.0  # ABS switches off below about 7 km/h, as production systems do
BRAKE_RISE_S = 0.15  # hydraulic brake pressure rise time to full torque; release as fast
TCS_CUT_SLIP, TCS_RESTORE_SLIP = 0.05, 0.02
ESC_CUT_SIDESLIP_RAD, ESC_RESTORE_SIDESLIP_RAD = math.radians(3.0), math.radians(2.0)
TCS_CUT_PER_S, TCS_RESTORE_PER_S = 5.0, 2.0
APPLY, HOLD, RELEASE = 0, 1, 2


@dataclass(frozen=True, eq=False)
class SpeedProfile:
    """Reference speed, linear between (times_s[k], speeds_mps[k]); acc_active[k] says whether ACC holds segment k."""

    times_s: np.ndarray
    speeds_mps: np.ndarray
    acc_active: np.ndarray | None = None

    def __post_init__(self):
        t = np.atleast_1d(np.asarray(self.times_s, dtype=np.float64))
        v = np.atleast_1d(np.asarray(self.speeds_mps, dtype=np.float64))
        acc = np.zeros(t.size, dtype=bool) if self.acc_active is None else np.atleast_1d(np.asarray(self.acc_active))
        if t.ndim != 1 or t.size < 1 or v.shape != t.shape or acc.shape != t.shape:
            raise ValueError(
                f"SpeedProfile needs times_s, speeds_mps and acc_active of one length, got {t.shape}, {v.shape}, {acc.shape}"
            )
        if not (np.isfinite(t).all() and np.isfinite(v).all()):
            raise ValueError("SpeedProfile times_s and speeds_mps must be finite")
        if t[0] != 0.0 or (np.diff(t) <= 0).any():
            raise ValueError(f"SpeedProfile.times_s must start at 0 and increase strictly, got {t.tolist()}")
        bad = v[(v < 0) | (v > SPEED_MAX_MPS)]
        if bad.size:
            raise ValueError(f"SpeedProfile.speeds_mps must lie in [0, {SPEED_MAX_MPS}], got {float(bad[0])!r}")
        object.__setattr__(self, "times_s", t)
        object.__setattr__(self, "speeds_mps", v)
        object.__setattr__(self, "acc_active", acc.astype(bool))

    @classmethod
    def accelerate_decelerate(cls, top_speed_mps: float, accelerate_s: float, total_s: float) -> SpeedProfile:
        """From standstill to the top speed, then back to standstill (the paper's 0 - 120 - 0 km/h)."""
        return cls([0.0, accelerate_s, total_s], [0.0, top_speed_mps, 0.0])

    def table(self) -> np.ndarray:
        """Rows (time_s, speed_mps, acc_active) for the compiled simulator."""
        return np.column_stack([self.times_s, self.speeds_mps, self.acc_active.astype(np.float64)])

    def distance_m(self, duration_s: float) -> float:
        """Distance the profile asks for over [0, duration_s] (trapezoid rule on its breakpoints)."""
        t = np.append(self.times_s[self.times_s < duration_s], duration_s)
        v = np.interp(t, self.times_s, self.speeds_mps)
        return float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)))


@dataclass(frozen=True)
class SteerInput:
    """Open-loop road-wheel steering delta = amplitude sin(2 pi f (t - start) + phase) for start <= t < end; the path
    follower steers outside that window. frequency 0 with phase pi/2 is a constant steer."""

    start_s: float = field(default=0.0, metadata=bounded(0.0, 1.0e6))
    end_s: float = field(default=0.0, metadata=bounded(0.0, 1.0e6))
    amplitude_rad: float = field(default=0.0, metadata=bounded(-0.6, 0.6))
    frequency_hz: float = field(default=0.0, metadata=bounded(0.0, 5.0))
    phase_rad: float = field(default=0.0, metadata=bounded(-math.pi, math.pi))

    def __post_init__(self):
        check_bounds(self)

    @classmethod
    def constant(cls, angle_rad: float, start_s: float = 0.0, end_s: float = 1.0e6) -> SteerInput:
        return cls(start_s, end_s, angle_rad, 0.0, math.pi / 2)

    def row(self) -> np.ndarray:
        return np.array([self.start_s, self.end_s, self.amplitude_rad, self.frequency_hz, self.phase_rad])


@njit(cache=True)
def speed_reference(table, n, t, k):
    """(v_ref, dv_ref/dt, acc_active, k) at time t from a (time, speed, acc) table, searching on from row k."""
    while k < n - 1 and table[k + 1, 0] <= t:
        k += 1
    if k == n - 1:
        return table[k, 1], 0.0, table[k, 2] > 0.5, k
    slope = (table[k + 1, 1] - table[k, 1]) / (table[k + 1, 0] - table[k, 0])
    return table[k, 1] + slope * (t - table[k, 0]), slope, table[k, 2] > 0.5, k


@njit(cache=True)
def speed_control(v_ref, slope, acc, vx, integral, dt):
    """Demanded acceleration (m/s^2) and the updated integral of the speed error (PI with anti-windup)."""
    err = v_ref - vx
    lo, hi = DRIVER_ACCEL_LIMITS_MPS2
    if acc:
        lo, hi = ACC_ACCEL_LIMITS_MPS2
    if v_ref <= 0.0 and vx < 0.5:
        return STANDSTILL_HOLD_MPS2, 0.0
    demand = slope + SPEED_KP_PER_S * err + SPEED_KI_PER_S2 * integral
    limited = min(max(demand, lo), hi)
    if limited == demand:
        limit = SPEED_INTEGRAL_LIMIT_MPS2 / SPEED_KI_PER_S2
        integral = min(max(integral + err * dt, -limit), limit)
    return limited, integral


@njit(cache=True)
def pure_pursuit(x, y, psi, target_x, target_y, wheelbase_m):
    """Road-wheel angle that puts the vehicle on a circle through the target point (pure pursuit)."""
    dx, dy = target_x - x, target_y - y
    fwd = dx * math.cos(psi) + dy * math.sin(psi)
    left = -dx * math.sin(psi) + dy * math.cos(psi)
    curvature = 2.0 * left / max(fwd * fwd + left * left, 1e-6)
    return math.atan(wheelbase_m * curvature)


@njit(cache=True)
def steer_input(row, t):
    """(active, road-wheel angle) of an open-loop steering row (start, end, amplitude, frequency, phase) at time t."""
    if row[0] <= t < row[1]:
        return True, row[2] * math.sin(2.0 * math.pi * row[3] * (t - row[0]) + row[4])
    return False, 0.0


@njit(cache=True)
def abs_step(mode, brake_torque, demand, slip, speed_mps, enabled, rate_nmps, dt):
    """One ABS (or plain hydraulic) step for one wheel: (mode, brake torque N m, intervening)."""
    modulating = enabled and speed_mps > ABS_MIN_SPEED_MPS
    if modulating:
        if slip < ABS_RELEASE_SLIP:
            mode = RELEASE
        elif slip > ABS_REAPPLY_SLIP:
            mode = APPLY
        elif mode == RELEASE:
            mode = HOLD
    else:
        mode = APPLY
    if mode == RELEASE:
        brake_torque = max(brake_torque - rate_nmps * dt, 0.0)
    elif mode == APPLY:
        brake_torque = min(brake_torque + rate_nmps * dt, demand) if brake_torque < demand else demand
    intervening = mode != APPLY and demand > brake_torque
    return mode, brake_torque, intervening


@njit(cache=True)
def traction_control(factor, max_driven_slip, sideslip_rad, dt):
    """Drive torque factor in [0, 1] after one step of traction and stability control; sideslip_rad is the body's
    sideslip beyond the kinematic one (the integrator's)."""
    if max_driven_slip > TCS_CUT_SLIP or abs(sideslip_rad) > ESC_CUT_SIDESLIP_RAD:
        return max(factor - TCS_CUT_PER_S * dt, 0.0)
    if max_driven_slip < TCS_RESTORE_SLIP and abs(sideslip_rad) < ESC_RESTORE_SIDESLIP_RAD:
        return min(factor + TCS_RESTORE_PER_S * dt, 1.0)
    return factor
