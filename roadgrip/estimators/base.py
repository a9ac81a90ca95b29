"""The one estimator interface, for offline files, benchmarks and the cloud alike.

An estimator is used per vehicle. Streaming: `start(vehicle)` makes that vehicle's state, `update(state, sample)` feeds one
100 ms sample (a dict in wire format v1) and returns the estimate for it, or None while the estimator cannot judge yet (a
window still filling). `reset(state)` forgets the past (after a gap in the stream). The state is a plain object that can be
saved with `state_to_dict` and restored with `state_from_dict`. A run of samples: `update_many(state, samples)` feeds
them in order, from the state and into it as `update` one by one would, and returns their estimates as columns
(`EstimateRun`): the same numbers to the last bit (tests/estimators/test_update_many.py), with the per-sample Python
left out where an estimator implements it (the guarded pmf); the default loops over `update`. Batch:
`estimate_batch(batch, vehicle)` over a validated telemetry batch (roadgrip/data/telemetry.py) from a fresh state, the
same numbers as streaming but vectorised.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
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


@dataclass(frozen=True)
class EstimateRun:
    """The estimates of a run of samples (`Estimator.update_many`), as columns: estimate k is for the run's sample
    `index[k]` (a sample the estimator could not judge has none), with `Estimate`'s fields; `mu_proven` None from an
    estimator without the guard (NaN in it: the estimator's own NaN, as `update` gives it)."""

    index: np.ndarray  # int64
    vehicle_id: list[str]
    timestamp_ms: np.ndarray  # int64
    mu: np.ndarray
    mu_lower: np.ndarray
    mu_upper: np.ndarray
    excited: np.ndarray  # bool
    estimator: list[str]
    mu_proven: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.index)

    @classmethod
    def of(cls, found: Sequence[tuple[int, Estimate]]) -> EstimateRun:
        """From (index in the run, Estimate) pairs; mu_proven None only when no estimate has one."""
        proven = [e.mu_proven for _, e in found]
        has_proven = any(p is not None for p in proven)
        return cls(
            np.array([k for k, _ in found], dtype=np.int64),
            [e.vehicle_id for _, e in found],
            np.array([e.timestamp_ms for _, e in found], dtype=np.int64),
            np.array([e.mu for _, e in found], dtype=np.float64),
            np.array([e.mu_lower for _, e in found], dtype=np.float64),
            np.array([e.mu_upper for _, e in found], dtype=np.float64),
            np.array([e.excited for _, e in found], dtype=bool),
            [e.estimator for _, e in found],
            np.array(proven, dtype=np.float64) if has_proven else None,
        )

    def rows(self) -> list[dict]:
        """One dict per estimate, as `Estimate.to_dict` gives it (Python ints, floats, bools; mu_proven None where
        there is none)."""
        proven = self.mu_proven.tolist() if self.mu_proven is not None else [None] * len(self.index)
        return [
            {
                "vehicle_id": v,
                "timestamp_ms": t,
                "mu": mu,
                "mu_lower": lo,
                "mu_upper": up,
                "excited": ex,
                "estimator": name,
                "mu_proven": p,
            }
            for v, t, mu, lo, up, ex, name, p in zip(
                self.vehicle_id,
                self.timestamp_ms.tolist(),
                self.mu.tolist(),
                self.mu_lower.tolist(),
                self.mu_upper.tolist(),
                self.excited.tolist(),
                self.estimator,
                proven,
            )
        ]


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

    def update_many(self, state, samples: Sequence[dict]) -> EstimateRun:
        """Feed a run of samples of the state's vehicle, in order, as `update` one by one would: the same state after
        it and the same estimates, to the last bit. This default is that loop; an estimator may replace it with one
        that leaves the per-sample Python out. A sample `update` refuses (ValueError) may refuse the whole run."""
        found = []
        for k, sample in enumerate(samples):
            estimate = self.update(state, sample)
            if estimate is not None:
                found.append((k, estimate))
        return EstimateRun.of(found)

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
