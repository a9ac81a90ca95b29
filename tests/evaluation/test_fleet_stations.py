"""The fleet benchmark's roadside stations (roadgrip/evaluation/fleet_benchmark.py, simulate_station_reports): placed
evenly along the network from the network alone (never from the patches), seeded, reports every 60 s in format v1
that read the truth with a biased, noisy friction sensor and misread states, and fail now and then; and the with /
without comparison of a tiny run (roadgrip/evaluation/fleet_report.py), whose headline is the vehicles alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import orjson
import pyarrow.csv as pacsv
import pytest

from roadgrip.cloud.domain.stations import parse_reports
from roadgrip.evaluation.fleet_benchmark import (
    STATION_FRICTION_BIAS,
    STATION_REPORT_S,
    FleetConfig,
    make_scenario,
    place_stations,
    simulate_station_reports,
    state_of,
)
from roadgrip.evaluation.fleet_report import run_fleet_benchmark
from roadgrip.fleet.network import points_at

START_MS = 1_700_000_000_000
CONFIG = FleetConfig(vehicles=2, duration_s=3600.0)


def test_state_of_reads_the_bands_of_the_benchmark():
    rng = np.random.default_rng(0)
    assert [state_of(mu, rng)[0] for mu in (0.05, 0.2, 0.3, 0.5, 0.8, 1.17)] == [
        "ice",
        "ice",
        "snow",
        "wet",
        "wet",
        "dry",
    ]
    assert state_of(0.5, rng)[1] > state_of(0.8, rng)[1]  # a slippery wet patch holds more water


def test_stations_are_seeded_placed_and_report_in_format_v1_with_failures():
    scenario = make_scenario(3, CONFIG)
    stations, reports = simulate_station_reports(scenario, START_MS)
    again, reports_again = simulate_station_reports(scenario, START_MS)
    assert stations == again and reports == reports_again
    assert len(stations) == 6 and [s.friction_sensor for s in stations] == [False, True] * 3
    patches = {p.name: p for p in scenario.network.patches}
    for station in stations:
        on = [p.name for p in patches.values() if p.contains(station.east_m, station.north_m)]
        assert on == ([station.patch] if station.patch else [])  # the truth, looked up after placing
        assert (
            abs(station.friction_bias) <= STATION_FRICTION_BIAS
            and (station.friction_bias != 0) == station.friction_sensor
        )
    for _, report in reports:  # every report passes the service's own validation
        parse_reports(orjson.dumps(report), station_id=report["station_id"], now_ms=START_MS + 3_600_000)
    for station in stations:
        times = np.array([t for t, r in reports if r["station_id"] == station.station_id])
        off = np.diff(times) % STATION_REPORT_S
        assert np.all(np.minimum(off, STATION_REPORT_S - off) < 0.2) and len(times) <= 60
    assert len(reports) < 6 * 60  # lost reports and outages
    at_patch = [s for s in stations if s.patch is not None]
    for station in at_patch:  # while its patch is there the station mostly reads it slippery
        patch = patches[station.patch]
        states = [
            r["surface_state"]
            for t, r in reports
            if r["station_id"] == station.station_id and patch.appear_s <= t < patch.dry_s
        ]
        if len(states) >= 10 and patch.mu <= 0.4:
            assert sum(s in ("ice", "snow") for s in states) >= 0.6 * len(states)


@pytest.mark.slow
def test_a_tiny_run_reports_detection_with_and_without_stations(tmp_path):
    config = FleetConfig(
        vehicles=3,
        duration_s=300.0,
        patches_per_band=1,
        control_patches=1,
        appear_max_s=20.0,
        life_s=(200.0, 250.0),
        snapshot_every_s=150.0,
        stations=3,
    )
    result = run_fleet_benchmark(tmp_path, seed=2, seeds=1, config=config)
    rows = pacsv.read_csv(tmp_path / "stations.csv").to_pylist()
    assert {r["seed"] for r in rows} == {"2", "pooled"}
    assert {r["group"] for r in rows} == {"mu<=0.2", "0.2-0.4", "0.4-0.6", "mu<=0.3", "all"}
    overall = next(r for r in rows if r["seed"] == "pooled" and r["group"] == "all")
    assert overall["warnings_with"] >= overall["warnings_without"]
    metrics = pacsv.read_csv(tmp_path / "metrics.csv").to_pylist()
    headline = next(r for r in metrics if r["seed"] == "pooled" and r["group"] == "all")
    assert headline["warnings"] == overall["warnings_without"]  # the headline is the vehicles alone
    report = (tmp_path / "fleet.md").read_text()
    assert "## Roadside stations: detection with and without them" in report
    assert "gives the service's warnings: yes" in report
    patches = pacsv.read_csv(tmp_path / "patches.csv").to_pylist()
    assert "detected_with_stations" in patches[0] and "cancelled_while_there" in patches[0]
    assert all(p["detected_with_stations"] >= p["detected"] for p in patches)
    assert result["paths"]["stations"] == tmp_path / "stations.csv"


def _distance_to_road(road, station) -> float:
    """Distance from the station to the road (sampled every metre)."""
    points = points_at(road.path, np.arange(0.0, road.path.length_m, 1.0))
    return float(np.hypot(*(points - [station.east_m, station.north_m]).T).min())


def test_stations_are_placed_from_the_network_alone_evenly_along_it():
    """The sites stand on the roads, spread over the network (every road longer than two spacings holds one), and do
    not move when the patches do: two seeds' scenarios differ in their patches, and the same generator draws the same
    sites on either."""
    a, b = make_scenario(3, CONFIG), make_scenario(4, CONFIG)
    assert a.network.patches != b.network.patches
    sites_a = place_stations(a, np.random.default_rng(7))
    sites_b = place_stations(b, np.random.default_rng(7))
    assert [(s.east_m, s.north_m, s.friction_bias) for s in sites_a] == [
        (s.east_m, s.north_m, s.friction_bias) for s in sites_b
    ]
    roads = a.network.roads
    assert all(min(_distance_to_road(r, s) for r in roads) < 1.0 for s in sites_a)
    spacing_m = sum(r.path.length_m for r in roads) / len(sites_a)
    for road in roads:
        if road.path.length_m > 2 * spacing_m:
            assert any(_distance_to_road(road, s) < 1.0 for s in sites_a), road.name
    no_stations = make_scenario(3, dataclasses.replace(CONFIG, stations=0))
    assert place_stations(no_stations, np.random.default_rng(7)) == []
