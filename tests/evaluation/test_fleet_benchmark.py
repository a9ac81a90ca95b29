"""The fleet benchmark: its metrics on hand-made cases, patches that come and go under the wheels, and a tiny run
through the cloud service."""

from __future__ import annotations

import dataclasses
import math

import h3
import numpy as np
import pyarrow.csv as pacsv
import pymap3d
import pytest

from roadgrip.data.schema import CHANNEL_NAMES, TELEMETRY_COLUMNS
from roadgrip.evaluation import fleet_report
from roadgrip.evaluation.fleet_benchmark import (
    Drives,
    FleetConfig,
    find_passes,
    make_scenario,
    observable,
    patch_cells,
    simulate_drives,
)
from roadgrip.evaluation.fleet_metrics import (
    Warning,
    band_of,
    classify,
    patch_outcome,
    score_cell,
    summarize_run,
    warning_from_row,
)
from roadgrip.evaluation.fleet_report import run_fleet_benchmark
from roadgrip.fleet.fleet import _speed_profile, planned_arrival
from roadgrip.fleet.network import SURFACE_MU, Network, Patch, Road
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate

ROAD = Road("straight", "urban", np.array([[0.0, 0.0], [600.0, 0.0]]))
ICE = Patch("ice", "ice", 300.0, 0.0, 30.0, appear_s=20.0, dry_s=60.0)
NETWORK = Network((ROAD,), (ICE,))


def test_bands():
    assert [band_of(m) for m in (0.05, 0.2, 0.3, 0.5, 0.6, 1.17)] == [
        "mu<=0.2",
        "mu<=0.2",
        "0.2-0.4",
        "0.4-0.6",
        "dry",
        "dry",
    ]


def test_a_patch_warned_at_its_second_pass_took_two_passes():
    passes = [("a", 25.0, 28.0), ("b", 40.0, 43.0), ("c", 50.0, 53.0)]
    warned = Warning("cell", 43.0, 70.0, "recovered")
    row = patch_outcome(ICE, passes, [warned], [], run_end_s=600.0)
    assert row["detected"] and row["passes_to_first"] == 2
    assert row["time_to_first_s"] == pytest.approx(23.0)
    assert row["eligible"]  # three vehicles drove it while it was there


def test_a_warning_outliving_its_patch_by_five_minutes():
    warned = Warning("cell", 30.0, ICE.dry_s + 300.0, "expired")
    row = patch_outcome(ICE, [("a", 25.0, 28.0)], [warned], [], run_end_s=3600.0)
    assert row["linger_s"] == pytest.approx(300.0) and not row["censored"]
    still = patch_outcome(ICE, [("a", 25.0, 28.0)], [Warning("cell", 30.0, None)], [], run_end_s=500.0)
    assert still["linger_s"] == pytest.approx(440.0) and still["censored"]
    summary = summarize_run([row], [], [], 1.0, 0, 0)[-1]
    assert summary["lingering"] == 1 and summary["linger_over_10min"] == 0 and summary["linger_max_s"] == 300.0


def test_linger_counts_from_the_last_ice_a_vehicle_drove_on():
    """ICE dries at 60 s, but a trip planned before drives it until 75 s (the simulator's mu is the patch as the trip
    planned to reach it): its low reading is true ice, and the warning's linger counts from 75 s, not 60 s."""
    warned = Warning("cell", 30.0, 75.0 + 600.0, "expired")
    row = patch_outcome(ICE, [("a", 25.0, 28.0), ("late", 70.0, 75.0)], [warned], [], run_end_s=3600.0)
    assert row["last_low_s"] == pytest.approx(75.0) and row["linger_s"] == pytest.approx(600.0)
    on_time = patch_outcome(ICE, [("a", 25.0, 28.0)], [warned], [], run_end_s=3600.0)
    assert on_time["last_low_s"] == pytest.approx(ICE.dry_s) and on_time["linger_s"] == pytest.approx(615.0)


def test_a_warning_that_expires_its_validity_after_the_last_ice_lingers_exactly_10_min():
    """Times are the service clock's milliseconds in seconds, and (988.686 + 600) - 988.686 is 600.0000000000001 in
    floats: such a warning counted as lingering over 10 min (report seed 1 at a02eba8: 600.0000000000002)."""
    patch = Patch("ice", "ice", 300.0, 0.0, 30.0, appear_s=300.0, dry_s=988.686)
    warned = Warning("cell", 400.0, patch.dry_s + 600.0, "expired")
    row = patch_outcome(patch, [("a", 390.0, 395.0)], [warned], [], run_end_s=3600.0)
    assert row["linger_s"] == 600.0
    assert summarize_run([row], [], [], 1.0, 0, 0)[-1]["linger_over_10min"] == 0


