"""The service with its own Mosquitto (mqtt=managed), end to end: a real MQTT client publishes a simulated run as its
terminal would; estimates come out on the vehicle's friction topic and in the API and the database. Runs on SQLite and
on a real PostgreSQL."""

from __future__ import annotations

import json
import time

import pytest
from drives import patch_drive
from fastapi.testclient import TestClient
from service_fixtures import ADMIN, collect, register_mqtt

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.serve import service as service_module
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.transport.mosquitto import mosquitto_available
from roadgrip.cloud.transport.mqtt import PublishRefused, UserClient, errors_topic, friction_topic, telemetry_topic
from roadgrip.fleet.demo import settle
from roadgrip.fleet.terminal import wire_samples

START_MS = int(time.time() * 1000) - 600_000


@pytest.fixture
def cloud(storage_url, tmp_path):
    assert mosquitto_available(), "mosquitto is not installed: run `bash scripts/install_system_deps.sh`"
    settings = Settings(
        data_dir=tmp_path,
        database_url=storage_url,
        mqtt="managed",
        admin_secret=ADMIN[1],
        flush_interval_s=0.02,
        reorder_window_s=0.2,
        map_clock="data",
    )
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        yield service, client


def test_a_run_published_over_mqtt_comes_back_as_estimates_everywhere(cloud):
    service, client = cloud
    vehicle_id, secret, url = register_mqtt(client, "mqtt-car")
    samples = wire_samples(patch_drive(0.2, 1), vehicle_id, START_MS)
    with UserClient(url, vehicle_id, secret).connect() as car:
        car.subscribe(friction_topic(vehicle_id))
        for k in range(0, len(samples), 2):  # two samples a message: a JSON array
            car.publish(telemetry_topic(vehicle_id), json.dumps(samples[k : k + 2]))
        car.publish(telemetry_topic(vehicle_id), json.dumps(samples[:5]))  # a repeated message
        published = collect(car.messages, lambda got: sum(len(json.loads(p)) for _, p in got) >= len(samples))
    estimates = [e for _, payload in published for e in json.loads(payload)]
    assert len(estimates) == len(samples)
    assert {e["vehicle_id"] for e in estimates} == {vehicle_id}
    assert {"mu", "mu_lower", "mu_upper", "excited", "estimator", "timestamp_ms"} <= set(estimates[0])
    assert service.storage.counts()["telemetry"] == len(samples)  # the repeated message stored once
    from_api = client.get(f"/v1/vehicles/{vehicle_id}/estimates", auth=(vehicle_id, secret)).json()["estimates"]
    assert [e["timestamp_ms"] for e in from_api] == sorted(e["timestamp_ms"] for e in estimates)
    assert len(service.storage.estimates(vehicle_id)) == len(samples)


@pytest.mark.slow
def test_estimate_messages_are_dropped_not_queued_while_the_broker_is_behind(cloud, monkeypatch):
    service, client = cloud
    monkeypatch.setattr(service_module, "MAX_UNACKNOWLEDGED_ESTIMATES", -1)  # as if the broker never caught up
    vehicle_id, secret, url = register_mqtt(client, "slow-car")
    samples = wire_samples(patch_drive(0.2, 1), vehicle_id, START_MS)[:100]
    with UserClient(url, vehicle_id, secret).connect() as car:
        car.subscribe(friction_topic(vehicle_id))
        car.publish(telemetry_topic(vehicle_id), json.dumps(samples))
        settle(service)
        time.sleep(2 * service.settings.friction_publish_interval_s)
        assert car.messages.empty()
    assert len(service.storage.estimates(vehicle_id)) == len(samples)  # stored all the same
    health = client.get("/v1/health", auth=(vehicle_id, secret)).json()["pipeline"]
    assert health["estimate_messages_dropped"] >= 1 and health["mqtt_unacknowledged"] == 0


def test_a_vehicle_cannot_publish_under_another_id(cloud):
    service, client = cloud
    a_id, a_secret, url = register_mqtt(client, "car-a")
    b_id, _, _ = register_mqtt(client, "car-b")
    sample = wire_samples(patch_drive(0.9, 3), b_id, START_MS)[:1]
    with UserClient(url, a_id, a_secret).connect() as car, pytest.raises(PublishRefused):
        car.publish(telemetry_topic(b_id), json.dumps(sample))
    time.sleep(0.3)
    assert service.storage.counts()["telemetry"] == 0


def test_bad_samples_are_reported_on_the_error_topic_and_the_good_ones_kept(cloud, caplog):
    service, client = cloud
    vehicle_id, secret, url = register_mqtt(client, "car-e")
    good = wire_samples(patch_drive(0.9, 3), vehicle_id, START_MS)[:3]
    bad = {**good[1], "timestamp_ms": START_MS + 50, "speed_mps": "fast"}
    with UserClient(url, vehicle_id, secret).connect() as car:
        car.subscribe(errors_topic(vehicle_id))
        car.publish(telemetry_topic(vehicle_id), json.dumps([good[0], bad, *good[1:]]))
        car.publish(telemetry_topic(vehicle_id), b"{not json")
        errors = collect(car.messages, lambda got: len(got) >= 2)
    reports = [json.loads(payload) for _, payload in errors]
    assert reports[0]["rejected"][0]["field"] == "speed_mps" and reports[0]["rejected"][0]["index"] == 1
    assert reports[1]["rejected"][0]["reason"]
    deadline = time.time() + 5
    while service.storage.counts()["telemetry"] < 3 and time.time() < deadline:
        time.sleep(0.05)
    assert service.storage.counts()["telemetry"] == 3
    assert "rejected" in caplog.text
    assert client.get("/v1/health", auth=ADMIN).json()["mqtt"] == "connected"
