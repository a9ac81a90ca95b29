"""AMQP connections to the RabbitMQ cluster (cluster mode, docs/CLUSTER.md): the one place that builds them, with one
set of time-outs, and the two ways the cluster uses a connection.

- `connect(brokers, start)`: a pika BlockingConnection to the first of the brokers' AMQP URLs that answers, trying
  brokers[start], brokers[start + 1], ... (mod the list) in turn, each once (failover). A user that spreads its
  connections over the nodes gives each a different `start` (a worker's partition p starts at node p mod the nodes).
- `ConfirmedPublisher`: publishes with publisher confirms through one connection at a time, and after a failure (a
  nack, a lost connection, no broker reachable) publishes again on a new connection, from the next broker, until
  confirmed or a deadline passes. Its users: a worker's region messages and an API replica's station evidence
  (roadgrip/cloud/cluster/regions.py), an API replica's telemetry (roadgrip/cloud/cluster/publisher.py).
- `consume(...)`: holds a consumer through one connection at a time until told to stop, connecting again through the
  next broker after a failure; with a queue with single-active-consumer, each connection is one registration: the
  consumer is active from its first delivery until the connection is closed, when the broker makes the next
  registered consumer active (roadgrip/cloud/transport/amqp.py). Its users: a worker's partition queues and its
  live-worker count (roadgrip/cloud/cluster/worker.py), the region queues (roadgrip/cloud/cluster/regions.py).

Time-outs, the same for every connection (pika's BlockingConnection; `connection_parameters`):

| setting | value | what it bounds |
| --- | --- | --- |
| heartbeat | HEARTBEAT_S, 5 s | a silent broker (a node frozen, not killed: no connection reset) is given up 10 to 20 s after it fell silent (pika looks for received data every HEARTBEAT_S + 5 s and gives up after one such window without any) |
| socket_timeout | SOCKET_TIMEOUT_S, 2 s | a connection attempt to a node that does not answer (a refused one fails at once) |
| blocked_connection_timeout | BLOCKED_CONNECTION_TIMEOUT_S, 10 s | a connection the broker blocks (a memory or disk alarm) is closed after this, and the next node tried |
| connection_attempts | 1 | each node once per `connect`; waiting and trying again is the caller's (RECONNECT_S) |

The workers had these; the API's telemetry publisher had a heartbeat of 10 s (a frozen node given up after 15 to
30 s) and a blocked-connection timeout of 30 s. The workers' values are kept for all: they are the shorter, and an API
request's publishes are given up PUBLISH_DEADLINE_S (10 s, roadgrip/cloud/cluster/publisher.py) after its first try,
a deadline checked between tries only, so a try held by a frozen or blocked node keeps the request past it for less
time with them; the workers' failover, which the cluster tests measure, is unchanged.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

import pika
import pika.exceptions

log = logging.getLogger(__name__)

HEARTBEAT_S = 5
SOCKET_TIMEOUT_S = 2.0
BLOCKED_CONNECTION_TIMEOUT_S = 10.0
RECONNECT_S = 0.2  # the wait before connecting again after a failure (through the next broker)


class BrokersUnreachable(pika.exceptions.AMQPConnectionError):
    """No broker of the list accepted a connection; the message names each one's failure."""


def connection_parameters(url: str) -> pika.URLParameters:
    """pika's parameters of an AMQP URL (amqp://user:password@host:port/vhost) with the module's time-outs;
    ValueError naming the URL when it is not one."""
    try:
        parameters = pika.URLParameters(url)
    except ValueError as exc:
        raise ValueError(f"invalid broker URL {url!r}: {exc}") from None
    parameters.heartbeat = HEARTBEAT_S
    parameters.socket_timeout = SOCKET_TIMEOUT_S
    parameters.blocked_connection_timeout = BLOCKED_CONNECTION_TIMEOUT_S
    parameters.connection_attempts = 1
    return parameters


def check_brokers(brokers: list[str]) -> list[str]:
    """The brokers' AMQP URLs, checked: at least one, each a valid URL (ValueError naming it)."""
    if not brokers:
        raise ValueError("brokers must name at least one AMQP URL (amqp://user:password@host:port/%2F), got none")
    for url in brokers:
        connection_parameters(url)
    return list(brokers)


