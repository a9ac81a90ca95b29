"""Helpers for the fault-injection tests (test_faults.py): simulated terminals that count what they sent and what was
acknowledged, the service as a real process, a PostgreSQL cluster of its own that a test may stop and start, and the
rows actually in the database.

- `warm_estimator()`: numba's kernels compiled into its cache before anything is timed.
- `drive_samples(vehicle_id, runs)`: `runs` simulated 30 s runs (tests/cloud/drives.py) one after the other, as wire
  samples of one vehicle (10 Hz), starting 10 minutes ago (inside the service's max_future_s however long it streams).
- `MqttTerminal`: a vehicle publishing over MQTT at QoS 1 through `UserClient.publish_nowait`, in a thread of its own,
  `per_message` samples a message every `period_s`. paho keeps every QoS 1 message until its PUBACK and sends it again
  after its own reconnect (also what it was handed while disconnected), so nothing is dropped on the vehicle's side.
  *Acknowledged* = the broker answered PUBACK with a success code: the broker has it, not yet the service.
- `HttpTerminal`: a vehicle posting `per_request` samples every `period_s` to POST /v1/telemetry, in a thread; a
  request that fails to connect, is cut or answers 503 is sent again (every `retry_s`) until it gets 200, a 429 after
  its Retry-After. *Acknowledged* = answered 200 (the service stored it).
- `ServeProcess`: `python -m roadgrip serve` with ROADGRIP_* environment variables, started, killed (SIGKILL) and
  started again on the same data directory and port.
- `serving_http(service)`: the HTTP API of an in-process CloudService under uvicorn in a thread (real sockets, so a
  503 is a real answer), as tests/cloud/api/test_dashboard.py does.
- `PostgresCluster`: initdb into a temporary directory, start / stop (`pg_ctl stop -m fast`) / start again on the same
  port; run as the `postgres` user when the tests run as root (initdb refuses root), as tests/cloud/conftest.py does.
- `stored_keys(url, table)`: the (vehicle_id, timestamp_ms) of every row of `table`, read straight from the database.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import sqlalchemy as sa
import uvicorn
from drives import patch_drive

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.localhost import free_port
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.storage.database import normalise_url
from roadgrip.cloud.storage.local_postgres import LocalPostgres
from roadgrip.cloud.transport.mqtt import UserClient, telemetry_topic
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.terminal import wire_samples
from roadgrip.vehicle.params import PAPER_SUV

RUN_MS = 30_000  # one patch_drive run: 300 samples, 0 to 29,900 ms
START_MS = int(time.time() * 1000) - 600_000

Key = tuple[str, int]


def drive_samples(vehicle_id: str, runs: int, start_ms: int = START_MS) -> list[dict]:
    """`runs` simulated runs of one vehicle back to back (a dry one, then a slippery patch, ...), 10 Hz."""
    samples = []
    for k in range(runs):
        samples += wire_samples(patch_drive(0.2 if k % 2 else 0.9, k), vehicle_id, start_ms + k * RUN_MS)
    return samples


def warm_estimator() -> float:
    """Run one EKF update here, so that numba compiles its kernels into its on-disk cache (seconds: about 15 on a cold
    cache) before a test times anything; the service, in this process or another, then loads them from the cache.
    The seconds it took."""
    started = time.perf_counter()
    estimator = load_estimator("ekf")
    estimator.update(estimator.start(PAPER_SUV), drive_samples("warm-up", 1)[0])
    return time.perf_counter() - started


def keys(samples: list[dict]) -> set[Key]:
    return {(s["vehicle_id"], s["timestamp_ms"]) for s in samples}


def wait_for(predicate, timeout_s: float, what: str, poll_s: float = 0.05) -> float:
    """Poll until `predicate()` is true; the seconds it took. TimeoutError naming `what` after `timeout_s`."""
    started = time.monotonic()
    while not predicate():
        if time.monotonic() - started > timeout_s:
            raise TimeoutError(f"{what}: not within {timeout_s} s")
        time.sleep(poll_s)
    return time.monotonic() - started


class _Paced(threading.Thread):
    """Sends `samples` in chunks of `per_chunk`, chunk k not before start + k * period_s (a chunk that had to wait
    for a retry delays the next ones, which then follow at once: the terminal's buffer drains)."""

    def __init__(self, name: str, samples: list[dict], per_chunk: int, period_s: float):
        super().__init__(name=name, daemon=True)
        self.chunks = [samples[k : k + per_chunk] for k in range(0, len(samples), per_chunk)]
        self.period_s = period_s
        self.error: BaseException | None = None
        self.started_at: float | None = None

    def run(self) -> None:
        self.started_at = time.monotonic()
        try:
            for k, chunk in enumerate(self.chunks):
                time.sleep(max(0.0, self.started_at + k * self.period_s - time.monotonic()))
                self.send(chunk)
        except Exception as exc:  # noqa: BLE001 (kept and raised again by finish(), in the test's thread)
            self.error = exc

    def send(self, chunk: list[dict]) -> None:
        raise NotImplementedError

    def finish(self, timeout_s: float) -> None:
        self.join(timeout_s)
        if self.is_alive():
            raise TimeoutError(f"{self.name} still sending after {timeout_s} s")
        if self.error is not None:
            raise self.error


class MqttTerminal(_Paced):
    """A vehicle over MQTT (module docstring). `sent`, `acknowledged()`, `refused`; `connection_log` holds
    (monotonic time, connected) at every change paho reported (its connect and disconnect callbacks: the sending loop
    may be done before a reconnect it would have seen)."""

    def __init__(self, url: str, vehicle_id: str, secret: str, samples: list[dict], per_message: int, period_s: float):
        super().__init__(f"mqtt-{vehicle_id}", samples, per_message, period_s)
        self.client = UserClient(url, vehicle_id, secret).connect()
        self.topic = telemetry_topic(vehicle_id)
        self.messages: list[tuple[float, int, list[dict]]] = []  # (monotonic time, message id, samples)
        self.connection_log: list[tuple[float, bool]] = [(time.monotonic(), True)]
        # PUBACKs by message id, from paho's callback (chained to UserClient's): `MQTTMessageInfo.is_published()`
        # raises for a message handed over while disconnected (rc NO_CONN), although paho sends it after the reconnect
        self.pubacks: dict[int, bool] = {}  # message id -> success reason code
        userclient_on_publish = self.client.paho.on_publish

        def on_publish(client, userdata, mid, reason_code, properties):
            self.pubacks[mid] = not reason_code.is_failure
            userclient_on_publish(client, userdata, mid, reason_code, properties)

        self.client.paho.on_publish = on_publish
        self.client.paho.on_connect = lambda client, userdata, flags, reason_code, properties: self._log(
            not reason_code.is_failure
        )
        self.client.paho.on_disconnect = lambda client, userdata, flags, reason_code, properties: self._log(False)

    def _log(self, connected: bool) -> None:
        if connected != self.connection_log[-1][1]:
            self.connection_log.append((time.monotonic(), connected))

    def send(self, chunk: list[dict]) -> None:
        self.messages.append((time.monotonic(), self.client.publish_nowait(self.topic, json.dumps(chunk)).mid, chunk))

    @property
    def sent(self) -> list[dict]:
        return [s for _, _, chunk in self.messages for s in chunk]

    def acknowledged(self) -> list[dict]:
        """Samples of the messages the broker acknowledged (PUBACK; refusals are counted in `refused`)."""
        return [s for _, mid, chunk in self.messages if self.pubacks.get(mid) for s in chunk]

    @property
    def refused(self) -> int:
        return self.client.refused

    def all_acknowledged(self) -> bool:
        return all(mid in self.pubacks for _, mid, _ in self.messages)

    def sent_between(self, since_s: float, until_s: float) -> int:
        """Samples handed to paho between two monotonic times."""
        return sum(len(chunk) for t, _, chunk in self.messages if since_s <= t <= until_s)

    def close(self) -> None:
        self.client.close()


class HttpTerminal(_Paced):
    """A vehicle over HTTP (module docstring). `sent`, `acknowledged`, `duplicates`, and every answer in `answers`:
    (monotonic time, status code or the transport error's name)."""

    def __init__(
        self,
        base_url: str,
        vehicle_id: str,
        secret: str,
        samples: list[dict],
        per_request: int,
        period_s: float,
        retry_s: float = 0.25,
    ):
        super().__init__(f"http-{vehicle_id}", samples, per_request, period_s)
        self.http = httpx.Client(base_url=base_url, auth=(vehicle_id, secret), timeout=10.0)
        self.retry_s = retry_s
        self.sent: list[dict] = []
        self.acknowledged: list[dict] = []
        self.duplicates = 0  # samples a 200 called already stored (a retry of a request whose answer was lost or 503)
        self.answers: list[tuple[float, int | str]] = []

    def send(self, chunk: list[dict]) -> None:
        self.sent += chunk
        body = "\n".join(json.dumps(s) for s in chunk)
        while True:
            try:
                answer = self.http.post("/v1/telemetry", content=body, headers={"content-type": "application/x-ndjson"})
            except httpx.TransportError as exc:  # refused, cut (the service killed), timed out
                self.answers.append((time.monotonic(), type(exc).__name__))
                time.sleep(self.retry_s)
                continue
            self.answers.append((time.monotonic(), answer.status_code))
            if answer.status_code == 200:
                self.acknowledged += chunk
                self.duplicates += answer.json()["duplicates"]
                return
            if answer.status_code == 503:
                time.sleep(self.retry_s)
            elif answer.status_code == 429:
                time.sleep(float(answer.headers.get("retry-after", 1)))
            else:
                raise AssertionError(f"{self.name}: unexpected answer {answer.status_code}: {answer.text[:300]}")

    def count(self, answer: int | str, since_s: float = -math.inf, until_s: float = math.inf) -> int:
        return sum(1 for t, a in self.answers if a == answer and since_s <= t <= until_s)

    def close(self) -> None:
        self.http.close()


class ServeProcess:
    """`python -m roadgrip serve` in its own process on 127.0.0.1:`port`, configured by the ROADGRIP_* variables in `env`
    alone (those of the test's environment are left out); its output goes to `workdir`/serve.log (appended at every
    start)."""

    def __init__(self, workdir: Path, env: dict[str, str], admin: tuple[str, str]):
        self.workdir = workdir
        self.port = free_port()
        self.admin = admin
        inherited = {k: v for k, v in os.environ.items() if not k.startswith("ROADGRIP_")}  # only the test's settings
        self.env = {
            **inherited,
            **env,
            "ROADGRIP_DATA_DIR": str(workdir),
            "ROADGRIP_PORT": str(self.port),
            "ROADGRIP_ADMIN_SECRET": admin[1],
        }
        self.process: subprocess.Popen | None = None
        self.http = httpx.Client(base_url=self.url, auth=admin, timeout=10.0)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 60) -> float:
        """Start and return once GET /v1/health answers 200; the seconds that took."""
        with open(self.workdir / "serve.log", "a") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "roadgrip", "serve"],
                env=self.env,
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
            )

        def up() -> bool:
            if self.process.poll() is not None:
                raise RuntimeError(f"roadgrip serve exited ({self.process.returncode}):\n{self.log_tail()}")
            try:
                return self.http.get("/v1/health").status_code == 200
            except httpx.TransportError:
                return False

        return wait_for(up, timeout_s, "roadgrip serve answering /v1/health")

    def health(self) -> dict:
        return self.http.get("/v1/health").json()

    def kill(self) -> None:
        """SIGKILL: no cleanup of any kind in the service."""
        self.process.send_signal(signal.SIGKILL)
        self.process.wait()

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.http.close()

    def log_tail(self, chars: int = 4000) -> str:
        path = self.workdir / "serve.log"
        return path.read_text(errors="replace")[-chars:] if path.exists() else ""


