"""Edge vehicles' MQTT messages in cluster mode (CONTRACTS 3.7; docs/CLUSTER.md "Edge vehicles"): friction
observations and heartbeats published by `roadgrip edge` agents to any RabbitMQ node, stored once and handed to the
region stage, as the API replicas do with those posted over HTTP (roadgrip/cloud/cluster/api_backend.py).

The way in (roadgrip/cloud/transport/amqp.py): the MQTT plugin publishes a vehicle's message into amq.topic with the
topic as routing key ('/' as '.'); the vehicle's topic permission lets it publish only its own observations and
heartbeat topics (roadgrip/cloud/transport/rabbit_users.py); amq.topic binds both kinds of topic to rg.edge, a quorum
queue with single-active-consumer, so the broker PUBACKs a message once a quorum of nodes holds it.

`EdgeConsumer` (every worker runs one; the broker makes one of them active, the next registered one after its
connection dies, as for the partitions): every FLUSH_S it takes what was delivered as one batch, in order (the first
batch after it took the queue: all that came in TAKEOVER_HOLD_S, since the broker returns the previous consumer's
unacknowledged messages out of order; results/trials/cluster/handover_order.py),
- parses each message with the one parser (roadgrip/cloud/ingest/observations.py) as the vehicle of its topic; a
  message refused whole is published on that vehicle's errors topic, as serve does, and acknowledged;
- stores the batch's observations in one transaction and its heartbeats in another (a repeat of a stored one is
  skipped: `Storage.put_observations`, `put_heartbeats`);
- hands the rows of the passes of every observation of the batch, repeats included, to the owners of their regions
  (roadgrip/cloud/cluster/regions.py `publish_observations`: one confirmed message per region), which apply a
  vehicle's rows once;
- then acknowledges the batch (one multiple-ack).
So a message is acknowledged only once it is stored and its passes are in the region queues: a consumer that dies
before leaves it to the next one, which stores it once more as a duplicate (nothing new) and hands its passes on
again (applied once). The database down or a region publish not confirmed within PUBLISH_DEADLINE_S gives the
connection up: the batch goes back to the queue and the consumer registers again through the next broker.

One queue in order: a region drops a vehicle's rows not newer than the newest it applied of that vehicle, so two
consumers taking one vehicle's messages side by side could lose the older one's. The cost is one active consumer for
the whole cluster (docs/CLUSTER.md says how far that carries).
"""

from __future__ import annotations

import json
import logging
import threading
import time

import pika

from roadgrip.cloud.cluster.publisher import PUBLISH_DEADLINE_S
from roadgrip.cloud.cluster.regions import RegionPublisher, check_region_resolution, publish_observations
from roadgrip.cloud.ingest.observations import ObservationError, parse_edge_message
from roadgrip.cloud.pipeline.pipeline import TAKEOVER_HOLD_S
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Storage, StorageUnavailable
from roadgrip.cloud.transport.amqp import EDGE_QUEUE, MQTT_EXCHANGE, mqtt_routing_key
from roadgrip.cloud.transport.amqp_client import check_brokers, consume
from roadgrip.cloud.transport.mqtt import errors_topic, vehicle_of_topic

log = logging.getLogger(__name__)

FLUSH_S = 0.05  # the consumer's wait for deliveries before it handles what came as one batch
EDGE_PREFETCH = 1000  # unacknowledged messages the consumer holds: one batch at most


class _EdgeHold:
    """rg.edge as one consumer connection holds it (an attempt of roadgrip/cloud/transport/amqp_client.py `consume`):
    the deliveries not yet handled."""

    def __init__(self, consumer: EdgeConsumer):
        self.consumer = consumer
        self.deliveries: list[tuple[str, int, bytes]] = []  # (routing key, delivery tag, body)
        # the first batch waits until then (monotonic s; set at the first delivery)
        self.hold_until: float | None = None

    def deliver(self, routing_key: str, tag: int, body: bytes) -> None:
        if self.hold_until is None:  # the queue taken: the previous consumer's returned messages come out of order
            self.hold_until = time.monotonic() + TAKEOVER_HOLD_S
        self.deliveries.append((routing_key, tag, body))

    def run(self, connection: pika.BlockingConnection) -> None:
        self.consumer._serve(self, connection)

    def ended(self, exc: BaseException | None, broker: int) -> None:
        if exc is not None and not self.consumer._closing.is_set():
            self.consumer.lost += 1
            log.warning(
                "edge queue: given up through broker %d (%r); its %d deliveries not acknowledged go back",
                broker,
                exc,
                len(self.deliveries),
            )


