"""Access control end to end, on SQLite and a real PostgreSQL (`storage_url`): who may write and read what over HTTP and
MQTT (the service with its own Mosquitto), revocation, secrets never in clear in the database, the broker's files or
the logs, SQL-injection strings treated as data, and model files that cannot run code."""

from __future__ import annotations

import base64
import json
import logging
import pickle
import time
from pathlib import Path
from urllib.parse import quote

import pytest
import sqlalchemy as sa
import torch
from broker_fixtures import wait_until
from fastapi.testclient import TestClient
from service_fixtures import ADMIN, RECENT_MS, add_reader, collect, register, samples_of, settings_for

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import metadata, normalise_url
from roadgrip.cloud.transport.mosquitto import mosquitto_available
from roadgrip.cloud.transport.mqtt import (
    FRICTION_SUBSCRIPTION,
    WARNINGS_TOPIC,
    BrokerRefused,
    PublishRefused,
    UserClient,
    VehicleClient,
    errors_topic,
    friction_topic,
    telemetry_topic,
)
from roadgrip.data.telemetry import VEHICLE_ID_RE
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.demo import settle

NOT_AUTHORIZED = 0x87


@pytest.fixture
def cloud(storage_url, tmp_path):
    with CloudService(settings_for(storage_url, tmp_path)) as service, TestClient(create_app(service)) as client:
        yield service, client


@pytest.fixture
def mqtt_cloud(storage_url, tmp_path):
    assert mosquitto_available(), "mosquitto is not installed: run `bash scripts/install_system_deps.sh`"
    with (
        CloudService(settings_for(storage_url, tmp_path, mqtt="managed")) as service,
        TestClient(create_app(service)) as client,
    ):
        yield service, client


def table_snapshot(service: CloudService) -> dict:
    return {
        "counts": service.storage.counts(),
        "credentials": [(c.name, c.role, c.revoked) for c in service.storage.credentials()],
    }


# ------------------------------------------------------------------------------------------------ HTTP


def test_a_vehicle_can_neither_write_nor_read_as_another(cloud):
    service, client = cloud
    a, b = register(client, "car-a"), register(client, "car-b")
    post = client.post("/v1/telemetry", json=samples_of("car-b", 5), auth=a)
    assert post.status_code == 422
    assert [(r["index"], r["field"]) for r in post.json()["rejected"]] == [(k, "vehicle_id") for k in range(5)]
    mixed = samples_of("car-a", 3) + samples_of("car-b", 3, RECENT_MS + 10_000)
    answer = client.post("/v1/telemetry", json=mixed, auth=a)
    assert answer.status_code == 200 and answer.json()["stored"] == 3
    assert {r["field"] for r in answer.json()["rejected"]} == {"vehicle_id"}
    assert client.post("/v1/telemetry", json=samples_of("car-b", 1), auth=("car-b", a[1])).status_code == 401
    assert client.post("/v1/telemetry", json=samples_of("car-b", 2), auth=b).status_code == 200
    settle(service)
    assert [r["vehicle_id"] for r in service.storage.telemetry("car-b")] == ["car-b"] * 2  # only its own two
    assert len(service.storage.telemetry("car-a")) == 3
    for path in (
        "/v1/vehicles/car-b",
        "/v1/vehicles/car-b/estimates",
        "/v1/vehicles/latest",
        "/v1/map",
        "/v1/map/datex2",
        "/v1/vehicles/CAR-A/estimates",
    ):
        assert client.get(path, auth=a).status_code == 403, path
    own = client.get("/v1/vehicles/car-a/estimates", auth=a).json()["estimates"]
    assert own and {e["vehicle_id"] for e in own} == {"car-a"}
    for method, path, body in (
        ("post", "/v1/vehicles", {"vehicle_id": "car-c"}),
        ("post", "/v1/readers", {"name": "spy"}),
        ("delete", "/v1/credentials/car-b", None),
    ):
        assert client.request(method, path, json=body, auth=a).status_code == 403, path
    assert service.storage.credential("car-b").revoked is False and service.storage.credential("spy") is None


