"""The live dashboard (roadgrip/cloud/api/dashboard.py) in a real browser: the service runs in-process under uvicorn on
127.0.0.1 (SQLite, no MQTT, the map's clock on the data), the patch drives of drives.py go in over HTTP, and headless
Chromium loads /dashboard with a reader's credentials in the URL fragment. The page's data-* attributes, read from
`--dump-dom`, say what it drew. `scripts/dashboard_screenshot.py` uses the same setup for docs/dashboard.png.

Chromium is part of what is tested: without it the test fails (install it with `bash scripts/install_system_deps.sh`).
"""

from __future__ import annotations

import httpx
import pytest
from dashboard_fixtures import (
    CHOSEN,
    READER,
    START_MS,
    attributes_by_id,
    dashboard_settings,
    load_patch_drives,
    post_samples,
    register_vehicle,
    require_chromium,
    run_chromium,
    serving,
    settle,
)
from drives import patch_drive
from fastapi.testclient import TestClient
from service_fixtures import ADMIN

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.api.dashboard import content_security_policy, tile_source
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import load_settings
from roadgrip.fleet.terminal import wire_samples


@pytest.mark.slow
def test_the_page_draws_the_cells_the_warning_the_vehicles_and_the_chosen_vehicles_chart(tmp_path):
    require_chromium()
    with serving(dashboard_settings(tmp_path)) as (service, base_url):
        secret = load_patch_drives(service, base_url)
        reader = (READER, secret)
        with httpx.Client(base_url=base_url, auth=reader) as client:
            features = client.get("/v1/map").json()["features"]
            warnings = client.get("/v1/warnings").json()["warnings"]
            chosen = client.get(f"/v1/vehicles/{CHOSEN}/estimates").json()["estimates"]
        measured = [f for f in features if f["properties"]["status"] == "measured"]
        assert measured and warnings and chosen, "the drives gave no map, warning or estimates to show"

        map_requests = []  # GET /v1/map is the page's only route that reads the map (the backend's current_map)
        current_map = service.current_map
        service.current_map = lambda: map_requests.append(1) or current_map()
        dom = run_chromium(f"{base_url}/dashboard?vehicle={CHOSEN}#{READER}:{secret}", "--dump-dom")
        page = attributes_by_id(dom)
        shown = page["dashboard"]
        assert len(map_requests) >= 3  # it polls: about one round per second of the page's 5 s
        assert shown["data-status"] == "ok", shown
        assert int(shown["data-cells"]) == len(features)
        assert int(shown["data-cells-measured"]) == len(measured) > 0
        assert int(shown["data-warnings"]) == len(warnings) > 0
        assert int(shown["data-vehicles"]) == 3
        assert shown["data-chart-vehicle"] == CHOSEN
        assert int(shown["data-chart-points"]) == len(chosen)  # the 30 s drive lies inside the chart's 5 min
        assert int(shown["data-updated"]) > 0
        assert "hidden" in page["login"]
        assert dom.count("warning-icon") == len(warnings)
        assert 'class="band"' in dom and 'class="line"' in dom
        assert secret not in dom

        dom = run_chromium(f"{base_url}/dashboard#{READER}:not-the-secret", "--dump-dom")
        page = attributes_by_id(dom)
        assert page["dashboard"]["data-status"] == "unauthorized", page["dashboard"]
        assert page["dashboard"]["data-cells"] == "0"
        assert "hidden" not in page["login"]


def test_the_page_is_public_and_the_latest_positions_need_a_reader(tmp_path):
    tiles = "https://{s}.tile.openstreetmap.org/{z}/{x}/{y}.png"
    with (
        CloudService(dashboard_settings(tmp_path, map_tiles_url=tiles)) as service,
        TestClient(create_app(service)) as client,
    ):
        page = client.get("/dashboard")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert 'id="dashboard"' in page.text
        assert "img-src 'self' data: https://*.tile.openstreetmap.org;" in page.headers["content-security-policy"]
        config = client.get("/dashboard/config.json").json()
        assert config["map_tiles_url"] == tiles and "OpenStreetMap" in config["map_tiles_attribution"]
        assert (config["h3_resolution"], config["refresh_interval_s"]) == (10, 1.0)
        assert ADMIN[1] not in client.get("/dashboard/config.json").text
        for path in (
            "dashboard.js",
            "dashboard.css",
            "leaflet/leaflet.js",
            "leaflet/leaflet.css",
            "leaflet/images/layers.png",
            "leaflet/LICENSE",
        ):
            assert client.get(f"/dashboard/static/{path}").status_code == 200, path

        assert client.get("/v1/vehicles/latest").status_code == 401
        vehicle = register_vehicle(client, "car-1", "paper-suv")
        assert client.get("/v1/vehicles/latest", auth=vehicle).status_code == 403
        reader = (READER, client.post("/v1/readers", json={"name": READER}, auth=ADMIN).json()["secret"])
        assert client.get("/v1/vehicles/latest", auth=reader).json() == {"vehicles": []}
        post_samples(client, vehicle, wire_samples(patch_drive(0.9, 3), "car-1", START_MS)[:30])
        settle(service)
        latest = client.get("/v1/vehicles/latest", auth=reader).json()["vehicles"]
        newest = client.get("/v1/vehicles/car-1/estimates", auth=reader).json()["estimates"][-1]
        assert latest == [newest] and newest["latitude_deg"] is not None
        assert client.get("/v1/vehicles/latest", auth=ADMIN).json()["vehicles"] == latest
        assert client.get("/v1/vehicles/car-1", auth=reader).json()["vehicle_id"] == "car-1"  # still its profile
        assert "/v1/vehicles/latest" in client.get("/openapi.json").json()["paths"]


def test_tile_sources_and_the_policy_without_tiles():
    assert tile_source(None) is None and tile_source("/tiles/{z}/{x}/{y}.png") is None
    assert tile_source("https://tile.openstreetmap.org/{z}/{x}/{y}.png") == "https://tile.openstreetmap.org"
    assert tile_source("https://{s}.tile.example.org/{z}/{x}/{y}.png") == "https://*.tile.example.org"
    assert tile_source("https://tiles-{s}.example.org/{z}/{x}/{y}.png") == "https:"
    policy = content_security_policy(None)
    assert "img-src 'self' data:;" in policy and "connect-src 'self'" in policy and "form-action 'none'" in policy
    with pytest.raises(ValueError, match="map_tiles_url"):
        load_settings(map_tiles_url="javascript:alert(1)")
