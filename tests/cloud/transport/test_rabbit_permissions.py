"""The cluster broker's topic permissions (roadgrip/cloud/transport/rabbit_users.py) as RabbitMQ applies them, a regular
expression on the routing key: vehicles and readers read both renderings of the warnings (JSON and UPER) and nothing
they should not."""

import re

import pytest

from roadgrip.cloud.transport.mqtt import WARNINGS_TOPIC, WARNINGS_UPER_TOPIC, friction_topic, telemetry_topic
from roadgrip.cloud.transport.rabbit_users import permissions, routing_key


@pytest.mark.parametrize("role", ["vehicle", "reader"])
def test_vehicles_and_readers_read_the_warnings_in_both_renderings_and_no_more(role):
    _, topic = permissions("car-1", role)
    readable = {key for key in map(routing_key, (WARNINGS_TOPIC, WARNINGS_UPER_TOPIC)) if re.match(topic["read"], key)}
    assert readable == {"roadgrip.v1.warnings", "roadgrip.v1.warnings.uper"}
    for key in ("", "roadgrip.v1.warnings.other", routing_key(telemetry_topic("car-2"))):
        assert not re.match(topic["read"], key), key
    assert bool(re.match(topic["read"], routing_key(friction_topic("car-2")))) == (role == "reader")
