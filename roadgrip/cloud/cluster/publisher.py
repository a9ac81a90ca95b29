"""HTTP telemetry into the cluster's broker (`roadgrip api`): each request's valid samples published to amq.topic with
the vehicle's telemetry routing key, as the vehicle's own MQTT publish arrives there (RabbitMQ's MQTT plugin: the topic
with '/' as '.'), so that the same binding carries it to the vehicle's partition queue and the worker that owns the
vehicle reads it like any MQTT message (roadgrip/cloud/cluster/worker.py: routing key and body only).

- Publisher confirms, `mandatory`: a publish is done when the broker confirmed it, which for a quorum queue means a
  quorum of its members have it. A message no queue took (the topology not declared) comes back (UnroutableError) and
  fails the request. A nack or a lost connection is tried again on a new connection to the next node of the list,
  every RETRY_S, until PUBLISH_DEADLINE_S after the first try; then the request fails (503). Not on the same
  channel after a nack: in four runs of the node-kill test of tests/cloud/cluster/test_api_backend.py (after the worker test),
  a channel opened on node 1 just after node 0 was killed had every publish nacked, every 0.2 s for the whole 10 s,
  while list_queues then showed the partition queues led by live nodes; elsewhere (a script, no worker before) a
  channel opened on node 1 after the kill had its publish confirmed 0.4 s after the kill. Why the channel stays
  nacked was not found. A message published
  twice is stored once: the worker skips the samples it has (vehicle_id, timestamp_ms).
- `connections` AMQP connections (pika's BlockingConnection, not thread-safe: one thread each, taking its work from
  its own queue); a vehicle always goes through the same one (by a hash of its id), so its requests are published in
  the order they came. One thread publishes one message at a time and waits for its confirm: the rate is about
  `connections` / (confirm latency) messages a second per replica.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import zlib
from concurrent.futures import Future

import pika
import pika.exceptions

from roadgrip.cloud.ingest.admission import IngestUnavailable
from roadgrip.cloud.metrics import BatchHistogram
from roadgrip.cloud.transport.amqp import MQTT_EXCHANGE

log = logging.getLogger(__name__)

DEFAULT_CONNECTIONS = 4
HEARTBEAT_S = 10
CONNECT_TIMEOUT_S = 2.0
PUBLISH_DEADLINE_S = 10.0  # a request's publishes are tried again for this long (the failover the issue asks for)
RETRY_S = 0.2
# publish to confirm: a quorum commit is a few ms on one machine; a leader election or a slow disk takes seconds
PUBLISH_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0)
_STOP = object()


class _Failed(Exception):
    """A publish given up; `state` is the thread's (connection, channel, node) after it."""

    def __init__(self, reason: str, state: tuple):
        super().__init__(reason)
        self.state = state


class TelemetryPublisher:
    def __init__(self, brokers: list[str], connections: int = DEFAULT_CONNECTIONS):
        if not brokers:
            raise ValueError("at least one broker URL (amqp://user:password@host:port/vhost) is needed")
        if connections < 1:
            raise ValueError(f"connections must be at least 1, got {connections!r}")
        self.parameters = []
        for url in brokers:
            try:
                parameters = pika.URLParameters(url)
            except ValueError as exc:
                raise ValueError(f"invalid broker URL {url!r}: {exc}") from None
            parameters.heartbeat = HEARTBEAT_S
            parameters.blocked_connection_timeout = 30
            parameters.socket_timeout = CONNECT_TIMEOUT_S
            self.parameters.append(parameters)
        self._queues = [queue.Queue() for _ in range(connections)]
        self._threads: list[threading.Thread] = []
        self._connected = [False] * connections
        self.published_messages = 0  # confirmed by the broker
        self.failed_messages = 0     # given up (every node tried, or unroutable)
        self.retries = 0
        self.confirm_seconds = BatchHistogram(PUBLISH_BUCKETS_S)

    @property
    def connections_up(self) -> int:
        return sum(self._connected)

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
        node = k % len(self.parameters)  # spread the connections over the nodes
        connection = channel = None
        while True:
            try:
                item = work.get(timeout=1.0)
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if item is None:  # idle: answer the broker's heartbeats
                if connection is not None:
                    try:
                        connection.process_data_events(0)
                    except pika.exceptions.AMQPError as exc:
                        log.warning("publisher %d: connection to node %d lost while idle: %r", k, node, exc)
                        self._close(k, connection)
                        connection = channel = None
                        node = (node + 1) % len(self.parameters)
                continue
            routing_key, bodies, future = item
            try:
                connection, channel, node = self._publish(k, connection, channel, node, routing_key, bodies)
            except _Failed as exc:
                connection, channel, node = exc.state
                self.failed_messages += len(bodies)
                future.set_exception(IngestUnavailable(f"the broker did not confirm the telemetry: {exc}"))
            except Exception as exc:  # a request must never wait for ever on a thread that died
                log.exception("publisher %d: unexpected failure", k)
                self._close(k, connection)
                connection = channel = None
                self.failed_messages += len(bodies)
                future.set_exception(IngestUnavailable(f"the broker did not confirm the telemetry: {exc!r}"))
            else:
                self.published_messages += len(bodies)
                future.set_result(None)
        self._close(k, connection)

    def _publish(self, k: int, connection, channel, node: int, routing_key: str, bodies: list[bytes]):
        """Publish `bodies` and wait for their confirms, trying again as the module docstring says; the thread's
        (connection, channel, node) afterwards. _Failed, with them, when it gave up."""
        deadline = time.monotonic() + PUBLISH_DEADLINE_S
        failure = None
        while failure is None or time.monotonic() < deadline:
            if failure is not None:
                self.retries += 1
                log.warning("publisher %d: %s; trying again", k, failure)
                time.sleep(RETRY_S)
            if channel is None:
                try:
                    connection = pika.BlockingConnection(self.parameters[node])
                    channel = connection.channel()
                    channel.confirm_delivery()
                    self._connected[k] = True
                except pika.exceptions.AMQPError as exc:
                    failure = f"cannot connect to node {node}: {exc!r}"
                    self._close(k, connection)
                    connection = channel = None
                    node = (node + 1) % len(self.parameters)
                    continue
            try:
                started = time.monotonic()
                for body in bodies:
                    channel.basic_publish(MQTT_EXCHANGE, routing_key, body, mandatory=True,
                                          properties=pika.BasicProperties(delivery_mode=2))
                self.confirm_seconds.add([time.monotonic() - started])
                return connection, channel, node
            except pika.exceptions.UnroutableError:
                raise _Failed(f"no queue is bound for {routing_key!r} (the partition topology is not declared, or "
                              "the vehicle id has a '.': docs/CLUSTER.md)", (connection, channel, node)) from None
            except pika.exceptions.AMQPError as exc:  # NackError too: a fresh connection, see the module docstring
                failure = f"node {node}: {exc!r}"
                self._close(k, connection)
                connection = channel = None
                node = (node + 1) % len(self.parameters)
        raise _Failed(failure, (connection, channel, node))

    def _close(self, k: int, connection) -> None:
        self._connected[k] = False
        if connection is not None and connection.is_open:
            try:
                connection.close()
            except pika.exceptions.AMQPError:
                pass  # closing a connection that already failed