def test_a_warning_cancelled_while_its_patch_persists_is_counted():
    """ICE is there from 20 s to 60 s: a dry pass that cancels its warning at 40 s read grip where the ice still was
    (or grip elsewhere in the cell); an expiry, or a cancellation after it dried, is not counted."""
    early = Warning("cell", 25.0, 40.0, "recovered")
    expired = Warning("cell", 26.0, 45.0, "expired")
    after = Warning("cell", 30.0, 70.0, "recovered")
    row = patch_outcome(ICE, [("a", 25.0, 28.0)], [early, expired, after], [], run_end_s=600.0)
    assert row["cancelled_while_there"] == 1 and row["linger_s"] == pytest.approx(10.0)
    beside = patch_outcome(ICE, [("a", 25.0, 28.0)], [], [early], run_end_s=600.0)
    assert beside["cancelled_while_there"] == 0  # a neighbour cell's warning may end while the patch is there
    overall = summarize_run([row, beside], [], [], 1.0, 0, 0)[-1]
    assert overall["cancelled_while_there"] == 1


def test_a_warning_on_dry_road_is_false_and_counted_per_100_km():
    cells = {ICE.name: patch_cells(NETWORK, ICE)}
    assert cells[ICE.name]
    on = Warning(next(iter(cells[ICE.name])), 30.0, None)
    far = h3.latlng_to_cell(*h3.cell_to_latlng(next(iter(cells[ICE.name]))), 10)
    far = next(c for c in h3.grid_ring(far, 4))  # four cells away: dry road
    assert classify(on, [ICE], cells, 600.0) == ("on", ICE)
    assert classify(Warning(on.cell, 10.0, None), [ICE], cells, 600.0)[0] == "false"  # before the ice appeared
    assert classify(Warning(on.cell, 100.0, None), [ICE], cells, 600.0) == ("beside", ICE)  # just after it dried
    assert classify(Warning(far, 30.0, None), [ICE], cells, 600.0) == ("false", None)
    overall = summarize_run([], [], ["on", "false"], dry_km=50.0, driven_cells=10, cells_with_evidence=4)[-1]
    assert overall["false_warnings"] == 1 and overall["false_per_100km"] == pytest.approx(2.0)
    assert overall["evidence_share"] == pytest.approx(0.4)


def test_map_cell_scores_against_the_range_of_true_mu():
    mixed = score_cell(0.1, 0.05, 0.2, (0.05, 1.17))  # a cell with ice and dry road: 0.1 lies in the range
    assert (mixed["band"], mixed["error"], mixed["covered"]) == ("mu<=0.2", 0.0, True)
    slippery_dry = {"status": "measured", **score_cell(0.3, 0.2, 0.5, (1.17, 1.17))}
    bounded = {"status": "bounded", **score_cell(0.8, 0.4, 1.17, (1.17, 1.17))}
    overall = summarize_run([], [{"status": "measured", **mixed}, slippery_dry, bounded], [], 1.0, 4, 3, 2)[-1]
    assert overall["dry_cells_read_slippery"] == 1.0  # of the measured dry cells
    assert (overall["map_cells"], overall["bounded_cells"], overall["bounded_coverage"]) == (2, 1, 1.0)
    assert (overall["evidence_share"], overall["measured_share"]) == (0.75, 0.5)
    assert mixed["error_low"] == pytest.approx(0.05) and mixed["covered_low"]
    dry = score_cell(0.4, 0.3, 0.6, (1.17, 1.17))
    assert dry["band"] == "dry" and dry["error"] == pytest.approx(0.77) and not dry["covered"]


def test_warning_from_a_storage_row():
    row = {
        "cell": "c",
        "status": "cancelled",
        "detection_ms": 61_000,
        "message": {"event": {"evidence_ms": 121_000, "reason": "recovered"}},
    }
    assert warning_from_row(row, 1_000) == Warning("c", 60.0, 120.0, "recovered")
    row = {**row, "status": "active"}
    assert warning_from_row(row, 1_000).end_s is None


def _drive(depart_s: float) -> tuple[Scenario, np.ndarray]:
    speed, duration = _speed_profile(15.0, [], ROAD.path.length_m, 60.0)
    mu = NETWORK.mu_profile(ROAD, planned_arrival(speed, depart_s))
    return Scenario(run_id=f"d{depart_s:g}", path=ROAD.path, mu=mu, speed=speed, duration_s=math.floor(duration)), mu


