"""Topics, the service's MqttClient and the vehicles' client against a real Mosquitto (broker_fixtures.managed_broker):
the ACL as each side sees it, persistent sessions, manual acknowledgement and reconnects."""

import threading

import broker_fixtures
import paho.mqtt.client as paho
import pytest
from broker_fixtures import Inbox, wait_until
from paho.mqtt.enums import CallbackAPIVersion

from roadgrip.cloud.transport.mosquitto import MAX_INFLIGHT_MESSAGES
from roadgrip.cloud.transport.mqtt import (
    FRICTION_SUBSCRIPTION,
    TELEMETRY_SUBSCRIPTION,
    WARNINGS_TOPIC,
    BrokerRefused,
    MqttClient,
    PublishRefused,
    UserClient,
    VehicleClient,
    errors_topic,
    friction_topic,
    parse_url,
    telemetry_topic,
    vehicle_of_topic,
)

NOT_AUTHORIZED = 0x87

managed_broker = broker_fixtures.managed_broker  # the fixture


def test_topics():
    assert telemetry_topic("car-1") == "roadgrip/v1/vehicles/car-1/telemetry"
    assert friction_topic("car-1") == "roadgrip/v1/vehicles/car-1/friction"
    assert errors_topic("car-1") == "roadgrip/v1/vehicles/car-1/errors"
    assert WARNINGS_TOPIC == "roadgrip/v1/warnings"
    assert TELEMETRY_SUBSCRIPTION == "roadgrip/v1/vehicles/+/telemetry"
    assert FRICTION_SUBSCRIPTION == "roadgrip/v1/vehicles/+/friction"
    for topic in (telemetry_topic("A.b_9"), friction_topic("A.b_9"), errors_topic("A.b_9")):
        assert vehicle_of_topic(topic) == "A.b_9"
    for topic in (
        "roadgrip/v1/warnings",
        "roadgrip/v1/vehicles/car-1",
        "roadgrip/v1/vehicles/car-1/other",
        "roadgrip/v1/vehicles/a/b/telemetry",
        "roadgrip/v1/vehicles//telemetry",
        "x/car-1/telemetry",
    ):
        assert vehicle_of_topic(topic) is None, topic
    for bad in ("", "+", "#", "a/b", "a b", "x" * 65):
        with pytest.raises(ValueError, match="vehicle_id must match"):
            telemetry_topic(bad)


def test_parse_url():
    assert parse_url("mqtt://127.0.0.1:1884") == ("127.0.0.1", 1884)
    assert parse_url("mqtt://broker") == ("broker", 1883)
    for bad in ("http://x:1", "mqtt://", "127.0.0.1:1883", "mqtt://x:1/path"):
        with pytest.raises(ValueError, match="url must be"):
            parse_url(bad)


@pytest.fixture
def fleet(managed_broker):
    """Two vehicles, A and B, and a reader; the broker."""
    for name in ("A", "B"):
        managed_broker.set_user(name, f"secret-{name}", "vehicle", name)
    managed_broker.set_user("dash", "secret-dash", "reader")
    return managed_broker


def until_end(messages):
    """Topics of the messages in a UserClient's queue, up to the one with payload b"end" (not included)."""
    topics = []
    while (message := messages.get(timeout=5))[1] != b"end":
        topics.append(message[0])
    return topics


def service(broker, inbox=None, client_id="svc"):
    client = MqttClient(broker.url, broker.service_user, broker.service_password, client_id, on_telemetry=inbox)
    client.connect(timeout_s=5)
    return client


def vehicle(broker, name):
    return VehicleClient(broker.url, name, f"secret-{name}").connect(timeout_s=5)


def test_service_receives_a_vehicles_telemetry_with_the_id_from_the_topic(fleet):
    inbox = Inbox()
    svc = MqttClient(fleet.url, fleet.service_user, fleet.service_password, "svc", on_telemetry=inbox)
    with svc, VehicleClient(fleet.url, "A", "secret-A") as a:  # entering connects
        assert svc.connected and a.paho.is_connected()
        a.publish_telemetry(b'{"n": 1}')
        assert inbox.payloads(1) == [("A", b'{"n": 1}')]


def test_the_broker_allows_max_inflight_messages_unacknowledged_and_the_client_checks_it(fleet, caplog):
    # the broker's Receive Maximum is exactly MAX_INFLIGHT_MESSAGES: a client set to it passes the check, one more not
    for max_inflight, complaint in ((MAX_INFLIGHT_MESSAGES, False), (MAX_INFLIGHT_MESSAGES + 1, True)):
        caplog.clear()
        with MqttClient(fleet.url, fleet.service_user, fleet.service_password, "svc", max_inflight=max_inflight) as svc:
            assert svc._client.max_inflight_messages == max_inflight
        assert any("unacknowledged publishes" in r.message for r in caplog.records) == complaint