def test_a_reader_reads_but_cannot_write_register_or_revoke(cloud):
    service, client = cloud
    vehicle = register(client, "car-r")
    client.post("/v1/telemetry", json=samples_of("car-r", 5), auth=vehicle)
    settle(service)
    reader = add_reader(client, "operator")
    before = table_snapshot(service)
    assert client.post("/v1/telemetry", json=samples_of("car-r", 5, RECENT_MS + 5_000), auth=reader).status_code == 403
    assert client.post("/v1/vehicles", json={"vehicle_id": "car-x"}, auth=reader).status_code == 403
    assert client.post("/v1/vehicles", json=[{"vehicle_id": "car-y"}], auth=reader).status_code == 403
    assert client.post("/v1/readers", json={"name": "operator-2"}, auth=reader).status_code == 403
    assert client.delete("/v1/credentials/car-r", auth=reader).status_code == 403
    assert client.delete("/v1/credentials/operator", auth=reader).status_code == 403
    assert table_snapshot(service) == before
    for path in (
        "/v1/vehicles/car-r",
        "/v1/vehicles/car-r/estimates",
        "/v1/map",
        "/v1/warnings",
        "/v1/vehicles/latest",
    ):
        assert client.get(path, auth=reader).status_code == 200, path


def test_a_revoked_credential_stops_working_at_once_over_http(cloud):
    service, client = cloud
    vehicle, reader = register(client, "car-v"), add_reader(client, "viewer")
    assert client.post("/v1/telemetry", json=samples_of("car-v", 1), auth=vehicle).status_code == 200
    assert client.get("/v1/map", auth=reader).status_code == 200  # both verified secrets are now cached
    assert client.delete("/v1/credentials/car-v", auth=ADMIN).status_code == 204
    assert client.post("/v1/telemetry", json=samples_of("car-v", 1, RECENT_MS + 100), auth=vehicle).status_code == 401
    assert client.get("/v1/vehicles/car-v/estimates", auth=vehicle).status_code == 401
    assert client.get("/v1/map", auth=reader).status_code == 200  # the others go on
    assert client.delete("/v1/credentials/viewer", auth=ADMIN).status_code == 204
    assert client.get("/v1/map", auth=reader).status_code == 401
    assert client.delete("/v1/credentials/viewer", auth=ADMIN).status_code == 404  # revoked already
    settle(service)
    assert len(service.storage.telemetry("car-v")) == 1


# ------------------------------------------------------------------------------------------------ MQTT


@pytest.mark.slow
def test_over_mqtt_a_vehicle_can_neither_publish_as_another_nor_read_its_estimates(mqtt_cloud):
    service, client = mqtt_cloud
    (a, a_secret), (b, b_secret) = register(client, "car-a"), register(client, "car-b")
    reader = add_reader(client, "dash")
    url = service.mqtt_url
    with (
        VehicleClient(url, a, a_secret) as car_a,
        VehicleClient(url, b, b_secret) as car_b,
        UserClient(url, *reader) as dash,
    ):
        for topic in (friction_topic(b), errors_topic(b), FRICTION_SUBSCRIPTION, "roadgrip/v1/vehicles/#", "#"):
            car_a.subscribe(topic)  # granted by Mosquitto: the ACL is checked on each delivery
        car_b.subscribe(friction_topic(b))
        dash.subscribe(FRICTION_SUBSCRIPTION)
        for topic, payload in (
            (telemetry_topic(b), json.dumps(samples_of(b, 3))),  # as another vehicle
            (friction_topic(a), b"[]"),
            (friction_topic(b), b"[]"),  # forged estimates
            (errors_topic(b), b"{}"),
            (WARNINGS_TOPIC, b"{}"),
        ):  # forged reports, warnings
            with pytest.raises(PublishRefused) as refused:
                car_a.publish(topic, payload)
            assert refused.value.reason_code.value == NOT_AUTHORIZED, topic
        with pytest.raises(PublishRefused):
            dash.publish(telemetry_topic(b), json.dumps(samples_of(b, 1)))  # a reader writes nothing
        samples = samples_of(b, 20)
        car_b.publish_telemetry(json.dumps(samples))
        car_b.publish_telemetry(json.dumps({"speed_mps": "fast"}))  # a rejection for B's error topic
        own = collect(car_b.messages, lambda got: sum(len(json.loads(p)) for _, p in got) >= len(samples))
        assert sum(len(json.loads(p)) for _, p in own) == len(samples)  # B's estimates were published ...
        seen_by_reader = collect(dash.messages, lambda got: sum(len(json.loads(p)) for _, p in got) >= len(samples))
        assert {t for t, _ in seen_by_reader} == {friction_topic(b)}  # ... a reader saw them ...
        time.sleep(0.5)
        leaked = collect(car_a.messages, lambda got: False, timeout_s=0.5)
        assert [t for t, _ in leaked if f"/{b}/" in t] == []  # ... and A saw nothing of B's
    settle(service)
    assert len(service.storage.telemetry(b)) == len(samples) and service.storage.telemetry(a) == []


