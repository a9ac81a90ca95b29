"""The embedded service as the cloud tests run it, and what they do with it over HTTP and MQTT: one definition each,
imported by the test modules (no test module imports another).

- `running_cloud`: the service (no MQTT unless asked, the map's clock on the data) with a TestClient of its API;
  `settings_for`: the settings of the access tests.
- `register` (a vehicle: its HTTP basic auth), `register_mqtt` (with its MQTT URL), `add_reader`, `post` (NDJSON in
  chunks), `samples_of` (the first samples of a patch drive, tests/cloud/drives.py), `collect` (MQTT messages off a
  queue until a condition or a time-out).
"""

from __future__ import annotations

import contextlib
import json
import queue
import time
from pathlib import Path

from drives import patch_drive
from fastapi.testclient import TestClient

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.fleet.terminal import wire_samples

ADMIN = ("admin", "admin-secret-for-tests-0123456789")
START_MS = int(time.time() * 1000) - 3_600_000  # an hour ago: inside max_future_s, like a recent drive
RECENT_MS = int(time.time() * 1000) - 600_000  # ten minutes ago


@contextlib.contextmanager
def running_cloud(storage_url, tmp_path, **settings):
    settings = Settings(
        **{
            "data_dir": tmp_path,
            "database_url": storage_url,
            "mqtt": "off",
            "admin_secret": ADMIN[1],
            "flush_interval_s": 0.01,
            "reorder_window_s": 0.2,
            "map_clock": "data",
            **settings,
        }
    )
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        yield service, client


def settings_for(storage_url: str, data_dir: Path, mqtt: str = "off") -> Settings:
    return Settings(
        data_dir=data_dir,
        database_url=storage_url,
        mqtt=mqtt,
        admin_secret=ADMIN[1],
        flush_interval_s=0.01,
        reorder_window_s=0.1,
        map_clock="data",
    )


def register(client, vehicle_id: str, profile: str = "paper-suv") -> tuple[str, str]:
    answer = client.post("/v1/vehicles", json={"vehicle_id": vehicle_id, "profile": profile}, auth=ADMIN)
    assert answer.status_code == 201, answer.text
    return vehicle_id, answer.json()["secret"]


def register_mqtt(client, vehicle_id: str) -> tuple[str, str, str]:
    """A vehicle of the default profile: (vehicle_id, secret, the MQTT URL it is told)."""
    answer = client.post("/v1/vehicles", json={"vehicle_id": vehicle_id}, auth=ADMIN).json()
    return vehicle_id, answer["secret"], answer["mqtt_url"]


def add_reader(client, name: str) -> tuple[str, str]:
    answer = client.post("/v1/readers", json={"name": name}, auth=ADMIN)
    assert answer.status_code == 201, answer.text
    return name, answer.json()["secret"]


def ndjson(samples: list[dict]) -> bytes:
    return "\n".join(json.dumps(s) for s in samples).encode()


def post(client, auth, samples, chunk: int = 10):
    answers = []
    for start in range(0, len(samples), chunk):
        answer = client.post(
            "/v1/telemetry",
            content=ndjson(samples[start : start + chunk]),
            auth=auth,
            headers={"content-type": "application/x-ndjson"},
        )
        assert answer.status_code == 200, answer.text
        answers.append(answer.json())
    return answers


def samples_of(vehicle_id: str, n: int, start_ms: int = RECENT_MS) -> list[dict]:
    return wire_samples(patch_drive(0.9, 3), vehicle_id, start_ms)[:n]


def collect(messages, until, timeout_s: float = 20.0) -> list[tuple[str, bytes]]:
    got, deadline = [], time.monotonic() + timeout_s
    while not until(got) and time.monotonic() < deadline:
        try:
            got.append(messages.get(timeout=0.05))
        except queue.Empty:
            continue
    return got
