"""Roadside stations in the service, on SQLite and a real PostgreSQL (`storage_url`): registration and the station
role (a vehicle cannot post a station's report, a station cannot post telemetry or another station's reports, over
HTTP and over MQTT with the service's own Mosquitto), the reports API, a warning raised by a station's ice reports and
cancelled by its later dry report, the evidence back on the map after a restart, and older databases whose
credentials table predates the station role."""

from __future__ import annotations

import json
import time

import httpx
import pytest
import sqlalchemy as sa
from broker_fixtures import wait_until
from dashboard_fixtures import attributes_by_id, dashboard_settings, require_chromium, run_chromium, serving
from fastapi.testclient import TestClient
from service_fixtures import ADMIN, add_reader, collect, register, samples_of, settings_for

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.domain.stations import covered_cells
from roadgrip.cloud.domain.warnings import WarningEngine
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.storage.database import normalise_url, open_storage
from roadgrip.cloud.transport.mqtt import (
    PublishRefused,
    UserClient,
    station_errors_topic,
    station_reports_topic,
    telemetry_topic,
)

NOT_AUTHORIZED = 0x87
LAT, LON = 48.1372, 11.5755


def report(station_id: str, t_ms: int, state: str = "ice", **fields) -> dict:
    return {
        "station_id": station_id,
        "timestamp_ms": t_ms,
        "latitude_deg": LAT,
        "longitude_deg": LON,
        "surface_state": state,
        "surface_temperature_c": -3.0 if state == "ice" else 4.0,
        "water_film_thickness_mm": 0.0,
        **fields,
    }


def add_station(client, station_id: str) -> tuple[str, str]:
    answer = client.post("/v1/stations", json={"station_id": station_id}, auth=ADMIN)
    assert answer.status_code == 201, answer.text
    assert answer.json()["role"] == "station"
    return station_id, answer.json()["secret"]


@pytest.fixture
def cloud(storage_url, tmp_path):
    settings = settings_for(storage_url, tmp_path).model_copy(update={"map_clock": "wall"})
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        yield service, client


@pytest.fixture
def mqtt_cloud(storage_url, tmp_path):
    settings = settings_for(storage_url, tmp_path, mqtt="managed").model_copy(update={"map_clock": "wall"})
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        yield service, client


def test_a_station_reports_over_http_and_readers_see_its_latest_report(cloud):
    service, client = cloud
    station = add_station(client, "rws-a9")
    now = int(time.time() * 1000)
    answer = client.post(
        "/v1/stations/rws-a9/reports",
        json=[report("rws-a9", now - 60_000, "wet"), report("rws-a9", now, "ice")],
        auth=station,
    )
    assert answer.status_code == 200, answer.text
    assert answer.json() == {
        "received": 2,
        "stored": 2,
        "duplicates": 0,
        "evidence_cells": 2 * len(covered_cells(LAT, LON, 10)),
    }
    again = client.post("/v1/stations/rws-a9/reports", json=report("rws-a9", now, "ice"), auth=station)
    assert again.json()["duplicates"] == 1 and again.json()["stored"] == 0  # a retry is stored once
    bad = client.post(
        "/v1/stations/rws-a9/reports",
        json=[report("rws-a9", now + 1), report("rws-a9", now + 2, "slush")],
        auth=station,
    )
    assert bad.status_code == 422 and bad.json()["detail"]["index"] == 1
    assert bad.json()["detail"]["field"] == "surface_state"
    assert (
        client.post(
            "/v1/stations/rws-a9/reports", content=b"{ice", auth=station, headers={"content-type": "application/json"}
        ).status_code
        == 400
    )
    reader = add_reader(client, "operator")
    latest = client.get("/v1/stations", auth=reader).json()
    [row] = latest["stations"]
    assert (row["station_id"], row["timestamp_ms"], row["surface_state"]) == ("rws-a9", now, "ice")
    assert row["mu_upper"] < 0.4 and row["cells"] == covered_cells(LAT, LON, 10)
    assert 0 <= latest["server_time_ms"] - now < 60_000
    assert len(service.storage.station_reports_since(0)) == 2  # the refused payload stored nothing


