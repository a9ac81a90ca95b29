"""The HTTP API end to end (FastAPI test client, the pipeline thread, real storage): every test runs on SQLite and on a
real PostgreSQL (the `storage_url` fixture)."""

from __future__ import annotations

import json
import time
import xml.etree.ElementTree as ET

import h3
import numpy as np
import pytest
from drives import patch_cells, patch_drive
from fastapi.testclient import TestClient
from service_fixtures import ADMIN, START_MS, ndjson, post, register, running_cloud

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.pipeline.pipeline import DEDUP_HORIZON_MS
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.demo import settle
from roadgrip.fleet.terminal import wire_samples
from roadgrip.vehicle.params import vehicle_by_name


@pytest.fixture
def cloud(storage_url, tmp_path):
    with running_cloud(storage_url, tmp_path) as running:
        yield running


def test_without_credentials_or_with_wrong_ones_everything_is_refused(cloud):
    service, client = cloud
    vehicle = register(client, "car-1")
    for method, path in (
        ("post", "/v1/telemetry"),
        ("get", "/v1/map"),
        ("get", "/v1/warnings"),
        ("get", "/v1/health"),
        ("get", "/v1/vehicles/car-1/estimates"),
        ("post", "/v1/vehicles"),
    ):
        assert client.request(method, path).status_code == 401
        assert client.request(method, path, auth=(vehicle[0], "wrong")).status_code == 401
    assert service.storage.counts()["telemetry"] == 0


def test_a_run_is_stored_and_estimated_like_the_offline_estimator_does(cloud):
    service, client = cloud
    auth = register(client, "suv-1")
    run = patch_drive(0.2, 1)
    samples = wire_samples(run, "suv-1", START_MS)
    answers = post(client, auth, samples)
    assert sum(a["stored"] for a in answers) == len(samples)
    settle(service)
    assert service.storage.counts()["telemetry"] == len(samples)
    got = client.get("/v1/vehicles/suv-1/estimates", auth=auth).json()["estimates"]
    offline = load_estimator(Settings().estimator).estimate_batch(
        run, np.zeros(run.num_rows, dtype=np.int64), vehicle_by_name("paper-suv")
    )
    assert len(got) == offline.num_rows
    np.testing.assert_allclose([e["mu"] for e in got], offline["mu"].to_numpy(), atol=1e-9)
    assert [e["excited"] for e in got] == offline["excited"].to_pylist()
    assert {e["estimator"] for e in got} == {Settings().estimator}
    assert all(e["h3_cell"] == h3.latlng_to_cell(e["latitude_deg"], e["longitude_deg"], 10) for e in got)
    window = client.get(
        "/v1/vehicles/suv-1/estimates", auth=auth, params={"start_ms": START_MS + 1000, "end_ms": START_MS + 2000}
    ).json()["estimates"]
    assert [e["timestamp_ms"] for e in window] == list(range(START_MS + 1000, START_MS + 2000, 100))
    pipeline = client.get("/v1/health", auth=auth).json()["pipeline"]  # what a soak reads
    assert pipeline["latency_since_start"]["n"] == pipeline["estimates"] >= len(got)
    assert pipeline["estimate_s"] > 0 and pipeline["write_s"] > 0 and pipeline["fanout_s"] > 0


def test_a_repeated_message_is_stored_once(cloud):
    service, client = cloud
    auth = register(client, "car-2")
    samples = wire_samples(patch_drive(0.9, 3), "car-2", START_MS)[:30]
    first = post(client, auth, samples, chunk=30)[0]
    again = post(client, auth, samples, chunk=30)[0]
    assert (first["stored"], first["duplicates"]) == (30, 0)
    assert (again["stored"], again["duplicates"]) == (0, 30)
    twice_in_one = post(client, auth, samples[:5] + samples[:5], chunk=10)[0]
    assert (twice_in_one["stored"], twice_in_one["duplicates"]) == (0, 10)
    settle(service)
    counts = service.storage.counts()
    assert counts["telemetry"] == 30
    assert counts["estimates"] == len(client.get("/v1/vehicles/car-2/estimates", auth=auth).json()["estimates"])


