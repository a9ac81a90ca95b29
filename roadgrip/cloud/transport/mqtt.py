"""The cloud's MQTT side (CONTRACTS 3.6): the topic names, the service's connection (`MqttClient`), and small clients for
the other logins: `VehicleClient` for vehicles (and the fleet simulator), `UserClient` for any login (readers, tests).
The broker itself is `roadgrip.cloud.transport.mosquitto`.

Topics, all QoS 1; this module is the one place that spells them:

| topic                                       | published by            | read by                 |
| ------------------------------------------- | ----------------------- | ----------------------- |
| roadgrip/v1/vehicles/{vehicle_id}/telemetry | the vehicle             | the service             |
| roadgrip/v1/vehicles/{vehicle_id}/friction  | the service (estimates) | that vehicle, readers   |
| roadgrip/v1/vehicles/{vehicle_id}/errors    | the service (rejected)  | that vehicle            |
| roadgrip/v1/vehicles/{vehicle_id}/observations | the vehicle (edge)   | the service             |
| roadgrip/v1/vehicles/{vehicle_id}/heartbeat | the vehicle (edge)      | the service             |
| roadgrip/v1/warnings                        | the service             | every vehicle, readers  |
| roadgrip/v1/warnings/uper                   | the service (UPER DENM) | every vehicle, readers  |
| roadgrip/v1/stations/{station_id}/reports   | the roadside station    | the service             |
| roadgrip/v1/stations/{station_id}/errors    | the service (rejected)  | that station            |

What Mosquitto 2.0.11 answers to a request outside a client's ACL (tests/cloud/transport/test_mqtt.py pins each of these):

- PUBLISH at QoS 1 under MQTT 5: PUBACK with reason code 0x87 (Not authorized); the message is dropped and the connection
  stays up. `UserClient` and `VehicleClient` speak MQTT 5 and raise `PublishRefused`. Under MQTT 3.1.1 the PUBACK has no reason code:
  the publisher sees a success and the message is silently dropped. At QoS 0 nobody can tell.
- SUBSCRIBE: granted (SUBACK 0x01); the built-in ACL does not check subscriptions. The ACL is checked on every delivery
  instead, so nothing outside the ACL ever arrives on such a subscription.
- CONNECT with a wrong password, an unknown user or none: CONNACK 0x87 (Not authorized).

Protocol versions: the service's connection speaks MQTT 5 (it needs Receive Maximum and session expiry). `UserClient`
and `VehicleClient` speak MQTT 5 by default, MQTT 3.1.1 when asked (`protocol="3.1.1"`), or the first of the two the
broker accepts (`protocol="auto"`): RabbitMQ 3.10's MQTT plugin, the cluster mode's broker (docs/CLUSTER.md), knows
MQTT 3.1 and 3.1.1 only and closes an MQTT 5 CONNECT without a CONNACK. Under 3.1.1 a PUBACK carries no reason code, so
a refused publish is not seen as such (Mosquitto drops it after a PUBACK; RabbitMQ closes the connection instead).

`MqttClient`, the service's connection, in short: paho-mqtt 2.x, MQTT 5, a persistent session (clean start off, a session
expiry interval), so that the broker keeps the service's subscription and queues QoS 1 telemetry while the service is
away (`max_queued_messages` in `roadgrip.cloud.transport.mosquitto`); manual acknowledgement, so that a message the service has not
yet handled is delivered again after a reconnect; automatic reconnects in paho's network thread, each followed by
subscribing again.

Size: over 500 lines because the topics and every MQTT client role (service, vehicle, reader, station) over one paho
set-up and reconnect rule.
"""

from __future__ import annotations

import logging
import queue
import secrets
import threading
import time
from collections.abc import Callable
from typing import Self
from urllib.parse import urlsplit

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode

from roadgrip.data.telemetry import VEHICLE_ID_RE

log = logging.getLogger(__name__)

