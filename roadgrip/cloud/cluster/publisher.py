"""HTTP telemetry into the cluster's broker (`roadgrip api`): each request's valid samples published to amq.topic with
the vehicle's telemetry routing key, as the vehicle's own MQTT publish arrives there (RabbitMQ's MQTT plugin: the topic
with '/' as '.'), so that the same binding carries it to the vehicle's partition queue and the worker that owns the
vehicle reads it like any MQTT message (roadgrip/cloud/cluster/worker.py: routing key and body only).

- Publisher confirms, `mandatory` (roadgrip/cloud/transport/amqp_client.py `ConfirmedPublisher`, and the connections'
  time-outs): a publish is done when the broker confirmed it, which for a quorum queue means a quorum of its members
  have it. A message no queue took (the topology not declared) comes back (UnroutableError) and fails the request. A
  nack or a lost connection is tried again on a new connection to the next node of the list, every RECONNECT_S
  (0.2 s), as long as the next try starts within PUBLISH_DEADLINE_S of the first; then the request fails (503). Not on
  the same channel after a nack: in four runs of the node-kill test of tests/cloud/cluster/test_api_backend.py (after
  the worker test), a channel opened on node 1 just after node 0 was killed had every publish nacked, every 0.2 s for
  the whole 10 s, while list_queues then showed the partition queues led by live nodes; elsewhere (a script, no worker
  before) a channel opened on node 1 after the kill had its publish confirmed 0.4 s after the kill. Why the channel
  stays nacked was not found. A message published twice is stored once: the worker skips the samples it has
  (vehicle_id, timestamp_ms).
- `connections` AMQP connections (a ConfirmedPublisher each, connection k starting at node k mod the nodes; pika's
  BlockingConnection is not thread-safe: one thread each, taking its work from its own queue); a vehicle always goes
  through the same one (by a hash of its id), so its requests are published in the order they came. One thread
  publishes one message at a time and waits for its confirm: the rate is about `connections` / (confirm latency)
  messages a second per replica.
"""

from __future__ import annotations

import logging
import queue
import threading
import zlib
from concurrent.futures import Future

import pika
import pika.exceptions

from roadgrip.cloud.ingest.admission import IngestUnavailable
from roadgrip.cloud.metrics import BatchHistogram
from roadgrip.cloud.transport.amqp import MQTT_EXCHANGE
from roadgrip.cloud.transport.amqp_client import ConfirmedPublisher, check_brokers

log = logging.getLogger(__name__)

DEFAULT_CONNECTIONS = 4
PUBLISH_DEADLINE_S = 10.0  # a request's publishes are tried again for this long (the failover the issue asks for)
IDLE_S = 1.0  # a connection's thread answers the broker's heartbeats after this long without work
# publish to confirm: a quorum commit is a few ms on one machine; a leader election or a slow disk takes seconds
PUBLISH_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0)
PERSISTENT = pika.BasicProperties(delivery_mode=2)
_STOP = object()


class TelemetryPublisher:
    def __init__(self, brokers: list[str], connections: int = DEFAULT_CONNECTIONS):
        check_brokers(brokers)
        if connections < 1:
            raise ValueError(f"connections must be at least 1, got {connections!r}")
        self._publishers = [ConfirmedPublisher(brokers, k, f"publisher {k}") for k in range(connections)]
        self._queues = [queue.Queue() for _ in range(connections)]
        self._threads: list[threading.Thread] = []
        self.failed_messages = 0  # given up (every node tried, or unroutable)
        self.confirm_seconds = BatchHistogram(PUBLISH_BUCKETS_S)

    @property
    def connections_up(self) -> int:
        return sum(p.connected for p in self._publishers)

    @property
    def published_messages(self) -> int:
        """Messages confirmed by the broker."""
        return sum(p.published for p in self._publishers)

    @property
    def retries(self) -> int:
        """Publishes tried again (a nack, a lost connection, no node reachable)."""
        return sum(p.retries for p in self._publishers)

    def start(self) -> None:
        for k, work in enumerate(self._queues):
            thread = threading.Thread(target=self._run, args=(k, work), name=f"amqp-publisher-{k}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        for work in self._queues:
            work.put(_STOP)
        for thread in self._threads:
            thread.join(10)
        self._threads.clear()

    def publish(self, key: str, routing_key: str, bodies: list[bytes]) -> Future:
        """Publish `bodies` in order with `routing_key` through the connection of `key` (a vehicle id). The future
        resolves to None once the broker confirmed them all, or fails with IngestUnavailable (some may have been
        taken: a retry of the request is harmless)."""
        future: Future = Future()
        self._queues[zlib.crc32(key.encode()) % len(self._queues)].put((routing_key, bodies, future))
        return future

    # -------------------------------------------------------------------------------------------- a connection's thread
    def _run(self, k: int, work: queue.Queue) -> None:
        publisher = self._publishers[k]
        while True:
            try:
                item = work.get(timeout=IDLE_S)
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if item is None:  # idle: answer the broker's heartbeats
                publisher.idle()
                continue
            routing_key, bodies, future = item
            try:
                seconds = publisher.publish(
                    MQTT_EXCHANGE,
                    routing_key,
                    bodies,
                    PERSISTENT,
                    mandatory=True,
                    deadline_s=PUBLISH_DEADLINE_S,
                    what=f"telemetry with key {routing_key}",
                )
            except pika.exceptions.UnroutableError:
                self.failed_messages += len(bodies)
                future.set_exception(
                    IngestUnavailable(
                        f"the broker did not confirm the telemetry: no queue is bound for {routing_key!r} (the partition "
                        "topology is not declared, or the vehicle id has a '.': docs/CLUSTER.md)"
                    )
                )
            except TimeoutError as exc:
                self.failed_messages += len(bodies)
                future.set_exception(IngestUnavailable(f"the broker did not confirm the telemetry: {exc}"))
            except Exception as exc:  # a request must never wait for ever on a thread that died
                log.exception("publisher %d: unexpected failure", k)
                publisher.drop()
                self.failed_messages += len(bodies)
                future.set_exception(IngestUnavailable(f"the broker did not confirm the telemetry: {exc!r}"))
            else:
                self.confirm_seconds.add([seconds])
                future.set_result(None)
        publisher.close()
