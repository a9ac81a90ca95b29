"""The cluster broker's topic permissions (roadgrip/cloud/transport/rabbit_users.py) as RabbitMQ applies them, a regular
expression on the routing key: vehicles and readers read both renderings of the warnings (JSON and UPER) and nothing
they should not; vehicles publish their own topics only."""

import re

import pytest

from roadgrip.cloud.transport.mqtt import (
    WARNINGS_TOPIC,
    WARNINGS_UPER_TOPIC,
    friction_topic,
    heartbeat_topic,
    observations_topic,
    telemetry_topic,
)
from roadgrip.cloud.transport.rabbit_users import permissions, routing_key
from roadgrip.edge.uplink import edge_client_id


@pytest.mark.parametrize("role", ["vehicle", "reader"])
def test_vehicles_and_readers_read_the_warnings_in_both_renderings_and_no_more(role):
    _, topic = permissions("car-1", role)
    readable = {key for key in map(routing_key, (WARNINGS_TOPIC, WARNINGS_UPER_TOPIC)) if re.match(topic["read"], key)}
    assert readable == {"roadgrip.v1.warnings", "roadgrip.v1.warnings.uper"}
    for key in ("", "roadgrip.v1.warnings.other", routing_key(telemetry_topic("car-2"))):
        assert not re.match(topic["read"], key), key
    assert bool(re.match(topic["read"], routing_key(friction_topic("car-2")))) == (role == "reader")


def test_a_vehicle_publishes_its_own_telemetry_observations_and_heartbeat_only():
    permission, topic = permissions("car-1", "vehicle")
    own = [telemetry_topic("car-1"), observations_topic("car-1"), heartbeat_topic("car-1")]
    assert all(re.match(topic["write"], routing_key(t)) for t in own)
    for t in (observations_topic("car-2"), heartbeat_topic("car-10"), friction_topic("car-1"), WARNINGS_TOPIC):
        assert not re.match(topic["write"], routing_key(t)), t
    # the edge uplink's client id: a subscription of its session would have a queue within the vehicle's permission
    queue = f"mqtt-subscription-{edge_client_id('car-1', 'secret')}qos1"
    assert re.match(permission["configure"], queue)
    assert not re.match(permission["configure"], f"mqtt-subscription-{edge_client_id('car-2', 'secret')}qos1")