VEHICLES_PREFIX = "roadgrip/v1/vehicles/"
TELEMETRY_SUBSCRIPTION = VEHICLES_PREFIX + "+/telemetry"
STATIONS_PREFIX = "roadgrip/v1/stations/"
STATION_REPORTS_SUBSCRIPTION = STATIONS_PREFIX + "+/reports"
STATION_ERRORS_SUBSCRIPTION = STATIONS_PREFIX + "+/errors"
FRICTION_SUBSCRIPTION = VEHICLES_PREFIX + "+/friction"
ERRORS_SUBSCRIPTION = VEHICLES_PREFIX + "+/errors"
OBSERVATIONS_SUBSCRIPTION = VEHICLES_PREFIX + "+/observations"  # friction observations of edge vehicles (CONTRACTS 3.7)
HEARTBEAT_SUBSCRIPTION = VEHICLES_PREFIX + "+/heartbeat"
EDGE_KINDS = ("observations", "heartbeat")
WARNINGS_TOPIC = "roadgrip/v1/warnings"
WARNINGS_UPER_TOPIC = WARNINGS_TOPIC + "/uper"  # the same DENMs, UPER-encoded (roadgrip/cloud/formats/denm.py)
VEHICLE_TOPIC_KINDS = ("telemetry", "friction", "errors", *EDGE_KINDS)
QOS = 1
DEFAULT_PORT = 1883
RECONNECT_MIN_DELAY_S = 0.25  # doubling after each failed attempt, up to the max
RECONNECT_MAX_DELAY_S = 10.0
DEFAULT_MAX_INFLIGHT = 20  # own QoS 1 publishes unacknowledged at once: paho's default, and Mosquitto's Receive Maximum
# The service's Receive Maximum (CONNECT): messages the broker may have unacknowledged towards it. Twice the edge
# intake's batch (roadgrip/cloud/serve/edge_intake.py), so that the broker fills the next batch while one is stored and
# a round trip never caps throughput; the edge intake's queue is sized from it. Mosquitto 2.0.11 keeps to it only until
# the first PUBACK (tests/cloud/serve/test_edge_intake.py measures it; fixed in 2.0.13): `Busy` is the bound that holds.
SERVICE_RECEIVE_MAXIMUM = 2_000
REDELIVERY_POLL_S = 0.2  # how often a client with deferred messages asks whether the service has room again
MQTT_PROTOCOLS = {"5": paho.MQTTv5, "3.1.1": paho.MQTTv311}  # what a client may be asked to speak, besides "auto"
UNSUPPORTED_PROTOCOL_VERSION = 0x84  # MQTT 5's CONNACK reason code for a protocol version the broker does not speak

TelemetryHandler = Callable[[str, bytes, Callable[[], None]], None]
EdgeHandler = Callable[[str, str, bytes, Callable[[], None]], None]  # (vehicle_id, kind of EDGE_KINDS, payload, ack)


def check_vehicle_id(vehicle_id: str) -> str:
    """`vehicle_id` if it is one (CONTRACTS 3.1: 1-64 of A-Za-z0-9_.-, hence never a topic wildcard or separator)."""
    if not isinstance(vehicle_id, str) or VEHICLE_ID_RE.fullmatch(vehicle_id) is None:
        raise ValueError(f"vehicle_id must match {VEHICLE_ID_RE.pattern}, got {vehicle_id!r}")
    return vehicle_id


def telemetry_topic(vehicle_id: str) -> str:
    return f"{VEHICLES_PREFIX}{check_vehicle_id(vehicle_id)}/telemetry"


def friction_topic(vehicle_id: str) -> str:
    return f"{VEHICLES_PREFIX}{check_vehicle_id(vehicle_id)}/friction"


def errors_topic(vehicle_id: str) -> str:
    return f"{VEHICLES_PREFIX}{check_vehicle_id(vehicle_id)}/errors"


def observations_topic(vehicle_id: str) -> str:
    return f"{VEHICLES_PREFIX}{check_vehicle_id(vehicle_id)}/observations"


def heartbeat_topic(vehicle_id: str) -> str:
    return f"{VEHICLES_PREFIX}{check_vehicle_id(vehicle_id)}/heartbeat"


def vehicle_of_topic(topic: str) -> str | None:
    """The vehicle id in a per-vehicle topic (`roadgrip/v1/vehicles/{id}/{kind}`, VEHICLE_TOPIC_KINDS); None for any
    other topic, or for an id that is not a valid vehicle_id."""
    if not topic.startswith(VEHICLES_PREFIX):
        return None
    parts = topic[len(VEHICLES_PREFIX) :].split("/")
    if len(parts) != 2 or parts[1] not in VEHICLE_TOPIC_KINDS or VEHICLE_ID_RE.fullmatch(parts[0]) is None:
        return None
    return parts[0]


def station_reports_topic(station_id: str) -> str:
    """A station's reports topic; its id follows the vehicle_id rule (roadgrip/cloud/domain/stations.py)."""
    return f"{STATIONS_PREFIX}{check_vehicle_id(station_id)}/reports"


def station_errors_topic(station_id: str) -> str:
    return f"{STATIONS_PREFIX}{check_vehicle_id(station_id)}/errors"


