"""Nothing an edge agent made is lost across a broker outage and a kill -9 of the agent during it (real Mosquitto,
the agent a real `roadgrip edge` process): the first run makes its observations while the broker is down and is killed
with SIGKILL once they are all in its outbox; the broker comes back; a second run of the same vehicle, with no new
samples, sends every one of them from the outbox. The drive's time is its own (the agent reads no clock)."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import time

import broker_fixtures
import orjson
import pytest
from broker_fixtures import wait_until
from drives import patch_drive

from roadgrip.cloud.transport.mqtt import UserClient
from roadgrip.edge.agent import EdgeAgent
from roadgrip.edge.outbox import Outbox
from roadgrip.edge.run import run_agent
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.terminal import wire_samples
from roadgrip.vehicle.params import PAPER_SUV

managed_broker = broker_fixtures.managed_broker  # the fixture
VEHICLE = "edge-kill"
START_MS = int(time.time() * 1000) - 600_000


def _edge(tmp_path, url: str, secret: str, input_path) -> subprocess.Popen:
    command = [sys.executable, "-m", "roadgrip.cli", "edge", "--vehicle-id", VEHICLE, "--input", str(input_path)]
    command += ["--mqtt", url, "--state-dir", str(tmp_path / "car"), "--drain-s", "120"]
    env = {**os.environ, "ROADGRIP_EDGE_PASSWORD": secret}
    return subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


@pytest.mark.slow
def test_an_agent_killed_during_a_broker_outage_loses_no_observation(tmp_path, managed_broker):
    secret = "edge-kill-secret-0123456789"
    managed_broker.set_user(VEHICLE, secret, "vehicle", VEHICLE)
    samples = wire_samples(patch_drive(0.2, 1), VEHICLE, START_MS)
    drive = tmp_path / "drive.ndjson"
    drive.write_bytes(b"".join(orjson.dumps(s) + b"\n" for s in samples))
    expected = Outbox(tmp_path / "expected.sqlite")  # what the agent makes of the drive, in this process
    run_agent(EdgeAgent(VEHICLE, PAPER_SUV, load_estimator("pmf"), expected), samples)
    made = {orjson.loads(p)["last_ms"] for _, t, p in expected.oldest(1000) if t.endswith("/observations")}
    assert made

    managed_broker.stop()  # the outage
    first = _edge(tmp_path, managed_broker.url, secret, drive)
    outbox_path = tmp_path / "car" / "outbox.sqlite"
    wait_until(lambda: outbox_path.exists(), timeout_s=120, what="the agent's outbox")
    wait_until(lambda: Outbox(outbox_path).pending >= expected.pending, timeout_s=120, what="every message made")
    first.send_signal(signal.SIGKILL)
    assert first.wait(10) == -signal.SIGKILL

    managed_broker.start()
    with UserClient(
        managed_broker.url, managed_broker.service_user, managed_broker.service_password
    ).connect() as cloud:
        cloud.subscribe(f"roadgrip/v1/vehicles/{VEHICLE}/observations")
        second = _edge(tmp_path, managed_broker.url, secret, os.devnull)
        output = second.communicate(timeout=180)[0].decode()
        assert second.returncode == 0, output
        got = set()
        deadline = time.monotonic() + 30
        while got != made and time.monotonic() < deadline:
            try:
                _, payload = cloud.messages.get(timeout=1)
            except queue.Empty:
                continue
            got.add(orjson.loads(payload)["last_ms"])
    assert got == made
    assert Outbox(outbox_path).pending == 0
