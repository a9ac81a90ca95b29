"""Fault injection (issue 8): the service killed, the broker restarted, the database stopped, each in the middle of a
stream. Each test counts what the vehicles sent, what was acknowledged to them (MQTT: the broker's PUBACK; HTTP: a 200)
and what is in the database at the end, and checks that every acknowledged sample is stored exactly once.

On MQTT a PUBACK to the vehicle only means that the broker has the message: it waits in the service's persistent
session until the service, having stored it, acknowledges it in turn (manual PUBACK). So "acknowledged" below is what
the vehicle got PUBACKs for, and the tests check that all of it ends up stored once the fault is over.

Each test prints one line of counts and timings (`pytest -s` shows them; docs/RELIABILITY.md quotes a run). Helpers
in fault_fixtures.py.
"""

from __future__ import annotations

import json
import time

import httpx
import pytest
from fault_fixtures import (
    HttpTerminal,
    MqttTerminal,
    PostgresCluster,
    ServeProcess,
    drive_samples,
    keys,
    serving_http,
    stored_keys,
    wait_for,
    warm_estimator,
)

from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.transport.mosquitto import INSTALL_HINT, ManagedBroker, mosquitto_available
from roadgrip.vehicle.params import vehicle_by_name

ADMIN = ("admin", "admin-secret-for-fault-tests-0123456789")
PACE_S = 0.025  # one sample every 25 ms: 40 samples/s, 4x a terminal's 10 Hz and under the default rate limit (50/s)


@pytest.fixture(scope="module", autouse=True)
def compiled_estimator():
    """The EKF's numba kernels compiled before any service starts: with a cold cache the first estimate of each new
    process takes ~15 s, which the service spends with its pipeline blocked (see docs/RELIABILITY.md)."""
    warm_estimator()


@pytest.fixture
def broker(tmp_path):
    """A Mosquitto of the test's own (not the service's): it outlives a killed service."""
    if not mosquitto_available():
        pytest.fail(f"mosquitto is not installed: {INSTALL_HINT}", pytrace=False)
    broker = ManagedBroker(tmp_path / "broker")
    broker.start()
    yield broker
    broker.stop()


def register(http: httpx.Client, vehicle_id: str) -> str:
    answer = http.post("/v1/vehicles", json={"vehicle_id": vehicle_id, "profile": "paper-suv"}, auth=ADMIN)
    answer.raise_for_status()
    return answer.json()["secret"]


def wait_stored(url: str, acknowledged: list[dict], timeout_s: float = 60) -> float:
    """Wait until every acknowledged sample is in the telemetry table; the seconds it took."""
    wanted = keys(acknowledged)
    return wait_for(
        lambda: wanted <= set(stored_keys(url, "telemetry")),
        timeout_s,
        f"{len(wanted)} acknowledged samples stored",
        poll_s=0.1,
    )


def check_stored_once(url: str, sent: list[dict], acknowledged: list[dict]) -> dict:
    """For the vehicles of `sent`: every acknowledged sample stored, none twice, nothing stored that was not sent, at
    most one estimate per stored sample; the counts."""
    vehicles = {s["vehicle_id"] for s in sent}
    telemetry = [k for k in stored_keys(url, "telemetry") if k[0] in vehicles]
    estimates = [k for k in stored_keys(url, "estimates") if k[0] in vehicles]
    assert len(telemetry) == len(set(telemetry)), "a sample stored twice"
    assert len(estimates) == len(set(estimates)), "two estimates for one sample"
    missing = keys(acknowledged) - set(telemetry)
    assert not missing, f"{len(missing)} acknowledged samples not stored, e.g. {sorted(missing)[:3]}"
    assert set(telemetry) <= keys(sent), "stored samples that were never sent"
    assert set(estimates) <= set(telemetry), "an estimate without its stored sample"
    return {"sent": len(sent), "acknowledged": len(acknowledged), "stored": len(telemetry), "estimates": len(estimates)}


def report(name: str, **figures) -> None:
    print(f"\nFAULT {name}: {json.dumps(figures)}")