def station_of_topic(topic: str) -> str | None:
    """The station id in `roadgrip/v1/stations/{id}/reports`; None for any other topic or an invalid id."""
    if not topic.startswith(STATIONS_PREFIX):
        return None
    parts = topic[len(STATIONS_PREFIX) :].split("/")
    if len(parts) != 2 or parts[1] != "reports" or VEHICLE_ID_RE.fullmatch(parts[0]) is None:
        return None
    return parts[0]


def parse_url(url: str) -> tuple[str, int]:
    """(host, port) of an `mqtt://host[:port]` URL (port 1883 when left out)."""
    parts = urlsplit(url)
    if parts.scheme != "mqtt" or not parts.hostname or parts.path not in ("", "/") or parts.query:
        raise ValueError(f"url must be mqtt://host[:port], got {url!r}")
    return parts.hostname, parts.port or DEFAULT_PORT


class Busy(Exception):
    """Raised by a `MqttClient` handler that has no room for a message now: it is left unacknowledged and counted
    (`deferred`); once the service has room again the client reconnects and the broker delivers it again."""


class BrokerRefused(ConnectionError):
    """The broker answered CONNECT (or SUBSCRIBE) with a failure reason code, e.g. 0x87 Not authorized."""

    def __init__(self, what: str, reason_code: ReasonCode):
        super().__init__(f"{what}: the broker refused with reason code {reason_code.value:#04x} ({reason_code})")
        self.reason_code = reason_code


class PublishRefused(RuntimeError):
    """The broker answered a QoS 1 PUBLISH with a failure reason code in its PUBACK (MQTT 5), e.g. 0x87 Not
    authorized for a topic outside the client's ACL."""

    def __init__(self, topic: str, reason_code: ReasonCode):
        super().__init__(
            f"publish to {topic!r} refused by the broker: reason code {reason_code.value:#04x} ({reason_code})"
        )
        self.topic = topic
        self.reason_code = reason_code


def connect_paho(
    url: str,
    username: str,
    password: str,
    *,
    client_id: str | None = None,
    timeout_s: float = 10,
    clean_start: bool = True,
    properties: Properties | None = None,
    manual_ack: bool = False,
    protocol: str = "5",
) -> paho.Client:
    """A paho client (MQTT 5, or `protocol` "3.1.1": clean session as `clean_start`, no properties) connected to `url`
    as `username`, its network loop then running in paho's thread (which reconnects by itself after a drop).

    Returns once the broker accepted the connection. Raises `BrokerRefused` when the CONNACK carries a failure, `OSError`
    when nothing listens at `url` or the connection closes before the CONNACK, `TimeoutError` when no CONNACK came within
    `timeout_s`; the client is disconnected then.
    The caller owns the client: `client.disconnect(); client.loop_stop()` ends it."""
    host, port = parse_url(url)
    if protocol not in MQTT_PROTOCOLS:
        raise ValueError(f"protocol must be one of {list(MQTT_PROTOCOLS)}, got {protocol!r}")
    if protocol != "5" and properties is not None:
        raise ValueError(f"properties are MQTT 5 only, got some for protocol {protocol!r}")
    v5 = protocol == "5"
    client = paho.Client(
        CallbackAPIVersion.VERSION2,
        client_id=client_id or f"roadgrip-{secrets.token_hex(6)}",
        protocol=MQTT_PROTOCOLS[protocol],
        manual_ack=manual_ack,
        clean_session=None if v5 else clean_start,
    )
    client.username_pw_set(username, password)
    answered = threading.Event()
    reply: list[ReasonCode] = []

    def on_connect(_client, _userdata, _flags, reason_code, _properties):
        if not answered.is_set():
            reply.append(reason_code)
            answered.set()

    client.on_connect = on_connect
    client.reconnect_delay_set(RECONNECT_MIN_DELAY_S, RECONNECT_MAX_DELAY_S)
    if v5:
        client.connect(host, port, keepalive=30, clean_start=clean_start, properties=properties)
    else:
        client.connect(host, port, keepalive=30)
    deadline = time.monotonic() + timeout_s
    while not answered.is_set() and time.monotonic() < deadline:  # in this thread, until the CONNACK
        if client.loop(timeout=0.05) != MQTTErrorCode.MQTT_ERR_SUCCESS:
            break
    client.on_connect = None
    if not reply or reply[0].is_failure:
        client.disconnect()
        if reply:
            raise BrokerRefused(f"connect to {url} as {username!r}", reply[0])
        if time.monotonic() < deadline:
            raise ConnectionError(f"{url} closed the connection before its CONNACK")
        raise TimeoutError(f"no CONNACK from {url} within {timeout_s} s")
    client.loop_start()
    return client


def _stop(client: paho.Client) -> None:
    client.disconnect()
    client.loop_stop()


