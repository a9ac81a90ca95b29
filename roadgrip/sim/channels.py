"""The optional channels a production car may send (CONTRACTS 3.1), from the simulator's true signals, each with its
error model; switched per run by `ProductionEffects` (gnss_speed, force_signals, steering_torque). A channel that is off
is absent (NaN: "not sent"), never zero. docs/SIMULATOR.md ("Optional channels") has the sources.

| channel | model | error model (defaults: `ChannelModel`) |
|---|---|---|
| gnss_speed_mps, gnss_speed_accuracy_mps | horizontal speed over ground, sqrt(v_x^2 + v_y^2), a GNSS Doppler fix every 100 ms (10 Hz, the stream's own rate, so no resampling beyond the latency's interpolation) | per-run latency uniform in [gnss_latency_min_s, gnss_latency_max_s] (0-0.2 s) (the fix describes t - latency); white noise gnss_noise_mps; dropouts: a two-state Markov chain with a gnss_dropout_share of the time lost in outages of mean gnss_dropout_mean_s (tunnels, underpasses); multipath outliers: a gnss_outlier_rate share of fixes off by N(0, gnss_outlier_mps), their reported accuracy left unchanged half the time; accuracy: gnss_noise_mps x U(0.8, 1.5) |
| drive_force_n, brake_force_n | the tires' longitudinal forces summed, split by the brake switch: brake force = -sum(min(f_x, 0)) while the driver brakes (0 otherwise), drive force = sum(f_x) + brake force (negative: engine drag); the wheels' own inertia is in the ECU's torque-based figure but not here | per-run scale error uniform +-force_scale_spread (the torque model of the engine ECU, brake pad friction), a lag (the signal describes t - force_lag_s, first-order smoothing of the same time constant), white noise force_noise_n |
| steering_torque_nm, eps_assist_torque_nm | the front axle's aligning moment M = (t_p + t_m) F_y,front, t_p the brush model's pneumatic trail t0 (1 - |alpha| / alpha_sl) (Pacejka, Tyre and Vehicle Dynamics, 3.2; 0 past alpha_sl = 3 mu F_z / C_alpha, C_alpha the run's tire model's own cornering stiffness: `cornering_stiffness_per_load`), t_m the caster's mechanical trail, through the steering ratio to the column, plus the column's Coulomb friction against the steering rate; the EPS gives the share assist_max T / (|T| + assist_half_nm) of the column torque T (an assist curve growing with the torque), the driver the rest | white noise torque_noise_nm on each |

Each run's draws come from its own generator (spawned by the caller), all of them whichever channels are on, so that
switching one channel never changes another's draws nor the base signals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from roadgrip.data.schema import CHANNEL_NAMES
from roadgrip.validation import bounded, check_bounds
from roadgrip.vehicle.params import TireParams, VehicleParams
from roadgrip.vehicle.tires.base import TireModel

WHEELS = ("fl", "fr", "rl", "rr")


@dataclass(frozen=True)
class ChannelModel:
    """Error models of the optional channels (SI units; 1 sigma for noises, half-widths for uniform per-run draws)."""

    gnss_noise_mps: float = field(default=0.05, metadata=bounded(0.0, 5.0))
    gnss_latency_min_s: float = field(default=0.0, metadata=bounded(0.0, 2.0))
    gnss_latency_max_s: float = field(default=0.2, metadata=bounded(0.0, 2.0))
    gnss_dropout_share: float = field(default=0.05, metadata=bounded(0.0, 0.9))
    gnss_dropout_mean_s: float = field(default=3.0, metadata=bounded(0.1, 600.0))
    gnss_outlier_rate: float = field(default=0.01, metadata=bounded(0.0, 0.5))
    gnss_outlier_mps: float = field(default=1.0, metadata=bounded(0.0, 20.0))
    force_scale_spread: float = field(default=0.05, metadata=bounded(0.0, 0.5))
    force_lag_s: float = field(default=0.1, metadata=bounded(0.0, 1.0))
    force_noise_n: float = field(default=50.0, metadata=bounded(0.0, 5000.0))
    # pneumatic trail at zero slip: the brush model's a / 3 (a the contact half-length); 2-5 cm on car tires
    trail_t0_m: float = field(default=0.04, metadata=bounded(0.0, 0.2))
    mechanical_trail_m: float = field(default=0.02, metadata=bounded(0.0, 0.1))  # caster trail
    column_friction_nm: float = field(default=0.3, metadata=bounded(0.0, 5.0))
    friction_rate_radps: float = field(default=0.05, metadata=bounded(0.001, 5.0))  # tanh smoothing of the friction
    assist_max: float = field(default=0.8, metadata=bounded(0.0, 0.99))
    assist_half_nm: float = field(default=2.0, metadata=bounded(0.01, 50.0))
    torque_noise_nm: float = field(default=0.05, metadata=bounded(0.0, 5.0))

    def __post_init__(self):
        check_bounds(self)
        if self.gnss_latency_min_s > self.gnss_latency_max_s:
            raise ValueError(
                f"ChannelModel.gnss_latency_min_s ({self.gnss_latency_min_s}) must not exceed gnss_latency_max_s "
                f"({self.gnss_latency_max_s})"
            )

    @classmethod
    def degraded_gnss(cls) -> ChannelModel:
        """GNSS at its worst that issue 26 asks the estimator to tolerate: latency 0.2 s on every run, 10 % of the
        time in outages, 5 % of fixes multipath outliers of N(0, 2 m/s)."""
        return cls(gnss_latency_min_s=0.2, gnss_dropout_share=0.1, gnss_outlier_rate=0.05, gnss_outlier_mps=2.0)


ALPHA_PROBE_RAD = 1e-4  # the slip angle at which a tire model's own cornering stiffness is read (its initial slope)


def cornering_stiffness_per_load(tire: TireModel, params: TireParams, fz_n, mu):
    """The tire model's cornering stiffness per load at zero slip (per rad) on a road of mu: its lateral force at a
    slip angle of ALPHA_PROBE_RAD over F_z and the angle. The catalogue's times the model's stiffness scale for Dugoff
    and the Magic Formula; for Burckhardt the slope of the surface its mu picks."""
    fz = np.maximum(np.asarray(fz_n, dtype=np.float64), 1.0)
    _, fy = tire.forces(params, 0.0, ALPHA_PROBE_RAD, fz, mu)
    return np.maximum(np.abs(fy) / (fz * ALPHA_PROBE_RAD), 1e-6)


def brush_trail_m(alpha_rad, mu, fz_n, c_alpha_per_load, t0_m):
    """The brush model's pneumatic trail, linearised: t0 (1 - |alpha| / alpha_sl), 0 beyond the full-sliding angle
    alpha_sl = atan(3 mu F_z / C_alpha) (C_alpha = c_alpha_per_load F_z)."""
    alpha_sl = np.arctan(3.0 * np.asarray(mu) / c_alpha_per_load)
    return t0_m * np.clip(1.0 - np.abs(alpha_rad) / np.maximum(alpha_sl, 1e-6), 0.0, 1.0)


def _lagged(t_s, x, lag_s):
    """x as a signal that describes t - lag and is smoothed over lag (first order)."""
    if lag_s <= 0.0:
        return x
    delayed = np.interp(t_s - lag_s, t_s, x)
    out = np.empty_like(delayed)
    dt = np.diff(t_s, prepend=t_s[0])
    state = delayed[0]
    for k in range(delayed.size):
        a = 1.0 - math.exp(-dt[k] / lag_s)
        state += a * (delayed[k] - state)
        out[k] = state
    return out


def _dropouts(n, sample_period_s, share, mean_s, u):
    """A two-state Markov chain (fix, no fix): outages of mean mean_s, a share of the time `share` (u: n uniforms)."""
    lost = np.zeros(n, dtype=bool)
    if share <= 0.0:
        return lost
    p_end = min(sample_period_s / mean_s, 1.0)
    p_start = min(p_end * share / max(1.0 - share, 1e-9), 1.0)
    state = u[0] < share
    for k in range(n):
        lost[k] = state
        state = (u[k] >= p_end) if state else (u[k] < p_start)
    return lost


def optional_channels(
    truth: dict[str, np.ndarray],
    vehicle: VehicleParams,
    sample_period_s: float,
    rng: np.random.Generator,
    *,
    gnss: bool,
    forces: bool,
    steering: bool,
    model: ChannelModel = ChannelModel(),
    tire: TireModel | None = None,
) -> dict[str, np.ndarray]:
    """The six optional channels of one run (NaN where a channel is off or, for GNSS, without a fix). The steering
    torques need the run's `tire` model: the pneumatic trail follows the tire's own cornering stiffness."""
    if steering and tire is None:
        raise ValueError("optional_channels: the steering torques need the run's tire model")
    t = truth["t_s"]
    n = t.size
    nan = np.full(n, np.nan)
    # every draw, whichever channels are on
    latency = model.gnss_latency_min_s + (model.gnss_latency_max_s - model.gnss_latency_min_s) * rng.uniform()
    u_drop = rng.uniform(size=n)
    outlier = rng.uniform(size=n) < model.gnss_outlier_rate
    outlier_size = rng.normal(0.0, model.gnss_outlier_mps, n)
    outlier_flagged = rng.uniform(size=n) < 0.5
    gnss_noise = rng.normal(0.0, model.gnss_noise_mps, n)
    accuracy_factor = rng.uniform(0.8, 1.5, n)
    force_scale = 1.0 + model.force_scale_spread * rng.uniform(-1.0, 1.0, 2)
    force_noise = rng.normal(0.0, model.force_noise_n, (2, n))
    torque_noise = rng.normal(0.0, model.torque_noise_nm, (2, n))
    out = {name: nan.copy() for name in CHANNEL_NAMES}
    if gnss:
        ground = np.hypot(truth["vx_mps"], truth["vy_mps"])
        speed = np.interp(t - latency, t, ground) + gnss_noise + np.where(outlier, outlier_size, 0.0)
        accuracy = model.gnss_noise_mps * accuracy_factor
        accuracy = np.where(outlier & outlier_flagged, accuracy + np.abs(outlier_size), accuracy)
        lost = _dropouts(n, sample_period_s, model.gnss_dropout_share, model.gnss_dropout_mean_s, u_drop)
        out["gnss_speed_mps"] = np.where(lost, np.nan, np.maximum(speed, 0.0))
        out["gnss_speed_accuracy_mps"] = np.where(lost, np.nan, accuracy)
    if forces:
        fx = np.column_stack([truth[f"fx_{w}_n"] for w in WHEELS])
        braking = truth["brake_active"] > 0.5
        brake = np.where(braking, -np.minimum(fx, 0.0).sum(axis=1), 0.0)
        drive = fx.sum(axis=1) + brake
        drive = _lagged(t, drive, model.force_lag_s) * force_scale[0] + force_noise[0]
        brake = _lagged(t, brake, model.force_lag_s) * force_scale[1] + np.where(braking, force_noise[1], 0.0)
        out["drive_force_n"] = drive
        out["brake_force_n"] = np.maximum(brake, 0.0)
    if steering:
        moment = np.zeros(n)
        for w in ("fl", "fr"):
            mu_w, fz_w = truth[f"mu_{w}"], truth[f"fz_{w}_n"]
            ca = cornering_stiffness_per_load(tire, vehicle.tire_front, fz_w, mu_w)
            trail = brush_trail_m(truth[f"slip_angle_{w}_rad"], mu_w, fz_w, ca, model.trail_t0_m)
            moment += (trail + model.mechanical_trail_m) * truth[f"fy_{w}_n"]
        # the aligning moment turns the wheels back; holding the steer takes its torque at the column, plus friction
        steer_rate = np.gradient(truth["steer_rad"], t) if n > 1 else np.zeros(n)
        column = moment / vehicle.steering_ratio + model.column_friction_nm * np.tanh(
            steer_rate * vehicle.steering_ratio / model.friction_rate_radps
        )
        share = model.assist_max * np.abs(column) / (np.abs(column) + model.assist_half_nm)
        out["eps_assist_torque_nm"] = share * column + torque_noise[0]
        out["steering_torque_nm"] = (1.0 - share) * column + torque_noise[1]
    return out