def test_the_service_client_counts_its_publishes_until_the_broker_acknowledges_them(fleet):
    with service(fleet) as svc:
        for k in range(50):
            svc.publish(WARNINGS_TOPIC, f"w{k}")
        assert 0 < svc.unacknowledged <= 50
        wait_until(lambda: svc.unacknowledged == 0, what="every PUBACK")


def test_a_vehicle_publishing_under_another_id_is_refused_and_never_reaches_the_service(fleet):
    """MQTT 5: PUBACK 0x87 (PublishRefused). MQTT 3.1.1: a plain PUBACK, so the publisher believes it went through;
    either way the service never sees it (the sentinel that follows arrives alone)."""
    inbox = Inbox()
    with service(fleet, inbox), vehicle(fleet, "A") as a:
        with pytest.raises(PublishRefused) as refused:
            a.publish(telemetry_topic("B"), b"forged v5")
        assert refused.value.reason_code.value == NOT_AUTHORIZED
        assert a.refused == 1 and a.paho.is_connected()  # the connection stays up

        old = paho.Client(CallbackAPIVersion.VERSION2, client_id="A-311", protocol=paho.MQTTv311)
        old.username_pw_set("A", "secret-A")
        old.connect(*parse_url(fleet.url))
        old.loop_start()
        try:
            info = old.publish(telemetry_topic("B"), b"forged v3.1.1", qos=1)
            info.wait_for_publish(5)
            assert info.is_published() and info.rc == paho.MQTT_ERR_SUCCESS  # looks delivered
        finally:
            old.disconnect()
            old.loop_stop()

        a.publish_telemetry(b"sentinel")
        assert inbox.payloads(1) == [("A", b"sentinel")]
        assert inbox.empty()


def test_a_vehicle_reads_only_its_own_friction_and_errors_and_the_warnings(fleet):
    with service(fleet) as svc, vehicle(fleet, "A") as a:
        assert a.subscribe(friction_topic("B")) == 1  # Mosquitto grants the subscription ...
        assert a.subscribe(FRICTION_SUBSCRIPTION) == 1
        for topic in (errors_topic("A"), WARNINGS_TOPIC):
            a.subscribe(topic)
        for topic in (friction_topic("B"), errors_topic("B"), friction_topic("A"), errors_topic("A"), WARNINGS_TOPIC):
            svc.publish(topic, b"x").wait_for_publish(5)
        svc.publish(WARNINGS_TOPIC, b"end").wait_for_publish(5)
        got = until_end(a.messages)
        # ... and delivers nothing of B's: the ACL is checked on each delivery
        assert got == [friction_topic("A"), errors_topic("A"), WARNINGS_TOPIC]


def test_a_reader_reads_all_friction_but_cannot_publish(fleet):
    with service(fleet) as svc, UserClient(fleet.url, "dash", "secret-dash").connect() as dash:
        dash.subscribe(FRICTION_SUBSCRIPTION)
        dash.subscribe(WARNINGS_TOPIC)
        for topic in (friction_topic("A"), friction_topic("B"), errors_topic("A"), WARNINGS_TOPIC):
            svc.publish(topic, b"mu").wait_for_publish(5)
        svc.publish(WARNINGS_TOPIC, b"end").wait_for_publish(5)
        assert until_end(dash.messages) == [friction_topic("A"), friction_topic("B"), WARNINGS_TOPIC]
        for topic in (telemetry_topic("A"), telemetry_topic("dash"), friction_topic("A"), WARNINGS_TOPIC):
            with pytest.raises(PublishRefused):
                dash.publish(topic, b"x")


def test_the_service_cannot_publish_telemetry(fleet):
    inbox = Inbox()
    with (
        service(fleet, inbox, client_id="svc-reader"),
        service(fleet, client_id="svc-writer") as writer,
        vehicle(fleet, "A") as a,
    ):
        writer.publish(telemetry_topic("A"), b"forged").wait_for_publish(5)
        a.publish_telemetry(b"sentinel")
        assert inbox.payloads(1) == [("A", b"sentinel")]


def test_refused_service_login_raises_with_the_reason_code(fleet):
    client = MqttClient(fleet.url, fleet.service_user, "wrong", "svc", on_telemetry=Inbox())
    with pytest.raises(BrokerRefused) as refused:
        client.connect(timeout_s=5)
    assert refused.value.reason_code.value == NOT_AUTHORIZED
    assert not client.connected
    with pytest.raises(OSError):
        MqttClient("mqtt://127.0.0.1:1", "u", "p", "svc").connect(timeout_s=5)


