"""The cloud service assembled from its parts: storage, credentials, ingest (rate limit, pipeline: estimation and
storage; in this process, or sharded over `ingest_processes`), the fan-out (map, warnings, publishing), the MQTT side
(a broker given by URL, or a Mosquitto started here), and the HTTP API.

Edge vehicles' observations and heartbeats (CONTRACTS 3.7, roadgrip/cloud/ingest/observations.py) do not either:
`edge_messages` stores the new ones (once per vehicle_id and last_ms, or timestamp_ms) in one transaction and hands
the new observations to the fan-out in one call, which feeds the map and the warnings the passes they stand for; from
the HTTP routes (`observations`, `heartbeats`: a request at a time), or from the MQTT intake, which queues the
messages and stores them in batches (roadgrip/cloud/serve/edge_intake.py: its bound, backpressure and exactly once).

Roadside stations (roadgrip/cloud/domain/stations.py) do not go through the vehicles' pipeline: `station_reports` stores a
station's validated reports (idempotent on station_id and timestamp_ms) and hands the evidence of the new ones to the
fan-out (map and warnings, under its lock), in this process, from the HTTP route or from the MQTT handler's own
thread (a station reports about once a minute; the vehicles' queue is not needed).

    service = CloudService(load_settings())
    service.start()          # storage opened, pipeline running, MQTT connected when configured
    app = create_app(service) # roadgrip.cloud.api.app (the service is its backend: roadgrip/cloud/api/backend.py)
    ...
    service.stop()
"""

from __future__ import annotations

import json
import logging
import secrets
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Self

from roadgrip.cloud.api.backend import EdgeIngest, StationIngest
from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.domain.observations import pass_rows
from roadgrip.cloud.domain.stations import ReportError, StationReport, parse_reports, stored_evidence_rows, stored_rows
from roadgrip.cloud.domain.warnings import WarningEvent
from roadgrip.cloud.ingest.admission import Ingest
from roadgrip.cloud.ingest.auth import ADMIN_NAME, Authenticator, hash_token, new_secret
from roadgrip.cloud.metrics import ServiceCollector
from roadgrip.cloud.pipeline.fanout import Fanout, new_friction_map, new_warning_engine
from roadgrip.cloud.pipeline.pipeline import Pipeline
from roadgrip.cloud.process import rss_mb, warm_up
from roadgrip.cloud.serve.edge_intake import EdgeIntake
from roadgrip.cloud.serve.shards import IngestShards
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Storage, StorageUnavailable, open_storage
from roadgrip.cloud.transport.mosquitto import MAX_INFLIGHT_MESSAGES, ManagedBroker, mosquitto_available
from roadgrip.cloud.transport.mqtt import DEFAULT_MAX_INFLIGHT, MqttClient, errors_topic, station_errors_topic
from roadgrip.estimators.learned import load_estimator
from roadgrip.vehicle.params import VehicleParams

log = logging.getLogger(__name__)
# Estimate messages (one per vehicle a second) the service lets wait for the broker before it drops new ones rather
# than queue them (5 s of 1,000 vehicles). When the broker takes them slower than they come, paho would hold up to
# max_queued_messages (100,000) in memory, several kB each (ten estimates): run d of docs/RELIABILITY.md grew by 950 MB
# in a stall; run e, with this bound, stayed level at 606 MB until its stall. The estimates stay stored and readable
# over HTTP; warnings and error reports are never dropped.
MAX_UNACKNOWLEDGED_ESTIMATES = 5_000