def connect(brokers: list[str], start: int = 0) -> tuple[pika.BlockingConnection, int]:
    """A connection to the first broker that accepts one, trying brokers[start], brokers[start + 1], ... (mod the
    list) each once; with the index (start + k, not reduced) of the one that answered, for the caller's next try to
    go on from. BrokersUnreachable when none did."""
    failures = []
    for k in range(len(brokers)):
        index = start + k
        try:
            return pika.BlockingConnection(connection_parameters(brokers[index % len(brokers)])), index
        except pika.exceptions.AMQPError as exc:
            failures.append(f"broker {index % len(brokers)}: {exc!r}")
    raise BrokersUnreachable(f"no broker of {len(brokers)} reachable: {'; '.join(failures)}")


def close_quietly(connection: pika.BlockingConnection | None, what: str) -> None:
    """Close a connection given up, if still open; a failure to close it is only logged (it failed already)."""
    if connection is not None and connection.is_open:
        try:
            connection.close()
        except (pika.exceptions.AMQPError, OSError):
            log.debug("%s: closing the given-up connection failed", what, exc_info=True)


class ConfirmedPublisher:
    """Publishes with publisher confirms through the brokers' AMQP URLs, one connection at a time (from
    brokers[start]), moving to the next broker after a failure (module docstring); also publishes without a confirm
    on a channel of its own. Calls from several threads are serialised by one lock (pika's connection is not
    thread-safe). `what` names it in the log."""

    def __init__(self, brokers: list[str], start: int = 0, what: str = "publisher"):
        self.brokers = check_brokers(brokers)
        self.what = what
        self.published = 0  # messages confirmed
        self.failures = 0  # tries that failed (a nack, a lost connection, no broker reachable)
        self.retries = 0  # failed tries made again
        self._index = start
        self._connection: pika.BlockingConnection | None = None
        self._confirmed = None  # a channel in confirm mode
        self._plain = None  # a channel for publishes without a confirm
        self._lock = threading.Lock()
        self._closing = threading.Event()

    @property
    def connected(self) -> bool:
        """Whether it holds an open connection (read from any thread)."""
        return self._connection is not None

    @property
    def broker(self) -> int:
        """The index in the list of the broker it publishes through (or will try next)."""
        return self._index % len(self.brokers)

    def _connect(self) -> None:
        self._connection, self._index = connect(self.brokers, self._index)
        self._confirmed = self._connection.channel()
        self._confirmed.confirm_delivery()
        self._plain = self._connection.channel()

    def _drop(self) -> None:
        """Close the connection after a failure; the next try goes through the next broker."""
        connection, self._connection, self._confirmed, self._plain = self._connection, None, None, None
        close_quietly(connection, self.what)
        self._index += 1

    def drop(self) -> None:
        """Give the connection up (after a failure the caller saw): the next publish connects again, through the
        next broker."""
        with self._lock:
            if self._connection is not None:
                self._drop()

    def publish(
        self,
        exchange: str,
        routing_key: str,
        bodies: list[bytes],
        properties: pika.BasicProperties,
        mandatory: bool = False,
        deadline_s: float | None = None,
        what: str = "a message",
    ) -> float:
        """Publish `bodies` in order, each waiting for its confirm; on a failure (a nack, a lost connection, no
        broker reachable) publish them all again on a new connection, from the next broker, every RECONNECT_S,
        until all are confirmed (a message confirmed before the failure is then published twice: the consumers take
        repeats once). Returns the seconds the try that was confirmed took.

        Without `deadline_s` it tries until confirmed (a worker's pipeline waits so: its deliveries stay
        unacknowledged meanwhile); with it, TimeoutError once the next try would start past `deadline_s` after the
        call (an HTTP request cannot wait for ever). The deadline counts the wait for another thread's publish and is
        checked between tries: a try under way is not cut short (a connection attempt ends after SOCKET_TIMEOUT_S; a
        silent broker is given up by the heartbeat; a broker that stays connected without confirming holds the try
        until it confirms). With `mandatory`, a message no queue took raises pika's UnroutableError at once (the
        topology is not declared: another broker would not route it either). RuntimeError once `close` was called
        and it is still not confirmed. `what` names the message in errors and the log."""
        started = time.monotonic()
        if not self._lock.acquire(timeout=-1 if deadline_s is None else max(0.0, deadline_s)):
            raise TimeoutError(
                f"{what} not published within {deadline_s:.1f} s: the publisher was busy with "
                "another message all that time"
            )
        try:
            while True:
                try:
                    if self._connection is None:
                        self._connect()
                    try_started = time.monotonic()
                    for body in bodies:
                        self._confirmed.basic_publish(exchange, routing_key, body, properties, mandatory=mandatory)
                    self.published += len(bodies)
                    return time.monotonic() - try_started
                except pika.exceptions.UnroutableError:
                    raise
                except (
                    pika.exceptions.AMQPError,
                    OSError,
                ) as exc:  # a nack too: a new connection, publisher.py says why
                    self.failures += 1
                    log.warning("%s: %s not confirmed through broker %d (%r)", self.what, what, self.broker, exc)
                    if self._connection is not None:
                        self._drop()
                    if self._closing.is_set():
                        raise RuntimeError(f"{what} not confirmed before the close") from exc
                    if deadline_s is not None and time.monotonic() - started + RECONNECT_S > deadline_s:
                        raise TimeoutError(f"{what} not confirmed within {deadline_s:.1f} s (last: {exc!r})") from exc
                    self.retries += 1
                    time.sleep(RECONNECT_S)
        finally:
            self._lock.release()

    def publish_unconfirmed(self, exchange: str, routing_key: str, body: bytes) -> None:
        """Publish without a confirm: at most once. A failure is logged and the message dropped (the next publish
        goes through the next broker)."""
        with self._lock:
            try:
                if self._connection is None:
                    self._connect()
                self._plain.basic_publish(exchange, routing_key, body)
            except (pika.exceptions.AMQPError, OSError) as exc:
                log.warning("%s: publishing with key %s failed (%r): dropped", self.what, routing_key, exc)
                if self._connection is not None:
                    self._drop()

    def idle(self) -> None:
        """Let the connection answer the broker's heartbeats (call it when idle, at least every HEARTBEAT_S / 2)."""
        with self._lock:
            if self._connection is None:
                return
            try:
                self._connection.process_data_events(time_limit=0)
            except (pika.exceptions.AMQPError, OSError) as exc:
                log.warning("%s: connection through broker %d lost while idle (%r)", self.what, self.broker, exc)
                self._drop()

    def close(self) -> None:
        """Close the connection; a publish still trying gives up (RuntimeError)."""
        self._closing.set()
        with self._lock:
            connection, self._connection, self._confirmed, self._plain = self._connection, None, None, None
            close_quietly(connection, self.what)


