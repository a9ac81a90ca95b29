"""The vehicle's MQTT uplink: the outbox (roadgrip/edge/outbox.py) sent to the cloud's broker, QoS 1, with paho-mqtt.

- MQTT 5, a persistent session (clean start off, a session expiry of `session_expiry_s`), the vehicle's own
  credentials (the same as its telemetry's, CONTRACTS 3.6). MQTT 3.1.1 when asked (`protocol="3.1.1"`: clean session
  off; the broker keeps the session as long as it keeps any): RabbitMQ 3.10's MQTT plugin, the cluster mode's broker,
  speaks nothing newer.
- Client id `{vehicle_id}-{8 hex}` (`edge_client_id`), the same on every run (a persistent session is the client
  id's), the hex from a hash of the vehicle's secret: a client id in use is taken over by whoever connects with it
  (docs/CLUSTER.md), so it is not one another vehicle can work out; and RabbitMQ lets a login touch only the
  subscription queues of its own name with such a suffix (roadgrip/cloud/transport/rabbit_users.py).
- `pump()` hands paho the oldest waiting messages, at most `max_inflight` unacknowledged at once; a message leaves
  the outbox only when its PUBACK comes back with success. A PUBACK with a failure reason code (MQTT 5: 0x87 Not
  authorized, a topic outside the vehicle's ACL) would fail again: the message is removed, counted in `refused` and
  logged. Under MQTT 3.1.1 a PUBACK carries no reason code: Mosquitto PUBACKs and drops a refused publish (removed
  as sent), RabbitMQ closes the connection (kept, and sent again after the reconnect).
- The agent need not be connected to run: it starts (`start`) with a non-blocking connect and paho's network thread
  reconnects after every drop (from RECONNECT_MIN_DELAY_S doubling up to RECONNECT_MAX_DELAY_S). Messages handed to
  paho before a drop are sent again by paho after the reconnect; messages of a killed agent are still in the outbox
  and are published again by the next one. Either way the broker may get a message twice: the cloud stores an
  observation once per (vehicle_id, last_ms) and a heartbeat once per (vehicle_id, timestamp_ms).
"""

from __future__ import annotations

import hashlib
import logging
import threading

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from roadgrip.cloud.transport.mqtt import (
    MQTT_PROTOCOLS,
    QOS,
    RECONNECT_MAX_DELAY_S,
    RECONNECT_MIN_DELAY_S,
    check_vehicle_id,
    parse_url,
)
from roadgrip.edge.outbox import Outbox

log = logging.getLogger(__name__)

SESSION_EXPIRY_S = 7 * 86_400  # the broker keeps the vehicle's session through a week off the air
MAX_INFLIGHT = 20  # Mosquitto's default Receive Maximum


def edge_client_id(vehicle_id: str, secret: str) -> str:
    """The uplink's MQTT client id (module docstring): the vehicle id, '-' and 8 hex digits of a hash of its secret."""
    return f"{check_vehicle_id(vehicle_id)}-{hashlib.sha256(b'roadgrip-edge:' + secret.encode()).hexdigest()[:8]}"


