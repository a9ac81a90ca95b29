"""Feature set `production`: inputs that hold on a production car, where the reported speed is computed from the wheel
speeds (CONTRACTS 3.1) and so is no slip reference.

Every slip-like quantity compares wheels with wheels (normalised by their own mean speed, with the part that the
car's yaw explains taken out) or a wheel speed's rate of change with the accelerometer; the accelerations are in g.
The vehicle profile (CONTRACTS 3.2) gives the wheel radius, steering ratio, wheelbase, tracks and drive layout.

With v_i = omega_i r the rolling speed of wheel i (m/s) and V = max(|v_mean|, SPEED_FLOOR_MPS):

- wheel_speed_mps = v_mean = (v_fl + v_fr + v_rl + v_rr) / 4: the speed from the wheels
- axle_slip = (v_front - v_rear) / V - (sqrt(1 + (r_z L / V)^2) - 1): front axle over rear; in a turn the front axle
  runs on the larger radius (its centre moves at sqrt(v^2 + (r_z L)^2) when the rear axle has no sideslip)
- side_slip_front = (v_fl - v_fr + r_z t_f) / V: left over right; in a left turn (r_z > 0) the right wheel runs
  r_z t_f faster. side_slip_rear = (v_rl - v_rr + r_z t_r) / V
- wheel_accel_front_g = (d v_front / dt - a_x) / g: the front wheels decelerating beyond the body, a slip that grows;
  wheel_accel_rear_g the same for the rear axle
- accel_lon_g = a_x / g, accel_lat_g = a_y / g, utilization_g = sqrt(a_x^2 + a_y^2) / g (the car proves mu >= it)
- yaw_rate_radps = r_z; centripetal_g = r_z v_mean / g
- road_wheel_angle_rad = delta = steering-wheel angle / steering ratio
- understeer_g = (v_mean^2 delta / L - r_z v_mean) / g: the lateral acceleration the steering asks (kinematic,
  Ackermann) less the one the yaw rate gives; it grows as the front axle saturates
- front_drive_share: the profile's share of drive torque at the front axle (fwd 1, rwd 0, awd its split)
- abs_active, tcs_active, esc_active: the flags, 0/1; tcs/esc are optional in wire format v1: absent or null reads 0

v_front, v_rear are the axles' mean wheel speeds. d/dt is the backward difference against the stream's previous sample
(its timestamp_ms); at a stream's first sample, or after a step outside (0, MAX_STEP_S], the wheel_accel features are 0.
So a batch (`segments` mark where the stream restarts) and a stream fed one sample at a time with its previous sample
(`previous`) give the same numbers.
"""

from __future__ import annotations

import numpy as np

from roadgrip.units import G_MPS2

WHEELS = ("fl", "fr", "rl", "rr")
WHEEL_SPEEDS = tuple(f"wheel_speed_{w}_radps" for w in WHEELS)
PRODUCTION_FEATURES = (
    "wheel_speed_mps",
    "axle_slip",
    "side_slip_front",
    "side_slip_rear",
    "wheel_accel_front_g",
    "wheel_accel_rear_g",
    "accel_lon_g",
    "accel_lat_g",
    "utilization_g",
    "yaw_rate_radps",
    "centripetal_g",
    "road_wheel_angle_rad",
    "understeer_g",
    "front_drive_share",
    "abs_active",
    "tcs_active",
    "esc_active",
)
PRODUCTION_INPUTS = (
    "timestamp_ms",
    "accel_lon_mps2",
    "accel_lat_mps2",
    "yaw_rate_radps",
    "steering_wheel_angle_rad",
    "abs_active",
) + WHEEL_SPEEDS
OPTIONAL_FLAGS = ("tcs_active", "esc_active")  # absent or null: not reported, read as not acting
PRODUCTION_PROFILE = (
    "wheel_radius_m",
    "steering_ratio",
    "wheelbase_m",
    "track_front_m",
    "track_rear_m",
    "front_drive_share",
)
# below 2 m/s (7 km/h) the ratios are noise: one CAN step of 0.01 km/h is 0.14 % of it, and wheel-speed sensors lose
# their lowest speeds; the floor keeps the ratios bounded at standstill
SPEED_FLOOR_MPS = 2.0
MAX_STEP_S = 0.5  # a longer step between samples is a gap: no derivative across it


def vehicle_profile(vehicle) -> dict:
    """The profile fields the feature sets use, from a VehicleParams."""
    return {
        "wheel_radius_m": vehicle.wheel_radius_m,
        "steering_ratio": vehicle.steering_ratio,
        "wheelbase_m": vehicle.wheelbase_m,
        "track_front_m": vehicle.track_front_m,
        "track_rear_m": vehicle.track_rear_m,
        "front_drive_share": vehicle.drive_split[0],
    }


