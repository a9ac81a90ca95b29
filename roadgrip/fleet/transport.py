"""How the fleet's terminals reach a running cloud: registration through the admin API, then each vehicle sending
with its own credentials over HTTP (`POST /v1/telemetry`) or MQTT (its telemetry topic, QoS 1).

Over MQTT each vehicle holds one `FailoverConnection`: a paho-mqtt client that knows every broker endpoint (its
assigned one first) and moves to the next when its connection is lost (docs/FLEET.md, "Failover"):

- reconnects in paho's network thread (`reconnect_delay_set`: from a minimum doubling up to RECONNECT_MAX_DELAY_S),
  the minimum drawn afresh at random in [0.5, 1.5] x RECONNECT_MIN_DELAY_S for every outage (jitter: the vehicles
  that lose one node do not come back in step); each attempt goes to the next endpoint in the list (paho's
  `connect_async` sets it), so the first attempt after a node dies already goes to another one;
- a persistent session (client id = vehicle_id; MQTT 5: clean start off and a session expiry of SESSION_EXPIRY_S;
  MQTT 3.1.1: clean session off). A broker that keeps the session (the same node, Mosquitto) resumes it; RabbitMQ
  3.10's sessions live on one node, so after a move there is none: either way paho resends every message that was
  not PUBACKed (with DUP set; the cloud keys telemetry by vehicle and timestamp, so a duplicate is stored once);
- a bounded buffer: paho keeps every message not yet PUBACKed (in flight, queued, or produced while disconnected),
  at most `buffer_messages` (BUFFER_MESSAGES, 6,000: 10 minutes of a terminal sending every 100 ms). When it is full
  a new message is not queued: its samples are counted as dropped (lost), with a warning, never silently;
- counting by PUBACK: `on_publish` (message id and reason code) tells acknowledged from refused (MQTT 5 reason code
  of failure); what is still unacknowledged when the connection is closed is counted as lost too.
"""

from __future__ import annotations

import json
import logging
import random
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import httpx
import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode

from roadgrip.cloud.ingest.wire import arrow_payload
from roadgrip.cloud.transport.mqtt import MQTT_PROTOCOLS, QOS, UserClient, parse_url, telemetry_topic

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


PAYLOADS = ("json", "arrow")  # how raw terminals encode their samples (CONTRACTS 3.1)
ARROW_CONTENT_TYPE = "application/vnd.apache.arrow.stream"


def _checked_payload(payload: str) -> str:
    if payload not in PAYLOADS:
        raise ValueError(f"payload must be one of {PAYLOADS}, got {payload!r}")
    return payload


class HttpTerminals:
    """Every vehicle posts its own batches; requests run on a small thread pool so that one slow answer does not hold
    the 10 Hz timeline. `close()` waits for the answers and counts them, in samples: `sent`, `stored` (the cloud's
    answer), `rejected` (refused by validation), `lost` (a request that failed or was answered with an error: the
    first such error is in `error`). It raises nothing for a failed request."""

    def __init__(self, base_url: str, secrets: dict[str, str], workers: int = 8, payload: str = "json"):
        self.payload = _checked_payload(payload)
        self.secrets = secrets
        self.client = httpx.Client(base_url=base_url, timeout=60.0)
        self.pool = ThreadPoolExecutor(workers)
        self.futures = []
        self.sent = self.stored = self.rejected = self.lost = 0
        self.error: str | None = None

    def send(self, vehicle_id: str, samples: list[dict]) -> None:
        if self.payload == "arrow":
            body, content_type = arrow_payload(samples), ARROW_CONTENT_TYPE
        else:
            body, content_type = "\n".join(json.dumps(s) for s in samples), "application/x-ndjson"
        self.sent += len(samples)
        self.futures.append(
            (
                len(samples),
                self.pool.submit(
                    self.client.post,
                    "/v1/telemetry",
                    content=body,
                    auth=(vehicle_id, self.secrets[vehicle_id]),
                    headers={"content-type": content_type},
                ),
            )
        )

    def close(self) -> None:
        try:
            for n, future in self.futures:
                try:
                    answer = future.result()
                except httpx.HTTPError as exc:
                    self._lose(n, f"a request failed: {exc}")
                    continue
                if answer.status_code != 200:
                    self._lose(n, f"the cloud refused a batch: HTTP {answer.status_code} {answer.text[:300]}")
                    continue
                result = answer.json()
                self.stored += result["stored"]
                self.rejected += len(result["rejected"])
            self.futures = []
        finally:
            self.pool.shutdown()
            self.client.close()

    def _lose(self, samples: int, error: str) -> None:
        self.lost += samples
        if self.error is None:
            self.error = error
            log.warning("%s (its samples are counted lost)", error)