class Uplink:
    """The outbox to the broker (module docstring). `pump` from the agent's loop; the rest runs in paho's thread."""

    def __init__(
        self,
        url: str,
        username: str,
        password: str,
        outbox: Outbox,
        *,
        client_id: str | None = None,
        protocol: str = "5",
        max_inflight: int = MAX_INFLIGHT,
        session_expiry_s: int = SESSION_EXPIRY_S,
        keepalive_s: int = 30,
    ):
        if protocol not in MQTT_PROTOCOLS:
            raise ValueError(f"protocol must be one of {list(MQTT_PROTOCOLS)}, got {protocol!r}")
        self.host, self.port = parse_url(url)
        self.url = url
        self.protocol = protocol
        self.client_id = client_id or edge_client_id(username, password)
        self.outbox = outbox
        self.max_inflight = max_inflight
        self.refused = 0  # messages the broker refused (PUBACK reason code >= 0x80)
        self.sent_payload_bytes = 0  # payload bytes handed to paho, repeats included
        self.sent_messages = 0
        self._lock = threading.Lock()
        self._inflight: dict[int, int] = {}  # paho mid -> outbox id
        self._early: dict[int, object] = {}  # mid -> reason code of a PUBACK that came before its mid was registered
        self._newest_inflight = 0  # highest outbox id handed to paho
        self._connected = threading.Event()
        v5 = protocol == "5"
        self._client = paho.Client(
            CallbackAPIVersion.VERSION2,
            client_id=self.client_id,
            protocol=MQTT_PROTOCOLS[protocol],
            clean_session=None if v5 else False,
        )
        self._client.username_pw_set(username, password)
        self._client.max_inflight_messages_set(max_inflight)
        self._client.reconnect_delay_set(RECONNECT_MIN_DELAY_S, RECONNECT_MAX_DELAY_S)
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = self._on_disconnect
        self._client.on_publish = self._on_publish
        self._properties = None
        if v5:
            self._properties = Properties(PacketTypes.CONNECT)
            self._properties.SessionExpiryInterval = session_expiry_s
        self._keepalive_s = keepalive_s

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    @property
    def inflight(self) -> int:
        return len(self._inflight)

    def start(self) -> None:
        """Connect in the background (the broker may be out of reach; paho keeps trying)."""
        if self._properties is None:  # MQTT 3.1.1: clean session off, set in the client
            self._client.connect_async(self.host, self.port, keepalive=self._keepalive_s)
        else:
            self._client.connect_async(
                self.host, self.port, keepalive=self._keepalive_s, clean_start=False, properties=self._properties
            )
        self._client.loop_start()

    def wait_connected(self, timeout_s: float) -> bool:
        return self._connected.wait(timeout_s)

    def pump(self) -> int:
        """Hand paho the oldest waiting messages not yet handed, up to max_inflight unacknowledged; how many."""
        if not self._connected.is_set():
            return 0
        with self._lock:
            room = self.max_inflight - len(self._inflight)
            after = self._newest_inflight
        if room <= 0:
            return 0
        handed = 0
        for message_id, topic, payload in self.outbox.oldest(room, after_id=after):
            # not under self._lock: paho calls on_publish holding its own lock, which publish() takes too
            info = self._client.publish(topic, payload, qos=QOS)
            if info.rc not in (paho.MQTT_ERR_SUCCESS, paho.MQTT_ERR_NO_CONN):
                log.warning("publish of outbox message %d failed: %s", message_id, paho.error_string(info.rc))
                break
            with self._lock:
                self._newest_inflight = message_id
                early = self._early.pop(info.mid, None)  # its PUBACK came before publish() returned
                if early is None:
                    self._inflight[info.mid] = message_id
            if early is not None:
                self._acknowledged(message_id, early)
            self.sent_payload_bytes += len(payload)
            self.sent_messages += 1
            handed += 1
        return handed

    def close(self) -> None:
        self._client.disconnect()
        self._client.loop_stop()

    # ------------------------------------------------------------------------------------------ paho's thread

    def _on_connect(self, _client, _userdata, flags, reason_code, _properties):
        if reason_code.is_failure:
            log.error("edge uplink: %s refused the connection: %s", self.url, reason_code)
            return
        log.info("edge uplink: connected to %s (session present: %s)", self.url, flags.session_present)
        self._connected.set()

    def _on_disconnect(self, _client, _userdata, _flags, reason_code, _properties):
        self._connected.clear()
        log.warning(
            "edge uplink: disconnected from %s (%s); %d messages wait", self.url, reason_code, self.outbox.pending
        )

    def _on_publish(self, _client, _userdata, mid, reason_code, _properties):
        with self._lock:
            message_id = self._inflight.pop(mid, None)
            if message_id is None:
                self._early[mid] = reason_code
                return
        self._acknowledged(message_id, reason_code)

    def _acknowledged(self, message_id: int, reason_code) -> None:
        if reason_code.is_failure:
            self.refused += 1
            log.error("edge uplink: the broker refused outbox message %d: %s; removed", message_id, reason_code)
        self.outbox.remove(message_id)
