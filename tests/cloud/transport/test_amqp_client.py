"""The AMQP connection builder, the confirmed publisher and the consumer loop (roadgrip/cloud/transport/amqp_client.py)
without a broker: the time-outs every connection gets, failover over the list, the deadline of a publish nobody
confirms, and how `consume` moves between brokers (a fake connection). With RabbitMQ: tests/cloud/cluster."""

from __future__ import annotations

import threading
import time

import pika.exceptions
import pytest

from roadgrip.cloud.localhost import free_ports
from roadgrip.cloud.transport import amqp_client
from roadgrip.cloud.transport.amqp_client import (
    BLOCKED_CONNECTION_TIMEOUT_S,
    HEARTBEAT_S,
    RECONNECT_S,
    SOCKET_TIMEOUT_S,
    BrokersUnreachable,
    ConfirmedPublisher,
    check_brokers,
    connect,
    connection_parameters,
    consume,
)


def refused_urls(n: int) -> list[str]:
    """AMQP URLs of ports nothing listens on (a connection is refused at once)."""
    return [f"amqp://svc:x@127.0.0.1:{port}/%2F" for port in free_ports(n)]


def test_every_connection_gets_the_same_time_outs():
    parameters = connection_parameters("amqp://svc:secret@127.0.0.1:5672/%2F")
    assert parameters.heartbeat == HEARTBEAT_S == 5
    assert parameters.socket_timeout == SOCKET_TIMEOUT_S == 2.0
    assert parameters.blocked_connection_timeout == BLOCKED_CONNECTION_TIMEOUT_S == 10.0
    assert parameters.connection_attempts == 1
    assert (parameters.host, parameters.port, parameters.virtual_host) == ("127.0.0.1", 5672, "/")


def test_broker_urls_are_checked_naming_the_bad_one():
    with pytest.raises(ValueError, match="at least one AMQP URL"):
        check_brokers([])
    with pytest.raises(ValueError, match="invalid broker URL 'amqp://svc:x@127.0.0.1:port/%2F'"):
        check_brokers(["amqp://svc:x@127.0.0.1:5672/%2F", "amqp://svc:x@127.0.0.1:port/%2F"])
    with pytest.raises(ValueError, match="at least one AMQP URL"):
        ConfirmedPublisher([])


def test_connect_tries_each_broker_once_from_start_and_names_each_failure():
    urls = refused_urls(3)
    with pytest.raises(BrokersUnreachable) as raised:
        connect(urls, start=4)
    message = str(raised.value)
    assert message.startswith("no broker of 3 reachable: broker 1: ")
    assert message.index("broker 1:") < message.index("broker 2:") < message.index("broker 0:")


def test_a_publish_nobody_confirms_is_given_up_at_its_deadline_after_trying_again():
    publisher = ConfirmedPublisher(refused_urls(2), what="test publisher")
    started = time.monotonic()
    try:
        with pytest.raises(TimeoutError, match=r"message m not confirmed within 0\.7 s \(last: .*no broker of 2"):
            publisher.publish(
                "rg.estimates", "key", [b"body"], pika.BasicProperties(), deadline_s=0.7, what="message m"
            )
    finally:
        publisher.close()
    took_s = time.monotonic() - started
    assert 0.7 - 2 * RECONNECT_S <= took_s < 0.7 + 0.3  # no sleep past the deadline
    assert publisher.published == 0 and not publisher.connected
    assert publisher.failures >= 3 and publisher.retries == publisher.failures - 1
    with pytest.raises(RuntimeError, match="not confirmed before the close"):
        publisher.publish("rg.estimates", "key", [b"body"], pika.BasicProperties(), what="message n")


class FakeConnection:
    def __init__(self, broker: int):
        self.broker = broker
        self.is_open = True

    def close(self) -> None:
        self.is_open = False


class Attempt:
    """Serves once per connection as `plan` says: 'release' returns, 'lose' raises a lost connection, 'storage' one
    of the caller's errors; records how each ended."""

    def __init__(self, plan: list[str], log: list, closing: threading.Event):
        self.plan, self.log, self.closing = plan, log, closing

    def run(self, connection: FakeConnection) -> None:
        step = self.plan.pop(0)
        if not self.plan:
            self.closing.set()
        if step == "lose":
            raise pika.exceptions.StreamLostError("lost")
        if step == "storage":
            raise LookupError("the database is down")

    def ended(self, exc, broker: int) -> None:
        self.log.append((type(exc).__name__ if exc else None, broker))


def test_consume_registers_again_on_the_same_broker_after_a_release_and_on_the_next_after_a_failure(monkeypatch):
    connections = []

    def fake_connect(brokers, start=0):
        connections.append(FakeConnection(start % len(brokers)))
        return connections[-1], start

    monkeypatch.setattr(amqp_client, "connect", fake_connect)
    monkeypatch.setattr(amqp_client, "RECONNECT_S", 0.0)
    closing = threading.Event()
    plan, log = ["release", "lose", "release", "storage", "lose"], []
    consume(["a", "b", "c"], 1, closing, lambda: Attempt(plan, log, closing), "test", (LookupError,))
    assert log == [(None, 1), ("StreamLostError", 1), (None, 2), ("LookupError", 2), ("StreamLostError", 0)]
    assert [c.broker for c in connections] == [1, 1, 2, 2, 0]
    assert not any(c.is_open for c in connections)  # every connection closed, released or given up


def test_consume_waits_and_tries_again_while_no_broker_answers_and_stops_when_told():
    closing = threading.Event()
    attempts = []
    thread = threading.Thread(target=consume, args=(refused_urls(2), 0, closing, lambda: attempts.append(1), "test"))
    thread.start()
    time.sleep(3 * RECONNECT_S)
    closing.set()
    thread.join(5)
    assert not thread.is_alive() and attempts == []
