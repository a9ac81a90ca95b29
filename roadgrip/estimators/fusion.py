"""Fusion of a physics filter and a learned model by their uncertainty (inverse-variance weighting).

Each estimate's 90 % interval gives its standard deviation, sigma = max(mu - lower, upper - mu) / 1.645 (the wider
side, since the reported intervals are clipped to [0, 1.5]); the fused estimate is

    w_i = 1 / sigma_i^2,   mu = (w_p mu_p + w_l mu_l) / (w_p + w_l),   sigma = (w_p + w_l)^-1/2,

with the interval mu +- 1.645 sigma clipped to [0, 1.5], and excited where either estimator judged the sample excited.
Where the learned model has no estimate yet (its window still filling) the physics estimate stands alone. The weighting
treats the two errors as independent and trusts both intervals. docs/ESTIMATORS.md (section 7) measures it: with the
shipped default model it does not beat both estimators (its intervals are too narrow off its training data), so no
estimator name is registered for it; it stays for that measurement (results/trials/estimators/physics_paper_accuracy.py).
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from roadgrip.estimators.base import Estimate, Estimator, estimate_table
from roadgrip.estimators.vehicle_model import INTERVAL_RANGE, INTERVAL_Z
from roadgrip.vehicle.params import VehicleParams

SIGMA_FLOOR = 1e-3  # a zero-width interval must not take all the weight with an infinite one


def _sigma(mu, lower, upper):
    return np.maximum(np.maximum(mu - lower, upper - mu) / INTERVAL_Z, SIGMA_FLOOR)


def fuse(mu_p, lower_p, upper_p, mu_l, lower_l, upper_l):
    """(mu, lower, upper) of the inverse-variance combination of two estimates (arrays or floats)."""
    w_p = 1.0 / _sigma(mu_p, lower_p, upper_p) ** 2
    w_l = 1.0 / _sigma(mu_l, lower_l, upper_l) ** 2
    mu = (w_p * mu_p + w_l * mu_l) / (w_p + w_l)
    half = INTERVAL_Z / np.sqrt(w_p + w_l)
    return mu, np.clip(mu - half, *INTERVAL_RANGE), np.clip(mu + half, *INTERVAL_RANGE)


class FusionEstimator(Estimator):
    """A physics estimator and a learned one run side by side, their estimates fused sample by sample."""

    def __init__(self, physics: Estimator, learned: Estimator, name: str = "fusion"):
        self.physics = physics
        self.learned = learned
        self.name = name

    def start(self, vehicle: VehicleParams | None = None):
        return {"physics": self.physics.start(vehicle), "learned": self.learned.start(vehicle)}

    def update(self, state, sample: dict) -> Estimate | None:
        p = self.physics.update(state["physics"], sample)
        learned = self.learned.update(state["learned"], sample)
        if p is None:
            return None
        if learned is None:
            return Estimate(p.vehicle_id, p.timestamp_ms, p.mu, p.mu_lower, p.mu_upper, p.excited, self.name)
        mu, lower, upper = fuse(p.mu, p.mu_lower, p.mu_upper, learned.mu, learned.mu_lower, learned.mu_upper)
        return Estimate(
            p.vehicle_id, p.timestamp_ms, float(mu), float(lower), float(upper), p.excited or learned.excited, self.name
        )

    def reset(self, state) -> None:
        self.physics.reset(state["physics"])
        self.learned.reset(state["learned"])

    def state_to_dict(self, state) -> dict:
        return {
            "physics": self.physics.state_to_dict(state["physics"]),
            "learned": self.learned.state_to_dict(state["learned"]),
        }

    def state_from_dict(self, data: dict):
        return {
            "physics": self.physics.state_from_dict(data["physics"]),
            "learned": self.learned.state_from_dict(data["learned"]),
        }

    def estimate_batch(self, table: pa.Table, segments, vehicle: VehicleParams | None = None) -> pa.Table:
        p = self.physics.estimate_batch(table, segments, vehicle)
        learned = self.learned.estimate_batch(table, segments, vehicle)
        col = {k: p[k].to_numpy().copy() for k in ("mu", "mu_lower", "mu_upper")}
        excited = p["excited"].to_numpy(zero_copy_only=False).copy()
        # a vehicle's timestamps are unique (validated), so they join the two outputs
        p_ts, l_ts = p["timestamp_ms"].to_numpy(), learned["timestamp_ms"].to_numpy()
        order = np.argsort(p_ts, kind="stable")
        where = (
            order[np.clip(np.searchsorted(p_ts[order], l_ts), 0, max(p.num_rows - 1, 0))]
            if p.num_rows
            else np.zeros(0, dtype=np.int64)
        )
        hit = p_ts[where] == l_ts if p.num_rows else np.zeros(l_ts.size, dtype=bool)
        where = where[hit]
        lm = {k: learned[k].to_numpy()[hit] for k in ("mu", "mu_lower", "mu_upper")}
        col["mu"][where], col["mu_lower"][where], col["mu_upper"][where] = fuse(
            col["mu"][where], col["mu_lower"][where], col["mu_upper"][where], lm["mu"], lm["mu_lower"], lm["mu_upper"]
        )
        excited[where] |= learned["excited"].to_numpy(zero_copy_only=False)[hit]
        return estimate_table(
            {
                "vehicle_id": p["vehicle_id"],
                "timestamp_ms": p["timestamp_ms"],
                **col,
                "excited": excited,
                "estimator": pa.array([self.name] * p.num_rows, pa.string()),
            }
        )
