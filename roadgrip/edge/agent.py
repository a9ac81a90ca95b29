"""The vehicle end's core: an estimator (roadgrip/estimators/base.py) over the car's own samples, its passes through
the map's cells, and what goes to the cloud instead of the samples: one friction observation per pass with evidence
and a sparse heartbeat (CONTRACTS 3.7), put in the outbox (roadgrip/edge/outbox.py) for the uplink to send.

- Samples (wire format v1 dicts) of one vehicle in time order. A gap longer than `max_gap_s` restarts the estimator
  (`reset`), as the cloud's pipeline does; a sample no newer than the last is skipped (counted in `skipped`).
- Passes: the cloud's own rule (roadgrip/cloud/domain/passes.py), with the cell of each estimated sample at the map's
  resolution (roadgrip/cloud/domain/cells.py); when a pass ends (the car left the cell, or pass_gap_s without an
  estimate there), it becomes an observation if it has evidence (roadgrip/cloud/domain/observations.py: both
  directions of pass and observation live there). Samples without a position are estimated but belong to no pass.
- The kind of evidence of each estimated sample (`evidence_of`): "abs", "tcs", "esc" where the sample says that
  controller acts; "bound" where its mu_proven reaches MIN_PROVEN_MU; for an excited estimate without a controller,
  "lateral" where the lateral acceleration exceeds the longitudinal one, else "slip_slope". A label of the manoeuvre
  from the sample's own channels, not a read-out of the estimator's internal terms.
- The heartbeat: every `heartbeat_interval_s` of the samples' time (default 300 s), and at `finish`.
- The estimator state (its self-calibration: pmf's accelerometer bias, radius ratios, slip line, stiffness) is kept in
  `state_path` (JSON, written to a new file and renamed over the old one): every `state_interval_s` of the samples'
  time and at `finish`, read at the start. A stored state is used when it is the same estimator's and its profile
  (the guard's `state["vehicle"]`) is this vehicle's; it is then `reset`, as after a gap: what the estimator keeps
  across gaps stays (roadgrip/cloud/pipeline/checkpoints.py says the same of the cloud's checkpoints).

Time is the samples' own: nothing here reads a clock, so a test replays a drive at any speed.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import orjson

from roadgrip.cloud.domain.cells import cell_of, validate_resolution
from roadgrip.cloud.domain.observations import (
    MIN_PROVEN_MU,
    POSITION_DECIMALS,
    ObservationPass,
    has_evidence,
    observation_of,
)
from roadgrip.cloud.domain.passes import Passes
from roadgrip.cloud.transport.mqtt import heartbeat_topic, observations_topic
from roadgrip.data.schema import TELEMETRY
from roadgrip.edge.outbox import Outbox
from roadgrip.estimators.base import Estimator
from roadgrip.vehicle.params import VehicleParams

log = logging.getLogger(__name__)

HEARTBEAT_INTERVAL_S = 300.0
STATE_INTERVAL_S = 60.0
OPTIONAL_CHANNELS = tuple(c.name for c in TELEMETRY if not c.required)
_CONTROLLERS = (("abs_active", "abs"), ("tcs_active", "tcs"), ("esc_active", "esc"))


def evidence_of(sample: dict, estimate: dict) -> list[str]:
    """The kinds of evidence of one estimated sample (module docstring)."""
    kinds = [kind for field, kind in _CONTROLLERS if sample.get(field)]
    proven = estimate.get("mu_proven")
    if proven is not None and proven >= MIN_PROVEN_MU:
        kinds.append("bound")
    if estimate["excited"] and not any(sample.get(field) for field, _ in _CONTROLLERS):
        lateral = abs(sample["accel_lat_mps2"]) > abs(sample["accel_lon_mps2"])
        kinds.append("lateral" if lateral else "slip_slope")
    return kinds


class EdgeAgent:
    """One vehicle's estimator, passes, observations and heartbeats (module docstring)."""

    def __init__(
        self,
        vehicle_id: str,
        profile: VehicleParams,
        estimator: Estimator,
        outbox: Outbox,
        *,
        state_path: str | Path | None = None,
        resolution: int = 10,
        pass_gap_s: float = 30.0,
        max_gap_s: float = 0.25,
        heartbeat_interval_s: float = HEARTBEAT_INTERVAL_S,
        state_interval_s: float = STATE_INTERVAL_S,
    ):
        self.vehicle_id = vehicle_id
        self.profile = profile
        self.estimator = estimator
        self.outbox = outbox
        self.state_path = None if state_path is None else Path(state_path)
        self.resolution = validate_resolution(resolution)
        self.max_gap_ms = max_gap_s * 1000.0
        self.heartbeat_ms = heartbeat_interval_s * 1000.0
        self.state_ms = state_interval_s * 1000.0
        self._observations_topic = observations_topic(vehicle_id)
        self._heartbeat_topic = heartbeat_topic(vehicle_id)
        self.passes = Passes(pass_gap_s, ObservationPass, self._pass_ended)
        self.channels: set[str] = set()
        self.samples = self.estimates = self.observations = self.heartbeats = self.skipped = 0
        self.restored = False
        self.state = self._restored_state()
        self._last_ms: int | None = None
        self._last_position: tuple[float | None, float | None] = (None, None)
        self._heartbeat_at: float | None = None
        self._state_at: float | None = None
        self._since_heartbeat = [0, 0]  # samples, observations

    # ------------------------------------------------------------------------------------------ samples in

    def feed(self, sample: dict) -> None:
        """One sample of this vehicle (wire format v1), newer than the last."""
        t = int(sample["timestamp_ms"])
        if self._last_ms is not None and t <= self._last_ms:
            self.skipped += 1
            return
        if self._last_ms is not None and t - self._last_ms > self.max_gap_ms:
            self.estimator.reset(self.state)
        self._last_ms = t
        self.samples += 1
        self._since_heartbeat[0] += 1
        self.channels.update(name for name in OPTIONAL_CHANNELS if sample.get(name) is not None)
        estimate = self.estimator.update(self.state, sample)
        lat, lon = sample.get("latitude_deg"), sample.get("longitude_deg")
        self._last_position = (lat, lon)
        if estimate is not None:
            self.estimates += 1
            row = estimate.to_dict()
            cell = cell_of(lat, lon, self.resolution)
            if cell is not None:
                p = self.passes.row(self.vehicle_id, cell, t)
                if p is not None:
                    p.add(row, lat, lon, evidence_of(sample, row))
        self.passes.close_idle(t)
        if self._heartbeat_at is None:
            self._heartbeat_at = t + self.heartbeat_ms
            self._state_at = t + self.state_ms
        if t >= self._heartbeat_at:
            self.heartbeat()
        if t >= self._state_at:
            self.save_state()
            self._state_at = t + self.state_ms

    def finish(self) -> None:
        """Ignition off: the pass in progress ends (an observation if it has evidence), a last heartbeat, the state
        saved."""
        if self._last_ms is None:
            return
        self.passes.close_idle(2**62)
        self.heartbeat()
        self.save_state()

    # ------------------------------------------------------------------------------------------ messages out

    def _pass_ended(self, p: ObservationPass) -> None:
        if not p.n or not has_evidence(p):
            return
        observation = observation_of(
            p, vehicle_class=self.profile.name, channels=self.channels, estimator=self.estimator.name
        )
        self.outbox.put(self._observations_topic, orjson.dumps(observation), now_ms=p.last_ms)
        self.observations += 1
        self._since_heartbeat[1] += 1

    def heartbeat(self) -> None:
        """Put a heartbeat (HEARTBEAT's fields) in the outbox now."""
        lat, lon = (None if x is None else round(x, POSITION_DECIMALS) for x in self._last_position)
        message = {
            "vehicle_id": self.vehicle_id,
            "timestamp_ms": self._last_ms,
            "latitude_deg": lat,
            "longitude_deg": lon,
            "n_samples": self._since_heartbeat[0],
            "n_observations": self._since_heartbeat[1],
            "outbox_pending": self.outbox.pending,
            "outbox_dropped": self.outbox.dropped,
        }
        self.outbox.put(self._heartbeat_topic, orjson.dumps(message), now_ms=self._last_ms)
        self.heartbeats += 1
        self._since_heartbeat = [0, 0]
        self._heartbeat_at = self._last_ms + self.heartbeat_ms

    # ------------------------------------------------------------------------------------------ state on disk

    def save_state(self) -> None:
        """Write the estimator's state (module docstring); a crash while writing leaves the previous file."""
        if self.state_path is None:
            return
        data = {"estimator": self.estimator.name, "state": self.estimator.state_to_dict(self.state)}
        self.state_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.state_path.with_name(self.state_path.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(orjson.dumps(data, option=orjson.OPT_SERIALIZE_NUMPY))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.state_path)

    def _restored_state(self):
        fresh = self.estimator.start(self.profile)
        if self.state_path is None or not self.state_path.is_file():
            return fresh
        try:
            data = json.loads(self.state_path.read_text())
            if data.get("estimator") != self.estimator.name:
                raise ValueError(f"a state of estimator {data.get('estimator')!r}, not {self.estimator.name!r}")
            profile = data["state"].get("vehicle")
            if profile is not None and VehicleParams.from_dict(profile) != self.profile:
                raise ValueError("a state of another vehicle profile")
            state = self.estimator.state_from_dict(data["state"])
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            log.warning("estimator state in %s not used (starting afresh): %s", self.state_path, exc)
            return fresh
        self.estimator.reset(state)
        self.restored = True
        return state