def test_a_repeat_older_than_the_pipelines_memory_is_a_duplicate_not_stored_nor_late(storage_url, tmp_path):
    with running_cloud(storage_url, tmp_path, rate_limit_samples_per_s=0) as (service, client):
        auth = register(client, "car-5")
        samples = [s for k in range(3) for s in wire_samples(patch_drive(0.9, k), "car-5", START_MS + 30_000 * k)]
        assert (samples[-1]["timestamp_ms"] - samples[0]["timestamp_ms"]) > 2 * DEDUP_HORIZON_MS
        post(client, auth, samples, chunk=100)
        settle(service)
        again = post(client, auth, samples[:30], chunk=30)[0]  # 90 s old: the pipeline forgot it, the database not
        settle(service)
        assert (again["stored"], again["duplicates"]) == (0, 30)
        counters = service.ingest.pipeline.counters
        assert (counters.stored, counters.duplicates, counters.late) == (len(samples), 30, 0)
        assert service.storage.counts()["telemetry"] == len(samples)


@pytest.mark.slow
def test_out_of_order_samples_inside_the_window_give_the_in_order_estimates(storage_url, tmp_path):
    # a window of 2 s: each post returns once its sample is stored, so on a slow disk two posts can lie more than
    # 0.2 s apart and the first of a pair would be released before the second came (a late sample, not estimated)
    with running_cloud(storage_url, tmp_path, reorder_window_s=2.0) as (service, client):
        _out_of_order_pairs(service, client)


def _out_of_order_pairs(service, client):
    auth = register(client, "car-3")
    run = patch_drive(0.2, 1)
    samples = wire_samples(run, "car-3", START_MS)[:120]
    shuffled = []
    for start in range(0, len(samples), 2):  # swap each pair: 100 ms late, inside the 200 ms window
        shuffled += samples[start : start + 2][::-1]
    post(client, auth, shuffled, chunk=1)
    settle(service)
    offline = load_estimator(Settings().estimator).estimate_batch(
        run.slice(0, 120), np.zeros(120, dtype=np.int64), vehicle_by_name("paper-suv")
    )
    deadline = time.time() + 10  # a loaded machine may need a round more to release the last reorder window
    while (
        len(got := client.get("/v1/vehicles/car-3/estimates", auth=auth).json()["estimates"]) < offline.num_rows
        and time.time() < deadline
    ):
        time.sleep(0.05)
    np.testing.assert_allclose([e["mu"] for e in got], offline["mu"].to_numpy(), atol=1e-9)
    assert service.ingest.pipeline.counters.late == 0


def test_a_gap_restarts_the_estimator_and_a_late_sample_is_stored_not_estimated(cloud):
    service, client = cloud
    auth = register(client, "car-4")
    samples = wire_samples(patch_drive(0.9, 3), "car-4", START_MS)
    before, after = samples[:50], samples[60:100]
    post(client, auth, before)
    post(client, auth, after)
    settle(service)
    assert service.ingest.pipeline.counters.restarts == 1
    post(client, auth, [samples[55]], chunk=1)  # arrives seconds late, behind estimated samples
    settle(service)
    assert service.ingest.pipeline.counters.late == 1
    assert service.storage.counts()["telemetry"] == 91


