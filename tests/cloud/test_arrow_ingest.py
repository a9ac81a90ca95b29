"""An Arrow IPC stream posted to /v1/telemetry (CONTRACTS 3.1) is stored as sent, on SQLite (INSERT) and PostgreSQL
(COPY); a stream that cannot be used is answered 400 with one line naming the problem, nothing stored."""

from __future__ import annotations

import pytest
from drives import patch_drive
from service_fixtures import START_MS, register, running_cloud

from roadgrip.cloud.ingest.wire import arrow_payload
from roadgrip.data.schema import TELEMETRY_COLUMNS
from roadgrip.fleet.demo import settle
from roadgrip.fleet.terminal import wire_samples

ARROW = {"content-type": "application/vnd.apache.arrow.stream"}


@pytest.fixture
def cloud(storage_url, tmp_path):
    with running_cloud(storage_url, tmp_path) as running:
        yield running


def test_what_a_vehicle_sends_as_arrow_is_what_is_stored(cloud):
    service, client = cloud
    auth = register(client, "arrow-1")
    samples = wire_samples(patch_drive(0.2, 1), "arrow-1", START_MS)
    for start in range(0, len(samples), 50):
        answer = client.post(
            "/v1/telemetry", content=arrow_payload(samples[start : start + 50]), auth=auth, headers=ARROW
        )
        assert answer.status_code == 200, answer.text
        assert answer.json()["rejected"] == []
    settle(service)
    assert service.storage.telemetry("arrow-1") == [{c: s.get(c) for c in TELEMETRY_COLUMNS} for s in samples]
    assert len(service.storage.estimates("arrow-1")) > 0


def test_a_broken_arrow_body_is_400_with_one_line_and_nothing_stored(cloud):
    service, client = cloud
    auth = register(client, "arrow-2")
    body = arrow_payload(wire_samples(patch_drive(0.2, 1), "arrow-2", START_MS)[:10])
    answer = client.post("/v1/telemetry", content=body[: len(body) // 2], auth=auth, headers=ARROW)
    assert answer.status_code == 400
    detail = answer.json()["detail"]
    assert "not an Arrow IPC stream" in str(detail) and "\n" not in str(detail)
    assert service.storage.counts()["telemetry"] == 0