class MqttClient:
    """The service's connection: paho-mqtt 2.x (CallbackAPIVersion.VERSION2), MQTT 5, QoS 1.

    - A persistent session: clean start off and a session expiry of `session_expiry_s`, so that QoS 1 telemetry
      published while the service is down (or reconnecting) waits in the broker and is delivered when it comes back.
      The session is keyed by `client_id`: give each service instance a fixed one.
    - Manual acknowledgement (paho's `manual_ack=True`): a telemetry message is acknowledged (PUBACK) only when the
      handler's `ack()` is called. A message not acknowledged before the connection drops is delivered again after the
      reconnect, with the DUP flag; the handler must therefore accept a message twice (the service keys telemetry by
      (vehicle_id, timestamp_ms)). Until acknowledged, a message holds one of `receive_maximum` slots: the broker sends
      at most that many unacknowledged messages (MQTT 5 Receive Maximum), then queues the rest.
    - At most `max_inflight` of its own QoS 1 publishes unacknowledged (paho's `max_inflight_messages`, 20 by default,
      which paho does not take from the broker's CONNACK): it must not exceed the broker's Receive Maximum (its
      `max_inflight_messages`; an error is logged when it does). The rest wait in paho, `max_queued_messages` at most.
    - Automatic reconnects (`reconnect_delay_set`, from `reconnect_min_delay_s` doubling up to `reconnect_max_delay_s`),
      in paho's network thread (`loop_start`); after every (re)connect the client subscribes to
      `TELEMETRY_SUBSCRIPTION` again (when it has a handler), and to `STATION_REPORTS_SUBSCRIPTION` (when it has
      `on_station_report`), in case the broker lost the session.

    `on_telemetry(vehicle_id, payload, ack)` is called on paho's network thread for each telemetry message, with the
    vehicle id taken from the topic (which the broker's ACL ties to the publisher's login). It must be cheap (the
    service puts the message on a queue) and must not block: no other message is read meanwhile. An exception in it
    is logged and the message is left unacknowledged. `on_station_report(station_id, payload, ack)` is the same for
    the roadside stations' reports, `on_edge(vehicle_id, kind, payload, ack)` for edge vehicles' observations and
    heartbeats (kind "observations" or "heartbeat").
    - Backpressure that never holds the network thread: a handler with no room raises `Busy`; the message is left
      unacknowledged and counted in `deferred`, and paho goes on reading, answering and pinging. A thread of the client
      then asks `room()` every `redelivery_poll_s` and, once it says yes, reconnects (the persistent session stays):
      the broker delivers every unacknowledged message again, the deferred ones included. (A broker that keeps to the
      Receive Maximum never sends more than `receive_maximum`; handlers sized to it never raise `Busy`. Mosquitto 2.0.11
      does not: module constants.) `drops` counts connections lost (not closed by this client).
    `ack()` may be called from any thread, at any later time, and
    more than once (only the first call counts): paho's `Client.ack` only appends a PUBACK to a deque (atomic in
    CPython) and wakes the network thread through its socket pair, the same path as `publish`. An `ack()` that comes
    after the connection the message arrived on has dropped does nothing: the broker delivers that message again.
    """

    def __init__(
        self,
        url: str,
        username: str,
        password: str,
        client_id: str,
        on_telemetry: TelemetryHandler | None = None,
        *,
        on_station_report: TelemetryHandler | None = None,
        on_edge: EdgeHandler | None = None,
        session_expiry_s: int = 86_400,
        receive_maximum: int = SERVICE_RECEIVE_MAXIMUM,
        max_queued_messages: int = 100_000,
        max_inflight: int = DEFAULT_MAX_INFLIGHT,
        keepalive_s: int = 30,
        reconnect_min_delay_s: float = RECONNECT_MIN_DELAY_S,
        reconnect_max_delay_s: float = RECONNECT_MAX_DELAY_S,
        room: Callable[[], bool] | None = None,
        redelivery_poll_s: float = REDELIVERY_POLL_S,
    ):
        self.host, self.port = parse_url(url)
        if not 1 <= receive_maximum <= 65_535:
            raise ValueError(f"receive_maximum must be in [1, 65535] (MQTT 5), got {receive_maximum}")
        if session_expiry_s < 0:
            raise ValueError(f"session_expiry_s must be >= 0, got {session_expiry_s}")
        self.url = url
        self.username = username
        self.client_id = client_id
        self.on_telemetry = on_telemetry
        self.on_station_report = on_station_report
        self.on_edge = on_edge
        self.session_expiry_s = session_expiry_s
        self.receive_maximum = receive_maximum
        self.max_queued_messages = max_queued_messages
        self.max_inflight = max_inflight
        self.keepalive_s = keepalive_s
        self.reconnect_min_delay_s = reconnect_min_delay_s
        self.reconnect_max_delay_s = reconnect_max_delay_s
        self.room = room or (lambda: True)
        self.redelivery_poll_s = redelivery_poll_s
        self.deferred = 0  # messages a handler had no room for (Busy), all connections together
        self.drops = 0  # connections lost, not closed by this client
        self.redeliveries = 0  # reconnects to have deferred messages delivered again
        self._redelivery: threading.Thread | None = None  # the one redelivery thread, while it runs
        self._pending = False  # a message was deferred since the last redelivery
        self._redelivering = False  # its disconnect is not a drop
        self._redelivery_disconnected = threading.Event()
        self._closed = threading.Event()
        self._password = password
        self._client: paho.Client | None = None
        self._lock = threading.Lock()
        self._generation = 0  # counts successful connects; an ack belongs to one
        self._ready = threading.Event()  # the first connect went through (and its subscription)
        self._failure: BaseException | None = None
        self._subscribe_mid: int | None = None
        self._unacknowledged = 0  # own QoS 1 publishes handed to paho and not yet acknowledged by the broker

    @property
    def connected(self) -> bool:
        client = self._client
        return client is not None and client.is_connected()

    def connect(self, timeout_s: float = 10) -> None:
        """Connect, subscribe to the telemetry of all vehicles when there is a handler, and start the network thread.

        Returns when the broker has accepted the connection and the subscription. Raises `BrokerRefused` (a
        `ConnectionError`, with the reason code) when the broker refuses, `OSError` when nothing listens at the URL,
        `TimeoutError` after `timeout_s`; the client is then stopped. Later disconnects are repaired in the background."""
        if self._client is not None:
            raise RuntimeError("connect() called twice: close() first")
        self._closed.clear()
        self._connect(timeout_s)

    def _connect(self, timeout_s: float) -> None:
        client = paho.Client(
            CallbackAPIVersion.VERSION2, client_id=self.client_id, protocol=paho.MQTTv5, manual_ack=True
        )
        client.username_pw_set(self.username, self._password)
        client.reconnect_delay_set(self.reconnect_min_delay_s, self.reconnect_max_delay_s)
        client.max_queued_messages_set(self.max_queued_messages)
        client.max_inflight_messages_set(self.max_inflight)
        client.on_connect = self._on_connect
        client.on_subscribe = self._on_subscribe
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        client.on_publish = self._on_publish
        properties = Properties(PacketTypes.CONNECT)
        properties.SessionExpiryInterval = self.session_expiry_s
        properties.ReceiveMaximum = self.receive_maximum
        self._ready.clear()
        self._failure = None
        self._client = client
        try:
            client.connect(self.host, self.port, keepalive=self.keepalive_s, clean_start=False, properties=properties)
        except OSError:
            self._client = None
            raise
        client.loop_start()
        if not self._ready.wait(timeout_s):
            self._disconnect()
            raise TimeoutError(f"{self.client_id}: not connected and subscribed to {self.url} within {timeout_s} s")
        if self._failure is not None:
            failure = self._failure
            self._disconnect()
            raise failure

    def publish(self, topic: str, payload: bytes | str, qos: int = QOS) -> paho.MQTTMessageInfo:
        """Hand a message to paho and return at once (its `MQTTMessageInfo` can be waited on).

        QoS 1 messages are queued inside paho while the connection is down and sent after the reconnect; at most
        `max_queued_messages` of them wait (sent and unacknowledged, or not yet sent); beyond that this raises
        `BufferError` and the message is not queued. A QoS 0 message while disconnected is dropped (info.rc says so)."""
        client = self._client
        if client is None:
            raise RuntimeError("publish() before connect()")
        info = client.publish(topic, payload, qos=qos)
        if info.rc == MQTTErrorCode.MQTT_ERR_QUEUE_SIZE:
            raise BufferError(
                f"{self.client_id}: {self.max_queued_messages} messages already wait to be published "
                f"(max_queued_messages); {topic!r} dropped"
            )
        if qos > 0:
            with self._lock:
                self._unacknowledged += 1
        return info

    @property
    def unacknowledged(self) -> int:
        """This client's QoS 1 publishes not yet acknowledged by the broker: in flight, or waiting in paho (which holds
        them in memory, up to max_queued_messages) because the window is full or the connection down."""
        return self._unacknowledged

    def close(self) -> None:
        """Disconnect (the broker keeps the session for `session_expiry_s`) and stop the network thread. Idempotent."""
        self._closed.set()
        redelivery = self._redelivery
        if redelivery is not None and redelivery is not threading.current_thread():
            redelivery.join()
        self._disconnect()

    def _disconnect(self) -> None:
        client, self._client = self._client, None
        if client is None:
            return
        client.disconnect()  # queued after the PUBACKs already handed to paho: they go out first
        client.loop_stop()
        with self._lock:
            self._generation += 1  # acks of this connection are void

    def __enter__(self) -> Self:
        """Connects (with the default timeout) unless `connect()` was called already."""
        if self._client is None:
            self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # paho callbacks, all on paho's network thread

    def _on_connect(self, client, _userdata, flags, reason_code, properties):
        if reason_code.is_failure:
            log.warning("%s: connect to %s refused: %s", self.client_id, self.url, reason_code)
            if not self._ready.is_set():
                self._failure = BrokerRefused(f"connect to {self.url} as {self.username!r}", reason_code)
                self._ready.set()
            return
        with self._lock:
            self._generation += 1
        log.info("%s: connected to %s (session present: %s)", self.client_id, self.url, flags.session_present)
        allowed = getattr(properties, "ReceiveMaximum", 65_535)  # absent: the MQTT 5 default
        if allowed < self.max_inflight:
            log.error(
                "%s: %s accepts %d unacknowledged publishes, this client sends up to %d (max_inflight): set "
                "the broker's max_inflight_messages to at least that",
                self.client_id,
                self.url,
                allowed,
                self.max_inflight,
            )
        if self.on_telemetry is None:
            self._ready.set()
            return
        subscriptions = [(TELEMETRY_SUBSCRIPTION, QOS)]
        if self.on_station_report is not None:
            subscriptions.append((STATION_REPORTS_SUBSCRIPTION, QOS))
        if self.on_edge is not None:
            subscriptions += [(OBSERVATIONS_SUBSCRIPTION, QOS), (HEARTBEAT_SUBSCRIPTION, QOS)]
        _, self._subscribe_mid = client.subscribe(subscriptions)

    def _on_subscribe(self, _client, _userdata, mid, reason_codes, _properties):
        if mid != self._subscribe_mid:
            return
        failed = next((code for code in reason_codes if code.is_failure), None)
        if failed is not None:
            log.error("%s: subscription to %s refused: %s", self.client_id, TELEMETRY_SUBSCRIPTION, failed)
            if not self._ready.is_set():
                self._failure = BrokerRefused(f"subscribe to {TELEMETRY_SUBSCRIPTION}", failed)
        self._ready.set()

    def _on_publish(self, _client, _userdata, _mid, _reason_code, _properties):
        with self._lock:
            self._unacknowledged -= 1

    def _on_disconnect(self, client, _userdata, _flags, reason_code, _properties):
        if self._redelivering:
            self._redelivery_disconnected.set()
            return
        if self._client is client:  # not our own close()
            self.drops += 1
            log.warning("%s: disconnected from %s (%s); reconnecting", self.client_id, self.url, reason_code)

    def _on_message(self, client, _userdata, message):
        try:
            self._dispatch(client, message)
        except Busy:
            self._defer()

    def _defer(self) -> None:
        """A handler had no room (Busy): count it and make sure the redelivery thread (one at a time) runs."""
        with self._lock:
            self.deferred += 1
            self._pending = True
            if self._redelivery is not None or self._closed.is_set():
                return
            self._redelivery = threading.Thread(target=self._redeliver, name="mqtt-redelivery", daemon=True)
        log.warning("%s: no room for a message; deferred until the service has room again", self.client_id)
        self._redelivery.start()

    def _redeliver(self) -> None:
        """Once `room()`, reconnect: the broker delivers the unacknowledged messages again (class docstring); again
        while messages were deferred since."""
        while not self._closed.wait(self.redelivery_poll_s):
            if not self.room():
                continue
            with self._lock:
                self._pending = False
                self._generation += 1  # acks of this connection are void: its messages come again
            self._reconnect_same_client()
            with self._lock:
                if not self._pending:
                    self._redelivery = None
                    return
        with self._lock:
            self._redelivery = None

    def _reconnect_same_client(self) -> None:
        """Disconnect and connect the same paho client (what it holds to publish stays queued in it)."""
        client = self._client
        if client is None:
            return
        self._redelivering = True
        self._redelivery_disconnected.clear()
        client.disconnect()  # queued after the PUBACKs already handed to paho: they go out first
        self._redelivery_disconnected.wait(RECONNECT_MAX_DELAY_S)  # written: those PUBACKs are out
        client.loop_stop()
        delay_s = self.reconnect_min_delay_s
        while not self._closed.is_set():
            try:
                client.reconnect()
                break
            except OSError as exc:
                log.warning("%s: reconnect for redelivery failed (%s); again in %.1f s", self.client_id, exc, delay_s)
                self._closed.wait(delay_s)
                delay_s = min(2 * delay_s, self.reconnect_max_delay_s)
        self._redelivering = False
        client.loop_start()  # paho's network thread again: it reconnects by itself from here should this one fail
        self.redeliveries += 1
        log.info("%s: reconnected for the redelivery of deferred messages", self.client_id)

    def _dispatch(self, client, message) -> None:
        """Hand a message to its handler; Busy goes through to `_on_message`."""
        vehicle_id = vehicle_of_topic(message.topic)
        ack = self._acker(client, message.mid, message.qos)
        station_id = station_of_topic(message.topic)
        if station_id is not None and self.on_station_report is not None:
            try:
                self.on_station_report(station_id, message.payload, ack)
            except Busy:
                raise
            except Exception:
                log.exception(
                    "%s: station report handler failed on a message of %s; left unacknowledged",
                    self.client_id,
                    station_id,
                )
            return
        kind = message.topic.rpartition("/")[2]
        if vehicle_id is not None and kind in EDGE_KINDS and self.on_edge is not None:
            try:
                self.on_edge(vehicle_id, kind, message.payload, ack)
            except Busy:
                raise
            except Exception:
                log.exception(
                    "%s: %s handler failed on a message of %s; left unacknowledged", self.client_id, kind, vehicle_id
                )
            return
        if self.on_telemetry is None or vehicle_id is None or not message.topic.endswith("/telemetry"):
            # a subscription left in the persistent session by an earlier client with this id, or a foreign topic
            log.warning("%s: message on %r dropped (not telemetry, or no handler)", self.client_id, message.topic)
            ack()
            return
        try:
            self.on_telemetry(vehicle_id, message.payload, ack)
        except Busy:
            raise
        except Exception:
            log.exception(
                "%s: telemetry handler failed on a message of %s; left unacknowledged", self.client_id, vehicle_id
            )

    def _acker(self, client: paho.Client, mid: int, qos: int) -> Callable[[], None]:
        generation = self._generation
        done = False

        def ack() -> None:
            nonlocal done
            with self._lock:
                if done or generation != self._generation:
                    return
                done = True
            try:
                client.ack(mid, qos)
            except OSError:  # paho's wake-up socket closed by a reconnect meanwhile: the message comes again
                log.debug("%s: PUBACK of message %d lost to a reconnect", self.client_id, mid)

        return ack