def test_a_vehicle_cannot_write_or_read_as_another_and_a_reader_cannot_write(cloud):
    service, client = cloud
    a = register(client, "car-a")
    register(client, "car-b")
    samples = wire_samples(patch_drive(0.9, 3), "car-b", START_MS)[:3]
    answer = client.post("/v1/telemetry", json=samples, auth=a)
    assert answer.status_code == 422
    assert {r["field"] for r in answer.json()["rejected"]} == {"vehicle_id"}
    assert client.get("/v1/vehicles/car-b/estimates", auth=a).status_code == 403
    assert client.get("/v1/vehicles/car-b", auth=a).status_code == 403
    assert client.get("/v1/map", auth=a).status_code == 403
    assert client.post("/v1/vehicles", json={"vehicle_id": "car-c"}, auth=a).status_code == 403
    reader = client.post("/v1/readers", json={"name": "operator"}, auth=ADMIN).json()
    reader_auth = ("operator", reader["secret"])
    assert client.get("/v1/vehicles/car-b/estimates", auth=reader_auth).status_code == 200
    assert client.post("/v1/telemetry", json=samples, auth=reader_auth).status_code == 403
    assert service.storage.counts()["telemetry"] == 0


def test_a_revoked_credential_stops_at_once_and_secrets_are_stored_hashed(cloud):
    service, client = cloud
    auth = register(client, "car-r")
    sample = wire_samples(patch_drive(0.9, 3), "car-r", START_MS)[:1]
    assert client.post("/v1/telemetry", json=sample, auth=auth).status_code == 200
    stored = service.storage.credential("car-r")
    assert auth[1] not in stored.secret_hash and stored.secret_hash.startswith("sha256$")
    assert service.storage.credential("admin").secret_hash.startswith("scrypt$")
    assert client.delete("/v1/credentials/car-r", auth=ADMIN).status_code == 204
    assert client.post("/v1/telemetry", json=sample, auth=auth).status_code == 401
    assert client.delete("/v1/credentials/admin", auth=ADMIN).status_code == 409


@pytest.mark.parametrize(
    "change, field",
    [
        ({"speed_mps": float("nan")}, "speed_mps"),
        ({"speed_mps": "fast"}, "speed_mps"),
        ({"yaw_rate_radps": 40.0}, "yaw_rate_radps"),
        ({"abs_active": "yes"}, "abs_active"),
        ({"sped_mps": 3.0}, "sped_mps"),
        ({"timestamp_ms": START_MS + 10 * 86_400_000}, "timestamp_ms"),
    ],
)
def test_a_bad_sample_is_rejected_naming_its_field_and_the_good_ones_are_kept(cloud, change, field):
    _service, client = cloud
    auth = register(client, "car-5")
    samples = wire_samples(patch_drive(0.9, 3), "car-5", START_MS)[:5]
    body = (
        ndjson(samples[:2]).decode().replace("NaN", "NaN")
        + "\n"
        + json.dumps({**samples[2], **change})
        + "\n"
        + ndjson(samples[3:]).decode()
    )
    answer = client.post(
        "/v1/telemetry", content=body.encode(), auth=auth, headers={"content-type": "application/x-ndjson"}
    )
    assert answer.status_code == 200, answer.text
    result = answer.json()
    assert (result["received"], result["accepted"], result["stored"]) == (5, 4, 4)
    assert [(r["index"], r["field"]) for r in result["rejected"]] == [(2, field)]
    assert field in result["rejected"][0]["reason"]


def test_unusable_bodies_are_refused_with_clear_errors(cloud):
    service, client = cloud
    auth = register(client, "car-6")
    bad_json = client.post(
        "/v1/telemetry", content=b'[{"vehicle_id": ', auth=auth, headers={"content-type": "application/json"}
    )
    assert bad_json.status_code == 400
    huge = b"[" + b" " * (service.settings.max_payload_bytes + 1) + b"]"
    assert (
        client.post("/v1/telemetry", content=huge, auth=auth, headers={"content-type": "application/json"}).status_code
        == 413
    )
    none_valid = client.post("/v1/telemetry", json=[{"vehicle_id": "car-6"}], auth=auth)
    assert none_valid.status_code == 422 and none_valid.json()["rejected"][0]["field"]
    assert client.get("/v1/health", auth=auth).json()["status"] == "ok"