def test_over_mqtt_a_revoked_vehicle_is_disconnected_at_once_and_refused_after(mqtt_cloud):
    service, client = mqtt_cloud
    vehicle_id, secret = register(client, "car-rv")
    other_id, other_secret = register(client, "car-ok")
    with (
        VehicleClient(service.mqtt_url, vehicle_id, secret) as live,
        VehicleClient(service.mqtt_url, other_id, other_secret) as other,
    ):
        live.publish_telemetry(json.dumps(samples_of(vehicle_id, 2)))
        wait_until(lambda: len(service.storage.telemetry(vehicle_id)) == 2, what="the first samples stored")
        assert client.delete(f"/v1/credentials/{vehicle_id}", auth=ADMIN).status_code == 204
        wait_until(lambda: not live.paho.is_connected(), what="the broker dropping the revoked vehicle")
        live.publish_nowait(live.topic, json.dumps(samples_of(vehicle_id, 2, RECENT_MS + 1_000)))  # lost, not stored
        other.publish_telemetry(json.dumps(samples_of(other_id, 1)))  # the others stay connected
        assert other.paho.is_connected()
    with pytest.raises(BrokerRefused) as refused:
        VehicleClient(service.mqtt_url, vehicle_id, secret).connect(timeout_s=5)
    assert refused.value.reason_code.value == NOT_AUTHORIZED
    settle(service)
    assert len(service.storage.telemetry(vehicle_id)) == 2
    assert (
        client.post(
            "/v1/telemetry", json=samples_of(vehicle_id, 1, RECENT_MS + 2_000), auth=(vehicle_id, secret)
        ).status_code
        == 401
    )


# ------------------------------------------------------------------------------------------------ secrets


def database_text(storage_url: str) -> bytes:
    """Every row of every table, as text, and for SQLite also the raw bytes of its files (main, WAL, shared memory)."""
    url = normalise_url(storage_url)
    engine = sa.create_engine(url)
    try:
        with engine.connect() as conn:
            text = "\n".join(
                repr(row) for table in metadata.sorted_tables for row in conn.execute(sa.select(table)).all()
            )
    finally:
        engine.dispose()
    if url.get_backend_name() != "sqlite":
        return text.encode()
    main = Path(url.database)
    return text.encode() + b"".join(p.read_bytes() for p in main.parent.glob(main.name + "*"))


