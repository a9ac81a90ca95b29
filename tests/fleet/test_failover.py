"""A vehicle's MQTT connection fails over (roadgrip/fleet/transport.py `FailoverConnection`): two real Mosquitto
brokers on free ports, one killed while the vehicle sends. What the vehicle sent is either PUBACKed (and then arrived
at a subscriber) or counted lost; nothing raises.

The brokers are frozen with SIGSTOP before they are killed, so that what the vehicle sends in between is written but
never PUBACKed: the messages the client must resend after it moves. Waits are on conditions (`wait_until`), never on a
fixed sleep; the outage clock is injected."""

from __future__ import annotations

import itertools
import json
import os
import random
import signal

import pytest
from broker_fixtures import Inbox, wait_until

from roadgrip.cloud.localhost import free_port
from roadgrip.cloud.transport.mosquitto import INSTALL_HINT, ManagedBroker, mosquitto_available
from roadgrip.cloud.transport.mqtt import MqttClient
from roadgrip.fleet.transport import FleetError, MqttTerminals

VEHICLE, SECRET = "car-1", "car-1-secret-0123456789"


@pytest.fixture
def brokers(tmp_path):
    """Two Mosquitto brokers, each with the vehicle's login and a service subscribed to the telemetry (its Inbox)."""
    if not mosquitto_available():
        pytest.fail(f"mosquitto is not installed: {INSTALL_HINT}", pytrace=False)
    started = []
    try:
        for name in ("a", "b"):
            broker = ManagedBroker(tmp_path / name)
            broker.start()
            broker.set_user(VEHICLE, SECRET, "vehicle")
            inbox = Inbox()
            service = MqttClient(broker.url, broker.service_user, broker.service_password, f"svc-{name}", inbox)
            service.connect()
            started.append((broker, service, inbox))
        yield started
    finally:
        for broker, service, _ in started:
            service.close()
            broker.stop()


def _sample(k: int) -> dict:
    return {"vehicle_id": VEHICLE, "timestamp_ms": k}


def _received(inbox: Inbox, expected: set[int]) -> set[int]:
    """The samples (timestamps) that reached the subscriber, once all of `expected` have (the broker passes a message
    on after its PUBACK) or the wait fails."""
    got: set[int] = set()

    def arrived() -> bool:
        while not inbox.empty():
            got.update(json.loads(payload)["timestamp_ms"] for _, payload in inbox.payloads(1))
        return got >= expected

    wait_until(arrived, what=f"samples {sorted(expected)} at the subscriber")
    return got


def _freeze_then_kill(broker: ManagedBroker, between) -> None:
    pid = broker._process.pid  # ManagedBroker has no kill of its own: a crash, not its clean stop()
    os.kill(pid, signal.SIGSTOP)
    between()
    os.kill(pid, signal.SIGKILL)
    broker._process.wait()


@pytest.mark.parametrize("protocol", ["5", "3.1.1"])
def test_a_vehicle_moves_to_the_live_broker_and_resends_what_was_not_pubacked(brokers, protocol):
    (a, _, inbox_a), (b, _, inbox_b) = brokers
    terminals = MqttTerminals(
        [a.url, b.url],
        {VEHICLE: SECRET},
        protocol,
        reconnect_min_delay_s=0.05,
        clock=itertools.count().__next__,  # each reading one tick on: an outage spans exactly one
        rng=random.Random(0),
    )
    connection = terminals.connections[VEHICLE]
    assert connection.counts.endpoint == a.url
    for k in range(10):
        terminals.send(VEHICLE, [_sample(k)])
    wait_until(lambda: connection.counts.acknowledged == 10, what="10 PUBACKs from broker a")

    def send_unacknowledged():
        for k in range(10, 20):
            terminals.send(VEHICLE, [_sample(k)])
        wait_until(lambda: connection.unacknowledged_messages == 10, what="10 messages in flight")

    _freeze_then_kill(a, send_unacknowledged)
    for k in range(20, 30):  # produced while the connection is down or moving: buffered, then sent
        terminals.send(VEHICLE, [_sample(k)])
    terminals.close(timeout_s=30)

    counts = terminals.counts[VEHICLE]
    assert (counts.sent, counts.acknowledged, counts.lost) == (30, 30, 0)
    assert (counts.endpoint, counts.moves, counts.connects) == (b.url, 1, 2)
    assert counts.longest_outage_s == 1
    assert _received(inbox_a, set(range(10))) == set(range(10))  # a PUBACKed these and passed them on before it died
    assert _received(inbox_b, set(range(10, 30))) == set(range(10, 30))  # the ten never PUBACKed, then the buffered


def test_a_full_buffer_counts_what_it_drops_as_lost(brokers):
    (a, _, _), _ = brokers
    terminals = MqttTerminals([a.url], {VEHICLE: SECRET}, "5", buffer_messages=5)
    connection = terminals.connections[VEHICLE]
    os.kill(a._process.pid, signal.SIGSTOP)  # nothing is PUBACKed while it is frozen
    try:
        for k in range(8):
            terminals.send(VEHICLE, [_sample(k), _sample(100 + k)])
    finally:
        os.kill(a._process.pid, signal.SIGCONT)
    terminals.close(timeout_s=30)
    counts = connection.counts
    assert (counts.sent, counts.acknowledged, counts.dropped, counts.lost) == (16, 10, 6, 6)


def test_what_is_never_pubacked_is_counted_lost_and_close_does_not_raise(brokers):
    (a, _, _), _ = brokers
    terminals = MqttTerminals([a.url], {VEHICLE: SECRET}, "3.1.1", reconnect_min_delay_s=0.05)
    _freeze_then_kill(a, lambda: terminals.send(VEHICLE, [_sample(1), _sample(2), _sample(3)]))
    wait_until(lambda: not terminals.connections[VEHICLE].connected, what="the connection lost")
    terminals.send(VEHICLE, [_sample(4)])  # while disconnected: the reported crash raised on such a message
    terminals.close(timeout_s=0.5)
    counts = terminals.counts[VEHICLE]
    assert (counts.sent, counts.acknowledged, counts.unacknowledged, counts.lost) == (4, 0, 4, 4)


def test_a_refused_login_and_no_live_broker_are_one_line_errors(brokers):
    (a, _, _), _ = brokers
    with pytest.raises(FleetError, match="refused 'car-1'"):
        MqttTerminals([a.url], {VEHICLE: "wrong-secret-0123456789"}, "5")
    with pytest.raises(FleetError, match="reached none of the brokers"):
        MqttTerminals([f"mqtt://127.0.0.1:{free_port()}"], {VEHICLE: SECRET}, "5", connect_timeout_s=0.5)