@contextlib.contextmanager
def serving_http(service: CloudService):
    """The service's HTTP API under uvicorn in a thread on 127.0.0.1 at a free port; yields its base URL."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        server = uvicorn.Server(uvicorn.Config(create_app(service), log_level="warning", lifespan="off"))
        thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
        thread.start()
        wait_for(lambda: server.started or not thread.is_alive(), 30, "uvicorn starting")
        if not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        try:
            yield f"http://127.0.0.1:{sock.getsockname()[1]}"
        finally:
            server.should_exit = True
            thread.join(timeout=30)


class PostgresCluster(LocalPostgres):
    """A PostgreSQL 15 server of its own (roadgrip/cloud/storage/local_postgres.py), started; `url` is its database
    `roadgrip_faults`. `stop()` and `start()` stop it and start it again on the same port; `close()` deletes it."""

    def __init__(self):
        super().__init__()
        self.start()
        self.url = self.create_database("roadgrip_faults")


def stored_keys(url: str, table: str) -> list[Key]:
    """(vehicle_id, timestamp_ms) of every row of `table` ("telemetry" or "estimates"), with repeats if there were
    any, read with a connection of its own."""
    engine = sa.create_engine(normalise_url(url))
    try:
        with engine.connect() as conn:
            return [(v, int(t)) for v, t in conn.execute(sa.text(f"SELECT vehicle_id, timestamp_ms FROM {table}"))]
    finally:
        engine.dispose()
