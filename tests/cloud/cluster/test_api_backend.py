"""`roadgrip api` in cluster mode against real servers: a 3-node RabbitMQ 3.10 cluster with the management plugin
(roadgrip/cloud/transport/amqp.py `RabbitCluster`, started once for the module), PostgreSQL (conftest.py), and two API
replicas, each a `roadgrip api` process of its own on the same database and broker. Vehicles are MQTT 3.1.1 clients of
the nodes' MQTT listeners; partition queues are read with pika."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import uuid
import zlib
from pathlib import Path

import h3
import httpx
import paho.mqtt.client as paho
import pika
import pytest
from cluster_fixtures import node_killed, running_rabbit_cluster
from drives import patch_drive
from fastapi.testclient import TestClient
from paho.mqtt.enums import CallbackAPIVersion

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.cluster.api_backend import ClusterBackend
from roadgrip.cloud.cluster.map_cells import cell_rows, new_friction_map, region_of
from roadgrip.cloud.cluster.publisher import PUBLISH_DEADLINE_S
from roadgrip.cloud.domain.stations import covered_cells
from roadgrip.cloud.formats.geojson import geojson
from roadgrip.cloud.ingest.wire import parse_payload
from roadgrip.cloud.localhost import free_ports
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.storage.local_postgres import create_database, drop_database
from roadgrip.cloud.transport.amqp import (
    HOST,
    REGION_QUEUES,
    SERVICE_USER,
    RabbitCluster,
    partition_queue,
    region_queue,
)
from roadgrip.cloud.transport.mqtt import WARNINGS_TOPIC, friction_topic, telemetry_topic
from roadgrip.cloud.transport.rabbit_users import RabbitUsers
from roadgrip.fleet.terminal import wire_samples

pytestmark = [pytest.mark.cluster, pytest.mark.timeout(900)]  # needs a local RabbitMQ cluster
PARTITIONS = 2
SECRET = "api-test-broker-secret"
ADMIN = ("admin", "admin-secret-for-cluster-tests-0123")
ROADGRIP = Path(sys.executable).parent / "roadgrip"
REVOCATION_LIMIT_S = 1.0  # from the DELETE's answer to the vehicle's MQTT connection closed


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    with running_rabbit_cluster(tmp_path_factory.mktemp("rabbit"), [], PARTITIONS, SECRET) as rabbit:
        yield rabbit


@pytest.fixture(scope="module")
def database_url(postgres_url):
    name = f"test_api_{uuid.uuid4().hex[:12]}"
    yield create_database(postgres_url, name)
    drop_database(postgres_url, name)


class Replica:
    """`roadgrip api` in a process of its own."""

    def __init__(self, cluster: RabbitCluster, database_url: str, brokers: list[int], log_path: Path):
        self.port = free_ports(1)[0]
        self.url = f"http://{HOST}:{self.port}"
        self.log_path = log_path
        args = [arg for i in brokers for arg in ("--broker", cluster.amqp_url(i))]
        args += [arg for i in brokers for arg in ("--management", cluster.management_url(i))]
        env = {**os.environ, "ROADGRIP_ADMIN_SECRET": ADMIN[1], "ROADGRIP_RATE_LIMIT_SAMPLES_PER_S": "0"}
        with open(log_path, "wb") as log:
            self.proc = subprocess.Popen(
                [
                    str(ROADGRIP),
                    "api",
                    "--database",
                    database_url,
                    "--port",
                    str(self.port),
                    "--mqtt",
                    cluster.mqtt_url(brokers[0]),
                    *args,
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
            )
        self.http = httpx.Client(base_url=self.url, timeout=30)

    def wait_ready(self, timeout_s: float = 60) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                if self.http.get("/v1/health", auth=ADMIN).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"api replica not ready:\n{self.log_path.read_text()[-3000:]}", pytrace=False)
            time.sleep(0.2)

    def stop(self) -> None:
        self.http.close()
        self.proc.terminate()
        self.proc.wait(30)


@pytest.fixture(scope="module")
def replicas(cluster, database_url, tmp_path_factory):
    logs = tmp_path_factory.mktemp("api")
    started = [
        Replica(cluster, database_url, [0, 1, 2], logs / "api1.log"),
        Replica(cluster, database_url, [2, 1, 0], logs / "api2.log"),
    ]
    try:
        for replica in started:
            replica.wait_ready()
        yield started
    finally:
        for replica in started:
            replica.stop()


def register(replica: Replica, vehicle_id: str) -> str:
    answer = replica.http.post("/v1/vehicles", json={"vehicle_id": vehicle_id, "profile": "paper-suv"}, auth=ADMIN)
    assert answer.status_code == 201, answer.text
    return answer.json()["secret"]


class MqttVehicle:
    """A vehicle's MQTT 3.1.1 connection (clean session, client id = its vehicle id), with its events timed."""

    def __init__(self, url: str, vehicle_id: str, secret: str):
        host, port = url.removeprefix("mqtt://").split(":")
        self.events: list[tuple[float, str, object]] = []
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id=vehicle_id, protocol=paho.MQTTv311)
        self.client.username_pw_set(vehicle_id, secret)
        self.client.reconnect_delay_set(5, 5)
        self.client.on_connect = lambda _c, _u, _f, code, _p: self.events.append((time.monotonic(), "connect", code))
        self.client.on_disconnect = lambda _c, _u, _f, code, _p: self.events.append(
            (time.monotonic(), "disconnect", code)
        )
        self.client.on_subscribe = lambda _c, _u, _m, codes, _p: self.events.append(
            (time.monotonic(), "suback", [c.value for c in codes])
        )
        self.client.connect(host, int(port))
        self.client.loop_start()

    def first(self, kind: str, timeout_s: float = 10) -> tuple[float, object]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for at, what, detail in list(self.events):
                if what == kind:
                    return at, detail
            time.sleep(0.01)
        raise AssertionError(f"no {kind} within {timeout_s} s: {self.events}")

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def test_registered_on_one_replica_works_on_the_other_and_revoked_on_it_is_refused_at_once(cluster, replicas):
    one, two = replicas
    secret = register(one, "rev-01")
    auth = ("rev-01", secret)
    assert two.http.get("/v1/vehicles/rev-01", auth=auth).status_code == 200
    assert one.http.get("/v1/vehicles/rev-01", auth=auth).status_code == 200  # verified once on each replica

    vehicle = MqttVehicle(cluster.mqtt_url(1), "rev-01", secret)
    try:
        assert vehicle.first("connect")[1] == 0
        vehicle.client.subscribe([(friction_topic("rev-01"), 1), (WARNINGS_TOPIC, 1)])
        assert vehicle.first("suback")[1] == [1, 1]  # granted at QoS 1 by its broker permissions
        users = RabbitUsers([cluster.management_url(0)], SERVICE_USER, SECRET)
        assert len(users.connections("rev-01")) == 1

        assert two.http.delete("/v1/credentials/rev-01", auth=ADMIN).status_code == 204
        answered = time.monotonic()
        assert one.http.get("/v1/vehicles/rev-01", auth=auth).status_code == 401  # no cache keeps it valid
        assert two.http.get("/v1/vehicles/rev-01", auth=auth).status_code == 401
        closed, _ = vehicle.first("disconnect")
        print(f"MQTT connection closed {closed - answered:+.3f} s after the revocation's answer")
        assert closed - answered < REVOCATION_LIMIT_S
        assert users.connections("rev-01") == []
        assert not users.exists("rev-01")
    finally:
        vehicle.close()
    again = MqttVehicle(cluster.mqtt_url(2), "rev-01", secret)
    try:
        assert again.first("connect")[1] != 0  # refused: bad user name or password
    finally:
        again.close()
    assert one.http.delete("/v1/credentials/rev-01", auth=ADMIN).status_code == 404


