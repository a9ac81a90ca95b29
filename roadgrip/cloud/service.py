"""The cloud service assembled from its parts: storage, credentials, the pipeline (estimation, map, warnings), the MQTT
side (a broker given by URL, or a Mosquitto started here), and the HTTP API.

    service = CloudService(load_settings())
    service.start()          # storage opened, pipeline running, MQTT connected when configured
    app = create_app(service) # roadgrip.cloud.api
    ...
    service.stop()
"""

from __future__ import annotations

import gc
import json
import logging
import secrets
import time
from pathlib import Path
from typing import Self

from roadgrip.cloud.auth import ADMIN_NAME, Authenticator, hash_token, new_secret
from roadgrip.cloud.broker import MAX_INFLIGHT_MESSAGES, ManagedBroker, mosquitto_available
from roadgrip.cloud.friction_map import FrictionMap
from roadgrip.cloud.mqtt import DEFAULT_MAX_INFLIGHT, MqttClient, errors_topic
from roadgrip.cloud.pipeline import Pipeline
from roadgrip.cloud.ratelimit import RateLimiter
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage import Storage, StorageUnavailable, open_storage
from roadgrip.cloud.warning_engine import WarningEngine, WarningEvent
from roadgrip.cloud.wire import PayloadError, parse_payload
from roadgrip.estimators.learned import load_estimator
from roadgrip.vehicle.params import PAPER_SUV, VehicleParams

log = logging.getLogger(__name__)

# Samples the MQTT side may queue for the pipeline (2 s of 1,000 vehicles at 10 Hz). Beyond it the MQTT handler waits,
# so paho's network thread stops reading: TCP pushes back and the broker keeps the rest in the service's persistent
# session, unacknowledged. (Mosquitto 2.0.11 did not stop at the client's Receive Maximum in the soak of
# docs/RELIABILITY.md: the service queued 116,000 messages and its memory grew; this bound is the service's own.) It
# also bounds a round: with 100,000 a service that fell behind ran rounds of 10 s and more, and each added its queue
# to the RSS for good (the allocator keeps its peak), where the broker holds a waiting message in 0.3 kB.
MAX_MQTT_BACKLOG = 20_000
# Estimate messages (one per vehicle a second) the service lets wait for the broker before it drops new ones rather
# than queue them (5 s of 1,000 vehicles). When the broker takes them slower than they come, paho would hold up to
# max_queued_messages (100,000) in memory, several kB each (ten estimates): run d of docs/RELIABILITY.md grew by 950 MB
# in a stall; run e, with this bound, stayed level at 606 MB until its stall. The estimates stay stored and readable
# over HTTP; warnings and error reports are never dropped.
MAX_UNACKNOWLEDGED_ESTIMATES = 5_000


# The young generation's collection threshold (CPython's default: 700 allocations): the ingest path allocates about a
# dozen containers a sample (dicts, tuples, futures), so at 10,000 samples/s the default collects some 170 times a
# second.
SERVING_GC_THRESHOLD = 50_000


def tune_gc_for_serving() -> None:
    """For a process that is the service (`roadgrip serve`), once it has started: move what exists now (modules,
    numba and torch, the settings, the restored map) out of the collector's sight (`gc.freeze`) and collect the young
    generation every SERVING_GC_THRESHOLD allocations.
    Collection took 2.4 s instead of 7.4 s over the 40 s of `python scripts/pipeline_cost.py --seconds 40`.
    Process-wide, hence not done by `CloudService.start`, which tests call many times in one process."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(SERVING_GC_THRESHOLD, *gc.get_threshold()[1:])


def _rss_mb() -> float | None:
    """The process's resident memory (Linux /proc), MB."""
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return None
    rss = [line for line in status.splitlines() if line.startswith("VmRSS:")]
    return int(rss[0].split()[1]) / 1024.0 if rss else None


def _warm_up(estimator) -> None:
    """One update on a made-up sample, so that compiling (or loading from numba's cache) the estimator's kernels
    happens before the service says it is up, not in the pipeline's first round (~15 s cold)."""
    state = estimator.start(PAPER_SUV)
    sample = {"vehicle_id": "warm-up", "timestamp_ms": 0, "latitude_deg": None, "longitude_deg": None,
              "speed_mps": 20.0, "accel_lon_mps2": 0.0, "accel_lat_mps2": 0.0, "yaw_rate_radps": 0.0,
              "steering_wheel_angle_rad": 0.0, "abs_active": False, "acc_active": False, "lateral_speed_mps": None,
              **{f"wheel_speed_{w}_radps": 20.0 / PAPER_SUV.wheel_radius_m for w in ("fl", "fr", "rl", "rr")}}
    for k in range(12):  # a learned model's window fills before it estimates
        estimator.update(state, {**sample, "timestamp_ms": 100 * k})