def test_roles_a_vehicle_cannot_report_for_a_station_nor_a_station_send_telemetry_or_read(cloud):
    service, client = cloud
    station, other = add_station(client, "rws-1"), add_station(client, "rws-2")
    vehicle = register(client, "car-s")
    now = int(time.time() * 1000)
    assert client.post("/v1/stations/rws-1/reports", json=report("rws-1", now), auth=vehicle).status_code == 403
    assert client.post("/v1/stations/rws-1/reports", json=report("rws-1", now), auth=other).status_code == 403
    as_other = client.post("/v1/stations/rws-2/reports", json=report("rws-1", now), auth=other)
    assert as_other.status_code == 422 and as_other.json()["detail"]["field"] == "station_id"
    assert client.post("/v1/telemetry", json=samples_of("rws-1", 3), auth=station).status_code == 403
    for path in (
        "/v1/stations",
        "/v1/map",
        "/v1/warnings",
        "/v1/vehicles/latest",
        "/v1/vehicles/car-s",
        "/v1/vehicles/car-s/estimates",
    ):
        assert client.get(path, auth=station).status_code == 403, path
    assert client.get("/v1/stations", auth=vehicle).status_code == 403
    assert client.post("/v1/stations", json={"station_id": "rws-3"}, auth=station).status_code == 403
    assert client.post("/v1/stations", json={"station_id": "car-s"}, auth=ADMIN).status_code == 409  # name taken
    assert service.storage.station_reports_since(0) == [] and service.storage.telemetry("rws-1") == []
    assert client.delete("/v1/credentials/rws-1", auth=ADMIN).status_code == 204
    assert client.post("/v1/stations/rws-1/reports", json=report("rws-1", now), auth=station).status_code == 401


def test_a_stations_ice_reports_raise_a_warning_and_its_later_dry_report_cancels_it(cloud):
    service, client = cloud
    station = add_station(client, "rws-bridge")
    reader = add_reader(client, "operator")
    now = int(time.time() * 1000)
    cells = covered_cells(LAT, LON, 10)
    first = client.post("/v1/stations/rws-bridge/reports", json=report("rws-bridge", now - 120_000), auth=station)
    assert first.status_code == 200
    raised = client.get("/v1/warnings", auth=reader).json()["warnings"]  # one low pass raises (the product's setting)
    assert sorted(w["roadgrip"]["cell"] for w in raised) == cells  # every covered cell, nowhere else
    client.post("/v1/stations/rws-bridge/reports", json=report("rws-bridge", now - 60_000), auth=station)
    warnings = client.get("/v1/warnings", auth=reader).json()["warnings"]
    assert sorted(w["roadgrip"]["cell"] for w in warnings) == cells
    assert all(w["roadgrip"]["update"] == 1 for w in warnings)  # refreshed by the second report
    assert {w["denm"]["situation"]["eventType"]["causeCode"] for w in warnings} == {6}
    assert all(w["roadgrip"]["n_vehicles"] == 1 and w["roadgrip"]["mu_upper"] < 0.4 for w in warnings)
    geojson = client.get("/v1/map", auth=reader).json()
    assert set(cells) <= {f["properties"]["cell"] for f in geojson["features"]}
    client.post("/v1/stations/rws-bridge/reports", json=report("rws-bridge", now, "dry"), auth=station)
    assert client.get("/v1/warnings", auth=reader).json()["warnings"] == []
    ended = [row for row in service.storage.warnings() if row["status"] != "active"]
    assert sorted(row["cell"] for row in ended) == cells
    assert {row["message"]["event"]["reason"] for row in ended} == {"recovered"}


def test_station_evidence_is_back_on_the_map_after_a_restart(storage_url, tmp_path):
    settings = settings_for(storage_url, tmp_path).model_copy(update={"map_clock": "wall"})
    now = int(time.time() * 1000)
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        station = add_station(client, "rws-r")
        client.post("/v1/stations/rws-r/reports", json=report("rws-r", now - 30_000), auth=station)
        before = {c.cell: c for c in service.friction_map.cells(now)}
    with CloudService(settings) as service:
        after = {c.cell: c for c in service.friction_map.cells(now)}
    cells = covered_cells(LAT, LON, 10)
    assert set(cells) <= set(after)
    assert [(after[c].mu, after[c].mu_upper) for c in cells] == [(before[c].mu, before[c].mu_upper) for c in cells]


def test_over_mqtt_a_station_publishes_only_its_own_reports(mqtt_cloud):
    service, client = mqtt_cloud
    (station_id, secret), (other_id, other_secret) = add_station(client, "rws-m"), add_station(client, "rws-n")
    vehicle_id, vehicle_secret = register(client, "car-m")
    url, now = service.mqtt_url, int(time.time() * 1000)
    with (
        UserClient(url, station_id, secret) as station,
        UserClient(url, other_id, other_secret) as other,
        UserClient(url, vehicle_id, vehicle_secret) as vehicle,
    ):
        station.subscribe(station_errors_topic(station_id))
        other.subscribe(station_errors_topic(station_id))  # granted; the ACL keeps the deliveries away
        station.publish(station_reports_topic(station_id), json.dumps(report(station_id, now)))
        wait_until(lambda: len(service.storage.station_reports_since(0)) == 1, what="the station's report stored")
        for client_, topic, payload in (
            (other, station_reports_topic(station_id), report(station_id, now + 1)),  # as another station
            (vehicle, station_reports_topic(station_id), report(station_id, now + 2)),  # a vehicle as a station
            (station, telemetry_topic(vehicle_id), samples_of(vehicle_id, 2)),  # a station as a vehicle
            (station, station_errors_topic(station_id), {}),
        ):  # forged error reports
            with pytest.raises(PublishRefused) as refused:
                client_.publish(topic, json.dumps(payload))
            assert refused.value.reason_code.value == NOT_AUTHORIZED, topic
        station.publish(station_reports_topic(station_id), json.dumps(report(station_id, now + 3, "slush")))
        [(topic, payload)] = collect(station.messages, lambda got: len(got) >= 1)
        assert topic == station_errors_topic(station_id)
        assert json.loads(payload)["rejected"][0]["field"] == "surface_state"
        time.sleep(0.3)
        assert collect(other.messages, lambda got: False, timeout_s=0.3) == []
    assert [(r["station_id"], r["timestamp_ms"]) for r in service.storage.station_reports_since(0)] == [
        (station_id, now)
    ]
    assert service.storage.telemetry(vehicle_id) == []