def test_a_patch_is_under_the_wheels_only_while_it_is_there():
    # the ice is there from 20 s to 60 s; at 15 m/s the car reaches it (station 270 m) 18 s after departing
    before, _ = _drive(0.0)  # reaches it at 18 s: not there yet
    during, _ = _drive(10.0)  # at 28 s
    after, _ = _drive(50.0)  # at 68 s: dried
    assert before.mu.at(300.0)[0] == pytest.approx(SURFACE_MU["dry"])
    assert during.mu.at(300.0)[0] == pytest.approx(ICE.mu)
    assert after.mu.at(300.0)[0] == pytest.approx(SURFACE_MU["dry"])
    assert NETWORK.mu_profile(ROAD).at(300.0)[0] == pytest.approx(ICE.mu)  # no clock: every patch counts
    table = simulate([before, during, after])
    for scenario, depart, icy in ((before, 0.0, False), (during, 10.0, True), (after, 50.0, False)):
        run = table.filter(table["run_id"].to_numpy(zero_copy_only=False) == scenario.run_id)
        x, mu, t = run["x_m"].to_numpy(), run["mu"].to_numpy(), run["t_s"].to_numpy()
        on = ICE.contains(x, run["y_m"].to_numpy())
        assert on.any()
        assert np.allclose(mu[on], ICE.mu if icy else SURFACE_MU["dry"])
        away = np.hypot(x - ICE.east_m, run["y_m"].to_numpy() - ICE.north_m) > ICE.radius_m + 3.0  # the 2 m mu steps
        assert np.allclose(mu[away], SURFACE_MU["dry"])
        passes = find_passes(t + depart, np.array(["v"] * len(t), dtype=object), x, run["y_m"].to_numpy(), mu, ICE)
        assert len(passes) == (1 if icy else 0)
        if icy:
            assert ICE.appear_s <= passes[0][1] < ICE.dry_s


def test_a_pass_is_observable_with_enough_excited_samples_on_the_patch():
    # two passes over the ice, 0.1 s a sample: the first with 3 excited samples on it, the second with 1 on it and
    # 2 more beyond its edge, which do not count
    east = np.array([290.0, 295.0, 300.0, 305.0, 290.0, 300.0, 340.0, 345.0])
    t_s = np.array([30.0, 30.1, 30.2, 30.3, 40.0, 40.1, 40.2, 40.3])
    excited = np.array([True, True, True, False, False, True, True, True])
    n = len(t_s)
    drives = Drives(
        None,
        t_s,
        np.array(["v"] * n, dtype=object),
        east,
        np.zeros(n),
        np.full(n, ICE.mu),
        np.ones(n),
        None,
        0,
        excited,
    )
    passes = find_passes(drives.t_s, drives.vehicle, drives.east_m, drives.north_m, drives.mu, ICE)
    assert len(passes) == 2
    assert observable(drives, ICE, passes) == 1  # the benchmark's: OBSERVABLE_SAMPLES (3)
    assert observable(drives, ICE, passes, min_samples=1) == 2
    assert observable(drives, ICE, passes[1:], min_samples=2) == 0


def test_patch_times_are_checked():
    with pytest.raises(ValueError, match="appear_s"):
        Patch("p", "ice", 0.0, 0.0, 10.0, appear_s=60.0, dry_s=30.0)
    with pytest.raises(ValueError, match="mu_value"):
        Patch("p", "wet", 0.0, 0.0, 10.0, mu_value=1.5)


def test_the_scenario_is_seeded_and_its_patches_fall_in_their_bands():
    config = FleetConfig(vehicles=3, duration_s=300.0, appear_max_s=60.0, life_s=(100.0, 200.0))
    a, b = make_scenario(5, config), make_scenario(5, config)
    assert [(t.vehicle_id, t.depart_s, t.scenario.road) for t in a.trips] == [
        (t.vehicle_id, t.depart_s, t.scenario.road) for t in b.trips
    ]
    mus = sorted(p.mu for p in a.network.patches)
    assert [band_of(m) for m in mus] == ["mu<=0.2"] * 3 + ["0.2-0.4"] * 3 + ["0.4-0.6"] * 3 + ["dry"] * 2
    assert all(0.0 <= p.appear_s < p.dry_s <= config.duration_s for p in a.network.patches)
    assert all(t.scenario.effects.speed_from_wheels for t in a.trips)  # production-terminal realism on
    assert not a.with_channels and not any(t.scenario.effects.any_channel for t in a.trips)


