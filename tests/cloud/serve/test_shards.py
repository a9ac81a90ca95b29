"""The service with its vehicles sharded over two ingest processes (`ingest_processes: 2`), its own Mosquitto, on SQLite
and on PostgreSQL: MQTT and HTTP telemetry stored exactly once and estimated, the estimates published by the service's
process, one rate limit for both transports, and an ingest process killed mid-stream (SIGKILL): started again, with
nothing acknowledged lost."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
from broker_fixtures import wait_until
from drives import patch_drive
from service_fixtures import ADMIN, collect, register_mqtt, running_cloud

from roadgrip.cloud.serve import shards
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.serve.shards import shard_of
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.transport.mosquitto import mosquitto_available
from roadgrip.cloud.transport.mqtt import UserClient, errors_topic, friction_topic, telemetry_topic
from roadgrip.fleet.terminal import wire_samples

START_MS = int(time.time() * 1000) - 600_000


def test_shard_of_is_stable_and_spreads_the_vehicles():
    ids = [f"car-{i:04d}" for i in range(2000)]
    assert [shard_of(v, 4) for v in ids] == [shard_of(v, 4) for v in ids]
    for count in (2, 3, 4):
        shares = [sum(shard_of(v, count) == k for v in ids) / len(ids) for k in range(count)]
        assert all(abs(share - 1 / count) < 0.05 for share in shares), shares
    assert {shard_of(v, 1) for v in ids} == {0}


def ids_on_each_shard(prefix: str, per_shard: int, count: int = 2) -> list[str]:
    """Vehicle ids, `per_shard` of them owned by each of `count` ingest processes."""
    chosen, k = {n: [] for n in range(count)}, 0
    while any(len(v) < per_shard for v in chosen.values()):
        vehicle_id = f"{prefix}-{k}"
        if len(chosen[shard_of(vehicle_id, count)]) < per_shard:
            chosen[shard_of(vehicle_id, count)].append(vehicle_id)
        k += 1
    return [v for n in range(count) for v in chosen[n]]


def running_sharded(storage_url, tmp_path, **settings):
    """test_api's running cloud with its own Mosquitto and two ingest processes."""
    assert mosquitto_available(), "mosquitto is not installed: run `bash scripts/install_system_deps.sh`"
    return running_cloud(
        storage_url,
        tmp_path,
        **{
            "mqtt": "managed",
            "flush_interval_s": 0.02,
            "ingest_processes": 2,
            "friction_publish_interval_s": 0.2,
            **settings,
        },
    )


@pytest.fixture
def sharded(storage_url, tmp_path):
    with running_sharded(storage_url, tmp_path) as running:
        yield running


@pytest.mark.slow
def test_mqtt_and_http_vehicles_on_both_processes_are_stored_once_and_estimated(sharded):
    service, client = sharded
    mqtt_ids, http_ids = ids_on_each_shard("mq", 1), ids_on_each_shard("ht", 1)
    runs = {v: wire_samples(patch_drive(0.9, k), v, START_MS) for k, v in enumerate(mqtt_ids + http_ids)}
    n = len(runs[mqtt_ids[0]])
    cars = {}
    for vehicle_id in mqtt_ids:
        _, secret, url = register_mqtt(client, vehicle_id)
        cars[vehicle_id] = UserClient(url, vehicle_id, secret).connect()
        cars[vehicle_id].subscribe(friction_topic(vehicle_id))
    http_auth = {v: register_mqtt(client, v)[:2] for v in http_ids}
    answers = []
    for k in range(0, n, 10):
        for vehicle_id, car in cars.items():
            car.publish(telemetry_topic(vehicle_id), json.dumps(runs[vehicle_id][k : k + 10]))
        for vehicle_id in http_ids:
            answers.append(client.post("/v1/telemetry", json=runs[vehicle_id][k : k + 10], auth=http_auth[vehicle_id]))
    car = cars[mqtt_ids[0]]
    car.publish(telemetry_topic(mqtt_ids[0]), json.dumps(runs[mqtt_ids[0]][:10]))  # a repeated message
    repeat = client.post("/v1/telemetry", json=runs[http_ids[0]][:10], auth=http_auth[http_ids[0]])
    assert all(a.status_code == 200 for a in answers) and sum(a.json()["stored"] for a in answers) == 2 * n
    assert repeat.json() | {"rejected": []} == {
        "received": 10,
        "accepted": 10,
        "stored": 0,
        "duplicates": 10,
        "rejected": [],
    }
    wait_until(lambda: len(service.storage.estimates(mqtt_ids[0])) == n, 30, "the estimates")
    for vehicle_id in mqtt_ids + http_ids:
        assert [s["timestamp_ms"] for s in service.storage.telemetry(vehicle_id)] == [
            s["timestamp_ms"] for s in runs[vehicle_id]
        ]
        wait_until(lambda v=vehicle_id: len(service.storage.estimates(v)) == n, 30, f"{vehicle_id}'s estimates")
    for vehicle_id, car in cars.items():  # published by the service's process, every estimate once
        got = collect(car.messages, lambda got: sum(len(json.loads(p)) for _, p in got) >= n)
        assert sorted(e["timestamp_ms"] for _, p in got for e in json.loads(p)) == [
            s["timestamp_ms"] for s in runs[vehicle_id]
        ]
        car.close()

    def counted() -> tuple[int, int, int]:  # health sums the counters each process sends every STATS_INTERVAL_S
        pipeline = client.get("/v1/health", auth=ADMIN).json()["pipeline"]
        return pipeline["stored"], pipeline["duplicates"], pipeline["estimates"]

    wait_until(lambda: counted() == (4 * n, 20, 4 * n), 30, "the counters in health")
    health = client.get("/v1/health", auth=ADMIN).json()
    assert health["status"] == "ok" and health["mqtt"] == "connected"
    pipeline = health["pipeline"]
    assert [(p["index"], p["alive"], p["restarts"]) for p in pipeline["ingest_processes"]] == [
        (0, True, 0),
        (1, True, 0),
    ]
    assert pipeline["latency_since_start"]["n"] == 4 * n and pipeline["forwarded_unacknowledged"] == 0
    assert health["memory_rss_mb"] > sum(p["rss_mb"] for p in pipeline["ingest_processes"])
    assert client.get("/v1/map", auth=ADMIN).json()["features"]  # the map, in the service's process