def test_secrets_are_never_stored_or_logged_in_clear(storage_url, tmp_path, caplog):
    caplog.set_level(logging.DEBUG)  # every logger, and SQLAlchemy's statements, parameters and rows (off by default)
    caplog.set_level(logging.DEBUG, logger="sqlalchemy.engine")
    with (
        CloudService(settings_for(storage_url, tmp_path, mqtt="managed")) as service,
        TestClient(create_app(service)) as client,
    ):
        issued = dict([register(client, "car-s1"), register(client, "car-s2"), add_reader(client, "reader-s")])
        answer = client.post("/v1/vehicles", json=[{"vehicle_id": "fleet-1"}, {"vehicle_id": "fleet-2"}], auth=ADMIN)
        issued.update({a["name"]: a["secret"] for a in answer.json()})
        guesses = [secret[:-1] + ("A" if secret[-1] != "A" else "B") for secret in issued.values()]
        for name, secret in issued.items():  # every credential used, and a wrong guess of each
            assert client.get("/v1/health", auth=(name, secret)).status_code == 200
            assert client.get("/v1/health", auth=(name, guesses.pop(0))).status_code == 401
        client.post("/v1/telemetry", json=samples_of("car-s1", 5), auth=("car-s1", issued["car-s1"]))
        with VehicleClient(service.mqtt_url, "car-s2", issued["car-s2"]) as car:
            car.publish_telemetry(json.dumps(samples_of("car-s2", 5)))
            car.publish_telemetry(b"{not json")  # a rejection: a log line that names the vehicle
        with pytest.raises(BrokerRefused):
            VehicleClient(service.mqtt_url, "car-s2", "a-wrong-guess-at-the-secret").connect(timeout_s=5)
        client.delete("/v1/credentials/fleet-2", auth=ADMIN)
        settle(service)
        secrets = {
            **issued,
            "admin": ADMIN[1],
            "broker service login": service.broker.service_password,
            "wrong guess": "a-wrong-guess-at-the-secret",
        }
        stored = database_text(storage_url)
        files = {p.relative_to(tmp_path).as_posix(): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    # the scans see what they should: the hashes, the broker's log and password file, the logins in the log
    assert b"sha256$car" not in stored and stored.count(b"sha256$") >= len(issued)
    assert {"mosquitto/mosquitto.log", "mosquitto/passwd", "mosquitto/logins.json"} <= set(files)
    assert b"car-s2" in files["mosquitto/mosquitto.log"]
    logged = caplog.text + "\n".join(r.getMessage() for r in caplog.records)
    assert "car-s2 over MQTT" in logged and "sha256$" in logged  # SQLAlchemy's parameters and rows were logged too
    for what, secret in secrets.items():
        assert secret.encode() not in stored, f"{what}'s secret in the database"
        for name, content in files.items():  # the SQLite files and the broker's: configuration, logins, log, state
            assert secret.encode() not in content, f"{what}'s secret in {name}"
        assert secret not in logged, f"{what}'s secret in the log"


# ------------------------------------------------------------------------------------------------ injection

INJECTIONS = [
    "'; DROP TABLE telemetry; --",
    "x' OR '1'='1",
    '"; DELETE FROM credentials; --',
    "Robert'); DROP TABLE vehicles;--",
    "' UNION SELECT secret_hash FROM credentials --",
    "1; UPDATE credentials SET revoked = false",
    "$1",
    "?",
    ":name",
    "%s",
    "%_%",
    "\\",
    "\x00",
    "car-a\x00'--",
    "\ud800",
]


def test_sql_injection_strings_are_refused_or_stored_as_data_and_the_tables_survive(cloud):
    service, client = cloud
    vehicle = register(client, "car-i")
    client.post("/v1/telemetry", json=samples_of("car-i", 5), auth=vehicle)
    reader = add_reader(client, "reader-i")
    settle(service)
    before = table_snapshot(service)
    for text in INJECTIONS:
        assert not VEHICLE_ID_RE.fullmatch(text)  # the id pattern allows none of them: refused where it applies
        path = quote(text, safe="", errors="surrogatepass")
        assert post_json(client, "/v1/vehicles", {"vehicle_id": text}, ADMIN).status_code == 422, text
        assert post_json(client, "/v1/readers", {"name": text}, ADMIN).status_code == 422, text
        assert client.get(f"/v1/vehicles/{path}/estimates", auth=ADMIN).status_code in (404, 422), text
        assert client.get(f"/v1/vehicles/{path}", auth=reader).status_code in (404, 422), text
        assert client.delete(f"/v1/credentials/{path}", auth=ADMIN).status_code in (404, 422), text
        assert client.get("/v1/map", headers=basic_auth(text, vehicle[1])).status_code == 401, text
        assert client.get("/v1/map", headers=basic_auth("reader-i", text)).status_code == 401, text
        sample = {**samples_of("car-i", 1, RECENT_MS + 50_000)[0], "vehicle_id": text}
        rejected = post_json(client, "/v1/telemetry", [sample], vehicle).json()["rejected"]
        assert rejected[0]["field"] == "vehicle_id", text
        for name in ("start_ms", "end_ms", "limit"):
            assert client.get(f"/v1/vehicles/car-i/estimates?{name}={path}", auth=ADMIN).status_code == 422, text
        assert client.get(f"/v1/warnings?active={path}", auth=ADMIN).status_code == 422, text
        assert (
            post_json(client, "/v1/vehicles", {"vehicle_id": "car-j", "profile": text}, ADMIN).status_code == 422
        )  # not a known vehicle
        assert (
            post_json(client, "/v1/vehicles", {"vehicle_id": "car-j", "profile": {text: 1.0}}, ADMIN).status_code == 422
        )  # not a profile field
    assert table_snapshot(service) == before
    # Free text (a profile's name) is stored as it was sent, and read back the same; what a database cannot hold
    # (NUL, a lone surrogate) is refused before anything is written.
    for k, text in enumerate(INJECTIONS):
        answer = post_json(client, "/v1/vehicles", {"vehicle_id": f"inj-{k}", "profile": {"name": text}}, ADMIN)
        if "\x00" in text or "\ud800" in text:
            assert answer.status_code == 422 and "NUL" in answer.json()["detail"]
            assert service.storage.credential(f"inj-{k}") is None
            continue
        assert answer.status_code == 201, (text, answer.text)
        assert client.get(f"/v1/vehicles/inj-{k}", auth=ADMIN).json()["profile"]["name"] == text
        auth = (f"inj-{k}", answer.json()["secret"])
        assert client.post("/v1/telemetry", json=samples_of(f"inj-{k}", 3), auth=auth).json()["stored"] == 3
    fleet = client.post(
        "/v1/vehicles",
        json=[{"vehicle_id": "fleet-ok"}, {"vehicle_id": "fleet-bad", "profile": {"name": "a\x00b"}}],
        auth=ADMIN,
    )
    assert fleet.status_code == 422 and service.storage.credential("fleet-ok") is None  # all or nothing
    settle(service)
    after = table_snapshot(service)
    assert after["counts"]["telemetry"] == before["counts"]["telemetry"] + 3 * (len(INJECTIONS) - 3)
    assert set(before["credentials"]) <= set(after["credentials"])
    assert len(client.get("/v1/vehicles/car-i/estimates", auth=vehicle).json()["estimates"]) == 5


def basic_auth(name: str, secret: str) -> dict:
    token = base64.b64encode(f"{name}:{secret}".encode("utf-8", "surrogatepass")).decode()
    return {"Authorization": f"Basic {token}"}


def post_json(client, path: str, body, auth):
    """POST `body` as JSON with non-ASCII escaped (\\uXXXX), so that a lone surrogate can be sent, as any client
    may."""
    return client.post(path, content=json.dumps(body).encode(), auth=auth, headers={"content-type": "application/json"})


# ------------------------------------------------------------------------------------------------ model files


class _RunsCode:
    """A pickle that runs code when loaded (what a crafted model file would do)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (exec, (f"import pathlib; pathlib.Path({str(self.marker)!r}).write_text('ran')",))


def test_a_model_file_that_would_run_code_is_refused_and_does_not_run(tmp_path):
    marker = tmp_path / "PWNED"
    as_torch = tmp_path / "evil.pt"
    torch.save({"format": "roadgrip-model-v1", "model": "dnn", "payload": _RunsCode(marker)}, as_torch)
    as_pickle = tmp_path / "evil-pickle.pt"
    as_pickle.write_bytes(pickle.dumps(_RunsCode(marker), protocol=2))  # torch.load's own protocol
    for path in (as_torch, as_pickle):
        with pytest.raises(ValueError, match="not a roadgrip model file that loads safely"):
            load_estimator(path)
        service = CloudService(
            Settings(data_dir=tmp_path / "data", mqtt="off", admin_secret=ADMIN[1], estimator=str(path))
        )
        try:
            with pytest.raises(ValueError, match="loads safely"):  # nor can the service be told to load it
                service.start()
        finally:
            service.stop()
    assert not marker.exists()
