"""`roadgrip fleet` against a running cloud: simulated vehicles and a replayed real log, each with its own credentials."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from roadgrip.cli import app
from roadgrip.cloud.edge.broker import free_port
from roadgrip.cloud.settings import Settings
from roadgrip.fleet.demo import LocalCloud, settle

ADMIN_SECRET = "fleet-test-admin-secret-0123"
LOG = Path(__file__).resolve().parents[2] / "data" / "real" / "bmw_m8_braking"
runner = CliRunner()


@pytest.fixture
def cloud(tmp_path, monkeypatch):
    monkeypatch.setenv("ROADGRIP_ADMIN_SECRET", ADMIN_SECRET)
    local = LocalCloud(Settings(data_dir=tmp_path, port=free_port(), mqtt="auto", admin_secret=ADMIN_SECRET,
                                rate_limit_samples_per_s=0))  # vehicles at 50x real time
    yield local
    local.stop()


@pytest.mark.parametrize("transport", ["mqtt", "http"])
def test_simulated_vehicles_drive_against_the_cloud(cloud, transport):
    result = runner.invoke(app, ["fleet", "--url", cloud.url, "--vehicles", "3", "--speed", "50", "--duration", "20",
                                 "--transport", transport, "--prefix", f"cli-{transport}"])
    assert result.exit_code == 0, result.output
    settle(cloud.service)
    counts = cloud.service.storage.counts()
    assert counts["telemetry"] == 3 * 200 and counts["estimates"] > 0
    assert sorted(cloud.service.storage.vehicle_ids()) == [f"cli-{transport}-{k:03d}" for k in range(3)]


def test_the_real_log_is_replayed_as_its_own_vehicle(cloud):
    result = runner.invoke(app, ["fleet", "--url", cloud.url, "--replay", str(LOG), "--speed", "50",
                                 "--transport", "http", "--prefix", "m8"])
    assert result.exit_code == 0, result.output
    settle(cloud.service)
    assert cloud.service.storage.counts()["telemetry"] == 96  # 9.6 s at 10 Hz
    assert cloud.service.storage.vehicle_profile("m8-bmw-m8")["mass_kg"] == pytest.approx(2074.4)


def test_without_an_admin_secret_the_fleet_says_so(tmp_path, monkeypatch):
    monkeypatch.delenv("ROADGRIP_ADMIN_SECRET", raising=False)
    result = runner.invoke(app, ["fleet", "--admin-secret-file", str(tmp_path / "nope")])
    assert result.exit_code == 2 and "admin secret" in result.output