# ------------------------------------------------------------------------------------------------- 1. SIGKILL
@pytest.mark.slow
def test_service_sigkill_mid_stream_loses_no_acknowledged_sample(broker, tmp_path):
    """`roadgrip serve` (SQLite, the test's broker) killed with SIGKILL while one vehicle publishes over MQTT and one
    posts over HTTP, kept down 2 s, started again on the same data directory (same MQTT client id: its persistent
    session); the vehicles go on throughout."""
    workdir = tmp_path / "service"
    workdir.mkdir()
    serve = ServeProcess(
        workdir,
        {
            "ROADGRIP_MQTT": broker.url,
            "ROADGRIP_MQTT_USERNAME": broker.service_user,
            "ROADGRIP_MQTT_PASSWORD": broker.service_password,
        },
        ADMIN,
    )
    database = f"sqlite:///{workdir / 'roadgrip.sqlite'}"
    car = truck = None
    try:
        serve.start()
        car_secret = register(serve.http, "kill-mqtt")
        # With a broker given by URL the service manages no broker logins: the operator adds the vehicle's.
        broker.set_user("kill-mqtt", car_secret, "vehicle", "kill-mqtt")
        truck_secret = register(serve.http, "kill-http")
        car = MqttTerminal(broker.url, "kill-mqtt", car_secret, drive_samples("kill-mqtt", 2), 1, PACE_S)
        truck = HttpTerminal(serve.url, "kill-http", truck_secret, drive_samples("kill-http", 2), 10, 10 * PACE_S)
        car.start()
        truck.start()
        time.sleep(4.0)
        stored_before = len(stored_keys(database, "telemetry"))
        serve.kill()
        killed = time.monotonic()
        time.sleep(2.0)
        start_s = serve.start()
        up = time.monotonic()
        held_by_broker = car.acknowledged()  # all of it PUBACKed by the broker, part of it not yet stored
        catch_up_s = wait_stored(database, held_by_broker + truck.acknowledged)
        car.finish(60)
        truck.finish(60)
        wait_for(car.all_acknowledged, 15, "PUBACKs for every MQTT message")
        wait_stored(database, car.acknowledged() + truck.acknowledged)
        health = serve.health()
    finally:
        for terminal in (car, truck):
            if terminal is not None:
                terminal.close()
        serve.stop()
    mqtt = check_stored_once(database, car.sent, car.acknowledged())
    http = check_stored_once(database, truck.sent, truck.acknowledged)
    assert car.refused == 0
    assert mqtt["sent"] == mqtt["acknowledged"] == mqtt["stored"] == 600
    assert http["sent"] == http["acknowledged"] == http["stored"] == 600
    published_while_down = car.sent_between(killed, up)
    refused_while_down = sum(truck.count(e, killed, up) for e in ("ConnectError", "ReadError", "RemoteProtocolError"))
    assert published_while_down > 0 and refused_while_down > 0, "the kill did not fall mid-stream"
    report(
        "sigkill",
        mqtt=mqtt,
        http=http,
        stored_before_kill=stored_before,
        mqtt_published_while_down=published_while_down,
        http_failed_tries_while_down=refused_while_down,
        http_already_stored_on_retry=truck.duplicates,
        down_s=round(up - killed, 2),
        restart_s=round(start_s, 2),
        catch_up_s=round(catch_up_s, 2),
        pipeline_after_restart={k: health["pipeline"][k] for k in ("stored", "duplicates", "late")},
    )


