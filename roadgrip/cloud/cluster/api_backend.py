"""The API's backend in cluster mode (`roadgrip api`, issue 17 item 4; roadgrip/cloud/api/backend.py for the interface,
docs/CLUSTER.md "Stateless API" for the whole): any number of replicas behind any load balancer, on one PostgreSQL and
one RabbitMQ cluster. A replica holds no state another replica would need:

- credentials: PostgreSQL on every call (`Authenticator(revalidate=True)`); vehicles' and readers' broker logins:
  RabbitMQ's own users and permissions (roadgrip/cloud/transport/rabbit_users.py), created inside the registration's
  database transaction (a broker failure rolls the registration back) and deleted on revocation (which closes their
  MQTT connections);
- telemetry: published to the broker with confirms (roadgrip/cloud/cluster/publisher.py) and stored by the workers;
- the map: the cells the region owners saved (roadgrip/cloud/cluster/map_cells.py `stored_friction_map`), read at most
  once a second per replica; warnings, estimates, profiles and station reports: storage;
- what a replica does keep is its own: its rate limiter (a per-replica limit, see roadgrip/cloud/api/app.py), its
  counters for /metrics, the admin's verified scrypt hash.

The admin secret must be given (`admin_secret`, ROADGRIP_ADMIN_SECRET): every replica checks the same one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from urllib.parse import unquote, urlsplit

import orjson
from prometheus_client.core import Metric
from prometheus_client.registry import Collector

from roadgrip.cloud.api.backend import Accepted, EdgeIngest, StationIngest, VehicleIdRefused
from roadgrip.cloud.cluster.map_cells import stored_friction_map
from roadgrip.cloud.cluster.publisher import (
    DEFAULT_CONNECTIONS,
    PUBLISH_BUCKETS_S,
    PUBLISH_DEADLINE_S,
    TelemetryPublisher,
)
from roadgrip.cloud.cluster.regions import (
    RegionPublisher,
    check_region_resolution,
    publish_observations,
    publish_station_evidence,
)
from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.domain.stations import StationReport, stored_evidence_rows, stored_rows
from roadgrip.cloud.ingest.admission import RateLimited
from roadgrip.cloud.ingest.auth import ADMIN_NAME, Authenticator, hash_token, new_secret
from roadgrip.cloud.ingest.ratelimit import RateLimiter
from roadgrip.cloud.metrics import counter, gauge, histogram
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Storage, StorageUnavailable, open_storage
from roadgrip.cloud.transport.mqtt import telemetry_topic
from roadgrip.cloud.transport.rabbit_users import BROKER_ROLES, BrokerUnavailable, RabbitUsers, routing_key
from roadgrip.vehicle.params import VehicleParams

log = logging.getLogger(__name__)

MAP_CACHE_S = (
    1.0  # a replica reads the stored map at most this often (the region owners save a cell about once a second)
)


def management_login(management_urls: list[str], brokers: list[str]) -> tuple[list[str], str, str]:
    """(management URLs without credentials, user, password): the login of the first management URL that carries
    one (http://user:password@host:port), else the first broker URL's (the service user of amqp://user:password@...)."""
    urls, login = [], None
    for url in management_urls:
        parts = urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"a management URL is http(s)://[user:password@]host:port, got {url!r}")
        if parts.username and login is None:
            login = (unquote(parts.username), unquote(parts.password or ""))
        port = f":{parts.port}" if parts.port else ""
        urls.append(f"{parts.scheme}://{parts.hostname}{port}{parts.path.rstrip('/')}")
    if login is None:
        parts = urlsplit(brokers[0])
        if not parts.username:
            raise ValueError(
                "no login for the management API: give it in --management (http://user:password@...) "
                f"or in the first --broker, got {brokers[0]!r}"
            )
        login = (unquote(parts.username), unquote(parts.password or ""))
    return urls, *login


