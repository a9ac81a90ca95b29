"""Estimator state checkpoints: each vehicle's estimator state kept in the database (table estimator_states,
roadgrip/cloud/storage/database.py), so that a restarted service, or ingest process, goes on from each car's self-calibration
instead of calibrating every car again (pmf: the accelerometer's bias, the left/right rolling-radius ratios, the slip
line and the tire-stiffness posterior, minutes of driving to settle; roadgrip/estimators/pmf.py).

When a state is written (by the pipeline's thread, `Checkpoints`):
- every CHECKPOINT_INTERVAL_MS (60 s) of a vehicle's data: a vehicle is due once its newest estimated sample is that
  much newer than its last checkpoint, the first time after 30-60 s of data since the pipeline's start (the fraction
  drawn from the vehicle_id: a fleet that starts together does not come due in the same second). Due vehicles are
  written at most once every CHECKPOINT_ROUND_S, up to MAX_CHECKPOINTS_PER_ROUND in one transaction, oldest due
  first, after the
  round's telemetry was stored (so that a state never holds samples the database lacks), and never while the
  database is down (the round is retried later);
- for every vehicle estimated since its last checkpoint when the pipeline stops cleanly (`roadgrip serve` stopped,
  an ingest process told to stop), in transactions of STOP_CHUNK vehicles.
A crash loses what a vehicle learnt since its last checkpoint (at most a minute of its data).

When a state is restored: when the pipeline first sees a vehicle after its start (or after `forget_vehicle`: a new
profile), one query for the round's new vehicles. The stored state of the configured estimator's name is used when the
profile it carries (`state["vehicle"]`, put there by the physics guard, roadgrip/estimators/guard.py) equals the
vehicle's profile now and the estimator accepts it (`state_from_dict`; a state of an older layout is refused there);
otherwise the vehicle starts afresh. The restored state is then `reset`, as after a gap in the stream: the per-segment
part (pmf: the mu posterior, back to the prior; the reference speed and the largest utilisation seen) starts again,
what the estimator keeps across gaps (pmf: the calibration and the stiffness marginal) stays. For the Kalman filters
(which keep only their counters across a gap) and the learned models (whose window empties), restoring is harmless
and changes no estimate.

Encoding (`pack_state`): JSON, with every list of at least PACK_MIN_FLOATS floats (pmf's memory of 825 numbers, the
Kalman filters' memory) as the base64 of its little-endian float64 bytes: lossless (rounding would move the slip
line's covariance, of order 1e-7), 10.0 kB for a pmf state against 17.0 kB as JSON numbers (zlib would save 5 % more:
a posterior's mantissas do not compress), and no NaN or infinity in the JSON (PostgreSQL's jsonb refuses them; a
non-finite number outside such a list makes that vehicle's state unwritable, logged). Measured cost: docs/CLOUD.md,
"Estimator state checkpoints" (its benchmark: bench/checkpoints.py).
"""

from __future__ import annotations

import base64
import itertools
import logging
import math
import time
import zlib
from collections.abc import Mapping
from typing import Protocol

import numpy as np

from roadgrip.cloud.storage.database import Storage, StorageUnavailable
from roadgrip.estimators.base import Estimator
from roadgrip.vehicle.params import VehicleParams

log = logging.getLogger(__name__)

CHECKPOINT_INTERVAL_MS = 60_000  # of a vehicle's data between two checkpoints of its state
CHECKPOINT_ROUND_S = 0.5  # at most one checkpoint round (one transaction) every half second ...
# ... of at most this many vehicles: 6,000 vehicles a pipeline kept every 60 s, and a round costs at most 5-20 ms
# (25 x 0.2 ms alone, up to 0.9 ms a vehicle in the soak's contention: docs/CLOUD.md)
MAX_CHECKPOINTS_PER_ROUND = 25
STOP_CHUNK = 1_000  # vehicles per transaction when the pipeline stops
PACK_MIN_FLOATS = 16  # shorter lists of floats stay JSON numbers (unless one is not finite)
FLOATS = "f64_base64"  # the key of a packed list


