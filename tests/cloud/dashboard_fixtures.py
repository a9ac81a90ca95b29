"""The service under uvicorn and headless Chromium, as the dashboard tests run them (tests/cloud/api/test_dashboard.py,
tests/cloud/test_station_service.py): the service with its HTTP API in a thread on 127.0.0.1 at a free port
(`serving`, with `dashboard_settings`), Chromium on a URL with a fresh profile (`run_chromium`; `require_chromium`
fails, never skips, without it), the attributes of the page's elements by id (`attributes_by_id`), and the patch
drives sent over HTTP (`load_patch_drives`; scripts/dashboard_screenshot.py uses them for docs/dashboard.png).
"""

from __future__ import annotations

import contextlib
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path

import httpx
import pytest
import uvicorn
from drives import patch_drive
from service_fixtures import ADMIN

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.fleet.terminal import wire_samples

VIRTUAL_TIME_BUDGET_MS = 5000  # page time Chromium lets pass (fetches pause it): about five polling rounds
CHROMIUM_TIMEOUT_S = 90
INSTALL_HINT = "run `bash scripts/install_system_deps.sh`"


def dashboard_settings(data_dir: Path, **overrides) -> Settings:
    return Settings(
        data_dir=data_dir,
        mqtt="off",
        admin_secret=ADMIN[1],
        flush_interval_s=0.01,
        reorder_window_s=0.2,
        map_clock="data",
        **overrides,
    )


@contextlib.contextmanager
def serving(settings: Settings) -> Iterator[tuple[CloudService, str]]:
    """The service with its HTTP API under uvicorn in a thread, on 127.0.0.1 at a free port; (service, base URL)."""
    with CloudService(settings) as service, socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        server = uvicorn.Server(uvicorn.Config(create_app(service), log_level="warning", lifespan="off"))
        thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
        thread.start()
        deadline = time.monotonic() + 30
        while not server.started:
            if not thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.02)
        try:
            yield service, f"http://127.0.0.1:{sock.getsockname()[1]}"
        finally:
            server.should_exit = True
            thread.join(timeout=30)


def chromium_binary() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        raise RuntimeError(f"chromium is not installed: {INSTALL_HINT}")
    return found


def run_chromium(url: str, *options: str, budget_ms: int = VIRTUAL_TIME_BUDGET_MS) -> str:
    """Headless Chromium on `url` with a fresh profile and no network but this server's; its stdout."""
    with tempfile.TemporaryDirectory(prefix="roadgrip-chromium-", ignore_cleanup_errors=True) as profile:
        command = [
            chromium_binary(),
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--no-first-run",
            f"--user-data-dir={profile}",
            f"--virtual-time-budget={budget_ms}",
            *options,
            url,
        ]
        done = subprocess.run(command, check=False, capture_output=True, text=True, timeout=CHROMIUM_TIMEOUT_S)
    if done.returncode != 0:
        raise RuntimeError(f"chromium exited with {done.returncode}: {done.stderr[-2000:]}")
    return done.stdout


class _Attributes(HTMLParser):
    """The attributes of every element with an id, by id."""

    def __init__(self):
        super().__init__()
        self.by_id: dict[str, dict[str, str | None]] = {}

    def handle_starttag(self, tag, attrs):
        attributes = dict(attrs)
        if "id" in attributes:
            self.by_id[attributes["id"]] = attributes


def attributes_by_id(dom: str) -> dict[str, dict[str, str | None]]:
    parser = _Attributes()
    parser.feed(dom)
    return parser.by_id


def require_chromium() -> None:
    """Fail (never skip) without Chromium: the page in a real browser is what these tests are for."""
    if shutil.which("chromium") is None and shutil.which("chromium-browser") is None:
        pytest.fail(f"chromium is not installed: {INSTALL_HINT}", pytrace=False)


READER = "operator"
START_MS = int(time.time() * 1000) - 3_600_000  # an hour ago: inside max_future_s, like a recent drive
CHOSEN = "suv-w"


def post_samples(client: httpx.Client, auth: tuple[str, str], samples: list[dict], chunk: int = 50) -> None:
    for start in range(0, len(samples), chunk):
        answer = client.post("/v1/telemetry", json=samples[start : start + chunk], auth=auth)
        answer.raise_for_status()


def register_vehicle(client: httpx.Client, vehicle_id: str, profile: str) -> tuple[str, str]:
    answer = client.post("/v1/vehicles", json={"vehicle_id": vehicle_id, "profile": profile}, auth=ADMIN)
    answer.raise_for_status()
    return vehicle_id, answer.json()["secret"]


def settle(service: CloudService) -> None:
    """Let the pipeline release what its reorder window still holds."""
    time.sleep(service.settings.reorder_window_s + 0.1)
    deadline = time.monotonic() + 10
    while service.ingest.backlog and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(3 * service.settings.flush_interval_s)


def load_patch_drives(service: CloudService, base_url: str) -> str:
    """The drives of test_api's patch test: an SUV and a sedan brake on the slippery patch (mu 0.2), which raises a
    warning; a hatchback on the dry road two minutes later closes their passes. Then a reader; its secret."""
    with httpx.Client(base_url=base_url, timeout=60) as client:
        for vehicle_id, profile, seed in ((CHOSEN, "paper-suv", 1), ("sedan-w", "midsize-sedan", 2)):
            auth = register_vehicle(client, vehicle_id, profile)
            post_samples(client, auth, wire_samples(patch_drive(0.2, seed, profile), vehicle_id, START_MS))
        auth = register_vehicle(client, "hatch-d", "compact-hatchback")
        post_samples(
            client, auth, wire_samples(patch_drive(0.9, 4, "compact-hatchback"), "hatch-d", START_MS + 120_000)
        )
        settle(service)
        answer = client.post("/v1/readers", json={"name": READER}, auth=ADMIN)
        answer.raise_for_status()
        return answer.json()["secret"]
