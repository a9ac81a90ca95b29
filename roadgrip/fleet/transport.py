"""How the fleet's terminals reach a running cloud: registration through the admin API, then each vehicle sending
with its own credentials over HTTP (`POST /v1/telemetry`) or MQTT (its telemetry topic, QoS 1)."""

from __future__ import annotations

import json
import logging
from concurrent.futures import ThreadPoolExecutor

import httpx

from roadgrip.cloud.edge.mqtt import UserClient, telemetry_topic

log = logging.getLogger(__name__)

# paho-mqtt waits on its sockets with select(), limited to file descriptors below 1024, three per client.
MAX_MQTT_VEHICLES = 300


class FleetError(RuntimeError):
    """The cloud refused the fleet (registration, credentials, a rejected message)."""


def register_fleet(base_url: str, admin_secret: str,
                   vehicles: list[tuple[str, str | dict]]) -> tuple[dict[str, str], str | None]:
    """Register (vehicle_id, profile) pairs in one call, a profile being a known vehicle's name or a DESIGN 3.2
    mapping; returns {vehicle_id: secret} and the broker's URL (None without one)."""
    body = [{"vehicle_id": vehicle_id, "profile": profile} for vehicle_id, profile in vehicles]
    try:
        answer = httpx.post(f"{base_url}/v1/vehicles", json=body, auth=("admin", admin_secret), timeout=120.0)
    except httpx.HTTPError as exc:
        raise FleetError(f"cannot reach the cloud at {base_url}: {exc}") from None
    if answer.status_code != 201:
        raise FleetError(f"registering the fleet failed: HTTP {answer.status_code} {answer.text[:300]}")
    issued = answer.json()
    return {c["name"]: c["secret"] for c in issued}, issued[0]["mqtt_url"]


class HttpTerminals:
    """Every vehicle posts its own batches; requests run on a small thread pool so that one slow answer does not hold
    the 10 Hz timeline. `close()` waits for the answers and checks them."""

    def __init__(self, base_url: str, secrets: dict[str, str], workers: int = 8):
        self.secrets = secrets
        self.client = httpx.Client(base_url=base_url, timeout=60.0)
        self.pool = ThreadPoolExecutor(workers)
        self.futures = []
        self.stored = self.rejected = 0

    def send(self, vehicle_id: str, samples: list[dict]) -> None:
        body = "\n".join(json.dumps(s) for s in samples)
        self.futures.append(self.pool.submit(
            self.client.post, "/v1/telemetry", content=body, auth=(vehicle_id, self.secrets[vehicle_id]),
            headers={"content-type": "application/x-ndjson"}))

    def close(self) -> None:
        try:
            for future in self.futures:
                answer = future.result()
                if answer.status_code != 200:
                    raise FleetError(f"the cloud refused a batch: HTTP {answer.status_code} {answer.text[:300]}")
                result = answer.json()
                self.stored += result["stored"]
                self.rejected += len(result["rejected"])
        finally:
            self.pool.shutdown()
            self.client.close()


class MqttTerminals:
    """One MQTT connection per vehicle, logged in as that vehicle; messages are queued in paho (QoS 1) and `close()`
    waits for every PUBACK."""

    def __init__(self, mqtt_url: str, secrets: dict[str, str]):
        if len(secrets) > MAX_MQTT_VEHICLES:
            raise ValueError(f"at most {MAX_MQTT_VEHICLES} MQTT vehicles in one process (paho uses select()), got "
                             f"{len(secrets)}: use --transport http or several fleet processes")
        self.clients = {vid: UserClient(mqtt_url, vid, secret).connect() for vid, secret in secrets.items()}
        self.pending = []
        self.acknowledged = self.refused = 0

    def send(self, vehicle_id: str, samples: list[dict]) -> None:
        payload = json.dumps(samples[0] if len(samples) == 1 else samples)
        self.pending.append((len(samples), self.clients[vehicle_id].publish_nowait(telemetry_topic(vehicle_id),
                                                                                   payload)))

    def close(self, timeout_s: float = 60.0) -> None:
        try:
            for n, info in self.pending:
                info.wait_for_publish(timeout_s)
                if info.is_published():
                    self.acknowledged += n
            self.refused = sum(c.refused for c in self.clients.values())
        finally:
            for client in self.clients.values():
                client.close()
