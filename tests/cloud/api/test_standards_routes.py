"""The standards at the service's edge, in `roadgrip serve` on SQLite: the DATEX II routes (measured data and site
table, an empty map and a map with a roadside station's ice) validate against the official DATEX II v3 schema with the
configured country; the DENMs of a warning's life (raised, refreshed, cancelled, from a station's reports) come over
GET /v1/warnings/uper and over the real MQTT topic roadgrip/v1/warnings/uper (the service's own Mosquitto) and decode
from UPER equal to the JSON DENMs sent beside them."""

from __future__ import annotations

import json
import time

from fastapi.testclient import TestClient
from service_fixtures import ADMIN, add_reader, collect, register, settings_for

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.domain.stations import covered_cells
from roadgrip.cloud.formats.denm import DENM_MEMBERS, decode_denm_uper, unframe
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.transport.mqtt import WARNINGS_TOPIC, WARNINGS_UPER_TOPIC, UserClient

LAT, LON = 48.1372, 11.5755


def report(station_id: str, t_ms: int, state: str) -> dict:
    return {
        "station_id": station_id,
        "timestamp_ms": t_ms,
        "latitude_deg": LAT,
        "longitude_deg": LON,
        "surface_state": state,
        "surface_temperature_c": -3.0 if state == "ice" else 4.0,
        "water_film_thickness_mm": 0.0,
    }


def add_station(client, station_id: str) -> tuple[str, str]:
    answer = client.post("/v1/stations", json={"station_id": station_id}, auth=ADMIN)
    assert answer.status_code == 201, answer.text
    return station_id, answer.json()["secret"]


def serving(tmp_path, mqtt: str = "off", **overrides):
    settings = settings_for(f"sqlite:///{tmp_path / 'roadgrip.sqlite'}", tmp_path, mqtt=mqtt)
    return settings.model_copy(update={"map_clock": "wall", **overrides})


def datex2(client, path: str, auth, schema) -> dict:
    answer = client.get(path, auth=auth)
    assert answer.status_code == 200 and answer.headers["content-type"].startswith("application/xml")
    assert [f"{e.path}: {e.reason}" for e in schema.iter_errors(answer.text)] == []
    return schema.to_dict(answer.text)


def uper_denms(client, auth, active: bool = True) -> list[dict]:
    answer = client.get("/v1/warnings/uper", params={"active": active}, auth=auth)
    assert answer.status_code == 200 and answer.headers["content-type"] == "application/octet-stream"
    return [decode_denm_uper(m) for m in unframe(answer.content)]


def json_denms(client, auth, active: bool = True) -> list[dict]:
    warnings = client.get("/v1/warnings", params={"active": active}, auth=auth).json()["warnings"]
    return [{k: w[k] for k in DENM_MEMBERS} for w in warnings]


def test_the_datex2_routes_validate_empty_and_with_a_stations_ice(tmp_path, datex2_schema):
    settings = serving(tmp_path, datex2_country="no")
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        reader = add_reader(client, "operator")
        for path in ("/v1/map/datex2", "/v1/map/datex2/sites"):
            empty = datex2(client, path, reader, datex2_schema)
            assert empty["@xsi:type"] == "com:GenericPublication"
            assert empty["com:publicationCreator"]["com:country"] == "NO"
        station = add_station(client, "rws-1")
        answer = client.post(
            "/v1/stations/rws-1/reports", json=report("rws-1", int(time.time() * 1000), "ice"), auth=station
        )
        assert answer.status_code == 200, answer.text
        data = datex2(client, "/v1/map/datex2", reader, datex2_schema)
        table = datex2(client, "/v1/map/datex2/sites", reader, datex2_schema)
        assert data["@xsi:type"] == "roa:MeasuredDataPublication"
        assert table["@xsi:type"] == "roa:MeasurementSiteTablePublication"
        [reference], [site_table] = data["roa:measurementSiteTableReference"], table["roa:measurementSiteTable"]
        assert (reference["@id"], reference["@version"]) == (site_table["@id"], site_table["@version"])
        sites = {s["@id"] for s in site_table["roa:measurementSite"]}
        assert {m["roa:measurementSiteReference"]["@id"] for m in data["roa:siteMeasurements"]} == sites
        assert sites == set(covered_cells(LAT, LON, settings.h3_resolution))
        assert client.get("/v1/map/datex2/sites", auth=station).status_code == 403


def test_a_warnings_denms_decode_from_uper_over_http_and_over_mqtt(tmp_path):
    settings = serving(tmp_path, mqtt="managed")
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        reader = add_reader(client, "operator")
        vehicle = register(client, "car-u")
        station = add_station(client, "rws-u")
        cells = covered_cells(LAT, LON, settings.h3_resolution)
        now = int(time.time() * 1000)
        with UserClient(service.mqtt_url, *reader) as listener, UserClient(service.mqtt_url, *vehicle) as car:
            listener.subscribe(WARNINGS_TOPIC)
            listener.subscribe(WARNINGS_UPER_TOPIC)
            car.subscribe(WARNINGS_UPER_TOPIC)  # every vehicle may read the warnings, in either rendering
            lives = []  # (what happened, the JSON DENMs and the UPER ones the HTTP routes answer after it)
            for t_ms, state, active in ((now - 120_000, "ice", True), (now - 60_000, "ice", True), (now, "dry", False)):
                posted = client.post("/v1/stations/rws-u/reports", json=report("rws-u", t_ms, state), auth=station)
                assert posted.status_code == 200, posted.text
                lives.append((json_denms(client, reader, active), uper_denms(client, reader, active)))
            # HTTP: raised (new), refreshed (update), cancelled; the UPER route answers the JSON route's DENMs
            for sent, decoded in lives:
                key = lambda d: d["denm"]["management"]["actionID"]["sequenceNumber"]
                assert len(sent) == len(cells) and sorted(decoded, key=key) == sorted(sent, key=key)
            assert all("termination" not in d["denm"]["management"] for d in lives[0][1] + lives[1][1])
            assert all(d["denm"]["management"]["termination"] == "isCancellation" for d in lives[2][1])
            assert uper_denms(client, vehicle) == []  # nothing active after the dry report; a vehicle may read it
            # MQTT: every DENM published as JSON came UPER-encoded on its own topic, equal once decoded
            n = 3 * len(cells)
            got = collect(listener.messages, lambda got: len(got) >= 2 * n)
            on_json = [json.loads(p) for t, p in got if t == WARNINGS_TOPIC]
            on_uper = [decode_denm_uper(p) for t, p in got if t == WARNINGS_UPER_TOPIC]
            assert len(on_json) == len(on_uper) == n
            assert on_uper == [{k: d[k] for k in DENM_MEMBERS} for d in on_json]
            by_car = collect(car.messages, lambda got: len(got) >= n)
            assert [decode_denm_uper(p) for _, p in by_car] == on_uper
            updates = [d["roadgrip"]["update"] for d in on_json]
            assert sorted(set(updates)) == [0, 1, 2]  # new, update, and the cancellation as the third event
        assert client.get("/v1/warnings/uper", auth=station).status_code == 403
