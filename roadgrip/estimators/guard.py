"""The physics guard: what a car's own acceleration proves about mu, applied to every estimator's output in one place.

The only horizontal forces on a car are the road's, on its tires, and the air's (CONTRACTS 3.1 axes). The accelerometer
measures their sum per mass (the specific force: gravity on a grade is not in it), so the road's force per mass is

    a_road_x = a_x + D(v) / m,   D(v) = 1/2 rho c_d A v^2  (drag, which decelerates the car without the road's help)
    a_road_y = a_y / (1 + g k_phi)                          (the rolled accelerometer's reading, vehicle_model.py)

and Coulomb's law at every tire, |F_i| <= mu F_z,i with sum F_z,i = m g, gives

    mu >= |a_road| / g.

Rolling resistance is not taken out: it is a moment of the vertical load about the wheel, not a force of the road
along it, so at the friction limit (a locked or ABS-held wheel) the road's force is mu F_z whatever it is; taking it out
as well would lower the bound by f_rr (0.012) for nothing. Drag is taken out: on the 0.1 section of the paper preset's
decreasing road the car decelerates at 1.22-1.30 m/s^2 while every wheel is at its limit, 0.98 m/s^2 of it the road's.

The measurement carries noise and bias, so the guard's bound is (|a_road| - k sigma_a) / g with sigma_a the
accelerometer's noise and bias allowance (GuardSettings). The guard then makes every estimate physical:

- mu_lower, mu and mu_upper are raised to the bound (0 at least): the car proved that much;
- an estimate whose whole interval lay below the bound was contradicted by the measurement: it is an inconsistency of
  the estimator's model, never evidence of low friction, so its interval widens to the prior's upper end
  (PRIOR_UPPER_MU), its mu goes no lower than PRIOR_MU, and it is not `excited`;
- 0 <= mu_lower <= mu <= mu_upper always;
- the bound itself goes out as the estimate's `mu_proven`, excited or not: what a calm pass still proves (a car
  cornering at 0.4 g shows mu >= 0.37 there), which the friction map counts (roadgrip/cloud/domain/friction_map.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from roadgrip.estimators.base import Estimate, EstimateRun, Estimator, estimate_table, profile_of_call
from roadgrip.estimators.vehicle_model import roll_per_lateral_accel
from roadgrip.units import G_MPS2
from roadgrip.validation import bounded, check_bounds
from roadgrip.vehicle.dynamics import AIR_DENSITY_KGPM3
from roadgrip.vehicle.params import VehicleParams

PRIOR_MU = 0.8  # the median of the prior a contradicted estimate falls back on (pmf.py: half dry asphalt)
# The highest friction a road is taken to have (dry, new asphalt with high-grip tires; the simulator's dry surfaces
# reach 1.17): the upper end of an interval where nothing is known above (pmf.py's where its evidence is silent, a
# contradicted estimate's here), which the friction map reads as no upper side
PRIOR_UPPER_MU = 1.2


@dataclass(frozen=True)
class GuardSettings:
    """sigma_a: the accelerometer's noise and bias allowance (m/s^2, 1 sigma); the bound is k sigma_a below |a_road|.
    The guard reads the raw signal, before any estimator's calibration, so the allowance is an uncalibrated production
    sensor's: a mounting tilt up to 2 degrees (0.34 m/s^2) and a MEMS offset up to 0.2 m/s^2, 0.54 together at worst;
    a production SUV's signal read -0.63 m/s^2 against d(speed)/dt (pmf.py BIAS_SIGMA0_MPS2). 0.3 m/s^2 with k = 2
    puts the bound 0.6 m/s^2 below |a_road|: under 8 % of |a| at 0.8 g, so that on dry asphalt the bound stays above
    0.92 |a| / g where drag is small. Half of it (0.15, a tilt under 1 degree) let a 30 s ABS stop on ice with a
    2-degree tilt prove mu 0.11-0.12 on a 0.104 road (docs/RESULTS.md, "The guard's allowance")."""

    accel_sigma_mps2: float = field(default=0.3, metadata=bounded(0.0, 5.0))
    k_sigma: float = field(default=2.0, metadata=bounded(0.0, 10.0))

    def __post_init__(self):
        check_bounds(self)


def drag_per_mass(vehicle: VehicleParams) -> float:
    """c with D(v) / m = c v^2 (1/m)."""
    return 0.5 * AIR_DENSITY_KGPM3 * vehicle.drag_coefficient * vehicle.frontal_area_m2 / vehicle.mass_kg


def road_acceleration(vehicle: VehicleParams, accel_lon_mps2, accel_lat_mps2, speed_mps):
    """(a_road_x, a_road_y): the road's force on the tires per mass (m/s^2), from the accelerometer's reading."""
    ax = np.asarray(accel_lon_mps2, dtype=np.float64) + drag_per_mass(vehicle) * np.square(speed_mps)
    ay = np.asarray(accel_lat_mps2, dtype=np.float64) / (1.0 + G_MPS2 * roll_per_lateral_accel(vehicle))
    return ax, ay


def tire_force_bound(
    vehicle: VehicleParams, accel_lon_mps2, accel_lat_mps2, speed_mps, settings: GuardSettings = GuardSettings()
) -> np.ndarray:
    """The lower bound on mu that the measured acceleration proves: (|a_road| - k sigma_a) / g, at least 0."""
    return _bound(
        accel_lon_mps2,
        accel_lat_mps2,
        speed_mps,
        drag_per_mass(vehicle),
        1.0 + G_MPS2 * roll_per_lateral_accel(vehicle),
        settings.k_sigma * settings.accel_sigma_mps2,
    )


def _bound(accel_lon_mps2, accel_lat_mps2, speed_mps, drag: float, roll: float, margin_mps2: float) -> np.ndarray:
    """tire_force_bound with the vehicle's constants: drag per mass (drag_per_mass), the rolled accelerometer's
    factor (road_acceleration) and the margin k sigma_a."""
    ax = np.asarray(accel_lon_mps2, dtype=np.float64) + drag * np.square(speed_mps)
    ay = np.asarray(accel_lat_mps2, dtype=np.float64) / roll
    # sqrt(x^2 + y^2), not hypot: the streaming path's math.hypot and np.hypot differ in the last bit on 0.5 % of
    # samples; IEEE sqrt, products and sums are the same in numpy and in Python floats (batch = streaming, exactly)
    return np.maximum((np.sqrt(ax * ax + ay * ay) - margin_mps2) / G_MPS2, 0.0)


def apply_bound_scalar(mu: float, lower: float, upper: float, excited: bool, bound: float):
    """apply_bound for one estimate, in plain floats (the streaming path: numpy on scalars costs 20 us)."""
    contradicted = not upper >= bound  # NaN counts as contradicted
    if contradicted:
        upper = max(PRIOR_UPPER_MU, bound)
        mu = max(mu, PRIOR_MU)  # NaN becomes the prior's
    lower = max(0.0 if math.isnan(lower) else lower, bound)
    mu = max(PRIOR_MU if math.isnan(mu) else mu, lower)
    return mu, lower, max(upper, mu), excited and not contradicted


def apply_bound(mu, mu_lower, mu_upper, excited, bound):
    """The guarded (mu, mu_lower, mu_upper, excited) of estimates (arrays) given the bound of each."""
    mu, lower, upper, bound = (np.asarray(a, dtype=np.float64) for a in (mu, mu_lower, mu_upper, bound))
    excited = np.asarray(excited, dtype=bool)
    contradicted = ~(upper >= bound)  # NaN counts as contradicted
    upper = np.where(contradicted, np.maximum(PRIOR_UPPER_MU, bound), upper)
    mu = np.where(contradicted, np.maximum(mu, PRIOR_MU), mu)
    lower = np.maximum(np.nan_to_num(lower, nan=0.0), bound)
    mu = np.maximum(np.nan_to_num(mu, nan=PRIOR_MU), lower)
    upper = np.maximum(upper, mu)
    return mu, lower, upper, excited & ~contradicted


def _speed(sample_or_table_speed, wheel_speeds, radius_m):
    """The speed for drag: the reported one, or the mean wheel speed where none is reported."""
    return np.where(np.isfinite(sample_or_table_speed), sample_or_table_speed, np.mean(wheel_speeds, axis=0) * radius_m)


WHEELS = ("wheel_speed_fl_radps", "wheel_speed_fr_radps", "wheel_speed_rl_radps", "wheel_speed_rr_radps")


def _sample_speed(sample: dict, vehicle: VehicleParams) -> float:
    """The speed for drag of one streamed sample: the reported one, or the mean wheel speed where none is reported
    (as _speed for a table, in the same order of operations)."""
    speed = sample.get("speed_mps")
    if speed is None or not math.isfinite(float(speed)):
        return sum(float(sample[w]) for w in WHEELS) / 4.0 * vehicle.wheel_radius_m
    return float(speed)


class GuardedEstimator(Estimator):
    """Any estimator with the physics guard on its output (the name and state are the inner estimator's)."""

    def __init__(
        self, inner: Estimator, settings: GuardSettings = GuardSettings(), vehicle: VehicleParams | None = None
    ):
        self.inner = inner
        self.settings = settings
        self.vehicle = vehicle
        self.name = inner.name

    def __getattr__(self, item):  # the inner estimator's own extras (diagnostics, model, ...)
        if item == "inner":
            raise AttributeError(item)
        return getattr(self.inner, item)

    def _vehicle(self, vehicle: VehicleParams | None) -> VehicleParams:
        return profile_of_call(vehicle, self.vehicle)

    def _state(self, vehicle: VehicleParams, inner) -> dict:
        # the bound's constants, so that a streamed sample costs a few float operations (numpy on scalars: 50 us)
        return {
            "vehicle": vehicle,
            "inner": inner,
            "drag": drag_per_mass(vehicle),
            "roll": 1.0 + G_MPS2 * roll_per_lateral_accel(vehicle),
            "margin": self.settings.k_sigma * self.settings.accel_sigma_mps2,
        }

    def start(self, vehicle: VehicleParams | None = None):
        vehicle = self._vehicle(vehicle)
        return self._state(vehicle, self.inner.start(vehicle))

    def update(self, state, sample: dict) -> Estimate | None:
        est = self.inner.update(state["inner"], sample)
        if est is None:
            return None
        speed = _sample_speed(sample, state["vehicle"])
        ax = float(sample["accel_lon_mps2"]) + state["drag"] * speed**2
        ay = float(sample["accel_lat_mps2"]) / state["roll"]
        road = math.sqrt(ax * ax + ay * ay)  # as tire_force_bound computes it, to the last bit
        bound = max((road - state["margin"]) / G_MPS2, 0.0)
        if bound <= est.mu_lower <= est.mu <= est.mu_upper:  # already physical: only the bound is added
            return Estimate(
                est.vehicle_id, est.timestamp_ms, est.mu, est.mu_lower, est.mu_upper, est.excited, est.estimator, bound
            )
        return Estimate(
            est.vehicle_id,
            est.timestamp_ms,
            *apply_bound_scalar(est.mu, est.mu_lower, est.mu_upper, est.excited, bound),
            est.estimator,
            bound,
        )

    def update_many(self, state, samples) -> EstimateRun:
        """The inner estimator's run, guarded: the bound with numpy (_bound), the estimates already physical kept as
        `update` keeps them, the others through apply_bound_scalar as `update` does; the same numbers to the last bit
        (IEEE products, sums and sqrt are numpy's and Python's alike)."""
        run = self.inner.update_many(state["inner"], samples)
        judged = [samples[k] for k in run.index.tolist()]
        vehicle = state["vehicle"]
        speed = np.array([_sample_speed(s, vehicle) for s in judged], dtype=np.float64)
        ax = np.array([s["accel_lon_mps2"] for s in judged], dtype=np.float64)
        ay = np.array([s["accel_lat_mps2"] for s in judged], dtype=np.float64)
        bound = _bound(ax, ay, speed, state["drag"], state["roll"], state["margin"])
        mu, lower, upper, excited = run.mu, run.mu_lower, run.mu_upper, run.excited
        physical = (bound <= lower) & (lower <= mu) & (mu <= upper)
        if not physical.all():
            mu, lower, upper, excited = mu.copy(), lower.copy(), upper.copy(), excited.copy()
            for k in np.flatnonzero(~physical).tolist():
                mu[k], lower[k], upper[k], excited[k] = apply_bound_scalar(
                    float(mu[k]), float(lower[k]), float(upper[k]), bool(excited[k]), float(bound[k])
                )
        return EstimateRun(run.index, run.vehicle_id, run.timestamp_ms, mu, lower, upper, excited, run.estimator, bound)

    def reset(self, state) -> None:
        self.inner.reset(state["inner"])

    def state_to_dict(self, state) -> dict:
        return {"vehicle": state["vehicle"].to_dict(), "inner": self.inner.state_to_dict(state["inner"])}

    def state_from_dict(self, data: dict):
        return self._state(VehicleParams.from_dict(data["vehicle"]), self.inner.state_from_dict(data["inner"]))

    def estimate_batch(self, table: pa.Table, segments, vehicle: VehicleParams | None = None) -> pa.Table:
        vehicle = self._vehicle(vehicle)
        est = self.inner.estimate_batch(table, segments, vehicle)
        if est.num_rows == 0:
            return est
        # the estimates' rows are a subset of the table's, in order, one vehicle: join on the timestamp
        where = np.searchsorted(table["timestamp_ms"].to_numpy(), est["timestamp_ms"].to_numpy())
        col = {
            c: table[c].to_numpy(zero_copy_only=False).astype(np.float64)[where]
            for c in ("accel_lon_mps2", "accel_lat_mps2", "speed_mps", *WHEELS)
        }
        speed = _speed(col["speed_mps"], np.stack([col[w] for w in WHEELS]), vehicle.wheel_radius_m)
        bound = tire_force_bound(vehicle, col["accel_lon_mps2"], col["accel_lat_mps2"], speed, self.settings)
        mu, lower, upper, excited = apply_bound(
            est["mu"].to_numpy(),
            est["mu_lower"].to_numpy(),
            est["mu_upper"].to_numpy(),
            est["excited"].to_numpy(zero_copy_only=False),
            bound,
        )
        return estimate_table(
            {
                "vehicle_id": est["vehicle_id"],
                "timestamp_ms": est["timestamp_ms"],
                "mu": mu,
                "mu_lower": lower,
                "mu_upper": upper,
                "excited": excited,
                "estimator": est["estimator"],
                "mu_proven": bound,
            }
        )