def test_a_repeated_query_parameter_is_refused_on_every_route(cloud):
    """Every declared query parameter is a scalar: given twice it is a 422 naming it, not its last value (a fuzzing
    case, issue 17); an undeclared one is ignored, as FastAPI does."""
    _service, client = cloud
    auth = register(client, "car-q")
    for path, params in (
        ("/v1/vehicles/car-q/estimates", [("limit", "5"), ("limit", "7")]),
        ("/v1/vehicles/car-q/estimates", [("start_ms", "1"), ("end_ms", "2"), ("end_ms", "3")]),
        ("/v1/warnings", [("active", "true"), ("active", "false")]),
    ):
        answer = client.get(path, params=params, auth=ADMIN if "warnings" in path else auth)
        assert answer.status_code == 422, (path, answer.text)
        repeated = {key for key, _ in params if sum(k == key for k, _ in params) > 1}
        assert {tuple(d["loc"]) for d in answer.json()["detail"]} == {("query", k) for k in repeated}
    assert client.get("/v1/warnings", params=[("x", "1"), ("x", "2")], auth=ADMIN).status_code == 200
    assert client.get("/v1/vehicles/car-q/estimates", params={"limit": 5}, auth=auth).status_code == 200


def test_vss_keyed_samples_are_accepted(cloud):
    service, client = cloud
    auth = register(client, "car-7")
    s = wire_samples(patch_drive(0.9, 3), "car-7", START_MS)[0]
    vss = {
        "timestamp_ms": s["timestamp_ms"],
        "Vehicle.VehicleIdentification.VIN": "car-7",
        "Vehicle.Speed": s["speed_mps"] * 3.6,
        "Vehicle.Acceleration.Longitudinal": s["accel_lon_mps2"],
        "Vehicle.Acceleration.Lateral": s["accel_lat_mps2"],
        "Vehicle.AngularVelocity.Yaw": np.degrees(s["yaw_rate_radps"]),
        "Vehicle.Chassis.SteeringWheel.Angle": np.degrees(s["steering_wheel_angle_rad"]),
        "Vehicle.ADAS.ABS.IsEngaged": s["abs_active"],
        "Vehicle.ADAS.CruiseControl.IsActive": s["acc_active"],
        "Vehicle.CurrentLocation.Latitude": s["latitude_deg"],
        "Vehicle.CurrentLocation.Longitude": s["longitude_deg"],
    }
    for row, side in (("Row1", "fl"), ("Row1", "fr"), ("Row2", "rl"), ("Row2", "rr")):
        wheel = "Left" if side[1] == "l" else "Right"
        vss[f"Vehicle.Chassis.Axle.{row}.Wheel.{wheel}.AngularSpeed"] = np.degrees(s[f"wheel_speed_{side}_radps"])
    answer = client.post("/v1/telemetry", json=vss, auth=auth)
    assert answer.status_code == 200 and answer.json()["stored"] == 1, answer.text
    settle(service)
    stored = service.storage.telemetry("car-7")[0]
    assert stored["speed_mps"] == pytest.approx(s["speed_mps"], rel=1e-12)
    assert stored["wheel_speed_rr_radps"] == pytest.approx(s["wheel_speed_rr_radps"], rel=1e-12)


def on_or_beside_the_patch() -> set[str]:
    """The patch's cells and their neighbours: one low pass raises (the product's setting, chosen by the fleet
    benchmark), and a vehicle braking on the patch still reads it low in the next cell (a "beside" warning there)."""
    return {near for cell in patch_cells() for near in h3.grid_disk(cell, 1)}