class CloudService:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.storage: Storage | None = None
        self.auth: Authenticator | None = None
        self.pipeline: Pipeline | None = None
        self.broker: ManagedBroker | None = None
        self.mqtt: MqttClient | None = None
        self.mqtt_url: str | None = None
        self.admin_secret: str | None = None
        self.friction_map = FrictionMap(settings.h3_resolution, settings.map_half_life_s, settings.map_max_age_s)
        self.warning_engine = WarningEngine(
            resolution=settings.h3_resolution, threshold_mu=settings.warning_threshold_mu,
            min_low_passes=settings.warning_min_low_passes, min_dry_passes=settings.warning_min_dry_passes,
            pass_gap_s=settings.warning_pass_gap_s, min_excited_per_pass=settings.warning_min_excited_per_pass,
            validity_s=settings.warning_validity_s, station_id=settings.station_id)
        self.mqtt_rejected = 0
        self.estimate_messages_dropped = 0
        self.rate_limiter = RateLimiter(settings.rate_limit_samples_per_s, settings.rate_limit_burst_s)

    # ------------------------------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        s = self.settings
        s.data_dir.mkdir(parents=True, exist_ok=True)
        self.storage = open_storage(s.storage_url)
        self.auth = Authenticator(self.storage)
        self.admin_secret = s.admin_secret or self._stored_admin_secret()
        self.auth.ensure_admin(self.admin_secret)
        self._restore_map()
        estimator = load_estimator(s.estimator)
        _warm_up(estimator)
        self.pipeline = Pipeline(self.storage, s, estimator, self.friction_map, self.warning_engine,
                                 publish=self._publish)
        self.pipeline.start()
        self._start_mqtt()
        log.info("cloud started: storage %s, mqtt %s, estimator %s", self.storage, self.mqtt_url or "off",
                 estimator.name)

    def stop(self) -> None:
        if self.mqtt is not None:
            self.mqtt.close()
            self.mqtt = None
        if self.pipeline is not None:
            self.pipeline.stop()
            self.pipeline = None
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
        log.info("restored the map from %d stored estimates and %d active warnings", len(rows), len(active))

    # ------------------------------------------------------------------------------------------------- MQTT
    def _start_mqtt(self) -> None:
        s = self.settings
        mode = s.mqtt
        if mode == "off":
            return
        if mode in ("auto", "managed"):
            if not mosquitto_available():
                if mode == "managed":
                    raise RuntimeError("mqtt=managed but mosquitto is not installed: run "
                                       "`bash scripts/install_system_deps.sh` or set mqtt to a broker URL")
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
        self.mqtt = MqttClient(self.mqtt_url, username, password, client_id="roadgrip-cloud",
                               on_telemetry=self._on_mqtt_telemetry,
                               max_inflight=MAX_INFLIGHT_MESSAGES if self.broker is not None else DEFAULT_MAX_INFLIGHT)
        self.mqtt.connect()

    def _publish(self, topic: str, payload: bytes) -> None:
        if self.mqtt is None:
            return
        if topic.rsplit("/", 1)[-1] == "friction" and self.mqtt.unacknowledged > MAX_UNACKNOWLEDGED_ESTIMATES:
            self.estimate_messages_dropped += 1
            if self.estimate_messages_dropped % 1000 == 1:
                log.warning("%d publishes wait for the broker: dropped %d estimate messages so far (the estimates "
                            "are stored)", self.mqtt.unacknowledged, self.estimate_messages_dropped)
            return
        self.mqtt.publish(topic, payload)

    def _on_mqtt_telemetry(self, vehicle_id: str, payload: bytes, ack) -> None:
        """One MQTT message from a vehicle (the broker's ACL made sure it is that vehicle): parse, report rejections on
        the vehicle's error topic, queue the valid samples, acknowledge once they are stored."""
        try:
            samples, errors = parse_payload(payload, now_ms=int(time.time() * 1000), vehicle_id=vehicle_id,
                                            max_bytes=self.settings.max_payload_bytes,
                                            max_samples=self.settings.max_samples_per_payload,
                                            max_future_ms=int(self.settings.max_future_s * 1000))
        except PayloadError as exc:
            self._reject_mqtt(vehicle_id, [{"index": None, "field": exc.field, "reason": str(exc)}])
            ack()
            return
        decision = self.rate_limiter.allow(vehicle_id, len(samples) + len(errors), time.monotonic())
        if not decision.allowed:  # acknowledged all the same: the broker must not deliver it again
            self._reject_mqtt(vehicle_id, [{"index": None, "field": None, "reason": decision.reason}])
            ack()
            return
        if errors:
            self._reject_mqtt(vehicle_id, [e.to_dict() for e in errors])
        if not samples:
            ack()
            return
        while self.pipeline.backlog > MAX_MQTT_BACKLOG and self.pipeline.running:
            time.sleep(0.01)  # backpressure: paho reads no more until the pipeline has caught up (module docstring)
        future = self.pipeline.submit(vehicle_id, samples, retry=True)
        future.add_done_callback(lambda f: ack() if f.exception() is None else None)

    def _reject_mqtt(self, vehicle_id: str, errors: list[dict]) -> None:
        self.mqtt_rejected += len(errors)
        log.warning("rejected %d sample(s) from vehicle %s over MQTT: %s", len(errors), vehicle_id,
                    errors[0]["reason"])
        # json, not orjson: a reason quotes what was sent, which may hold a lone surrogate (escaped by json)
        self._publish(errors_topic(vehicle_id), json.dumps({"vehicle_id": vehicle_id, "rejected": errors}).encode())

    # ------------------------------------------------------------------------------------------------- registration
    def register_vehicles(self, vehicles: list[tuple[str, VehicleParams]]) -> list[str]:
        """Store each profile and create each vehicle's credential (HTTP and MQTT, one broker reload for all);
        returns their secrets. All or nothing (one transaction): ValueError when a vehicle_id is taken or given
        twice."""
        secrets_ = [new_secret() for _ in vehicles]
        self.storage.register_vehicles([(vehicle_id, profile.to_dict(), hash_token(secret))
                                        for (vehicle_id, profile), secret in zip(vehicles, secrets_)])
        for vehicle_id, _ in vehicles:
            self.pipeline.forget_vehicle(vehicle_id)
        if self.broker is not None:
            self.broker.set_users([(v, s, "vehicle", v) for (v, _), s in zip(vehicles, secrets_)])
        return secrets_

    def register_reader(self, name: str) -> str:
        if self.storage.credential(name) is not None:
            raise ValueError(f"credential name {name!r} is already taken")
        secret = self.auth.create(name, "reader")
        if self.broker is not None:
            self.broker.set_user(name, secret, "reader")
        return secret

    def revoke(self, name: str) -> bool:
        if name == ADMIN_NAME:
            raise ValueError("the admin credential cannot be revoked; change admin_secret instead")
        revoked = self.auth.revoke(name)
        if self.broker is not None:
            self.broker.remove_user(name)
        return revoked

    def health(self) -> dict:
        status = {"status": "ok", "storage": "ok", "mqtt": "off" if self.mqtt is None else
                  ("connected" if self.mqtt.connected else "disconnected")}
        try:
            self.storage.ping()
        except StorageUnavailable as exc:
            status.update(status="unavailable", storage=str(exc))
        if self.pipeline.storage_down:
            status.update(status="unavailable", storage=status["storage"] if status["storage"] != "ok"
                          else "writes failing; retrying")
        if self.mqtt is not None and not self.mqtt.connected:
            status["status"] = "degraded" if status["status"] == "ok" else status["status"]
        status["pipeline"] = {**self.pipeline.counters.to_dict(), "backlog": self.pipeline.backlog,
                              "mqtt_rejected": self.mqtt_rejected,
                              "mqtt_unacknowledged": None if self.mqtt is None else self.mqtt.unacknowledged,
                              "estimate_messages_dropped": self.estimate_messages_dropped,
                              "latency": self.pipeline.latency.recent(),
                              "latency_since_start": self.pipeline.latency.since_start()}
        status["memory_rss_mb"] = _rss_mb()
        return status