def flag(data: dict, name: str, n: int) -> np.ndarray:
    """A boolean column as 0/1 floats; absent, None or NaN reads 0."""
    if name not in data:
        return np.zeros(n)
    values = np.asarray(data[name]).reshape(-1)
    if values.dtype == object:
        return np.array(
            [
                0.0 if v is None or (isinstance(v, (float, np.floating)) and np.isnan(v)) else float(bool(v))
                for v in values
            ]
        )
    return np.nan_to_num(values.astype(np.float64), nan=0.0)


def production_features(data: dict, profile: dict, segments=None, previous: dict | None = None) -> np.ndarray:
    """(n, len(PRODUCTION_FEATURES)) float32 features of n consecutive samples (column arrays in `data`).

    `segments`: an id per sample; a change starts a new stream (no derivative across it). `previous`: the stream's
    sample just before data's first one (its timestamp_ms and wheel speeds), or None at a stream's start."""
    missing = [f for f in PRODUCTION_PROFILE if profile.get(f) is None]
    if missing:
        raise ValueError(f"feature set 'production' needs the vehicle profile field(s) {missing}")
    col = {c: np.asarray(data[c], dtype=np.float64).reshape(-1) for c in PRODUCTION_INPUTS}
    n = len(col["timestamp_ms"])
    p = {f: np.broadcast_to(np.asarray(profile[f], dtype=np.float64), (n,)) for f in PRODUCTION_PROFILE}
    r = p["wheel_radius_m"]
    v = {w: col[f"wheel_speed_{w}_radps"] * r for w in WHEELS}
    v_front, v_rear = (v["fl"] + v["fr"]) / 2.0, (v["rl"] + v["rr"]) / 2.0
    v_mean = (v_front + v_rear) / 2.0
    v_ref = np.maximum(np.abs(v_mean), SPEED_FLOOR_MPS)
    yaw = col["yaw_rate_radps"]
    ax, ay = col["accel_lon_mps2"], col["accel_lat_mps2"]
    delta = col["steering_wheel_angle_rad"] / p["steering_ratio"]
    f = {
        "wheel_speed_mps": v_mean,
        "axle_slip": (v_front - v_rear) / v_ref - (np.sqrt(1.0 + (yaw * p["wheelbase_m"] / v_ref) ** 2) - 1.0),
        "side_slip_front": (v["fl"] - v["fr"] + yaw * p["track_front_m"]) / v_ref,
        "side_slip_rear": (v["rl"] - v["rr"] + yaw * p["track_rear_m"]) / v_ref,
        "accel_lon_g": ax / G_MPS2,
        "accel_lat_g": ay / G_MPS2,
        "utilization_g": np.hypot(ax, ay) / G_MPS2,
        "yaw_rate_radps": yaw,
        "centripetal_g": yaw * v_mean / G_MPS2,
        "road_wheel_angle_rad": delta,
        "understeer_g": (v_mean**2 * delta / p["wheelbase_m"] - yaw * v_mean) / G_MPS2,
        "front_drive_share": p["front_drive_share"],
        "abs_active": flag(data, "abs_active", n),
        "tcs_active": flag(data, "tcs_active", n),
        "esc_active": flag(data, "esc_active", n),
    }
    # backward differences against the previous sample of the same stream
    t_s = col["timestamp_ms"] / 1000.0
    prev_t, prev_front, prev_rear = np.empty(n), np.empty(n), np.empty(n)
    prev_t[1:], prev_front[1:], prev_rear[1:] = t_s[:-1], v_front[:-1], v_rear[:-1]
    starts = np.zeros(n, dtype=bool)
    if previous is None:
        starts[0] = True
    else:
        r0 = r[0]
        prev_t[0] = float(previous["timestamp_ms"]) / 1000.0
        prev_front[0] = (float(previous["wheel_speed_fl_radps"]) + float(previous["wheel_speed_fr_radps"])) * r0 / 2.0
        prev_rear[0] = (float(previous["wheel_speed_rl_radps"]) + float(previous["wheel_speed_rr_radps"])) * r0 / 2.0
    if segments is not None:
        segments = np.asarray(segments)
        starts[1:] |= segments[1:] != segments[:-1]
    dt = t_s - prev_t
    valid = ~starts & (dt > 0.0) & (dt <= MAX_STEP_S)
    dt = np.where(valid, dt, 1.0)
    f["wheel_accel_front_g"] = np.where(valid, ((v_front - prev_front) / dt - ax) / G_MPS2, 0.0)
    f["wheel_accel_rear_g"] = np.where(valid, ((v_rear - prev_rear) / dt - ax) / G_MPS2, 0.0)
    return np.column_stack([f[c] for c in PRODUCTION_FEATURES]).astype(np.float32)