def test_a_vehicle_reaching_for_another_vehicles_topic_is_cut_off(cluster, replicas):
    """RabbitMQ 3.10 refuses the binding or the publish (topic permissions) and closes the connection."""
    one, _ = replicas
    secret = register(one, "nosy-01")
    register(one, "other-01")
    vehicle = MqttVehicle(cluster.mqtt_url(0), "nosy-01", secret)
    try:
        assert vehicle.first("connect")[1] == 0
        vehicle.client.subscribe(friction_topic("other-01"), 1)
        vehicle.first("disconnect")
    finally:
        vehicle.close()
    vehicle = MqttVehicle(cluster.mqtt_url(1), "nosy-01", secret)
    try:
        assert vehicle.first("connect")[1] == 0
        vehicle.client.publish(telemetry_topic("other-01"), b"[]", qos=1)
        vehicle.first("disconnect")
    finally:
        vehicle.close()


def test_a_client_id_in_use_is_taken_over_whatever_the_login(cluster, replicas):
    """What docs/CLUSTER.md says of client ids (the reason for VehicleClient's random suffix): RabbitMQ 3.10 closes
    the connection that had a client id when another login connects with it, on another node."""
    one, _ = replicas
    victim = MqttVehicle(cluster.mqtt_url(0), "bare-01", register(one, "bare-01"))
    try:
        assert victim.first("connect")[1] == 0
        intruder = paho.Client(CallbackAPIVersion.VERSION2, client_id="bare-01", protocol=paho.MQTTv311)
        intruder.username_pw_set("bare-02", register(one, "bare-02"))
        intruder.connect(HOST, cluster.mqtt_ports[1])
        intruder.loop_start()
        try:
            victim.first("disconnect")
        finally:
            intruder.disconnect()
            intruder.loop_stop()
    finally:
        victim.close()