@pytest.mark.slow
def test_a_slippery_patch_raises_a_warning_there_only_and_dry_passes_cancel_it(cloud):
    service, client = cloud
    for vehicle_id, profile, seed in (("suv-w", "paper-suv", 1), ("sedan-w", "midsize-sedan", 2)):
        auth = register(client, vehicle_id, profile)
        post(client, auth, wire_samples(patch_drive(0.2, seed, profile), vehicle_id, START_MS), chunk=20)
    # a vehicle far away, later, closes the passes on the patch (their vehicles were last seen pass_gap_s before)
    later = START_MS + 120_000
    auth = register(client, "hatch-d", "compact-hatchback")
    post(client, auth, wire_samples(patch_drive(0.9, 4, "compact-hatchback"), "hatch-d", later), chunk=20)
    settle(service)
    active = client.get("/v1/warnings", auth=ADMIN).json()["warnings"]
    assert active, "the patch raised no warning"
    assert {w["roadgrip"]["cell"] for w in active} & patch_cells()
    assert {w["roadgrip"]["cell"] for w in active} <= on_or_beside_the_patch()
    for w in active:
        assert w["denm"]["situation"]["eventType"]["causeCode"] == 6
        assert "termination" not in w["denm"]["management"]
    geo = client.get("/v1/map", auth=ADMIN).json()
    assert geo["type"] == "FeatureCollection" and geo["features"]
    measured = {
        f["properties"]["cell"]: f["properties"] for f in geo["features"] if f["properties"]["status"] == "measured"
    }
    assert measured and ET.fromstring(client.get("/v1/map/datex2", auth=ADMIN).content) is not None
    # later again, vehicles brake on the patch's middle and far end too: grip is proven wherever the ice was read (the
    # low readings of the first two ran on over the whole patch, 250-400 m), and every warned cell on it has recovered
    for vehicle_id, profile, seed, brake_s, k in (
        ("suv-d", "paper-suv", 3, 13.0, 1),
        ("sedan-d", "midsize-sedan", 5, 15.0, 2),
    ):
        auth = register(client, vehicle_id, profile)
        drive = patch_drive(0.9, seed, profile, brake_s=brake_s)
        post(client, auth, wire_samples(drive, vehicle_id, later + 120_000 * k), chunk=20)
        settle(service)
    left = {w["roadgrip"]["cell"] for w in client.get("/v1/warnings", auth=ADMIN).json()["warnings"]}
    assert not left & patch_cells(), "dry passes did not cancel the warnings on the patch"
    assert left <= on_or_beside_the_patch() - patch_cells()  # beside it, where nobody braked again: it will expire
    every = client.get("/v1/warnings", params={"active": False}, auth=ADMIN).json()["warnings"]
    assert {w["roadgrip"]["cell"] for w in every} <= on_or_beside_the_patch()
    assert all(
        w["denm"]["management"].get("termination") == "isCancellation"
        for w in every
        if w["roadgrip"]["cell"] in patch_cells()
    )


def test_a_restarted_service_keeps_its_map_and_active_warnings(storage_url, tmp_path):
    settings = Settings(
        data_dir=tmp_path,
        database_url=storage_url,
        mqtt="off",
        admin_secret=ADMIN[1],
        flush_interval_s=0.01,
        reorder_window_s=0.2,
        map_clock="data",
    )
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        for vehicle_id, profile, seed in (("suv-w", "paper-suv", 1), ("sedan-w", "midsize-sedan", 2)):
            auth = register(client, vehicle_id, profile)
            post(client, auth, wire_samples(patch_drive(0.2, seed, profile), vehicle_id, START_MS), chunk=50)
        auth = register(client, "far-away", "paper-suv")  # closes the passes on the patch
        post(client, auth, wire_samples(patch_drive(0.9, 3), "far-away", START_MS + 120_000)[:5], chunk=50)
        settle(service)
        before = client.get("/v1/warnings", auth=ADMIN).json()["warnings"]
        cells_before = {f["properties"]["cell"] for f in client.get("/v1/map", auth=ADMIN).json()["features"]}
    assert before
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        assert client.get("/v1/warnings", auth=ADMIN).json()["warnings"] == before
        assert {w.warning_id for w in service.warning_engine.active()} == {w["roadgrip"]["warning_id"] for w in before}
        assert {f["properties"]["cell"] for f in client.get("/v1/map", auth=ADMIN).json()["features"]} == cells_before