class ClusterBackend:
    """`roadgrip api`'s backend: `start()`, then `create_app(backend)`, then `stop()`."""

    def __init__(
        self,
        settings: Settings,
        brokers: list[str],
        management: list[str],
        publisher_connections: int = DEFAULT_CONNECTIONS,
    ):
        if not (settings.database_url or "").startswith(("postgresql://", "postgresql+psycopg://")):
            raise ValueError(
                "the cluster's API replicas share one PostgreSQL database: database_url must be "
                f"postgresql://..., got {settings.database_url!r}"
            )
        if settings.admin_secret is None:
            raise ValueError(
                "the cluster's API replicas share the admin secret: set admin_secret "
                "(ROADGRIP_ADMIN_SECRET or the settings file)"
            )
        if not brokers:
            raise ValueError("at least one broker URL (amqp://user:password@host:port/%2F) is needed")
        if not management:
            raise ValueError("at least one RabbitMQ management URL (http://host:15672) is needed")
        self.settings = settings
        self.brokers = brokers
        self.management_urls, self._management_user, self._management_password = management_login(management, brokers)
        self.mqtt_url = settings.mqtt if settings.mqtt.startswith(("mqtt://", "tcp://")) else None
        self.station_mqtt_url = None  # stations report over HTTP in the cluster (rabbit_users.py)
        self.storage: Storage | None = None
        self.auth: Authenticator | None = None
        self.users: RabbitUsers | None = None
        self.publisher = TelemetryPublisher(brokers, publisher_connections)
        self.region_resolution = check_region_resolution(settings)
        self.region_publisher = RegionPublisher(brokers)
        self.rate_limiter = RateLimiter(settings.rate_limit_samples_per_s, settings.rate_limit_burst_s)
        self._rate_lock = threading.Lock()
        self._map_lock = threading.Lock()
        self._map: tuple[float, FrictionMap, int] | None = None
        self.http_payloads_rejected = 0
        self.received = self.invalid = self.rate_limited = 0
        self.registered = self.revoked = 0

    # ------------------------------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        self.storage = open_storage(self.settings.database_url)
        self.auth = Authenticator(self.storage, revalidate=True)
        try:
            self.auth.ensure_admin(self.settings.admin_secret)
        except ValueError:  # another replica starting at the same moment stored it first
            self.auth.ensure_admin(self.settings.admin_secret)
        self.users = RabbitUsers(self.management_urls, self._management_user, self._management_password)
        self.publisher.start()
        log.info(
            "cluster API backend started: storage %s, brokers %d, management %s",
            self.storage,
            len(self.brokers),
            ", ".join(self.management_urls),
        )

    def stop(self) -> None:
        self.publisher.stop()
        self.region_publisher.close()
        if self.users is not None:
            self.users.close()
            self.users = None
        if self.storage is not None:
            self.storage.close()
            self.storage = None

    # ------------------------------------------------------------------------------------------------- credentials
    def register_vehicles(self, vehicles: list[tuple[str, VehicleParams]]) -> list[str]:
        """As embedded, and each vehicle's RabbitMQ user with its permissions, created before the database commits:
        a broker that does not take them rolls the registration back (BrokerUnavailable: 503). Should the commit
        itself fail after that, the users are deleted again. A vehicle id with a '.' is refused (VehicleIdRefused):
        RabbitMQ 3.10's MQTT plugin turns a topic's '/' into '.' and leaves its dots, so such an id would add words
        to the routing key: its telemetry would match no partition binding and its friction topic would reach MQTT
        subscribers under another topic."""
        dotted = [vehicle_id for vehicle_id, _ in vehicles if "." in vehicle_id]
        if dotted:
            raise VehicleIdRefused(
                f"vehicle_id {dotted[0]!r}: a '.' cannot be carried in cluster mode (RabbitMQ's "
                "MQTT plugin maps topic levels to '.'-separated words); use A-Za-z0-9_-"
            )
        secrets_ = [new_secret() for _ in vehicles]
        logins = [(vehicle_id, secret, "vehicle") for (vehicle_id, _), secret in zip(vehicles, secrets_)]
        rows = [
            (vehicle_id, profile.to_dict(), hash_token(secret))
            for (vehicle_id, profile), secret in zip(vehicles, secrets_)
        ]
        self._with_logins(logins, lambda put: self.storage.register_vehicles(rows, before_commit=put))
        self.registered += len(vehicles)
        return secrets_

    def register_reader(self, name: str) -> str:
        secret = new_secret()
        self._with_logins(
            [(name, secret, "reader")],
            lambda put: self.storage.add_credential(name, "reader", hash_token(secret), before_commit=put),
        )
        return secret

    def register_station(self, station_id: str) -> str:
        """A station's credential, HTTP only in the cluster (rabbit_users.py: no broker login)."""
        secret = new_secret()
        self.storage.add_credential(station_id, "station", hash_token(secret))
        return secret

    def _with_logins(self, logins: list[tuple[str, str, str]], store) -> None:
        """`store(put)` with `put` creating `logins` on the broker inside the store's transaction."""
        put_done = []

        def put() -> None:
            self.users.put_logins(logins)
            put_done.append(True)

        try:
            store(put)
        except StorageUnavailable:
            if put_done:  # the users exist, the credentials do not: remove the users again
                self.users.delete_logins([name for name, _, _ in logins])
            raise

    def revoke(self, name: str) -> bool:
        """Revoke in PostgreSQL (every replica refuses it from its next call on), then delete the broker user, which
        closes its MQTT connections. The broker step runs even when the database had nothing active to revoke, so
        that a revocation whose broker step failed (BrokerUnavailable, 503) completes when asked again."""
        if name == ADMIN_NAME:
            raise ValueError("the admin credential cannot be revoked; change admin_secret instead")
        credential = self.storage.credential(name)
        revoked = self.auth.revoke(name)
        if credential is None or credential.role in BROKER_ROLES:
            self.users.delete_login(name)
        self.revoked += revoked
        return revoked

    # ------------------------------------------------------------------------------------------------- telemetry
    def submit_telemetry(self, vehicle_id: str, samples: list[dict], received: int) -> Future:
        """This replica's rate limit, then the samples published to the vehicle's partition (the future resolves to
        `Accepted` once the broker confirmed every message)."""
        with self._rate_lock:
            decision = self.rate_limiter.allow(vehicle_id, received, time.monotonic())
            self.received += received
            if not decision.allowed:
                self.rate_limited += received
            else:
                self.invalid += received - len(samples)
        if not decision.allowed:
            future: Future = Future()
            future.set_exception(RateLimited(decision.reason, decision.retry_after_s))
            return future
        if not samples:
            future = Future()
            future.set_result(Accepted(0, 0))
            return future
        bodies = self._bodies([{k: v for k, v in sample.items() if v is not None} for sample in samples])
        confirmed = self.publisher.publish(vehicle_id, routing_key(telemetry_topic(vehicle_id)), bodies)
        result: Future = Future()

        def done(f: Future) -> None:
            if f.exception() is not None:
                result.set_exception(f.exception())
            else:
                result.set_result(Accepted(len(samples), len(bodies)))

        confirmed.add_done_callback(done)
        return result

    def _bodies(self, samples: list[dict]) -> list[bytes]:
        """The samples as JSON arrays of at most max_payload_bytes each (what the worker accepts in one message): one,
        unless re-encoding made a request near the limit larger (an integral float timestamp written as an int)."""
        body = orjson.dumps(samples)
        if len(body) <= self.settings.max_payload_bytes or len(samples) == 1:
            return [body]
        half = len(samples) // 2
        return self._bodies(samples[:half]) + self._bodies(samples[half:])

    # ------------------------------------------------------------------------------------------------- stations
    def station_reports(self, reports: list[StationReport]) -> StationIngest:
        """Store validated reports (idempotent on station_id and timestamp_ms), as embedded, then hand the evidence of
        every report of the payload to the owners of their regions (roadgrip/cloud/cluster/regions.py
        `publish_station_evidence`: one confirmed message per region), which add it to the map and the warnings.

        The reports are stored first: when the broker does not confirm the evidence within PUBLISH_DEADLINE_S (the
        telemetry's deadline), BrokerUnavailable (503) says so, with the reports stored. Sending them again is the
        way to hand the evidence on: they are then duplicates, and the evidence of a duplicate is published again,
        as stored (not as sent again). A region applies a station's evidence once: its map keeps a station's newest
        report per cell, its warning engine skips a station's evidence not newer than the last it applied there,
        except in a region restored on another worker since (its engine does not know which station reports it
        applied, as after serve's restart: a report sent again then counts once more towards its cell's warning)."""
        rows, evidence_of = stored_rows(reports, self.settings.h3_resolution)
        new = self.storage.put_station_reports(rows)
        fresh = [row for key in sorted(new, key=lambda k: k[1]) for row in evidence_of[key]]
        repeated = [
            row
            for stored in self.storage.station_reports_of(evidence_of.keys() - new)
            for row in stored_evidence_rows(stored)
        ]
        if fresh or repeated:
            try:
                publish_station_evidence(
                    self.region_publisher, fresh + repeated, self.region_resolution, PUBLISH_DEADLINE_S
                )
            except TimeoutError as exc:
                raise BrokerUnavailable(
                    f"{len(new)} new report(s) of {len(reports)} stored, but their evidence was "
                    f"not handed to the map ({exc}); send them again"
                ) from exc
        return StationIngest(len(reports), len(new), len(reports) - len(new), len(fresh))

    def observations(self, observations: list[dict]) -> EdgeIngest:
        """Store validated observations of edge vehicles (once per vehicle_id and last_ms), then hand the rows of the
        passes of every observation of the payload (a duplicate's too: sending again is how a caller retries) to the
        owners of their regions, as the workers hand a round's estimates (roadgrip/cloud/cluster/regions.py
        `publish_observations`: one confirmed message per region). BrokerUnavailable (503) when the broker does not confirm
        within PUBLISH_DEADLINE_S, with the observations stored; a region applies a vehicle's rows once."""
        new = self.storage.put_observations(observations)
        try:
            publish_observations(self.region_publisher, observations, self.region_resolution, PUBLISH_DEADLINE_S)
        except TimeoutError as exc:
            raise BrokerUnavailable(
                f"{len(new)} new observation(s) of {len(observations)} stored, but not handed to the map ({exc}); "
                "send them again"
            ) from exc
        return EdgeIngest(len(observations), len(new), len(observations) - len(new))

    def heartbeats(self, heartbeats: list[dict]) -> EdgeIngest:
        """Store validated heartbeats of edge vehicles."""
        stored = self.storage.put_heartbeats(heartbeats)
        return EdgeIngest(len(heartbeats), stored, len(heartbeats) - stored)

    # ------------------------------------------------------------------------------------------------- reads
    def current_map(self) -> tuple[FrictionMap, int]:
        """The map the region owners saved, at this replica's clock (or the newest stored sample's, map_clock data),
        read again when the last read is over MAP_CACHE_S old."""
        with self._map_lock:
            if self._map is not None and time.monotonic() - self._map[0] < MAP_CACHE_S:
                return self._map[1], self._map[2]
            if self.settings.map_clock == "data":
                now = max(self.storage.latest_timestamps().values(), default=0)
            else:
                now = int(time.time() * 1000)
            fmap = stored_friction_map(self.storage, self.settings, now)
            self._map = (time.monotonic(), fmap, now)
            return fmap, now

    def health(self) -> dict:
        """storage: reachable or why not (unavailable: 503); broker: the management API reachable and the
        publisher's open connections (degraded when the API does not answer or no connection is open while one
        was needed)."""
        status = {"status": "ok", "storage": "ok"}
        try:
            self.storage.ping()
        except StorageUnavailable as exc:
            status.update(status="unavailable", storage=str(exc))
        broker = {
            "management": "ok",
            "publisher_connections": self.publisher.connections_up,
            "publisher_failed_messages": self.publisher.failed_messages,
        }
        try:
            self.users.ping()
        except BrokerUnavailable as exc:
            broker["management"] = str(exc)
            if status["status"] == "ok":
                status["status"] = "degraded"
        status["broker"] = broker
        return status

    def metrics_collector(self) -> Collector:
        return ApiCollector(self)