def consume_partitions(cluster: RabbitCluster, want: int, timeout_s: float = 20) -> list[tuple[str, bytes]]:
    """Up to `want` messages from the partition queues (this is their single active consumer: no worker runs)."""
    connection = pika.BlockingConnection(pika.URLParameters(cluster.amqp_url(0)))
    channel = connection.channel()
    got: list[tuple[str, bytes]] = []
    for p in range(PARTITIONS):
        channel.basic_consume(
            partition_queue(p),
            lambda ch, method, _props, body: (
                got.append((method.routing_key, body)),
                ch.basic_ack(method.delivery_tag),
            ),
        )
    deadline = time.monotonic() + timeout_s
    while len(got) < want and time.monotonic() < deadline:
        connection.process_data_events(0.2)
    connection.close()
    return got


def test_telemetry_posted_over_http_reaches_the_vehicles_partition_queue_as_its_mqtt_publish_would(cluster, replicas):
    one, two = replicas
    secret = register(one, "tel-01")
    samples = wire_samples(patch_drive(0.3, 1), "tel-01", int(time.time() * 1000) - 60_000)[:20]
    bad = {**samples[5], "timestamp_ms": -5}
    body = [*samples[:5], bad, *samples[5:]]
    answer = two.http.post("/v1/telemetry", json=body, auth=("tel-01", secret))
    assert answer.status_code == 202, answer.text
    assert answer.json()["received"] == 21 and answer.json()["accepted"] == 20
    assert [r["index"] for r in answer.json()["rejected"]] == [5]

    messages = consume_partitions(cluster, want=1)
    assert [key for key, _ in messages] == ["roadgrip.v1.vehicles.tel-01.telemetry"]
    parsed, errors = parse_payload(messages[0][1], now_ms=int(time.time() * 1000), vehicle_id="tel-01")
    assert errors == []
    expected, _ = parse_payload(json.dumps(samples).encode(), now_ms=int(time.time() * 1000), vehicle_id="tel-01")
    assert parsed == expected

    assert two.http.post("/v1/telemetry", json=[bad], auth=("tel-01", secret)).status_code == 422
    metrics = two.http.get("/metrics", auth=ADMIN).text
    assert "roadgrip_api_messages_published_total 1.0" in metrics


