"""What the HTTP API's routes (roadgrip/cloud/api/app.py) need from the cloud behind them: one narrow interface, two
implementations, one set of routes.

| implementation | mode | where things are |
| --- | --- | --- |
| `roadgrip.cloud.serve.service.CloudService` | embedded (`roadgrip serve`) | everything in this process: the pipeline, the map, Mosquitto's users |
| `roadgrip.cloud.cluster.api_backend.ClusterBackend` | cluster (`roadgrip api`, any number of replicas) | PostgreSQL, RabbitMQ's users and partition queues; nothing a replica keeps that another one would need |

Reads of stored data go to `storage` directly (roadgrip/cloud/storage/database.py: the same tables in both modes).
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass
from typing import Protocol

from prometheus_client.registry import Collector

from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.ingest.auth import Authenticator
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Storage
from roadgrip.vehicle.params import VehicleParams


@dataclass(frozen=True)
class Accepted:
    """Telemetry the broker confirmed (cluster mode): in a partition queue, replicated on a quorum of its nodes, not
    stored yet (a worker stores it: roadgrip/cloud/cluster/worker.py)."""

    samples: int
    messages: int  # AMQP messages it took (a request whose samples exceed max_payload_bytes is split)


class VehicleIdRefused(ValueError):
    """A vehicle id valid by the telemetry contract that this mode cannot carry (the message says why): 422."""


@dataclass(frozen=True)
class StationIngest:
    """What `station_reports` did with a payload of reports."""

    received: int
    stored: int  # new reports (a repeat of a stored one is a duplicate)
    duplicates: int
    evidence_cells: int  # cells that got evidence from the new reports


@dataclass(frozen=True)
class EdgeIngest:
    """What `observations` or `heartbeats` did with a payload of an edge vehicle (CONTRACTS 3.7)."""

    received: int
    stored: int  # new ones (a repeat of a stored one is a duplicate)
    duplicates: int


class ApiBackend(Protocol):
    settings: Settings
    storage: Storage
    auth: Authenticator
    mqtt_url: str | None  # what vehicles and readers are told to connect to; None: no MQTT
    station_mqtt_url: str | None  # what roadside stations are told; None: they report over HTTP
    http_payloads_rejected: int  # telemetry requests refused whole (400, 413, 415): counted by the route

    def register_vehicles(self, vehicles: list[tuple[str, VehicleParams]]) -> list[str]:
        """Profiles and credentials (HTTP and MQTT) of new vehicles, all or nothing; their secrets. ValueError when a
        vehicle_id is taken or given twice."""

    def register_reader(self, name: str) -> str: ...

    def register_station(self, station_id: str) -> str: ...

    def revoke(self, name: str) -> bool:
        """Revoke a credential at once, over HTTP and MQTT (open MQTT connections closed); False when there was no
        active one. ValueError for the admin."""

    def submit_telemetry(self, vehicle_id: str, samples: list[dict], received: int) -> Future:
        """Valid samples of one vehicle, out of `received`. The future resolves to a SubmitResult once stored
        (embedded) or to `Accepted` once the broker confirmed them (cluster); it fails with RateLimited,
        StorageUnavailable or IngestUnavailable (nothing taken: retry)."""

    def station_reports(self, reports: list) -> StationIngest:
        """Store validated station reports and give the new ones' evidence to the map and the warnings."""

    def observations(self, observations: list[dict]) -> EdgeIngest:
        """Store validated friction observations of edge vehicles and give the new ones to the map and warnings."""

    def heartbeats(self, heartbeats: list[dict]) -> EdgeIngest:
        """Store validated heartbeats of edge vehicles."""

    def current_map(self) -> tuple[FrictionMap, int]:
        """The friction map and the clock (ms) to read it at."""

    def health(self) -> dict:
        """At least {"status": "ok" | "degraded" | "unavailable", "storage": ...}; "unavailable" answers 503."""

    def metrics_collector(self) -> Collector:
        """This process's Prometheus metrics (GET /metrics)."""