class ApiCollector(Collector):
    """The metrics of an API replica (docs/CLUSTER.md "Stateless API"): the samples it received, refused and had
    confirmed by the broker, its publishes' confirm latency, its registrations and revocations."""

    def __init__(self, backend: ClusterBackend):
        self.backend = backend

    def collect(self) -> Iterator[Metric]:
        b, p = self.backend, self.backend.publisher
        yield counter(
            "roadgrip_samples_received",
            "Samples received in readable payloads (valid or not)",
            [(["api", "http"], b.received)],
            ["process", "transport"],
        )
        yield counter(
            "roadgrip_samples_rejected",
            "Samples refused: invalid (validation) or rate_limited (this replica's limit)",
            [(["api", "http", "invalid"], b.invalid), (["api", "http", "rate_limited"], b.rate_limited)],
            ["process", "transport", "reason"],
        )
        yield counter(
            "roadgrip_payloads_rejected",
            "HTTP requests refused whole before any sample was read",
            [(["api", "http"], b.http_payloads_rejected)],
            ["process", "transport"],
        )
        yield counter(
            "roadgrip_api_messages_published", "Telemetry messages the broker confirmed", [([], p.published_messages)]
        )
        yield counter(
            "roadgrip_api_messages_failed",
            "Telemetry messages the broker did not confirm on any node (the request answered 503)",
            [([], p.failed_messages)],
        )
        yield counter(
            "roadgrip_api_publish_retries", "Publishes tried again (a nack, a lost connection)", [([], p.retries)]
        )
        yield histogram(
            "roadgrip_api_publish_seconds",
            "From a request's first publish to the broker's confirm of its last",
            PUBLISH_BUCKETS_S,
            [([], p.confirm_seconds.state())],
        )
        yield gauge(
            "roadgrip_api_broker_connections",
            "Open AMQP connections of the telemetry publisher",
            [([], p.connections_up)],
        )
        yield counter(
            "roadgrip_api_vehicles_registered", "Vehicles registered through this replica", [([], b.registered)]
        )
        yield counter("roadgrip_api_credentials_revoked", "Credentials revoked through this replica", [([], b.revoked)])