class CloudService:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.storage: Storage | None = None
        self.auth: Authenticator | None = None
        self.fanout: Fanout | None = None
        self.ingest: Ingest | IngestShards | None = None
        self.broker: ManagedBroker | None = None
        self.mqtt: MqttClient | None = None
        self.mqtt_url: str | None = None
        self.admin_secret: str | None = None
        self.friction_map = new_friction_map(settings)
        self.warning_engine = new_warning_engine(settings)
        self.mqtt_rejected = 0
        self.estimate_messages_dropped = 0
        self.http_payloads_rejected = 0  # telemetry requests refused whole: 400, 413, 415 (metrics)
        self._station_worker: ThreadPoolExecutor | None = None  # MQTT station reports, off paho's network thread
        self.edge_intake: EdgeIntake | None = None  # edge vehicles' MQTT messages, in batches

    # ------------------------------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        s = self.settings
        s.data_dir.mkdir(parents=True, exist_ok=True)
        self.storage = open_storage(s.storage_url)
        self.auth = Authenticator(self.storage)
        self.admin_secret = s.admin_secret or self._stored_admin_secret()
        self.auth.ensure_admin(self.admin_secret)
        self._restore_map()
        self.fanout = Fanout(self.storage, s, self.friction_map, self.warning_engine, publish=self._publish)
        if s.ingest_processes:
            self.ingest = IngestShards(s, self.fanout, reject=self._reject_mqtt)
        else:
            estimator = load_estimator(s.estimator)
            warm_up(estimator)
            self.ingest = Ingest(s, Pipeline(self.storage, s, estimator, self.fanout), reject=self._reject_mqtt)
        self.ingest.start()
        self._start_mqtt()
        log.info(
            "cloud started: storage %s, mqtt %s, estimator %s, ingest %s",
            self.storage,
            self.mqtt_url or "off",
            s.estimator,
            f"in {s.ingest_processes} processes" if s.ingest_processes else "in this process",
        )

    def stop(self) -> None:
        if self.mqtt is not None:
            self.mqtt.close()
            self.mqtt = None
        if self._station_worker is not None:
            self._station_worker.shutdown(wait=True)
            self._station_worker = None
        if self.edge_intake is not None:
            self.edge_intake.stop()
            self.edge_intake = None
        if self.ingest is not None:
            self.ingest.stop()
            self.ingest = None
        if self.broker is not None:
            self.broker.stop()
            self.broker = None
        if self.storage is not None:
            self.storage.close()
            self.storage = None

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _stored_admin_secret(self) -> str:
        path = self.settings.data_dir / "admin-secret"
        if path.is_file():
            return path.read_text().strip()
        secret = secrets.token_urlsafe(32)
        path.touch(mode=0o600)
        path.write_text(secret + "\n")
        log.info("generated the admin secret in %s", path)
        return secret

    def _restore_map(self) -> None:
        """After a restart the map starts from the stored estimates that are still young enough to count, and the
        warning engine from the active warnings."""
        since = 0 if self.settings.map_clock == "data" else int((time.time() - self.settings.map_max_age_s) * 1000)
        rows = self.storage.estimates_since(since)
        self.friction_map.add(rows)
        active = [WarningEvent(**row["message"]["event"]) for row in self.storage.warnings(active_only=True)]
        self.warning_engine.restore(active)
        reports = self.storage.station_reports_since(since)
        self.friction_map.add_station([row for report in reports for row in stored_evidence_rows(report)])
        observations = self.storage.observations_since(since)
        self.friction_map.add([row for o in observations for row in pass_rows(o)])
        log.info(
            "restored the map from %d stored estimates, %d observations, %d station reports and %d active warnings",
            len(rows),
            len(observations),
            len(reports),
            len(active),
        )

    # ------------------------------------------------------------------------------------------------- MQTT
    def _start_mqtt(self) -> None:
        s = self.settings
        mode = s.mqtt
        if mode == "off":
            return
        if mode in ("auto", "managed"):
            if not mosquitto_available():
                if mode == "managed":
                    raise RuntimeError(
                        "mqtt=managed but mosquitto is not installed: run "
                        "`bash scripts/install_system_deps.sh` or set mqtt to a broker URL"
                    )
                log.warning("mosquitto is not installed: serving HTTP ingest only")
                return
            self.broker = ManagedBroker(Path(s.data_dir) / "mosquitto", port=s.mqtt_port)
            self.broker.start()
            self.mqtt_url = self.broker.url
            username, password = self.broker.service_user, self.broker.service_password
        else:
            if not (s.mqtt_username and s.mqtt_password):
                raise RuntimeError("mqtt is a broker URL: set mqtt_username and mqtt_password for the service's login")
            self.mqtt_url = mode
            username, password = s.mqtt_username, s.mqtt_password
        # a broker of our own allows MAX_INFLIGHT_MESSAGES; another one, Mosquitto's default
        self._station_worker = ThreadPoolExecutor(1, thread_name_prefix="station-reports")
        self.edge_intake = EdgeIntake(s, self.edge_messages, self._reject_mqtt)
        self.edge_intake.start()
        self.mqtt = MqttClient(
            self.mqtt_url,
            username,
            password,
            client_id="roadgrip-cloud",
            on_telemetry=self.ingest.mqtt_message,
            on_station_report=self._station_message,
            on_edge=self.edge_intake.submit,
            room=self._mqtt_room,
            max_inflight=MAX_INFLIGHT_MESSAGES if self.broker is not None else DEFAULT_MAX_INFLIGHT,
        )
        self.mqtt.connect()

    def _mqtt_room(self) -> bool:
        """Whether MQTT messages deferred for want of room (Busy) may come again (MqttClient's redelivery): the edge
        intake and the raw pipeline (or the ingest processes, IngestShards.has_room) both have room."""
        ingest_room = getattr(self.ingest, "has_room", None)
        return self.edge_intake.has_room() and (ingest_room is None or ingest_room())

    def _publish(self, topic: str, payload: bytes) -> None:
        if self.mqtt is None:
            return
        if topic.rsplit("/", 1)[-1] == "friction" and self.mqtt.unacknowledged > MAX_UNACKNOWLEDGED_ESTIMATES:
            self.estimate_messages_dropped += 1
            if self.estimate_messages_dropped % 1000 == 1:
                log.warning(
                    "%d publishes wait for the broker: dropped %d estimate messages so far (the estimates are stored)",
                    self.mqtt.unacknowledged,
                    self.estimate_messages_dropped,
                )
            return
        self.mqtt.publish(topic, payload)

    def _reject_mqtt(self, vehicle_id: str, errors: list[dict]) -> None:
        """Rejections of an MQTT message (roadgrip/cloud/ingest/admission.py): counted, logged, published on the vehicle's error
        topic."""
        self.mqtt_rejected += len(errors)
        log.warning("rejected %d sample(s) from vehicle %s over MQTT: %s", len(errors), vehicle_id, errors[0]["reason"])
        # json, not orjson: a reason quotes what was sent, which may hold a lone surrogate (escaped by json)
        self._publish(errors_topic(vehicle_id), json.dumps({"vehicle_id": vehicle_id, "rejected": errors}).encode())

    # ------------------------------------------------------------------------------------------------- stations
    def station_reports(self, reports: list[StationReport]) -> StationIngest:
        """Store validated reports (roadgrip/cloud/domain/stations.py) and hand the evidence of the new ones to the map and
        the warning engine. StorageUnavailable when the database is down (nothing stored)."""
        rows, evidence_of = stored_rows(reports, self.settings.h3_resolution)
        new = self.storage.put_station_reports(rows)
        fresh = [row for key in sorted(new, key=lambda k: k[1]) for row in evidence_of[key]]
        self.fanout.station_reports(fresh)
        return StationIngest(len(reports), len(new), len(reports) - len(new), len(fresh))

    def _station_message(self, station_id: str, payload: bytes, ack) -> None:
        """An MQTT message on a station's reports topic (the broker's ACL made sure it is that station): handled on
        the station worker thread; rejections go to the station's errors topic. Acknowledged once stored, or at once
        when refused (it would never pass)."""
        self._station_worker.submit(self._handle_station_message, station_id, payload, ack)

    def _handle_station_message(self, station_id: str, payload: bytes, ack) -> None:
        s = self.settings
        try:
            reports = parse_reports(
                payload, station_id=station_id, now_ms=int(time.time() * 1000), max_future_ms=int(s.max_future_s * 1000)
            )
        except ReportError as exc:
            self.mqtt_rejected += 1
            log.warning("rejected a message of station %s over MQTT: %s", station_id, exc)
            self._publish(
                station_errors_topic(station_id),
                json.dumps({"station_id": station_id, "rejected": [exc.to_dict()]}).encode(),
            )
            ack()
            return
        try:
            self.station_reports(reports)
        except StorageUnavailable as exc:
            log.warning("station %s: storage unavailable, its report is left unacknowledged: %s", station_id, exc)
            return
        ack()

    # ------------------------------------------------------------------------------------------------- edge vehicles
    def edge_messages(self, observations: list[dict], heartbeats: list[dict]) -> tuple[EdgeIngest, EdgeIngest]:
        """Store validated observations and heartbeats (roadgrip/cloud/ingest/observations.py) in one transaction,
        the first of each key, and hand the new observations to the map and the warning engine in one call.
        StorageUnavailable when the database is down (nothing stored)."""
        unique = list({(o["vehicle_id"], o["last_ms"]): o for o in reversed(observations)}.values())[::-1]
        beats = list({(h["vehicle_id"], h["timestamp_ms"]): h for h in reversed(heartbeats)}.values())
        new, stored_beats = self.storage.put_edge(unique, beats)
        fresh = [o for o in unique if (o["vehicle_id"], o["last_ms"]) in new]
        self.fanout.observations(fresh)
        return (
            EdgeIngest(len(observations), len(fresh), len(observations) - len(fresh)),
            EdgeIngest(len(heartbeats), stored_beats, len(heartbeats) - stored_beats),
        )

    def observations(self, observations: list[dict]) -> EdgeIngest:
        """Store validated observations and hand the new ones to the map and the warning engine (`edge_messages`)."""
        return self.edge_messages(observations, [])[0]

    def heartbeats(self, heartbeats: list[dict]) -> EdgeIngest:
        """Store validated heartbeats (`edge_messages`)."""
        return self.edge_messages([], heartbeats)[1]

    # ------------------------------------------------------------------------------------------------- registration
    def register_vehicles(self, vehicles: list[tuple[str, VehicleParams]]) -> list[str]:
        """Store each profile and create each vehicle's credential (HTTP and MQTT, one broker reload for all);
        returns their secrets. All or nothing (one transaction): ValueError when a vehicle_id is taken or given
        twice."""
        secrets_ = [new_secret() for _ in vehicles]
        self.storage.register_vehicles(
            [
                (vehicle_id, profile.to_dict(), hash_token(secret))
                for (vehicle_id, profile), secret in zip(vehicles, secrets_)
            ]
        )
        for vehicle_id, _ in vehicles:
            self.ingest.forget_vehicle(vehicle_id)
        if self.broker is not None:
            self.broker.set_users([(v, s, "vehicle", v) for (v, _), s in zip(vehicles, secrets_)])
        return secrets_

    def register_reader(self, name: str) -> str:
        return self._register(name, "reader")

    def register_station(self, station_id: str) -> str:
        """A roadside station's credential (login name = station_id, HTTP and MQTT); returns its secret."""
        return self._register(station_id, "station")

    def _register(self, name: str, role: str) -> str:
        if self.storage.credential(name) is not None:
            raise ValueError(f"credential name {name!r} is already taken")
        secret = self.auth.create(name, role)
        if self.broker is not None:
            self.broker.set_user(name, secret, role)
        return secret

    def revoke(self, name: str) -> bool:
        if name == ADMIN_NAME:
            raise ValueError("the admin credential cannot be revoked; change admin_secret instead")
        revoked = self.auth.revoke(name)
        if self.broker is not None:
            self.broker.remove_user(name)
        return revoked

    # ------------------------------------------------------------------------------------------------- the API's backend
    @property
    def station_mqtt_url(self) -> str | None:
        """Stations report over MQTT to the same broker as vehicles."""
        return self.mqtt_url

    def submit_telemetry(self, vehicle_id: str, samples: list[dict], received: int) -> Future:
        """HTTP telemetry into this process's ingest (rate limit, pipeline): resolves once stored."""
        return self.ingest.submit(vehicle_id, samples, received)

    def current_map(self) -> tuple[FrictionMap, int]:
        return self.friction_map, self.fanout.now_ms()

    def metrics_collector(self) -> ServiceCollector:
        return ServiceCollector(self)

    def health(self) -> dict:
        status = {
            "status": "ok",
            "storage": "ok",
            "mqtt": "off" if self.mqtt is None else ("connected" if self.mqtt.connected else "disconnected"),
        }
        try:
            self.storage.ping()
        except StorageUnavailable as exc:
            status.update(status="unavailable", storage=str(exc))
        ingest = self.ingest.stats()
        if ingest.pop("storage_down"):
            status.update(
                status="unavailable",
                storage=status["storage"] if status["storage"] != "ok" else "writes failing; retrying",
            )
        if self.mqtt is not None and not self.mqtt.connected:
            status["status"] = "degraded" if status["status"] == "ok" else status["status"]
        processes = ingest.get("ingest_processes", [])
        status["pipeline"] = {
            **ingest,
            "fanout_s": self.fanout.busy_s,
            "mqtt_rejected": self.mqtt_rejected,
            "mqtt_unacknowledged": None if self.mqtt is None else self.mqtt.unacknowledged,
            "mqtt_flow": None
            if self.mqtt is None
            else {"deferred": self.mqtt.deferred, "redeliveries": self.mqtt.redeliveries, "drops": self.mqtt.drops},
            "estimate_messages_dropped": self.estimate_messages_dropped,
            "latency": self.fanout.latency.recent(),
            "latency_since_start": self.fanout.latency.since_start(),
            "edge": None if self.edge_intake is None else self.edge_intake.stats(),
            "observation_latency": self.fanout.observation_latency.recent(),
            "observation_latency_since_start": self.fanout.observation_latency.since_start(),
        }
        # the service's processes together: this one and its ingest processes
        own = rss_mb()
        status["memory_rss_mb"] = None if own is None else own + sum(p["rss_mb"] or 0.0 for p in processes)
        return status