BUFFER_MESSAGES = 6_000  # per vehicle, messages not yet PUBACKed: 10 min of one message every 100 ms
RECONNECT_MIN_DELAY_S = 0.25  # the first wait after a lost connection, drawn in [0.5, 1.5] x this per outage
RECONNECT_MAX_DELAY_S = 4.0  # paho doubles the wait after each failed attempt, up to this
KEEPALIVE_S = 10  # a silent broker (no answer to PINGREQ) is taken for lost after 1.5 x this
SESSION_EXPIRY_S = 3_600  # MQTT 5: how long the broker keeps a vehicle's session after it is gone
CONNECT_TIMEOUT_S = 30.0  # the most `MqttTerminals` waits for every vehicle's first connection
REFUSED_LOGIN = (0x86, 0x87)  # CONNACK: bad user name or password, not authorized (3.1.1's 4 and 5, as paho maps them)


@dataclass
class VehicleCounts:
    """What one vehicle's connection did, in samples (a message carries one or more): handed to it (`sent`),
    PUBACKed (`acknowledged`), refused in a PUBACK (`refused`, MQTT 5), not queued because the buffer was full
    (`dropped`), and still unacknowledged when it closed (`unacknowledged`). Connections: `connects` (the first
    included), `moves` (connects to another endpoint than the previous connection's), `endpoint` (the last one
    connected), `longest_outage_s` (the longest time from a lost connection to the next CONNACK)."""

    sent: int = 0
    acknowledged: int = 0
    refused: int = 0
    dropped: int = 0
    unacknowledged: int = 0
    connects: int = 0
    moves: int = 0
    endpoint: str | None = None
    longest_outage_s: float = 0.0

    @property
    def lost(self) -> int:
        return self.refused + self.dropped + self.unacknowledged


