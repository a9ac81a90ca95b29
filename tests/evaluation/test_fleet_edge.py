"""The fleet benchmark in edge mode (roadgrip/evaluation/fleet_edge.py): the same drives, each vehicle estimating on
board, its observations reaching the service's map and warning engine through the cloud's parser and intake."""

from __future__ import annotations

import time

import pytest

from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import open_storage
from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario, patch_cells, run_service, simulate_drives

CONFIG = FleetConfig(
    vehicles=3,
    duration_s=240.0,
    patches_per_band=1,
    control_patches=1,
    appear_max_s=20.0,
    life_s=(100.0, 150.0),
    snapshot_every_s=120.0,
)


@pytest.mark.slow
def test_edge_vehicles_reach_the_map_as_observations_and_warn_on_a_patch(tmp_path):
    scenario = make_scenario(3, CONFIG)  # seed 3: the vehicles alone warn (test_fleet_benchmark's tiny run)
    drives = simulate_drives(scenario, int(time.time() - 2 * 3600) * 1000)
    run = run_service(scenario, drives, tmp_path, mode="edge")
    storage = open_storage(Settings(data_dir=tmp_path, admin_secret="fleet-benchmark-admin").storage_url)
    try:
        observations = storage.observations_since(0)
        heartbeats = storage.latest_heartbeats()
        counts = storage.counts()
    finally:
        storage.close()
    assert counts["telemetry"] == 0 and counts["estimates"] == 0  # no sample crossed the air
    assert observations and {h["vehicle_id"] for h in heartbeats} == set(scenario.kinds)
    assert run.rejected == 0 and run.samples_sent == drives.table.num_rows
    # the engine took the rows of the observations' passes, and the map holds measured cells
    assert run.estimates.num_rows >= sum(o["n_excited"] for o in observations)
    assert any(c.status == "measured" for cells in run.snapshots.values() for c in cells)
    slippery = set().union(*(patch_cells(scenario.network, p) for p in scenario.network.patches if p.mu < 0.6))
    assert {w["cell"] for w in run.warnings} & slippery, run.warnings


def test_an_unknown_mode_is_refused(tmp_path):
    scenario = make_scenario(3, CONFIG)
    with pytest.raises(ValueError, match="mode must be raw or edge, got 'cloud'"):
        run_service(scenario, None, tmp_path, mode="cloud")