# ------------------------------------------------------------------------------------------------- 2. broker restart
@pytest.mark.parametrize("down_s", [0.0, 3.0], ids=["restart", "down-3s"])
@pytest.mark.slow
def test_broker_restart_mid_stream_everyone_reconnects_and_nothing_acknowledged_is_lost(broker, tmp_path, down_s):
    """The broker stopped (SIGTERM: it saves its sessions) and started again while a vehicle publishes, at once
    (`ManagedBroker.restart`) or after `down_s`; the vehicle's paho client and the service's MqttClient reconnect by
    themselves (paho's backoff: 0.25 s doubling to 10 s)."""
    settings = Settings(
        data_dir=tmp_path / "service",
        mqtt=broker.url,
        mqtt_username=broker.service_user,
        mqtt_password=broker.service_password,
        admin_secret=ADMIN[1],
    )
    database = settings.storage_url
    with CloudService(settings) as service:
        [secret] = service.register_vehicles([("restart-car", vehicle_by_name("paper-suv"))])
        broker.set_user("restart-car", secret, "vehicle", "restart-car")
        car = MqttTerminal(broker.url, "restart-car", secret, drive_samples("restart-car", 1), 1, PACE_S)
        try:
            car.start()
            time.sleep(2.5)
            stopping = time.monotonic()
            if down_s:
                broker.stop()
                time.sleep(down_s)
                broker.start()
            else:
                broker.restart()
            restarted = time.monotonic()
            service_back_s = wait_for(
                lambda: service.health()["mqtt"] == "connected", 10, "the service's MQTT connection back"
            )
            car.finish(30)
            wait_for(car.all_acknowledged, 15, "PUBACKs for every message")
            wait_stored(database, car.acknowledged())
            health = service.health()
        finally:
            car.close()
    counts = check_stored_once(database, car.sent, car.acknowledged())
    assert car.refused == 0
    assert counts["sent"] == counts["acknowledged"] == counts["stored"] == 300
    drops = [t for t, connected in car.connection_log if not connected]
    assert drops, "the vehicle never saw the broker go"
    back = [t for t, connected in car.connection_log if connected and t > drops[0]]
    assert back, "the vehicle's client did not reconnect by itself"
    assert health["status"] == "ok" and health["mqtt"] == "connected"
    assert service_back_s < 5.0
    report(
        f"broker-{'down' if down_s else 'restart'}",
        **counts,
        broker_down_s=round(restarted - stopping, 2),
        service_reconnected_after_s=round(service_back_s, 2),
        vehicle_reconnected_after_s=round(back[0] - restarted, 2),
        vehicle_published_while_disconnected=car.sent_between(drops[0], back[0]),
    )


# ------------------------------------------------------------------------------------------------- 3. PostgreSQL down
OUTAGE_S = 30.0