class FailoverConnection:
    """One vehicle's MQTT connection over `endpoints` (mqtt:// URLs, the assigned one first), as the module docstring
    says. `start()` connects in the background; `publish(payload, samples)` queues one message of `samples`
    samples (False when the buffer is full); `wait_connected(timeout_s)`; `close(timeout_s)` waits for the PUBACKs
    and disconnects. `counts` is a `VehicleCounts`. `clock` (monotonic seconds) times the outages and `rng` draws the
    jitter: injected in tests."""

    def __init__(
        self,
        endpoints: list[str],
        vehicle_id: str,
        secret: str,
        *,
        protocol: str = "5",
        buffer_messages: int = BUFFER_MESSAGES,
        keepalive_s: int = KEEPALIVE_S,
        reconnect_min_delay_s: float = RECONNECT_MIN_DELAY_S,
        reconnect_max_delay_s: float = RECONNECT_MAX_DELAY_S,
        clock=time.monotonic,
        rng: random.Random | None = None,
    ):
        if not endpoints:
            raise ValueError(f"endpoints must name at least one broker for {vehicle_id!r}, got an empty list")
        if protocol not in MQTT_PROTOCOLS:
            raise ValueError(f"protocol must be one of {list(MQTT_PROTOCOLS)}, got {protocol!r}")
        if buffer_messages < 1:
            raise ValueError(f"buffer_messages must be >= 1, got {buffer_messages}")
        if not 0 < reconnect_min_delay_s <= reconnect_max_delay_s:
            raise ValueError(
                f"need 0 < reconnect_min_delay_s <= reconnect_max_delay_s, got {reconnect_min_delay_s}, "
                f"{reconnect_max_delay_s}"
            )
        self.endpoints = [parse_url(url) for url in endpoints]
        self.urls = list(endpoints)
        self.vehicle_id = vehicle_id
        self.topic = telemetry_topic(vehicle_id)
        self.protocol = protocol
        self.buffer_messages = buffer_messages
        self.keepalive_s = keepalive_s
        self.reconnect_min_delay_s = reconnect_min_delay_s
        self.reconnect_max_delay_s = reconnect_max_delay_s
        self.counts = VehicleCounts()
        self.refusal: ReasonCode | None = None  # the CONNACK that refused the login, when one did
        self._clock = clock
        self._rng = rng or random.Random()
        self._lock = threading.Lock()
        self._settled = threading.Condition(self._lock)  # notified on every PUBACK and every CONNACK
        self._pending: dict[int, int] = {}  # samples by message id, not yet PUBACKed
        self._early: dict[int, ReasonCode] = {}  # PUBACKs that came before publish() returned their message id
        self._target = 0  # index of the endpoint the next connection attempt goes to
        self._connected_to: int | None = None  # index of the endpoint of the previous connection
        self._lost_at: float | None = None
        self._closing = False  # no reconnecting any more: closed, or the login refused
        self._stopped = False
        v5 = protocol == "5"
        self._client = paho.Client(
            CallbackAPIVersion.VERSION2,
            client_id=vehicle_id,
            protocol=MQTT_PROTOCOLS[protocol],
            clean_session=None if v5 else False,
        )
        self._client.username_pw_set(vehicle_id, secret)
        self._client.max_queued_messages_set(buffer_messages)
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = self._on_disconnect
        self._client.on_connect_fail = self._on_connect_fail
        self._client.on_publish = self._on_publish
        self._properties = None
        if v5:
            self._properties = Properties(PacketTypes.CONNECT)
            self._properties.SessionExpiryInterval = SESSION_EXPIRY_S

    @property
    def connected(self) -> bool:
        return self._client.is_connected()

    @property
    def unacknowledged_messages(self) -> int:
        with self._lock:
            return len(self._pending)

    def start(self) -> None:
        """Connect to the first endpoint in paho's network thread (which goes on to the others when it fails)."""
        self._jitter()
        self._aim(0)
        self._lost_at = self._clock()
        self._client.loop_start()

    def wait_connected(self, timeout_s: float) -> bool:
        """True once connected (or connected before); False after `timeout_s`, or at once when the login was refused
        (`refusal` says why)."""
        with self._settled:
            return self._settled.wait_for(lambda: self.counts.connects > 0 or self.refusal is not None, timeout_s) and (
                self.refusal is None
            )

    def publish(self, payload: bytes | str, samples: int) -> bool:
        """Queue one message of `samples` samples at QoS 1; False (the samples counted as dropped) when the buffer
        is full. Connected or not: paho sends it once connected."""
        info = self._client.publish(self.topic, payload, qos=QOS)
        with self._lock:
            self.counts.sent += samples
            if info.rc == MQTTErrorCode.MQTT_ERR_QUEUE_SIZE:
                self.counts.dropped += samples
                if self.counts.dropped == samples:
                    log.warning(
                        "%s: %d messages wait for their PUBACK (the buffer is full): new samples are dropped "
                        "and counted as lost",
                        self.vehicle_id,
                        self.buffer_messages,
                    )
                return False
            early = self._early.pop(info.mid, None)
            if early is None:
                self._pending[info.mid] = samples
            else:
                self._count_puback(samples, early)
        return True

    def close(self, timeout_s: float = 60.0) -> VehicleCounts:
        """Wait up to `timeout_s` for every queued message's PUBACK (reconnecting meanwhile if needed), then
        disconnect and stop the network thread; what is still unacknowledged is counted as lost. Idempotent."""
        with self._settled:
            self._settled.wait_for(lambda: not self._pending or self.refusal is not None, timeout_s)
            if self._stopped:
                return self.counts
            self._closing = self._stopped = True
        self._client.disconnect()
        self._client.loop_stop()
        with self._lock:
            self.counts.unacknowledged = sum(self._pending.values())
            self._pending.clear()
        return self.counts

    # paho callbacks, on paho's network thread

    def _aim(self, index: int) -> None:
        """The next connection attempt goes to endpoint `index` (paho's connect_async only sets where to)."""
        self._target = index % len(self.endpoints)
        host, port = self.endpoints[self._target]
        if self.protocol == "5":
            self._client.connect_async(
                host, port, keepalive=self.keepalive_s, clean_start=False, properties=self._properties
            )
        else:
            self._client.connect_async(host, port, keepalive=self.keepalive_s)

    def _jitter(self) -> None:
        low = self.reconnect_min_delay_s * self._rng.uniform(0.5, 1.5)
        self._client.reconnect_delay_set(min(low, self.reconnect_max_delay_s), self.reconnect_max_delay_s)

    def _on_connect(self, client, _userdata, flags, reason_code, _properties):
        if reason_code.is_failure:
            log.warning("%s: %s refused the connection: %s", self.vehicle_id, self.urls[self._target], reason_code)
            if reason_code.value in REFUSED_LOGIN:
                with self._settled:
                    self.refusal = reason_code
                    self._closing = True
                    self._settled.notify_all()
                client.disconnect()  # a login refused here is refused everywhere: stop trying
            return
        with self._settled:
            if self._connected_to is not None and self._connected_to != self._target:
                self.counts.moves += 1
                log.info("%s: moved to %s", self.vehicle_id, self.urls[self._target])
            if self._lost_at is not None and self.counts.connects:
                self.counts.longest_outage_s = max(self.counts.longest_outage_s, self._clock() - self._lost_at)
            self._lost_at = None
            self._connected_to = self._target
            self.counts.connects += 1
            self.counts.endpoint = self.urls[self._target]
            self._settled.notify_all()

    def _on_disconnect(self, _client, _userdata, _flags, reason_code, _properties):
        with self._lock:
            if self._closing:
                return
            if self._lost_at is None:
                self._lost_at = self._clock()
            log.warning(
                "%s: connection to %s lost (%s); %d messages unacknowledged, trying %s",
                self.vehicle_id,
                self.urls[self._target],
                reason_code,
                len(self._pending),
                self.urls[(self._target + 1) % len(self.urls)],
            )
        self._jitter()
        self._aim(self._target + 1)

    def _on_connect_fail(self, _client, _userdata):
        if not self._closing:
            self._aim(self._target + 1)

    def _on_publish(self, _client, _userdata, mid, reason_code, _properties):
        with self._settled:
            samples = self._pending.pop(mid, None)
            if samples is None:
                self._early[mid] = reason_code  # publish() has not yet recorded this message id
            else:
                self._count_puback(samples, reason_code)
            self._settled.notify_all()

    def _count_puback(self, samples: int, reason_code: ReasonCode) -> None:
        if reason_code.is_failure:
            self.counts.refused += samples
            log.warning("%s: the broker refused a publish: %s", self.vehicle_id, reason_code)
        else:
            self.counts.acknowledged += samples


