"""The fleet benchmark's vehicles in edge mode (issue 27; `roadgrip evaluate --benchmark fleet --mode edge`): each
vehicle runs the vehicle end (roadgrip/edge/agent.py: the estimator on board, its passes, friction observations and
heartbeats into its outbox) on its own samples, and what its outbox holds reaches the service as an edge vehicle's
messages do: each checked by the cloud's parser (roadgrip/cloud/ingest/observations.py, as the MQTT handler and the
HTTP route do) and handed to `CloudService.observations` / `heartbeats`, which store them and feed the map and the
warning engine the rows of the passes they stand for (roadgrip/cloud/domain/observations.py, `pass_rows`).

What differs from raw mode is only where the estimator runs and what crosses the air; the drives, the estimator (the
service's default, pmf), each vehicle's profile (its catalogue kind, the one raw mode registers), the map, the engine
and the scoring are the same. Delivery is immediate: a message leaves the outbox the second of data it was made in
(a vehicle always in coverage), so the delay measured is the passes' own (an observation is sent when its pass ends).

Ignition: a vehicle's agent is finished (`EdgeAgent.finish`: its pass in progress ends, a heartbeat) when its trip
ends (Trip.depart_s + its drive's duration), as a car's ignition goes off when it parks; its next trip starts with
a reset estimator (a gap), the self-calibration kept, as across an ignition cycle.
"""

from __future__ import annotations

import time
from pathlib import Path

from roadgrip.cloud.ingest.observations import ObservationError, parse_edge_message
from roadgrip.edge.agent import EdgeAgent
from roadgrip.edge.outbox import Outbox
from roadgrip.estimators.learned import load_estimator


class EdgeFleet:
    """Every vehicle of a FleetScenario with its own agent and outbox under `folder` (module docstring)."""

    def __init__(self, scenario, folder: Path, settings, estimator: str = "pmf"):
        self.settings = settings
        self.agents = {
            vid: EdgeAgent(
                vid,
                profile,
                load_estimator(estimator),
                Outbox(Path(folder) / f"{vid}.sqlite"),
                resolution=settings.h3_resolution,
            )
            for vid, profile in sorted(scenario.kinds.items())
        }
        self._trip_ends = sorted((t.depart_s + t.scenario.duration_s, t.vehicle_id) for t in scenario.trips)
        self.observations = self.heartbeats = self.rejected = self.payload_bytes = 0

    def feed(self, vehicle_id: str, samples: list[dict]) -> None:
        """A vehicle's samples (wire format v1, in time order) into its agent."""
        agent = self.agents[vehicle_id]
        for sample in samples:
            agent.feed(sample)

    def ignition_off(self, t_s: float) -> None:
        """Finish the agents of the trips that ended by `t_s` (seconds since the run's start)."""
        while self._trip_ends and self._trip_ends[0][0] <= t_s:
            _, vehicle_id = self._trip_ends.pop(0)
            self.agents[vehicle_id].finish()

    def deliver(self, service) -> None:
        """Every waiting message of every outbox to the service, as its MQTT handler takes it; emptied outboxes."""
        s = self.settings
        now_ms = int(time.time() * 1000)
        for vehicle_id, agent in self.agents.items():
            outbox = agent.outbox
            if not outbox.pending:
                continue
            observations, heartbeats = [], []
            for message_id, topic, payload in outbox.oldest(outbox.pending):
                self.payload_bytes += len(payload)
                try:
                    parsed = parse_edge_message(
                        "observations" if topic.endswith("/observations") else "heartbeat",
                        payload,
                        vehicle_id=vehicle_id,
                        settings=s,
                        now_ms=now_ms,
                    )
                    (observations if topic.endswith("/observations") else heartbeats).extend(parsed)
                except ObservationError:
                    self.rejected += 1
                outbox.remove(message_id)
            if observations:
                self.observations += service.observations(observations).stored
            if heartbeats:
                self.heartbeats += service.heartbeats(heartbeats).stored

    def finish(self, service) -> None:
        """Ignition off for every vehicle, the last messages delivered, the outboxes closed."""
        for agent in self.agents.values():
            agent.finish()
        self.deliver(service)
        for agent in self.agents.values():
            agent.outbox.close()