def test_map_and_warnings_are_read_from_storage_by_every_replica(replicas, database_url):
    settings = Settings()
    now = int(time.time() * 1000)
    fmap = new_friction_map(settings)
    rows = [
        {
            "vehicle_id": "m1",
            "timestamp_ms": now - 20_000 + 100 * k,
            "latitude_deg": 38.0,
            "longitude_deg": 114.5 + 2.0 / 111_000 * k * 1.27,
            "mu": 0.25,
            "mu_lower": 0.2,
            "mu_upper": 0.3,
            "excited": True,
            "mu_proven": None,
        }
        for k in range(100)
    ]
    fmap.add(rows, now)
    cell = h3.latlng_to_cell(38.0, 114.5, settings.h3_resolution)
    warning = {
        "warning_id": "w-1",
        "cell": cell,
        "status": "active",
        "detection_ms": now,
        "updated_ms": now,
        "message": {"denm": {"cell": cell, "test": True}, "event": {}},
    }
    storage = open_storage(database_url)
    try:
        storage.put_region_output([warning], cell_rows(fmap, fmap.cells_by_id_, 5))
    finally:
        storage.close()
    expected = {f["properties"]["cell"]: f["properties"]["mu"] for f in geojson(fmap.cells(now))["features"]}
    assert expected
    for replica in replicas:
        time.sleep(1.1)  # past the replica's map cache of a second
        features = replica.http.get("/v1/map", auth=ADMIN).json()["features"]
        assert {f["properties"]["cell"]: f["properties"]["mu"] for f in features} == pytest.approx(expected, abs=0.01)
        assert replica.http.get("/v1/warnings", auth=ADMIN).json() == {"warnings": [{"cell": cell, "test": True}]}
        assert replica.http.get("/v1/map/datex2", auth=ADMIN).status_code == 200


def test_health_says_storage_and_broker_are_reachable(replicas):
    for replica in replicas:
        health = replica.http.get("/v1/health", auth=ADMIN).json()
        assert health["status"] == "ok" and health["storage"] == "ok"
        assert health["broker"]["management"] == "ok"


def test_a_registration_the_broker_does_not_take_stores_nothing(cluster, database_url, tmp_path):
    """A replica whose management API is unreachable: 503, and the vehicle is not registered (the database
    transaction rolled back), so that registering it again through a working replica succeeds."""
    dead = free_ports(1)[0]
    env = {**os.environ, "ROADGRIP_ADMIN_SECRET": ADMIN[1]}
    port = free_ports(1)[0]
    log = tmp_path / "api.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [
                str(ROADGRIP),
                "api",
                "--database",
                database_url,
                "--port",
                str(port),
                "--broker",
                cluster.amqp_url(0),
                "--management",
                f"http://{HOST}:{dead}",
            ],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
        )
    try:
        http = httpx.Client(base_url=f"http://{HOST}:{port}", timeout=30)
        deadline = time.monotonic() + 60
        while True:
            try:
                health = http.get("/v1/health", auth=ADMIN)
                break
            except httpx.TransportError:
                assert proc.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
                time.sleep(0.2)
        assert health.status_code == 200 and health.json()["status"] == "degraded"
        answer = http.post("/v1/vehicles", json={"vehicle_id": "lost-01"}, auth=ADMIN)
        assert answer.status_code == 503, answer.text
        storage = open_storage(database_url)
        try:
            assert storage.credential("lost-01") is None and storage.vehicle_profile("lost-01") is None
        finally:
            storage.close()
        http.close()
    finally:
        proc.terminate()
        proc.wait(30)


def test_replicas_register_a_fleet_at_once_with_one_broker_request(cluster, replicas):
    one, two = replicas
    fleet = [{"vehicle_id": f"fl-{k:03d}"} for k in range(50)]
    answer = one.http.post("/v1/vehicles", json=fleet, auth=ADMIN)
    assert answer.status_code == 201
    users = RabbitUsers([cluster.management_url(1)], SERVICE_USER, SECRET)
    assert all(users.exists(v["vehicle_id"]) for v in fleet[::7])
    assert two.http.post("/v1/vehicles", json=fleet[:1], auth=ADMIN).status_code == 409
    dotted = two.http.post("/v1/vehicles", json=[{"vehicle_id": "fl-ok"}, {"vehicle_id": "car.1"}], auth=ADMIN)
    assert dotted.status_code == 422 and "car.1" in dotted.json()["detail"]
    assert not users.exists("fl-ok") and not users.exists("car.1")  # all or nothing
    answers = answer.json()
    assert {a["mqtt_url"] for a in answers} == {cluster.mqtt_url(0)}
    for a in answers[::10]:
        assert two.http.get(f"/v1/vehicles/{a['name']}", auth=(a["name"], a["secret"])).status_code == 200