def pack_state(data):
    """`data` (an estimator's state_to_dict) with its lists of floats packed (module docstring); ValueError for a
    non-finite number outside such a list."""
    if isinstance(data, dict):
        return {key: pack_state(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        if data and all(type(x) is float for x in data):
            values = np.asarray(data, dtype="<f8")
            if len(data) >= PACK_MIN_FLOATS or not np.isfinite(values).all():
                return {FLOATS: base64.b64encode(values.tobytes()).decode("ascii")}
            return list(data)
        return [pack_state(value) for value in data]
    if isinstance(data, float) and not math.isfinite(data):
        raise ValueError(f"estimator state holds a non-finite number ({data}) outside a list of numbers")
    return data


def unpack_state(data):
    """The inverse of pack_state."""
    if isinstance(data, dict):
        if data.keys() == {FLOATS}:
            return np.frombuffer(base64.b64decode(data[FLOATS]), dtype="<f8").tolist()
        return {key: unpack_state(value) for key, value in data.items()}
    if isinstance(data, list):
        return [unpack_state(value) for value in data]
    return data


def restore_state(estimator: Estimator, stored: dict, vehicle: VehicleParams):
    """The state to go on from (reset: a new segment), or None where the stored one does not fit this vehicle and
    estimator (another profile, another layout, a damaged row)."""
    try:
        data = unpack_state(stored)
        profile = data.get("vehicle") if isinstance(data, dict) else None
        if profile is None:
            return None  # the profile cannot be checked: an unguarded estimator's state
        if VehicleParams.from_dict(profile) != vehicle:
            return None
        state = estimator.state_from_dict(data)
        estimator.reset(state)
        return state
    except (ValueError, TypeError, KeyError, IndexError, AttributeError) as exc:  # another layout, a damaged row
        log.warning("stored %s state of a vehicle not restored: %r", estimator.name, exc)
        return None
    except Exception:  # a bug must not cost the round: the vehicle starts afresh
        log.exception("restoring a stored %s state failed", estimator.name)
        return None


class _Stream(Protocol):
    """What Checkpoints needs of a pipeline's per-vehicle stream (roadgrip/cloud/pipeline/pipeline.py `_VehicleStream`)."""

    state: object
    last_estimated_ms: int | None
    checkpoint_at_ms: float  # data time at which the vehicle is due (inf: due, or nothing estimated to write yet)
    written_ms: int | None  # last_estimated_ms of the stored state


class Checkpoints:
    """A pipeline's checkpoints (module docstring). Called from the pipeline's thread only; `counters` is the
    pipeline's PipelineCounters (checkpoints_written, checkpoints_restored, checkpoint_s)."""

    def __init__(
        self,
        storage: Storage,
        estimator: Estimator,
        counters,
        interval_ms: int = CHECKPOINT_INTERVAL_MS,
        round_s: float = CHECKPOINT_ROUND_S,
        per_round: int = MAX_CHECKPOINTS_PER_ROUND,
    ):
        self.storage = storage
        self.estimator = estimator
        self.counters = counters
        self.interval_ms = interval_ms
        self.round_s = round_s
        self.per_round = per_round
        self._due: dict[str, None] = {}  # vehicles due, in the order they came due
        self._next_round_s = 0.0

    def start_states(self, vehicles: Mapping[str, VehicleParams]) -> dict:
        """vehicle_id -> its state for vehicles first seen: restored where a stored one fits, else fresh. One query;
        StorageUnavailable when the database is down (nothing done)."""
        stored = self.storage.estimator_states(list(vehicles), self.estimator.name) if vehicles else {}
        states = {}
        for vehicle_id, params in vehicles.items():
            state = restore_state(self.estimator, stored[vehicle_id], params) if vehicle_id in stored else None
            if state is not None:
                self.counters.checkpoints_restored += 1
            else:
                state = self.estimator.start(params)
            states[vehicle_id] = state
        return states

    def first_due_ms(self, vehicle_id: str, first_ms: float) -> float:
        """When a vehicle first seen with a sample at `first_ms` is first due: after 30-60 s of data, by vehicle_id."""
        return first_ms + self.interval_ms * (0.5 + 0.5 * (zlib.crc32(vehicle_id.encode()) % 1024) / 1024)

    def due(self, vehicle_id: str, stream: _Stream) -> None:
        stream.checkpoint_at_ms = math.inf
        self._due[vehicle_id] = None

    def write_due(self, streams: Mapping[str, _Stream]) -> None:
        """A checkpoint round, when one is due: up to `per_round` due vehicles, one transaction."""
        if not self._due or time.monotonic() < self._next_round_s:
            return
        self._next_round_s = time.monotonic() + self.round_s
        taken = list(itertools.islice(self._due, self.per_round))
        if self._write(taken, streams):
            for vehicle_id in taken:
                del self._due[vehicle_id]

    def write_all(self, streams: Mapping[str, _Stream]) -> None:
        """Every vehicle estimated since its last checkpoint (the pipeline stops)."""
        changed = [
            v for v, s in streams.items() if s.last_estimated_ms is not None and s.last_estimated_ms != s.written_ms
        ]
        for start in range(0, len(changed), STOP_CHUNK):
            if not self._write(changed[start : start + STOP_CHUNK], streams):
                log.error(
                    "the estimator states of %d vehicles were not stored at the stop: they restart "
                    "from their last checkpoint",
                    len(changed) - start,
                )
                return
        self._due.clear()

    def write(self, vehicle_ids: list[str], streams: Mapping[str, _Stream]) -> int | None:
        """Store these vehicles' states now, in one transaction (they leave the pipeline: `Pipeline.hand_over`): the
        number written, None while the database is down."""
        before = self.counters.checkpoints_written
        if not self._write(vehicle_ids, streams):
            return None
        for vehicle_id in vehicle_ids:
            self._due.pop(vehicle_id, None)
        return self.counters.checkpoints_written - before

    def _write(self, vehicle_ids: list[str], streams: Mapping[str, _Stream]) -> bool:
        """Store these vehicles' states in one transaction; False (kept due) while the database is down."""
        started = time.perf_counter()
        rows, written = [], []
        for vehicle_id in vehicle_ids:
            stream = streams.get(vehicle_id)
            if stream is None or stream.last_estimated_ms is None:  # forgotten meanwhile, or nothing new
                continue
            try:
                state = pack_state(self.estimator.state_to_dict(stream.state))
            except ValueError as exc:
                log.warning("estimator state of vehicle %s not stored: %s", vehicle_id, exc)
                stream.checkpoint_at_ms = stream.last_estimated_ms + self.interval_ms
                continue
            rows.append({"vehicle_id": vehicle_id, "estimator": self.estimator.name, "state": state})
            written.append((stream, stream.last_estimated_ms))
        try:
            self.storage.put_estimator_states(rows)
        except StorageUnavailable as exc:
            log.warning("estimator states of %d vehicles not stored (retried later): %s", len(rows), exc)
            return False
        except Exception:  # a bug must not stop the pipeline: these vehicles come due again later
            log.exception("storing the estimator states of %d vehicles failed", len(rows))
            for stream, _ in written:
                stream.checkpoint_at_ms = stream.last_estimated_ms + self.interval_ms
            return True
        finally:
            self.counters.checkpoint_s += time.perf_counter() - started
        for stream, at_ms in written:
            stream.written_ms = at_ms
            stream.checkpoint_at_ms = at_ms + self.interval_ms
        self.counters.checkpoints_written += len(rows)
        return True