class EdgeConsumer:
    """A consumer of rg.edge (module docstring) on the brokers' AMQP URLs, storing into `storage`: `start`, `stop`."""

    def __init__(self, brokers: list[str], settings: Settings, storage: Storage):
        self.brokers = check_brokers(brokers)
        self.settings = settings
        self.region_resolution = check_region_resolution(settings)
        self.storage = storage
        self.publisher = RegionPublisher(brokers)
        self.messages = 0  # messages handled (acknowledged)
        self.rejected = 0  # messages refused whole
        self.observations = self.observation_duplicates = 0
        self.heartbeats = self.heartbeat_duplicates = 0
        self.region_messages = 0
        self.lost = 0  # connections given up
        self._closing = threading.Event()
        self._registered = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, ready_timeout_s: float = 60.0) -> None:
        """Register the consumer; returns once it is registered (TimeoutError after `ready_timeout_s`)."""
        self._thread = threading.Thread(target=self._consume, name="edge-queue", daemon=True)
        self._thread.start()
        if not self._registered.wait(ready_timeout_s):
            raise TimeoutError(f"{EDGE_QUEUE}: no consumer registered within {ready_timeout_s} s")

    def stop(self) -> None:
        """Finish the batch in hand, acknowledge it, close (what was delivered and not taken goes back)."""
        self._closing.set()
        if self._thread is not None:
            self._thread.join(PUBLISH_DEADLINE_S + 20)
            self._thread = None
        self.publisher.close()

    def stats(self) -> dict:
        return {
            "edge_messages": self.messages,
            "edge_rejected": self.rejected,
            "edge_observations_stored": self.observations,
            "edge_observations_duplicate": self.observation_duplicates,
            "edge_heartbeats_stored": self.heartbeats,
            "edge_heartbeats_duplicate": self.heartbeat_duplicates,
            "edge_region_messages": self.region_messages,
            "edge_connections_lost": self.lost,
        }

    def _consume(self) -> None:
        consume(self.brokers, 0, self._closing, lambda: _EdgeHold(self), "edge queue", (StorageUnavailable,))

    def _serve(self, hold: _EdgeHold, connection: pika.BlockingConnection) -> None:
        channel = connection.channel()
        channel.basic_qos(prefetch_count=EDGE_PREFETCH)
        channel.basic_consume(
            EDGE_QUEUE,
            lambda _ch, method, _props, body: hold.deliver(method.routing_key, method.delivery_tag, body),
        )
        self._registered.set()
        while not self._closing.is_set():
            connection.process_data_events(time_limit=FLUSH_S)
            if hold.deliveries and time.monotonic() >= hold.hold_until:
                self._handle(hold.deliveries, channel)
                channel.basic_ack(hold.deliveries[-1][1], multiple=True)
                self.messages += len(hold.deliveries)
                hold.deliveries = []
            else:
                self.publisher.idle()

    def _handle(self, deliveries: list[tuple[str, int, bytes]], channel) -> None:
        """Parse, store, hand on (module docstring). StorageUnavailable, or TimeoutError (an OSError) from the
        region publish, when that could not be done: nothing is acknowledged then."""
        s = self.settings
        now_ms = int(time.time() * 1000)
        observations: list[dict] = []
        heartbeats: list[dict] = []
        for key, _tag, body in deliveries:
            topic = mqtt_routing_key(key)
            vehicle_id, kind = vehicle_of_topic(topic), topic.rsplit("/", 1)[-1]
            if vehicle_id is None or kind not in ("observations", "heartbeat"):
                log.warning("edge queue: a message with routing key %r is no edge vehicle's; dropped", key)
                continue
            try:
                parsed = parse_edge_message(kind, body, vehicle_id=vehicle_id, settings=s, now_ms=now_ms)
                (observations if kind == "observations" else heartbeats).extend(parsed)
            except ObservationError as exc:
                self._reject(channel, vehicle_id, kind, exc)
        if observations:
            new = self.storage.put_observations(observations)
            self.region_messages += publish_observations(
                self.publisher, observations, self.region_resolution, PUBLISH_DEADLINE_S
            )
            self.observations += len(new)
            self.observation_duplicates += len(observations) - len(new)
        if heartbeats:
            stored = self.storage.put_heartbeats(heartbeats)
            self.heartbeats += stored
            self.heartbeat_duplicates += len(heartbeats) - stored

    def _reject(self, channel, vehicle_id: str, kind: str, exc: ObservationError) -> None:
        """A message refused whole: counted, logged, published on the vehicle's errors topic (as serve does)."""
        self.rejected += 1
        log.warning("rejected a %s message of vehicle %s: %s", kind, vehicle_id, exc)
        # json, not orjson: a reason quotes what was sent, which may hold a lone surrogate (escaped by json)
        body = json.dumps({"vehicle_id": vehicle_id, "rejected": [exc.to_dict()]}).encode()
        channel.basic_publish(MQTT_EXCHANGE, mqtt_routing_key(errors_topic(vehicle_id)), body)