@pytest.mark.slow
def test_postgresql_outage_of_30_s_loses_no_acknowledged_sample(broker, tmp_path):
    """A PostgreSQL cluster of the test's own, stopped (`pg_ctl stop -m fast`) for 30 s while one vehicle publishes
    over MQTT and one posts over HTTP: health says unavailable (503), HTTP ingest answers 503, MQTT messages wait
    unacknowledged in the service; started again, the service recovers by itself and stores them."""
    cluster = PostgresCluster()
    try:
        settings = Settings(
            data_dir=tmp_path / "service",
            database_url=cluster.url,
            mqtt=broker.url,
            mqtt_username=broker.service_user,
            mqtt_password=broker.service_password,
            admin_secret=ADMIN[1],
        )
        with (
            CloudService(settings) as service,
            serving_http(service) as base_url,
            httpx.Client(base_url=base_url, auth=ADMIN, timeout=10) as admin,
        ):
            car_secret = register(admin, "pg-mqtt")
            broker.set_user("pg-mqtt", car_secret, "vehicle", "pg-mqtt")
            truck_secret = register(admin, "pg-http")
            assert admin.get("/v1/health").json()["status"] == "ok"
            # 20 samples/s each: the 45 s stream stays under the rate limit with everything sent during the outage
            car = MqttTerminal(broker.url, "pg-mqtt", car_secret, drive_samples("pg-mqtt", 3), 1, 0.05)
            truck = HttpTerminal(base_url, "pg-http", truck_secret, drive_samples("pg-http", 3), 10, 0.5, retry_s=0.5)
            try:
                car.start()
                truck.start()
                time.sleep(5.0)
                stopping = time.monotonic()
                cluster.stop()
                stopped = time.monotonic()
                during = []  # (time, HTTP status, health body) every 0.5 s of the outage
                while time.monotonic() < stopped + OUTAGE_S:
                    answer = admin.get("/v1/health")
                    during.append((time.monotonic(), answer.status_code, answer.json()))
                    time.sleep(0.5)
                starting = time.monotonic()
                cluster.start()
                started = time.monotonic()
                health_back_s = wait_for(lambda: admin.get("/v1/health").status_code == 200, 15, "health ok")
                car.finish(60)
                truck.finish(60)
                wait_for(car.all_acknowledged, 15, "PUBACKs for every MQTT message")
                sent, acknowledged = car.sent + truck.sent, car.acknowledged() + truck.acknowledged
                drain_s = wait_stored(cluster.url, acknowledged)
                health = admin.get("/v1/health").json()
            finally:
                car.close()
                truck.close()
        mqtt = check_stored_once(cluster.url, car.sent, car.acknowledged())
        http = check_stored_once(cluster.url, truck.sent, truck.acknowledged)
    finally:
        cluster.close()
    # during the outage: health 503 "unavailable" throughout, no HTTP sample acknowledged, MQTT held
    assert during and all(code == 503 and body["status"] == "unavailable" for _, code, body in during), [
        (code, body["status"]) for _, code, body in during if code != 503 or body["status"] != "unavailable"
    ]
    assert truck.count(200, stopped + 0.5, starting) == 0, "HTTP samples acknowledged while the database was down"
    answered_503 = truck.count(503, stopped, starting)
    assert answered_503 > 0
    held_mqtt = max(body["pipeline"]["backlog"] for _, _, body in during)
    published_during = car.sent_between(stopped, starting)
    assert held_mqtt > 0 and published_during > 0
    # afterwards: back by itself, everything sent acknowledged and stored once
    assert health_back_s < 5.0 and health["status"] == "ok"
    assert car.refused == 0
    assert mqtt["sent"] == mqtt["acknowledged"] == mqtt["stored"] == 900
    assert http["sent"] == http["acknowledged"] == http["stored"] == 900
    report(
        "postgresql-outage",
        mqtt=mqtt,
        http=http,
        outage_s=round(starting - stopping, 1),
        pg_stop_s=round(stopped - stopping, 2),
        pg_start_s=round(started - starting, 2),
        health_ok_after_start_s=round(health_back_s, 2),
        drain_after_stream_s=round(drain_s, 2),
        health_503_answers=len(during),
        http_503_answers=answered_503,
        http_429_answers=truck.count(429),
        http_already_stored_on_retry=truck.duplicates,
        mqtt_published_during_outage=published_during,
        mqtt_held_in_service_max=held_mqtt,
        sent_total=len(sent),
    )


# ------------------------------------------------------------------------------------------------- 4. SIGTERM
@pytest.mark.slow
def test_service_sigterm_stops_cleanly_and_estimates_what_it_held(tmp_path):
    """SIGTERM (systemd, docker stop, `roadgrip bench`) is the clean stop: `roadgrip serve` runs CloudService.stop(),
    whose last pipeline round releases every reorder window, so every stored sample gets its estimate. A 5 s window
    makes sure the last samples are still held when the signal comes."""
    workdir = tmp_path / "service"
    workdir.mkdir()
    serve = ServeProcess(workdir, {"ROADGRIP_MQTT": "off", "ROADGRIP_REORDER_WINDOW_S": "5"}, ADMIN)
    database = f"sqlite:///{workdir / 'roadgrip.sqlite'}"
    try:
        serve.start()
        secret = register(serve.http, "term-car")
        samples = drive_samples("term-car", 1)
        answer = serve.http.post("/v1/telemetry", json=samples, auth=("term-car", secret))
        assert answer.status_code == 200 and answer.json()["stored"] == len(samples)
        serve.process.terminate()
        serve.process.wait(30)
    finally:
        serve.stop()
    counts = check_stored_once(database, samples, samples)
    report("sigterm", **counts, exit_status=serve.process.returncode)
    assert counts["estimates"] == counts["stored"] == len(samples), (
        f"{counts['stored'] - counts['estimates']} stored samples left without an estimate: CloudService.stop() "
        f"did not run\n{serve.log_tail(1500)}"
    )