class MqttTerminals:
    """One `FailoverConnection` per vehicle, logged in as that vehicle (module docstring).

    `mqtt_url`: one broker, or a list (the nodes of a cluster without a load balancer in front): vehicle k is assigned
    the (k mod n)-th and holds the others, in order after it, to fail over to. `protocol`: "5", "3.1.1" or "auto"
    (MQTT 5, else 3.1.1 when the broker does not take 5: RabbitMQ 3.10), found once with the first vehicle's login.
    Returns once every vehicle has connected (FleetError when a login is refused or a vehicle reaches no broker
    within `connect_timeout_s`). `close()` waits for the PUBACKs, never raises for a lost connection, and leaves
    the counts in `counts` (per vehicle), `acknowledged`, `refused` and `lost` (samples)."""

    def __init__(
        self,
        mqtt_url: str | list[str],
        secrets: dict[str, str],
        protocol: str = "5",
        *,
        buffer_messages: int = BUFFER_MESSAGES,
        reconnect_min_delay_s: float = RECONNECT_MIN_DELAY_S,
        reconnect_max_delay_s: float = RECONNECT_MAX_DELAY_S,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
        clock=time.monotonic,
        rng: random.Random | None = None,
        payload: str = "json",
    ):
        self.payload = _checked_payload(payload)
        if len(secrets) > MAX_MQTT_VEHICLES:
            raise ValueError(
                f"at most {MAX_MQTT_VEHICLES} MQTT vehicles in one process (paho uses select()), got "
                f"{len(secrets)}: use --transport http or several fleet processes"
            )
        urls = [mqtt_url] if isinstance(mqtt_url, str) else list(mqtt_url)
        if not urls:
            raise ValueError("mqtt_url must name at least one broker, got an empty list")
        if protocol == "auto" and secrets:
            protocol = protocol_of(urls, *next(iter(secrets.items())))
        self.protocol = protocol
        self.urls = urls
        rng = rng or random.Random()
        self.connections = {
            vid: FailoverConnection(
                urls[k % len(urls) :] + urls[: k % len(urls)],
                vid,
                secret,
                protocol=protocol,
                buffer_messages=buffer_messages,
                reconnect_min_delay_s=reconnect_min_delay_s,
                reconnect_max_delay_s=reconnect_max_delay_s,
                clock=clock,
                rng=random.Random(rng.random()),
            )
            for k, (vid, secret) in enumerate(secrets.items())
        }
        for connection in self.connections.values():
            connection.start()
        deadline = time.monotonic() + connect_timeout_s
        for vid, connection in self.connections.items():
            if not connection.wait_connected(max(0.0, deadline - time.monotonic())):
                self.close(timeout_s=0.0)
                if connection.refusal is not None:
                    raise FleetError(
                        f"the broker refused {vid!r}'s login: {connection.refusal} (is the vehicle registered?)"
                    )
                raise FleetError(f"{vid} reached none of the brokers {urls} within {connect_timeout_s:.0f} s")

    def send(self, vehicle_id: str, samples: list[dict]) -> None:
        if self.payload == "arrow":
            payload = arrow_payload(samples)
        else:
            payload = json.dumps(samples[0] if len(samples) == 1 else samples)
        self.connections[vehicle_id].publish(payload, len(samples))

    def close(self, timeout_s: float = 60.0) -> None:
        """Wait up to `timeout_s` in all for the PUBACKs, then disconnect every vehicle (module docstring)."""
        deadline = time.monotonic() + timeout_s
        for connection in self.connections.values():
            connection.close(max(0.0, deadline - time.monotonic()))

    @property
    def counts(self) -> dict[str, VehicleCounts]:
        return {vid: c.counts for vid, c in self.connections.items()}

    @property
    def acknowledged(self) -> int:
        return sum(c.acknowledged for c in self.counts.values())

    @property
    def refused(self) -> int:
        return sum(c.refused for c in self.counts.values())

    @property
    def lost(self) -> int:
        return sum(c.lost for c in self.counts.values())


def protocol_of(urls: list[str], vehicle_id: str, secret: str) -> str:
    """The MQTT version the brokers take ("5" or "3.1.1"), asked of the first that answers, as `vehicle_id`."""
    failures = []
    for url in urls:
        try:
            probe = UserClient(url, vehicle_id, secret, protocol="auto").connect()
        except OSError as exc:  # ConnectionError, BrokerRefused and TimeoutError included
            failures.append(f"{url}: {exc}")
            continue
        probe.close()
        return probe.protocol
    raise FleetError(f"no broker answered {vehicle_id!r}: {'; '.join(failures)}")


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