def test_a_vehicle_speaks_mqtt_3_1_1_when_asked_and_auto_keeps_5_where_the_broker_takes_it(fleet):
    """The fleet's "auto" falls back to 3.1.1 only for a broker that does not take MQTT 5 (RabbitMQ 3.10: the local
    cluster's test, tests/cloud/cluster/test_local.py); Mosquitto does, so nothing changes for serve."""
    inbox = Inbox()
    with (
        service(fleet, inbox),
        VehicleClient(fleet.url, "A", "secret-A", protocol="3.1.1") as old,
        VehicleClient(fleet.url, "B", "secret-B", protocol="auto") as new,
    ):
        assert old.protocol == "3.1.1" and old.paho.protocol == paho.MQTTv311
        assert new.protocol == "5" and new.paho.protocol == paho.MQTTv5
        old.publish_telemetry(b"over 3.1.1")
        new.publish_telemetry(b"over 5")
        assert sorted(inbox.payloads(2)) == [("A", b"over 3.1.1"), ("B", b"over 5")]


def test_auto_does_not_fall_back_on_a_refused_login(fleet):
    with pytest.raises(BrokerRefused) as refused:
        UserClient(fleet.url, "A", "wrong", protocol="auto").connect(timeout_s=5)
    assert refused.value.reason_code.value == NOT_AUTHORIZED
    with pytest.raises(ValueError, match="protocol must be"):
        UserClient(fleet.url, "A", "secret-A", protocol="3")


def test_telemetry_published_while_the_service_is_away_is_delivered_when_it_returns(fleet):
    with service(fleet, Inbox()):
        pass  # the persistent session, with its subscription, now waits in the broker
    with vehicle(fleet, "A") as a, vehicle(fleet, "B") as b:
        for i in range(5):
            a.publish_telemetry(f"a{i}")
            b.publish_telemetry(f"b{i}")
    inbox = Inbox()
    with service(fleet, inbox):
        got = inbox.payloads(10)
    assert [p for v, p in got if v == "A"] == [f"a{i}".encode() for i in range(5)]  # in order, per vehicle
    assert [p for v, p in got if v == "B"] == [f"b{i}".encode() for i in range(5)]


def test_a_message_not_acknowledged_is_delivered_again_after_a_reconnect(fleet):
    held = Inbox(auto_ack=False)
    with service(fleet, held), vehicle(fleet, "A") as a:
        a.publish_telemetry(b"first")
        a.publish_telemetry(b"second")
        (_, _, ack_first), _ = held.take(2)
        ack_first()  # from this thread; "second" stays unacknowledged
        ack_first()  # a second call does nothing
    again = Inbox(auto_ack=False)
    with service(fleet, again):
        ((vid, payload, ack),) = again.take(1)
        assert (vid, payload) == ("A", b"second")
        acker = threading.Thread(target=ack)  # ack from another thread
        acker.start()
        acker.join()
    inbox = Inbox()
    with service(fleet, inbox), vehicle(fleet, "A") as a:
        a.publish_telemetry(b"sentinel")
        assert inbox.payloads(1) == [("A", b"sentinel")]  # "second" was not delivered a third time


def test_an_ack_after_the_connection_dropped_does_nothing(fleet):
    held = Inbox(auto_ack=False)
    svc = service(fleet, held)
    with vehicle(fleet, "A") as a:
        a.publish_telemetry(b"one")
    ((_, _, ack),) = held.take(1)
    svc.close()
    ack()  # void: the broker delivers the message again
    with service(fleet, held):
        assert held.payloads(1) == [("A", b"one")]


def test_the_service_reconnects_by_itself_after_a_broker_restart(fleet):
    inbox = Inbox()
    with service(fleet, inbox) as svc:
        fleet.restart()
        wait_until(lambda: svc.connected, what="service reconnected")
        with vehicle(fleet, "A") as a:
            a.publish_telemetry(b"after restart")
        assert inbox.payloads(1) == [("A", b"after restart")]
        svc.publish(friction_topic("A"), b"mu").wait_for_publish(5)


def test_queued_telemetry_survives_a_broker_restart(fleet):
    with service(fleet, Inbox()):
        pass
    with vehicle(fleet, "A") as a:
        for i in range(3):
            a.publish_telemetry(f"{i}")
    fleet.restart()  # a clean stop saves the persistence database
    inbox = Inbox()
    with service(fleet, inbox):
        assert inbox.payloads(3) == [("A", f"{i}".encode()) for i in range(3)]