def test_a_share_of_the_fleet_sends_the_optional_channels_and_nothing_else_changes():
    """Issue 26, item 2: half the vehicles (every second one, so every kind) send GNSS speed, the forces and the
    steering torques, through the same wire as the rest; the other half sends none of them; the drives, the patches
    and every base signal are those of the same seed without channels."""
    config = FleetConfig(vehicles=6, duration_s=90.0, appear_max_s=30.0, life_s=(40.0, 50.0), channel_share=0.5)
    half = make_scenario(7, config)
    none = make_scenario(7, dataclasses.replace(config, channel_share=0.0))
    assert half.with_channels == {"bench-001", "bench-003", "bench-005"}
    assert {half.kinds[v].name for v in half.with_channels} == {k.name for k in half.kinds.values()}
    assert half.network.patches == none.network.patches
    for a, b in zip(half.trips, none.trips, strict=True):
        assert a.scenario.effects.any_channel == (a.vehicle_id in half.with_channels)
        assert a.scenario.effects.with_channels(False) == b.scenario.effects
        assert (a.vehicle_id, a.depart_s, a.scenario.run_id, a.scenario.seed, a.scenario.duration_s) == (
            b.vehicle_id,
            b.depart_s,
            b.scenario.run_id,
            b.scenario.seed,
            b.scenario.duration_s,
        )
    drives, bare = simulate_drives(half, 0), simulate_drives(none, 0)
    for name in TELEMETRY_COLUMNS:
        if name in drives.table.column_names and name not in CHANNEL_NAMES:
            assert drives.table[name].equals(bare.table[name]), name
    sends = np.isin(drives.vehicle, sorted(half.with_channels))
    for name in CHANNEL_NAMES:
        values = drives.table[name].to_numpy(zero_copy_only=False).astype(float)
        assert np.all(np.isnan(values[~sends])), name  # not sent
        assert np.isfinite(values[sends]).mean() > 0.9, name  # sent (GNSS has its dropouts)
    with pytest.raises(ValueError, match="channel_share"):
        FleetConfig(channel_share=1.5)


SHARES = (
    "recall",
    "recall_all",
    "within_1st_pass",
    "within_2nd_pass",
    "within_3rd_pass",
    "map_coverage",
    "map_coverage_low",
    "bounded_coverage",
    "bounded_coverage_low",
    "dry_cells_read_slippery",
    "evidence_share",
    "measured_share",
)
COUNTS = (
    "patches",
    "eligible",
    "warned_and_dried",
    "lingering",
    "linger_over_10min",
    "censored",
    "cancelled_while_there",
    "map_cells",
    "bounded_cells",
    "warnings",
    "warnings_on_patch",
    "warnings_beside",
    "false_warnings",
)
NON_NEGATIVE = (
    "time_to_first_median_s",
    "time_to_first_max_s",
    "passes_to_first_median",
    "passes_to_first_max",
    "linger_median_s",
    "linger_max_s",
    "map_mae",
    "map_mae_low",
    "bounded_mae",
    "bounded_mae_low",
    "dry_km",
    "false_per_100km",
)


def overlaps(cell: str, patch: Patch, origin: tuple[float, float]) -> bool:
    """Whether an H3 cell and a patch's disc can meet: the cell's centre within the disc's radius plus the cell's
    circumradius (its farthest vertex) of the patch's centre, in metres on the network's plane."""
    lat, lon = h3.cell_to_latlng(cell)
    east, north, _ = pymap3d.geodetic2enu(lat, lon, 0.0, *origin, 0.0)
    corners = [pymap3d.geodetic2enu(a, b, 0.0, *origin, 0.0)[:2] for a, b in h3.cell_to_boundary(cell)]
    circumradius = max(math.hypot(e - east, n - north) for e, n in corners)
    return math.hypot(east - patch.east_m, north - patch.north_m) <= patch.radius_m + circumradius


