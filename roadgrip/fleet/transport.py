"""How the fleet's terminals reach a running cloud: registration through the admin API, then each vehicle sending
with its own credentials over HTTP (`POST /v1/telemetry`) or MQTT (its telemetry topic, QoS 1)."""

from __future__ import annotations

import json
import logging
import time
from concurrent.futures import ThreadPoolExecutor

import httpx

from roadgrip.cloud.transport.mqtt import UserClient, telemetry_topic

log = logging.getLogger(__name__)

# paho-mqtt waits on its sockets with select(), limited to file descriptors below 1024, three per client.
MAX_MQTT_VEHICLES = 300


class FleetError(RuntimeError):
    """The cloud refused the fleet (registration, credentials, a rejected message)."""


def register_fleet(
    base_url: str, admin_secret: str, vehicles: list[tuple[str, str | dict]]
) -> tuple[dict[str, str], str | None]:
    """Register (vehicle_id, profile) pairs in one call, a profile being a known vehicle's name or a CONTRACTS 3.2
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
        self.futures.append(
            self.pool.submit(
                self.client.post,
                "/v1/telemetry",
                content=body,
                auth=(vehicle_id, self.secrets[vehicle_id]),
                headers={"content-type": "application/x-ndjson"},
            )
        )

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
    waits for every PUBACK.

    `mqtt_url`: one broker, or a list (the nodes of a cluster without a load balancer in front): vehicle k connects to
    the (k mod n)-th. `protocol`: "5", "3.1.1" or "auto" (roadgrip.cloud.transport.mqtt.UserClient); with "auto" the first
    vehicle finds the version the broker takes and the others use it, so that each connects once."""

    def __init__(self, mqtt_url: str | list[str], secrets: dict[str, str], protocol: str = "5"):
        if len(secrets) > MAX_MQTT_VEHICLES:
            raise ValueError(
                f"at most {MAX_MQTT_VEHICLES} MQTT vehicles in one process (paho uses select()), got "
                f"{len(secrets)}: use --transport http or several fleet processes"
            )
        urls = [mqtt_url] if isinstance(mqtt_url, str) else list(mqtt_url)
        if not urls:
            raise ValueError("mqtt_url must name at least one broker, got an empty list")
        self.clients = {}
        for k, (vid, secret) in enumerate(secrets.items()):
            self.clients[vid] = UserClient(urls[k % len(urls)], vid, secret, protocol=protocol).connect()
            protocol = self.clients[vid].protocol
        self.protocol = protocol
        self.pending = []
        self.acknowledged = self.refused = 0

    def send(self, vehicle_id: str, samples: list[dict]) -> None:
        payload = json.dumps(samples[0] if len(samples) == 1 else samples)
        self.pending.append(
            (len(samples), self.clients[vehicle_id].publish_nowait(telemetry_topic(vehicle_id), payload))
        )

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


def read_back(
    base_url: str, admin_secret: str, vehicle_ids: list[str], timeout_s: float = 60.0, poll_s: float = 1.0
) -> dict:
    """What a cloud (any API replica of a cluster) has stored of the fleet: each vehicle's estimates, counted, and the
    cells of the friction map. The telemetry is still on its way through the broker and the workers when the drive
    ends, so this waits until every vehicle has estimates and two polls `poll_s` apart counted the same, or until
    `timeout_s`; `settled` says which. Returns {"estimates": {vehicle_id: n}, "map_cells": n, "settled": bool,
    "wait_s": s}."""
    started = time.monotonic()
    auth = ("admin", admin_secret)
    with httpx.Client(base_url=base_url, auth=auth, timeout=30.0) as client:

        def get(path: str, **params) -> dict:
            try:
                answer = client.get(path, params=params)
            except httpx.HTTPError as exc:
                raise FleetError(f"cannot read from the cloud at {base_url}: {exc}") from None
            if answer.status_code != 200:
                raise FleetError(f"GET {path} failed: HTTP {answer.status_code} {answer.text[:300]}")
            return answer.json()

        previous = None
        while True:
            counts = {vid: len(get(f"/v1/vehicles/{vid}/estimates", limit=100_000)["estimates"]) for vid in vehicle_ids}
            settled = counts == previous and all(counts.values())
            if settled or time.monotonic() - started > timeout_s:
                break
            previous = counts
            time.sleep(poll_s)
        cells = len(get("/v1/map")["features"])
    return {"estimates": counts, "map_cells": cells, "settled": settled, "wait_s": time.monotonic() - started}