class UserClient:
    """A plain connection as one login (clean start), for vehicles, readers, tests and the fleet simulator.

    `protocol`: "5" (the default), "3.1.1", or "auto": MQTT 5, and MQTT 3.1.1 when the broker does not take it (it
    closes the connection before its CONNACK, as RabbitMQ 3.10 does, or answers 0x84 Unsupported protocol version);
    `protocol` then holds the version connected with. `connect()` returns the client itself;
    `with UserClient(url, name, secret) as c:` connects too. `publish` waits for the PUBACK and raises `PublishRefused`
    when its reason code is a failure (Mosquitto 2.0 sends 0x87 for a topic outside the ACL; MQTT 3.1.1 has no reason
    codes); `publish_nowait` only queues and counts refusals in `refused`. Messages on the subscriptions made with
    `subscribe` land in `messages`, a queue of (topic, payload). `paho` is the underlying paho client."""

    def __init__(self, url: str, username: str, password: str, client_id: str | None = None, protocol: str = "5"):
        parse_url(url)
        if protocol != "auto" and protocol not in MQTT_PROTOCOLS:
            raise ValueError(f"protocol must be auto or one of {list(MQTT_PROTOCOLS)}, got {protocol!r}")
        self.url = url
        self.protocol = protocol
        self.username = username
        self.client_id = client_id or f"{username}-{secrets.token_hex(4)}"
        self.messages: queue.Queue[tuple[str, bytes]] = queue.Queue()
        self.refused = 0
        self.paho: paho.Client | None = None
        self._password = password
        self._acks: dict[int, ReasonCode] = {}  # PUBACK reason code by message id (so at most 65,535 entries)
        self._subacks: dict[int, ReasonCode] = {}
        self._subscribed = threading.Condition()

    def connect(self, timeout_s: float = 10) -> Self:
        """Connect (raises like `connect_paho`) and return self."""
        if self.paho is not None:
            raise RuntimeError("connect() called twice: close() first")
        if self.protocol != "auto":
            client = connect_paho(
                self.url,
                self.username,
                self._password,
                client_id=self.client_id,
                timeout_s=timeout_s,
                protocol=self.protocol,
            )
        else:
            try:
                client = connect_paho(
                    self.url, self.username, self._password, client_id=self.client_id, timeout_s=timeout_s, protocol="5"
                )
                self.protocol = "5"
            except ConnectionError as exc:
                if isinstance(exc, BrokerRefused) and exc.reason_code.value != UNSUPPORTED_PROTOCOL_VERSION:
                    raise
                log.info("%s: %s did not take MQTT 5 (%s); connecting with MQTT 3.1.1", self.client_id, self.url, exc)
                client = connect_paho(
                    self.url,
                    self.username,
                    self._password,
                    client_id=self.client_id,
                    timeout_s=timeout_s,
                    protocol="3.1.1",
                )
                self.protocol = "3.1.1"
        client.on_publish = self._on_publish
        client.on_subscribe = self._on_subscribe
        client.on_message = lambda _client, _userdata, message: self.messages.put((message.topic, message.payload))
        self.paho = client
        return self

    def publish(self, topic: str, payload: bytes | str, timeout_s: float = 10) -> None:
        """Publish at QoS 1 and return once the broker acknowledged the message.

        Raises `PublishRefused` when the PUBACK carries a failure reason code, `ConnectionError` when not connected,
        `TimeoutError` when no PUBACK came within `timeout_s`."""
        info = self.publish_nowait(topic, payload)
        if info.rc != MQTTErrorCode.MQTT_ERR_SUCCESS:
            raise ConnectionError(f"{self.client_id}: publish to {topic!r} failed: {paho.error_string(info.rc)}")
        info.wait_for_publish(timeout_s)
        if not info.is_published():
            raise TimeoutError(f"{self.client_id}: no PUBACK for {topic!r} within {timeout_s} s")
        reason = self._acks.pop(info.mid)
        if reason.is_failure:
            raise PublishRefused(topic, reason)

    def publish_nowait(self, topic: str, payload: bytes | str) -> paho.MQTTMessageInfo:
        """Queue one message at QoS 1 in paho and return its `MQTTMessageInfo` at once."""
        if self.paho is None:
            raise RuntimeError("publish before connect()")
        return self.paho.publish(topic, payload, qos=QOS)

    def subscribe(self, topic_filter: str, timeout_s: float = 10) -> int:
        """Subscribe at QoS 1; return the QoS the broker granted. Raises `BrokerRefused` when the SUBACK carries a
        failure (Mosquitto 2.0.11 grants any filter and applies the ACL to each delivery instead)."""
        if self.paho is None:
            raise RuntimeError("subscribe before connect()")
        with self._subscribed:
            _, mid = self.paho.subscribe(topic_filter, qos=QOS)
            if not self._subscribed.wait_for(lambda: mid in self._subacks, timeout_s):
                raise TimeoutError(f"{self.client_id}: no SUBACK for {topic_filter!r} within {timeout_s} s")
            reason = self._subacks.pop(mid)
        if reason.is_failure:
            raise BrokerRefused(f"subscribe to {topic_filter!r}", reason)
        return reason.value

    def close(self) -> None:
        """Disconnect and stop the network thread. Idempotent."""
        client, self.paho = self.paho, None
        if client is not None:
            _stop(client)

    def __enter__(self) -> Self:
        """Connects (with the default timeout) unless `connect()` was called already."""
        if self.paho is None:
            self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _on_publish(self, _client, _userdata, mid, reason_code, _properties):
        # Called before paho marks the message published, so `publish` finds the code after its wait.
        self._acks[mid] = reason_code
        if reason_code.is_failure:
            self.refused += 1
            log.warning("%s: publish refused: %s", self.client_id, reason_code)

    def _on_subscribe(self, _client, _userdata, mid, reason_codes, _properties):
        with self._subscribed:
            self._subacks[mid] = reason_codes[0]
            self._subscribed.notify_all()


class VehicleClient(UserClient):
    """A vehicle's connection: its login name is its vehicle_id; `publish_telemetry` publishes on its own telemetry
    topic (waiting for the PUBACK, like `publish`), `publish_telemetry_nowait` only queues (for the fleet simulator)."""

    def __init__(self, url: str, vehicle_id: str, secret: str, client_id: str | None = None, protocol: str = "5"):
        super().__init__(url, check_vehicle_id(vehicle_id), secret, client_id, protocol)
        self.vehicle_id = vehicle_id
        self.topic = telemetry_topic(vehicle_id)

    def publish_telemetry(self, payload: bytes | str, timeout_s: float = 10) -> None:
        self.publish(self.topic, payload, timeout_s)

    def publish_telemetry_nowait(self, payload: bytes | str) -> paho.MQTTMessageInfo:
        return self.publish_nowait(self.topic, payload)