@pytest.mark.slow
def test_a_tiny_run_goes_through_the_service_and_yields_metrics(tmp_path, monkeypatch):
    """Three vehicles and roadside stations for 4 minutes through the service. What it writes is read back: the
    figures are finite and in range, the counts agree across metrics.csv, patches.csv and cells.csv and with the
    warnings the service raised, and every warning counted on a patch was raised over that patch while it was there
    (checked on the map's geometry, not by the scorer's cell lists)."""
    config = FleetConfig(
        vehicles=3,
        duration_s=240.0,
        patches_per_band=1,
        control_patches=1,
        appear_max_s=20.0,
        life_s=(100.0, 150.0),
        snapshot_every_s=120.0,
    )
    seeds = []
    run_seed = fleet_report.run_seed
    monkeypatch.setattr(
        fleet_report, "run_seed", lambda *args, **kwargs: seeds.append(run_seed(*args, **kwargs)) or seeds[-1]
    )
    result = run_fleet_benchmark(tmp_path, seed=3, seeds=1, config=config)  # seed 3: the vehicles alone warn
    (seed,) = seeds
    rows = pacsv.read_csv(tmp_path / "metrics.csv").to_pylist()
    assert result["rows"][-1]["seed"] == "pooled"
    by_seed = {name: {r["group"]: r for r in rows if r["seed"] == name} for name in ("3", "pooled")}
    assert by_seed["3"] == {g: {**r, "seed": "3"} for g, r in by_seed["pooled"].items()}  # one seed: pooled is it
    for row in rows:
        for key in SHARES:
            assert row[key] is None or 0.0 <= row[key] <= 1.0, (row["group"], key, row[key])
        for key in COUNTS:
            assert row.get(key) is None or (row[key] >= 0 and row[key] == int(row[key])), (row["group"], key)
        for key in NON_NEGATIVE:
            assert row.get(key) is None or (math.isfinite(row[key]) and row[key] >= 0), (row["group"], key)
        if row["within_1st_pass"] is not None:
            assert row["within_1st_pass"] <= row["within_2nd_pass"] <= row["within_3rd_pass"] <= row["recall"]
    overall = by_seed["3"]["all"]
    assert [by_seed["3"][band]["patches"] for band in ("mu<=0.2", "0.2-0.4", "0.4-0.6")] == [1, 1, 1]
    assert overall["patches"] == 3 and overall["dry_km"] > 1.0

    kinds = seed.kinds
    assert overall["warnings"] == len(seed.warnings) == len(kinds) >= 1
    assert (overall["warnings_on_patch"], overall["warnings_beside"], overall["false_warnings"]) == (
        kinds.count("on"),
        kinds.count("beside"),
        kinds.count("false"),
    )
    assert overall["false_per_100km"] == pytest.approx(overall["false_warnings"] / (overall["dry_km"] / 100.0))

    patches = pacsv.read_csv(tmp_path / "patches.csv").to_pylist()
    assert sorted(p["band"] for p in patches) == ["0.2-0.4", "0.4-0.6", "mu<=0.2"]  # the dry control is not scored
    assert sum(p["warnings"] for p in patches) == overall["warnings_on_patch"] + overall["warnings_beside"]
    assert sum(p["detected"] for p in patches) == pytest.approx(overall["recall_all"] * 3)
    assert sum(p["linger_s"] is not None for p in patches) == overall["warned_and_dried"]
    for p in patches:
        assert 0.0 <= p["appear_s"] < p["dry_s"] <= config.duration_s and 0.0 < p["mu"] < 0.6
        assert p["vehicles"] <= p["passes"] and p["observable_passes"] <= p["passes"]
        assert p["detected"] == (p["time_to_first_s"] is not None) and p["warnings"] >= p["detected"]
        if p["detected"]:
            assert 0.0 <= p["time_to_first_s"] <= config.duration_s - p["appear_s"]
            assert 0 <= p["passes_to_first"] <= p["passes"]

    cells = pacsv.read_csv(tmp_path / "cells.csv").to_pylist()
    assert len(cells) == overall["map_cells"] + overall["bounded_cells"]
    assert {c["t_s"] for c in cells} <= {120.0, 240.0}
    for c in cells:
        assert c["status"] in ("measured", "bounded") and 0.0 <= c["mu"] <= c["mu_upper"] <= 2.0
        assert 0.0 < c["mu_truth"] <= SURFACE_MU["dry"] and 0.0 <= c["error"] <= c["error_low"] + 1e-12

    network = seed.scenario.network
    slippery = [p for p in network.patches if p.mu < 0.6]
    on_patch = [w for w, kind in zip(seed.warnings, kinds) if kind == "on"]
    assert on_patch, "the tiny run raised no warning on a patch: nothing to check"
    for warning in on_patch:
        assert any(
            overlaps(warning.cell, p, network.origin) and p.appear_s <= warning.detection_s < p.dry_s for p in slippery
        ), warning
    for name in ("fleet.md", "map_vs_truth.png", "detection_delay.png"):
        assert (tmp_path / name).stat().st_size > 0
