"""Prometheus metrics (`GET /metrics`, roadgrip/cloud/metrics.py): parsed with prometheus_client's own parser, the
counters moved by telemetry over HTTP and over MQTT (the service's own Mosquitto), rejections counted by reason, the
ingest processes' figures labelled by process, and read by anyone authenticated, as /v1/health."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from broker_fixtures import wait_until
from drives import patch_drive
from prometheus_client.parser import text_string_to_metric_families
from service_fixtures import ADMIN, register_mqtt, running_cloud

from roadgrip.cloud.metrics import BatchHistogram
from roadgrip.cloud.transport.mosquitto import mosquitto_available
from roadgrip.cloud.transport.mqtt import UserClient, telemetry_topic
from roadgrip.fleet.terminal import wire_samples

START_MS = int(time.time() * 1000) - 600_000


def scrape(client, auth=ADMIN) -> dict[tuple[str, tuple], float]:
    """Every sample of /metrics, parsed by prometheus_client: (sample name, sorted labels) -> value."""
    answer = client.get("/metrics", auth=auth)
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-type"].startswith("text/plain; version=0.0.4")
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(answer.text)
        for s in family.samples
    }


def value(values: dict, name: str, **labels) -> float:
    return values.get((name, tuple(sorted(labels.items()))), 0.0)


def metric_names(values: dict) -> set[str]:
    return {name for name, _ in values}


@pytest.fixture
def cloud(tmp_path):
    assert mosquitto_available(), "mosquitto is not installed: run `bash scripts/install_system_deps.sh`"
    with running_cloud(
        f"sqlite:///{tmp_path / 'roadgrip.db'}", tmp_path, mqtt="managed", flush_interval_s=0.02
    ) as running:
        yield running


def test_batch_histogram_counts_a_bound_in_its_bucket_and_negatives_as_zero():
    histogram = BatchHistogram((0.1, 1.0))
    histogram.add(np.array([-0.5, 0.1, 0.5, 1.0, 7.0]))
    histogram.add([])
    assert histogram.state() == {"counts": [2, 2, 1], "sum": pytest.approx(8.6)}
    with pytest.raises(ValueError, match="increasing"):
        BatchHistogram((1.0, 0.5))


def test_metrics_need_a_credential_as_health_does(cloud):
    _service, client = cloud
    assert client.get("/metrics").status_code == 401
    assert client.get("/metrics", auth=("admin", "wrong")).status_code == 401
    vehicle_id, secret, _ = register_mqtt(client, "metrics-reader-car")
    assert client.get("/v1/health", auth=(vehicle_id, secret)).status_code == 200
    values = scrape(client, auth=(vehicle_id, secret))
    assert {
        "roadgrip_samples_received_total",
        "roadgrip_estimate_latency_seconds_bucket",
        "roadgrip_estimator_update_seconds_count",
        "roadgrip_warnings_total",
        "process_resident_memory_bytes",
        "roadgrip_mqtt_connected",
    } <= metric_names(values)
    assert value(values, "roadgrip_mqtt_connected") == 1.0


def test_http_samples_move_the_counters_and_rejections_are_counted_by_reason(cloud):
    _service, client = cloud
    vehicle_id, secret, _ = register_mqtt(client, "metrics-http-car")
    samples = wire_samples(patch_drive(0.9, 0), vehicle_id, START_MS)
    bad = {**samples[0], "timestamp_ms": samples[0]["timestamp_ms"] - 50, "speed_mps": "fast"}
    answer = client.post("/v1/telemetry", json=[*samples, bad], auth=(vehicle_id, secret)).json()
    assert (answer["stored"], len(answer["rejected"])) == (len(samples), 1)
    assert client.post("/v1/telemetry", json=samples[:20], auth=(vehicle_id, secret)).json()["duplicates"] == 20
    assert (
        client.post(
            "/v1/telemetry",
            content=b"{not json",
            headers={"content-type": "application/json"},
            auth=(vehicle_id, secret),
        ).status_code
        == 400
    )
    flooder, flooder_secret, _ = register_mqtt(client, "metrics-flooder")
    flood = wire_samples(patch_drive(0.9, 1), flooder, START_MS) * 2  # 600 samples: over the 500 of the burst
    assert client.post("/v1/telemetry", json=flood, auth=(flooder, flooder_secret)).status_code == 413

    def estimated() -> bool:
        values = scrape(client)
        return value(values, "roadgrip_estimates_total", process="main") == len(samples) and value(
            values, "roadgrip_estimate_latency_seconds_count"
        ) == len(samples)

    wait_until(estimated, timeout_s=20, what="every sample estimated")
    values = scrape(client)
    main = {"process": "main"}
    assert value(values, "roadgrip_samples_received_total", transport="http", **main) == len(samples) + 1 + 20 + 600
    assert value(values, "roadgrip_samples_stored_total", **main) == len(samples)
    assert value(values, "roadgrip_samples_duplicate_total", **main) == 20
    assert value(values, "roadgrip_samples_rejected_total", transport="http", reason="invalid", **main) == 1
    assert value(values, "roadgrip_samples_rejected_total", transport="http", reason="rate_limited", **main) == 600
    assert value(values, "roadgrip_payloads_rejected_total", transport="http", **main) == 1
    assert value(values, "roadgrip_samples_received_total", transport="mqtt", **main) == 0
    assert value(values, "roadgrip_estimator_update_seconds_count", **main) >= len(samples)
    assert value(values, "roadgrip_estimator_update_seconds_bucket", le="+Inf", **main) == value(
        values, "roadgrip_estimator_update_seconds_count", **main
    )
    assert value(values, "roadgrip_estimator_update_seconds_sum", **main) > 0
    # the latencies are those of health's recorder: the samples are 10 minutes old
    assert value(values, "roadgrip_estimate_latency_seconds_bucket", le="300") == 0
    assert value(values, "roadgrip_pipeline_backlog_samples", **main) == 0
    assert value(values, "roadgrip_pipeline_rounds_total", **main) > 0
    assert value(values, "roadgrip_pipeline_storage_failing", **main) == 0


def test_mqtt_samples_move_the_counters_and_rejections_are_counted(cloud):
    _service, client = cloud
    vehicle_id, secret, url = register_mqtt(client, "metrics-mqtt-car")
    samples = wire_samples(patch_drive(0.9, 2), vehicle_id, START_MS)
    bad = {**samples[0], "timestamp_ms": samples[0]["timestamp_ms"] - 50, "speed_mps": "fast"}
    with UserClient(url, vehicle_id, secret).connect() as car:
        for k in range(0, len(samples), 10):
            car.publish(telemetry_topic(vehicle_id), json.dumps(samples[k : k + 10]))
        car.publish(telemetry_topic(vehicle_id), json.dumps([bad]))
        car.publish(telemetry_topic(vehicle_id), b"\xff\xfe not UTF-8")
    main = {"process": "main"}
    wait_until(
        lambda: value(scrape(client), "roadgrip_samples_stored_total", **main) == len(samples),
        timeout_s=20,
        what="every MQTT sample stored",
    )
    values = scrape(client)
    assert value(values, "roadgrip_samples_received_total", transport="mqtt", **main) == len(samples) + 1
    assert value(values, "roadgrip_samples_rejected_total", transport="mqtt", reason="invalid", **main) == 1
    assert value(values, "roadgrip_payloads_rejected_total", transport="mqtt", **main) == 1
    assert value(values, "roadgrip_samples_received_total", transport="http", **main) == 0
    assert value(values, "roadgrip_mqtt_estimate_messages_dropped_total") == 0


def test_ingest_processes_report_their_counters_under_their_own_label(tmp_path):
    with running_cloud(
        f"sqlite:///{tmp_path / 'roadgrip.db'}", tmp_path, ingest_processes=1, flush_interval_s=0.02
    ) as (_service, client):
        vehicle_id, secret, _ = register_mqtt(client, "metrics-shard-car")
        samples = wire_samples(patch_drive(0.9, 3), vehicle_id, START_MS)
        bad = {**samples[0], "timestamp_ms": samples[0]["timestamp_ms"] - 50, "speed_mps": "fast"}
        assert client.post("/v1/telemetry", json=[*samples, bad], auth=(vehicle_id, secret)).json()["stored"] == len(
            samples
        )
        shard = {"process": "ingest-0"}
        wait_until(
            lambda: value(scrape(client), "roadgrip_estimates_total", **shard) == len(samples),
            timeout_s=20,
            what="the ingest process's counters",
        )
        values = scrape(client)
        assert value(values, "roadgrip_samples_received_total", transport="http", **shard) == len(samples) + 1
        assert value(values, "roadgrip_samples_rejected_total", transport="http", reason="invalid", **shard) == 1
        assert value(values, "roadgrip_samples_stored_total", **shard) == len(samples)
        assert value(values, "roadgrip_estimator_update_seconds_count", **shard) >= len(samples)
        assert value(values, "roadgrip_ingest_process_up", **shard) == 1
        assert value(values, "roadgrip_ingest_process_restarts_total", **shard) == 0
        assert value(values, "roadgrip_ingest_process_resident_memory_bytes", **shard) > 10e6
        assert value(values, "roadgrip_estimate_latency_seconds_count") == len(samples)  # the fan-out: main process
        in_main = {name for name, labels in values if ("process", "main") in labels}
        assert in_main == {"roadgrip_payloads_rejected_total"}  # only HTTP bodies refused whole count in it
