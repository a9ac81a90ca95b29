"""Production cars through the cloud: with every production-terminal effect on (speed from the wheels, biased and tilted
accelerometers, worn tires, graded road), dry roads raise no warning and an icy patch braked on still does. Runs the
service's whole path (HTTP ingest, per-vehicle estimators, storage, map, warning engine) on SQLite and PostgreSQL."""

from __future__ import annotations

import pytest
from drives import patch_cells, patch_drive
from service_fixtures import ADMIN, START_MS, post, register, running_cloud

from roadgrip.fleet.demo import settle
from roadgrip.fleet.terminal import wire_samples

VEHICLES = (("paper-suv", 1), ("midsize-sedan", 2), ("compact-hatchback", 3))


def _drive(client, patch_mu: float, offset_ms: int, tag: str, brake_s: float = 10.5):
    for k, (profile, seed) in enumerate(VEHICLES):
        vehicle_id = f"{tag}-{profile}"
        auth = register(client, vehicle_id, profile)
        run = patch_drive(patch_mu, seed, profile, brake_s, production=True)
        post(client, auth, wire_samples(run, vehicle_id, START_MS + offset_ms + 40_000 * k), chunk=20)


@pytest.mark.slow
def test_dry_roads_driven_by_production_cars_raise_no_warning(storage_url, tmp_path):
    with running_cloud(storage_url, tmp_path) as (service, client):
        _drive(client, 0.9, 0, "dry")  # cruising, then braking at 0.65 g
        _drive(client, 0.9, 200_000, "late", brake_s=13.0)
        settle(service)
        every = client.get("/v1/warnings", params={"active": False}, auth=ADMIN).json()["warnings"]
        assert every == []
        assert service.storage.counts()["estimates"] > 0


@pytest.mark.slow
def test_an_icy_patch_braked_on_by_production_cars_is_warned_about(storage_url, tmp_path):
    with running_cloud(storage_url, tmp_path) as (service, client):
        _drive(client, 0.15, 0, "ice")
        _drive(client, 0.9, 200_000, "far", brake_s=25.0)  # closes the passes: the vehicles leave
        settle(service)
        active = client.get("/v1/warnings", auth=ADMIN).json()["warnings"]
        assert active, "the icy patch raised no warning"
        assert {w["roadgrip"]["cell"] for w in active} <= patch_cells()
