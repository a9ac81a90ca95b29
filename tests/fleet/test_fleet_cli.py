"""`roadgrip fleet` against a running cloud: simulated vehicles and a replayed real log, each with its own credentials."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from roadgrip.cli import app
from roadgrip.cloud.localhost import free_port
from roadgrip.cloud.settings import Settings
from roadgrip.fleet.demo import LocalCloud, settle

ADMIN_SECRET = "fleet-test-admin-secret-0123"
LOG = Path(__file__).resolve().parents[2] / "data" / "real" / "bmw_m8_braking"
runner = CliRunner()


def wait_stored(service, samples: int, timeout_s: float = 120.0) -> None:
    """Wait until the service has stored `samples` telemetry samples (over MQTT the broker PUBACKs a vehicle before the
    service has taken its message: on a loaded machine the fleet command ends well before the store), then settle."""
    deadline = time.monotonic() + timeout_s
    while service.storage.counts()["telemetry"] < samples and time.monotonic() < deadline:
        time.sleep(0.1)
    settle(service)


@pytest.fixture
def cloud(tmp_path, monkeypatch):
    monkeypatch.setenv("ROADGRIP_ADMIN_SECRET", ADMIN_SECRET)
    local = LocalCloud(
        Settings(
            data_dir=tmp_path, port=free_port(), mqtt="auto", admin_secret=ADMIN_SECRET, rate_limit_samples_per_s=0
        )
    )  # vehicles at 50x real time
    yield local
    local.stop()


@pytest.mark.parametrize("transport", ["mqtt", "http"])
@pytest.mark.slow
def test_simulated_vehicles_drive_against_the_cloud(cloud, transport):
    result = runner.invoke(
        app,
        [
            "fleet",
            "--url",
            cloud.url,
            "--vehicles",
            "3",
            "--speed",
            "50",
            "--duration",
            "20",
            "--transport",
            transport,
            "--prefix",
            f"cli-{transport}",
        ],
    )
    assert result.exit_code == 0, result.output
    wait_stored(cloud.service, 3 * 200)
    counts = cloud.service.storage.counts()
    assert counts["telemetry"] == 3 * 200 and counts["estimates"] > 0
    assert sorted(cloud.service.storage.vehicle_ids()) == [f"cli-{transport}-{k:03d}" for k in range(3)]


@pytest.mark.slow
def test_vehicles_spread_over_given_brokers_in_mqtt_3_1_1_and_the_estimates_read_back(cloud):
    """The options a cluster needs (--mqtt for each node, --mqtt-protocol 3.1.1, --read-url for another replica),
    here against serve's own broker and API."""
    mqtt_url = cloud.service.mqtt_url
    result = runner.invoke(
        app,
        [
            "fleet",
            "--url",
            cloud.url,
            "--vehicles",
            "2",
            "--speed",
            "50",
            "--duration",
            "20",
            "--mqtt",
            mqtt_url,
            "--mqtt",
            mqtt_url,
            "--mqtt-protocol",
            "3.1.1",
            "--read-url",
            cloud.url,
            "--prefix",
            "spread",
        ],
    )
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())  # rich wraps long lines
    assert "over MQTT 3.1.1 to 2 broker(s)" in said
    wait_stored(cloud.service, 2 * 200)
    stored = {v: len(cloud.service.storage.estimates(v, limit=100_000)) for v in ("spread-000", "spread-001")}
    assert cloud.service.storage.counts()["telemetry"] == 2 * 200 and all(stored.values())
    assert f"read back from {cloud.url}: {sum(stored.values()):,} estimates of 2 of 2 vehicles" in said


@pytest.mark.slow
def test_a_vehicle_whose_broker_is_down_goes_to_the_next_and_the_fleet_reports_per_vehicle(cloud):
    """Vehicle 0 is assigned a port where nothing listens: it connects to the next endpoint; nothing is lost."""
    dead = f"mqtt://127.0.0.1:{free_port()}"
    result = runner.invoke(
        app,
        ["fleet", "--url", cloud.url, "--vehicles", "2", "--speed", "50", "--duration", "10"]
        + ["--mqtt", dead, "--mqtt", cloud.service.mqtt_url, "--prefix", "dead"],
    )
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert "PUBACKed 200, lost 0" in said and "dead-000" in said and "dead-001" in said
    settle(cloud.service)
    assert cloud.service.storage.counts()["telemetry"] == 2 * 100


def test_the_real_log_is_replayed_as_its_own_vehicle(cloud):
    result = runner.invoke(
        app,
        ["fleet", "--url", cloud.url, "--replay", str(LOG), "--speed", "50", "--transport", "http", "--prefix", "m8"],
    )
    assert result.exit_code == 0, result.output
    settle(cloud.service)
    assert cloud.service.storage.counts()["telemetry"] == 96  # 9.6 s at 10 Hz
    assert cloud.service.storage.vehicle_profile("m8-bmw-m8")["mass_kg"] == pytest.approx(2074.4)


def test_without_an_admin_secret_the_fleet_says_so(tmp_path, monkeypatch):
    monkeypatch.delenv("ROADGRIP_ADMIN_SECRET", raising=False)
    result = runner.invoke(app, ["fleet", "--admin-secret-file", str(tmp_path / "nope")])
    assert result.exit_code == 2 and "admin secret" in result.output