def test_a_database_from_before_the_station_role_accepts_station_credentials(storage_url):
    engine = sa.create_engine(normalise_url(storage_url))
    with engine.begin() as conn:  # the credentials table as versions before stations created it, with a row
        conn.execute(
            sa.text(
                "CREATE TABLE credentials (name VARCHAR NOT NULL PRIMARY KEY, role VARCHAR NOT NULL "
                "CONSTRAINT ck_credentials_role CHECK (role IN ('vehicle', 'reader', 'admin')), "
                "secret_hash VARCHAR NOT NULL, vehicle_id VARCHAR, revoked BOOLEAN NOT NULL, "
                "created_ms BIGINT NOT NULL)"
            )
        )
        conn.execute(sa.text("INSERT INTO credentials VALUES ('car-old', 'vehicle', 'sha256$00', 'car-old', false, 1)"))
    engine.dispose()
    storage = open_storage(storage_url)
    try:
        storage.add_credential("rws-new", "station", "sha256$11")
        assert [(c.name, c.role) for c in storage.credentials()] == [("car-old", "vehicle"), ("rws-new", "station")]
        with pytest.raises(ValueError, match="role"):
            storage.add_credential("x", "superuser", "sha256$22")
    finally:
        storage.close()
    open_storage(storage_url).close()  # a second open finds it done


def test_the_warning_engine_judges_a_station_report_by_its_interval():
    engine = WarningEngine(min_low_passes=2, validity_s=600.0)
    cell = covered_cells(LAT, LON, 10)[0]

    def row(t_ms, lo, hi, station="s1"):
        return {
            "station_id": station,
            "cell": cell,
            "timestamp_ms": t_ms,
            "mu": (lo + hi) / 2,
            "mu_lower": lo,
            "mu_upper": hi,
        }

    assert engine.station_evidence([row(0, 0.05, 0.3)], 0) == []  # one low report: not yet
    assert engine.station_evidence([row(10_000, 0.05, 0.3)], 10_000) == []  # within pass_gap_s: the same visit
    assert engine.station_evidence([row(5_000, 0.05, 0.3, "s1")], 70_000) == []  # older than its last: dropped
    assert engine.late_rows_ == 1
    [raised] = engine.station_evidence([row(60_000, 0.05, 0.3)], 60_000)
    assert (raised.status, raised.cell, raised.n_passes, raised.n_vehicles) == ("active", cell, 2, 1)
    assert engine.station_evidence([row(120_000, 0.2, 0.7)], 120_000) == []  # unknown: changes nothing
    [ended] = engine.station_evidence([row(180_000, 0.5, 1.0, "s2")], 180_000)  # another station reads it dry
    assert (ended.status, ended.reason, ended.evidence_ms) == ("cancelled", "recovered", 180_000)
    with pytest.raises(ValueError, match="mu_lower"):
        engine.station_evidence([row(240_000, 0.5, 0.3)], 240_000)


@pytest.mark.slow
def test_the_dashboard_draws_the_stations_with_their_latest_report(tmp_path):
    require_chromium()
    now = int(time.time() * 1000)
    with (
        serving(dashboard_settings(tmp_path).model_copy(update={"map_clock": "wall"})) as (_service, base_url),
        httpx.Client(base_url=base_url, timeout=30) as client,
    ):
        stations = [add_station(client, name) for name in ("rws-icy", "rws-dry")]
        for (name, secret), state in zip(stations, ("ice", "dry")):
            answer = client.post(
                f"/v1/stations/{name}/reports", json=report(name, now - 300_000, state), auth=(name, secret)
            )
            assert answer.status_code == 200, answer.text
        secret = client.post("/v1/readers", json={"name": "operator"}, auth=ADMIN).json()["secret"]
        dom = run_chromium(f"{base_url}/dashboard#operator:{secret}", "--dump-dom")
    shown = attributes_by_id(dom)["dashboard"]
    assert shown["data-status"] == "ok", shown
    assert shown["data-stations"] == "2" and dom.count("station-icon") == 2
    assert "rws-icy" in dom and "ice, -3.0 °C" in dom and "5 min ago" in dom