class ConsumerAttempt(Protocol):
    """One connection's life in `consume`."""

    def run(self, connection: pika.BlockingConnection) -> None:
        """Register the consumer on `connection` and serve it; return to have the connection closed and register
        again (a release, or the stop), raise to give the connection up."""

    def ended(self, exc: BaseException | None, broker: int) -> None:
        """After the connection was closed: `exc` None when `run` returned, else what it (or the close) raised;
        `broker` the index in the list of the broker it went through."""


def consume(
    brokers: list[str],
    start: int,
    closing: threading.Event,
    attempt: Callable[[], ConsumerAttempt],
    what: str,
    errors: tuple[type[BaseException], ...] = (),
) -> None:
    """Until `closing` is set: connect (`connect`, from brokers[start]), run a fresh `attempt()` on the connection,
    close it, tell the attempt how it ended. A connection given up (pika's errors, OSError, or one of `errors`
    raised by the attempt) is closed, and the next attempt goes through the next broker after RECONNECT_S; after a
    normal end, through the same one at once. `what` names the consumer in the log."""
    index = start
    while not closing.is_set():
        try:
            connection, index = connect(brokers, index)
        except BrokersUnreachable as exc:
            log.warning("%s: %s", what, exc)
            time.sleep(RECONNECT_S)
            continue
        current = attempt()
        try:
            current.run(connection)
            connection.close()
        except (pika.exceptions.AMQPError, OSError, *errors) as exc:
            close_quietly(connection, what)  # given up: what it was delivered and did not acknowledge goes back
            current.ended(exc, index % len(brokers))
            if closing.is_set():
                return
            index += 1
            time.sleep(RECONNECT_S)
        else:
            current.ended(None, index % len(brokers))