@pytest.mark.slow
def test_http_and_mqtt_share_the_owners_rate_limit(tmp_path):
    with running_sharded(
        f"sqlite:///{tmp_path / 'roadgrip.db'}", tmp_path, rate_limit_samples_per_s=1.0, rate_limit_burst_s=50.0
    ) as (service, client):  # 50 samples of burst, 1 a second more
        vehicle_id, secret, url = register_mqtt(client, "limited-car")
        samples = wire_samples(patch_drive(0.9, 3), vehicle_id, START_MS)
        assert client.post("/v1/telemetry", json=samples[:45], auth=(vehicle_id, secret)).status_code == 200
        with UserClient(url, vehicle_id, secret).connect() as car:
            car.subscribe(errors_topic(vehicle_id))
            car.publish(telemetry_topic(vehicle_id), json.dumps(samples[45:55]))  # over what HTTP left
            ((_, payload),) = collect(car.messages, lambda got: len(got) >= 1)
        assert "rate limit" in json.loads(payload)["rejected"][0]["reason"]
        over = client.post("/v1/telemetry", json=samples[45:100], auth=(vehicle_id, secret))
        assert over.status_code == 413 and "send at most 50 a message" in over.json()["detail"]
        assert len(service.storage.telemetry(vehicle_id)) == 45


@pytest.mark.slow
def test_an_ingest_process_killed_mid_stream_is_started_again_and_loses_nothing_acknowledged(sharded):
    service, client = sharded
    vehicle_id, secret, url = register_mqtt(client, "crash-car")
    samples = wire_samples(patch_drive(0.9, 5), vehicle_id, START_MS)
    owner = shard_of(vehicle_id, 2)
    pid = client.get("/v1/health", auth=ADMIN).json()["pipeline"]["ingest_processes"][owner]["pid"]
    with UserClient(url, vehicle_id, secret).connect() as car:
        for k in range(0, len(samples), 5):
            car.publish(telemetry_topic(vehicle_id), json.dumps(samples[k : k + 5]))  # PUBACK: the broker has it
            if k == len(samples) // 2:
                os.kill(pid, signal.SIGKILL)
    wait_until(lambda: len(service.storage.telemetry(vehicle_id)) == len(samples), 120, "every sample stored")
    stored = [s["timestamp_ms"] for s in service.storage.telemetry(vehicle_id)]
    assert stored == [s["timestamp_ms"] for s in samples]  # each once, none lost
    process = client.get("/v1/health", auth=ADMIN).json()["pipeline"]["ingest_processes"][owner]
    assert process["alive"] and process["restarts"] == 1 and process["pid"] != pid
    wait_until(
        lambda: client.get("/v1/health", auth=ADMIN).json()["pipeline"]["forwarded_unacknowledged"] == 0,
        30,
        "every forwarded message acknowledged",
    )


def test_an_ingest_process_without_room_defers_to_the_broker_and_nothing_is_lost_or_stored_twice(
    storage_url, tmp_path, monkeypatch
):
    """Backpressure through the MQTT client's Busy: with at most 3 messages forwarded to an ingest process and not
    acknowledged, a car's 40 messages outrun the pipeline (its reorder window holds each 0.2 s); the rest are deferred
    to Mosquitto, not waited for in paho's network thread, and come again once there is room: every sample stored
    once, in order."""
    monkeypatch.setattr(shards, "MAX_FORWARDED_MESSAGES", 3)
    with running_sharded(storage_url, tmp_path) as (service, client):
        vehicle_id, secret, url = register_mqtt(client, "busy-car")
        samples = wire_samples(patch_drive(0.9, 20), vehicle_id, START_MS)
        with UserClient(url, vehicle_id, secret).connect() as car:
            for k in range(0, len(samples), 5):
                car.publish(telemetry_topic(vehicle_id), json.dumps(samples[k : k + 5]))  # PUBACK: the broker has it
        wait_until(lambda: len(service.storage.telemetry(vehicle_id)) == len(samples), 60, "every sample stored")
        stored = [s["timestamp_ms"] for s in service.storage.telemetry(vehicle_id)]
        assert stored == [s["timestamp_ms"] for s in samples]  # each once, none lost
        assert service.mqtt.deferred > 0 and service.mqtt.redeliveries >= 1
        assert service.mqtt.drops == 0  # the network thread went on answering the broker


def test_an_ingest_process_that_cannot_start_stops_the_service_starting_with_its_reason(tmp_path):
    settings = Settings(
        data_dir=tmp_path, mqtt="off", admin_secret=ADMIN[1], ingest_processes=1, estimator="no-such-model"
    )
    service = CloudService(settings)
    with pytest.raises(RuntimeError, match="ingest process 0 failed to start(.|\n)*no-such-model"):
        service.start()
    service.stop()
