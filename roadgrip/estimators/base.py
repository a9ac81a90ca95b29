"""The one estimator interface, for offline files, benchmarks and the cloud alike.

An estimator is used per vehicle. Streaming: `start(vehicle)` makes that vehicle's state, `update(state, sample)` feeds one
100 ms sample (a dict in wire format v1) and returns the estimate for it, or None while the estimator cannot judge yet (a
window still filling). `reset(state)` forgets the past (after a gap in the stream). The state is a plain object that can be
saved with `state_to_dict` and restored with `state_from_dict`. Batch: `estimate_batch(batch, vehicle)` over a validated
telemetry batch (roadgrip/data/telemetry.py), the same numbers as streaming but vectorised.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from roadgrip.vehicle.params import PAPER_SUV, VehicleParams

ESTIMATE_SCHEMA = pa.schema(
    [
        pa.field("vehicle_id", pa.string(), nullable=False),
        pa.field("timestamp_ms", pa.int64(), nullable=False),
        pa.field("mu", pa.float64(), nullable=False),
        pa.field("mu_lower", pa.float64(), nullable=False),
        pa.field("mu_upper", pa.float64(), nullable=False),
        pa.field("excited", pa.bool_(), nullable=False),
        pa.field("estimator", pa.string(), nullable=False),
        pa.field("mu_proven", pa.float64(), nullable=True),
    ]
)


def estimate_table(columns: dict) -> pa.Table:
    """An ESTIMATE_SCHEMA table from its columns; mu_proven null where the caller has none (an unguarded estimator)."""
    if "mu_proven" not in columns:
        columns = {**columns, "mu_proven": pa.nulls(len(columns["timestamp_ms"]), pa.float64())}
    return pa.table(columns, schema=ESTIMATE_SCHEMA)


@dataclass(frozen=True)
class Estimate:
    """CONTRACTS 3.4: the most probable mu, a 90 % interval (5 % and 95 %), and whether the manoeuvre made mu observable.

    mu_proven (added to CONTRACTS 3.4, docs/ESTIMATORS.md): what the car's own acceleration proves at this sample,
    (|a_road| - k sigma_a) / g at least 0 (roadgrip/estimators/guard.py), excited or not; mu_lower >= mu_proven. None
    from an estimator without the guard. A pass that is not excited still proves this much: the map counts it."""

    vehicle_id: str
    timestamp_ms: int
    mu: float
    mu_lower: float
    mu_upper: float
    excited: bool
    estimator: str
    mu_proven: float | None = None

    def to_dict(self) -> dict:
        # by hand: dataclasses.asdict deep-copies field by field, ten times slower (the cloud calls this 10,000 times a s)
        return {
            "vehicle_id": self.vehicle_id,
            "timestamp_ms": self.timestamp_ms,
            "mu": self.mu,
            "mu_lower": self.mu_lower,
            "mu_upper": self.mu_upper,
            "excited": self.excited,
            "estimator": self.estimator,
            "mu_proven": self.mu_proven,
        }


def profile_of_call(vehicle: VehicleParams | None, own: VehicleParams | None) -> VehicleParams:
    """The profile a call uses: the one it passes, else the estimator's own, else the paper's SUV."""
    if vehicle is not None:
        return vehicle
    return PAPER_SUV if own is None else own


def memory_state(data: dict, name: str, n_memory: int) -> tuple[VehicleParams, np.ndarray]:
    """(profile, memory) of a state saved by a filter with one flat memory vector (the Kalman filters, pmf), checked:
    the estimator's name and the memory's length must be this filter's."""
    if data.get("estimator") != name:
        raise ValueError(f"state of estimator {data.get('estimator')!r} given to {name!r}")
    memory = np.asarray(data["memory"], dtype=np.float64)
    if memory.shape != (n_memory,):
        raise ValueError(f"{name} state memory must hold {n_memory} numbers, got shape {memory.shape}")
    return VehicleParams.from_dict(data["vehicle"]), memory.copy()


class Estimator(ABC):
    name: str

    @abstractmethod
    def start(self, vehicle: VehicleParams):
        """A fresh per-vehicle state."""

    @abstractmethod
    def update(self, state, sample: dict) -> Estimate | None:
        """Feed one sample (wire format v1 dict) of the state's vehicle; the estimate for it, or None."""

    @abstractmethod
    def reset(self, state) -> None:
        """Forget the past samples (a gap in the stream): the next estimates start afresh."""

    @abstractmethod
    def state_to_dict(self, state) -> dict:
        """The state as plain JSON-able data."""

    @abstractmethod
    def state_from_dict(self, data: dict):
        """The inverse of state_to_dict."""

    @abstractmethod
    def estimate_batch(self, table: pa.Table, segments, vehicle: VehicleParams) -> pa.Table:
        """Estimates (ESTIMATE_SCHEMA) for the rows of a validated telemetry table of one vehicle, in order; `segments`
        gives an id per row that changes at every gap, where the estimator restarts."""