def test_a_worker_stores_what_a_replica_accepted_and_a_stations_evidence_reaches_the_map(
    cluster, replicas, database_url, tmp_path
):
    """The whole path with a `roadgrip worker`: telemetry accepted (202) by replica two is stored; a station's report
    posted to replica one goes to its region's owner (the worker) and is in the map replica two reads."""
    one, two = replicas
    log_path = tmp_path / "worker.log"
    env = {**os.environ, "ROADGRIP_RATE_LIMIT_SAMPLES_PER_S": "0"}
    with open(log_path, "wb") as log:
        worker = subprocess.Popen(
            [
                str(ROADGRIP),
                "worker",
                "--database",
                database_url,
                "--partitions",
                str(PARTITIONS),
                "--broker",
                cluster.amqp_url(1),
                "--broker",
                cluster.amqp_url(2),
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
        )
    try:
        deadline = time.monotonic() + 120
        while "worker consuming" not in log_path.read_text():
            assert worker.poll() is None and time.monotonic() < deadline, log_path.read_text()[-3000:]
            time.sleep(0.2)
        secret = register(one, "whole-01")
        samples = wire_samples(patch_drive(0.3, 3), "whole-01", int(time.time() * 1000) - 60_000)[:50]
        for start in range(0, 50, 10):
            answer = two.http.post("/v1/telemetry", json=samples[start : start + 10], auth=("whole-01", secret))
            assert answer.status_code == 202, answer.text
        storage = open_storage(database_url)
        try:
            deadline = time.monotonic() + 30
            while len(storage.telemetry("whole-01")) < 50:
                assert time.monotonic() < deadline, log_path.read_text()[-3000:]
                time.sleep(0.2)
            assert [r["timestamp_ms"] for r in storage.telemetry("whole-01")] == [s["timestamp_ms"] for s in samples]
        finally:
            storage.close()

        station = one.http.post("/v1/stations", json={"station_id": "rws-01"}, auth=ADMIN).json()
        assert station["mqtt_url"] is None  # stations report over HTTP in the cluster
        report = {
            "station_id": "rws-01",
            "timestamp_ms": int(time.time() * 1000) - 1000,
            "latitude_deg": 47.2,
            "longitude_deg": 8.6,
            "surface_state": "ice",
        }
        answer = one.http.post("/v1/stations/rws-01/reports", json=report, auth=("rws-01", station["secret"]))
        assert answer.status_code == 200 and answer.json()["evidence_cells"] > 0, answer.text
        cell = h3.latlng_to_cell(47.2, 8.6, Settings().h3_resolution)
        deadline = time.monotonic() + 30
        while True:
            features = two.http.get("/v1/map", auth=ADMIN).json()["features"]
            if cell in {f["properties"]["cell"] for f in features}:
                break
            assert time.monotonic() < deadline, log_path.read_text()[-3000:]
            time.sleep(0.5)
    finally:
        worker.terminate()
        worker.wait(60)


def region_messages(cluster: RabbitCluster) -> int:
    """Messages waiting in the region queues (no worker consumes them now)."""
    connection = pika.BlockingConnection(pika.URLParameters(cluster.amqp_url(1)))
    try:
        channel = connection.channel()
        return sum(
            channel.queue_declare(region_queue(q), passive=True).method.message_count for q in range(REGION_QUEUES)
        )
    finally:
        connection.close()


def test_a_station_report_sent_again_is_handed_on_again_and_without_a_broker_answers_503_stored(cluster, database_url):
    """A replica's backend in this process, through the API's routes: a station's report is stored and its evidence
    handed to the region stage (a message per region of its cells); sent again, it is a duplicate whose evidence is
    handed on again (the region owner applies it once). With no broker reachable, a new report is stored and the
    route answers 503 after the publish deadline, saying so."""
    settings = Settings(database_url=database_url, admin_secret=ADMIN[1])
    management = [cluster.management_url(1)]
    reachable = ClusterBackend(settings, [cluster.amqp_url(1)], management)
    unreachable = ClusterBackend(
        settings, [f"amqp://{SERVICE_USER}:{SECRET}@{HOST}:{free_ports(1)[0]}/%2F"], management
    )
    reachable.start()
    unreachable.start()
    try:
        with TestClient(create_app(reachable)) as client:
            station = client.post("/v1/stations", json={"station_id": "rws-again"}, auth=ADMIN).json()
            auth = ("rws-again", station["secret"])
            report = {
                "station_id": "rws-again",
                "timestamp_ms": int(time.time() * 1000) - 5000,
                "latitude_deg": 46.9,
                "longitude_deg": 7.4,
                "surface_state": "ice",
            }
            regions = {
                region_of(cell, settings.region_resolution) for cell in covered_cells(46.9, 7.4, settings.h3_resolution)
            }
            before = region_messages(cluster)
            first = client.post("/v1/stations/rws-again/reports", json=report, auth=auth)
            assert first.status_code == 200 and first.json()["stored"] == 1, first.text
            assert region_messages(cluster) == before + len(regions)
            again = client.post("/v1/stations/rws-again/reports", json=report, auth=auth)
            assert again.status_code == 200 and again.json()["duplicates"] == 1, again.text
            assert region_messages(cluster) == before + 2 * len(regions)
        later = {**report, "timestamp_ms": report["timestamp_ms"] + 1000}
        with TestClient(create_app(unreachable)) as client:
            started = time.monotonic()
            answer = client.post("/v1/stations/rws-again/reports", json=later, auth=auth)
            took_s = time.monotonic() - started
        assert answer.status_code == 503 and "1 new report(s) of 1 stored" in answer.json()["detail"], answer.text
        assert PUBLISH_DEADLINE_S - 1 < took_s < PUBLISH_DEADLINE_S + 2
        assert len(reachable.storage.station_reports_of([("rws-again", later["timestamp_ms"])])) == 1
        assert region_messages(cluster) == before + 2 * len(regions)
    finally:
        unreachable.stop()
        reachable.stop()


def test_telemetry_is_still_accepted_through_the_next_node_when_a_broker_node_dies(cluster, replicas):
    """Replica one publishes through nodes 0, 1, 2; the vehicle's publisher connection is one of those on node 0,
    which is killed: the next request goes through node 1, confirmed. Node 0 is started again after the test."""
    one, _ = replicas
    vehicle_id = next(f"kill-{k:02d}" for k in range(100) if zlib.crc32(f"kill-{k:02d}".encode()) % 4 == 0)
    secret = register(one, vehicle_id)
    samples = wire_samples(patch_drive(0.3, 2), vehicle_id, int(time.time() * 1000) - 60_000)[:20]
    assert one.http.post("/v1/telemetry", json=samples[:10], auth=(vehicle_id, secret)).status_code == 202
    with node_killed(cluster, 0):
        answer = one.http.post("/v1/telemetry", json=samples[10:], auth=(vehicle_id, secret))
        if answer.status_code != 202:
            queues = cluster.ctl(1, "list_queues", "-q", "name", "type", "leader", "members", "online", "messages")
            bindings = cluster.ctl(1, "list_bindings", "-q", "source_name", "destination_name", "routing_key")
            pytest.fail(
                f"{answer.status_code} {answer.text}\nqueues (node 1):\n{queues}\nbindings:\n{bindings}", pytrace=False
            )
        connection = pika.BlockingConnection(pika.URLParameters(cluster.amqp_url(1)))
        channel = connection.channel()
        got: list[bytes] = []
        for p in range(PARTITIONS):
            channel.basic_consume(
                partition_queue(p),
                lambda ch, method, _props, body: (
                    got.append(body) if method.routing_key == f"roadgrip.v1.vehicles.{vehicle_id}.telemetry" else None,
                    ch.basic_ack(method.delivery_tag),
                ),
            )
        deadline = time.monotonic() + 30
        while len(got) < 2 and time.monotonic() < deadline:
            connection.process_data_events(0.2)
        connection.close()
        stamps = [s["timestamp_ms"] for body in got for s in json.loads(body)]
        assert stamps == [s["timestamp_ms"] for s in samples]
