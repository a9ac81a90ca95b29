"""`roadgrip fleet --mode` and `roadgrip demo --mode` against a real `serve` with its own Mosquitto: edge vehicles run
the vehicle end on their simulated samples and send friction observations and heartbeats (CONTRACTS 3.7); a mixed
fleet's raw vehicles send telemetry beside them."""

from __future__ import annotations

import logging

import pytest
from typer.testing import CliRunner

from roadgrip.cli import app
from roadgrip.cloud.localhost import free_port
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.transport.mosquitto import mosquitto_available
from roadgrip.edge.outbox import Outbox
from roadgrip.fleet.demo import LocalCloud, run_demo, settle, wait_observations

ADMIN_SECRET = "fleet-modes-admin-secret-0123"
runner = CliRunner()


@pytest.fixture
def cloud(tmp_path, monkeypatch):
    assert mosquitto_available(), "mosquitto is not installed: run `bash scripts/install_system_deps.sh`"
    monkeypatch.setenv("ROADGRIP_ADMIN_SECRET", ADMIN_SECRET)
    local = LocalCloud(
        Settings(
            data_dir=tmp_path, port=free_port(), mqtt="managed", admin_secret=ADMIN_SECRET, rate_limit_samples_per_s=0
        )
    )
    yield local
    local.stop()


@pytest.mark.slow
def test_a_mixed_fleet_stores_telemetry_of_its_raw_vehicles_and_observations_of_its_edge_ones(cloud, tmp_path):
    args = ["fleet", "--url", cloud.url, "--vehicles", "4", "--speed", "50", "--duration", "60"]
    args += ["--per-slippery-patch", "1", "--prefix", "mix", "--mode", "mixed", "--edge-state-dir", str(tmp_path)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    out = " ".join(result.output.split())
    assert "edge vehicles over MQTT: 2 estimated" in out and "lost 0 (still in the outboxes 0," in out, out
    made = int(out.split("made ")[1].split(" observations")[0].replace(",", ""))
    assert made > 0
    service = cloud.service
    assert wait_observations(service, made) == made
    settle(service)
    raw, edge = {"mix-000", "mix-002"}, {"mix-001", "mix-003"}
    assert set(service.storage.telemetry_extent()) == raw
    observations = service.storage.observations_since(0)
    assert {o["vehicle_id"] for o in observations} <= edge
    assert {h["vehicle_id"] for h in service.storage.latest_heartbeats()} == edge
    for vehicle_id in edge:  # each vehicle's own outbox, on disk, is empty: every message was PUBACKed
        outbox = Outbox(tmp_path / vehicle_id / "outbox.sqlite")
        assert outbox.pending == 0
        outbox.close()
    assert all(service.storage.estimates(vid, limit=10) for vid in raw)


def test_an_unknown_mode_is_refused_in_one_line(cloud):
    result = runner.invoke(app, ["fleet", "--url", cloud.url, "--mode", "sideways"])
    assert result.exit_code != 0
    assert "mode must be one of ['raw', 'edge', 'mixed'], got 'sideways'" in " ".join(result.output.split())


@pytest.mark.slow
def test_the_demo_in_edge_mode_warns_on_its_ice_patch(tmp_path):
    assert mosquitto_available(), "mosquitto is not installed: run `bash scripts/install_system_deps.sh`"
    logger = logging.getLogger("roadgrip")
    kept = logger.handlers[:], logger.propagate, logger.level  # the demo sends the cloud's log to its file
    try:
        report, cloud = run_demo(vehicles=8, speed=20, duration_s=80, data_dir=tmp_path, mqtt="managed", mode="edge")
        cloud.stop()
    finally:
        logger.handlers, logger.propagate = kept[0], kept[1]
        logger.setLevel(kept[2])
    assert report.mode == "edge" and report.transport == "mqtt"
    assert report.telemetry_stored == 0 and report.estimates_stored == 0
    assert report.observations_stored > 0 and report.heartbeats_stored == 8
    on_ice = [w for w in report.warnings if w["nearest_patch"] == "ice-expressway" and w["patch_distance_m"] < 100]
    assert on_ice, report.warnings
