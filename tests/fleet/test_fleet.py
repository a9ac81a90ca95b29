"""Fleet planning, simulation and the streaming timeline."""

from __future__ import annotations

import math

import numpy as np
import pytest

from roadgrip.data.telemetry import validate_telemetry
from roadgrip.fleet.fleet import plan_fleet, simulate_fleet, timeline
from roadgrip.fleet.network import generated_network
from roadgrip.vehicle.params import VEHICLES


def test_plans_cycle_vehicle_kinds_and_brake_on_patches():
    network = generated_network()
    plans = plan_fleet(network, 9, duration_s=100.0, seed=3, patch_braking_share=1.0)
    assert [p.vehicle.name for p in plans[:3]] == list(VEHICLES)
    assert len({p.vehicle_id for p in plans}) == 9
    for plan in plans:
        patches = network.patch_stations(plan.road)
        if patches:
            assert any(first <= b <= last for b in plan.brakes_at_m for first, last, _ in patches)
        assert plan.scenario.duration_s <= 100.0
    assert (
        plan_fleet(network, 9, duration_s=100.0, seed=3, patch_braking_share=1.0)[4].brakes_at_m == plans[4].brakes_at_m
    )
    with pytest.raises(ValueError, match="vehicles"):
        plan_fleet(network, 0)


def test_simulated_fleet_telemetry_is_valid_wire_format():
    network = generated_network()
    plans = plan_fleet(network, 3, duration_s=30.0, seed=1)
    samples = simulate_fleet(plans, network)
    assert set(samples) == {p.vehicle_id for p in plans}
    import pyarrow as pa

    rows = [s for run in samples.values() for s in run]
    batch = validate_telemetry(pa.Table.from_pylist(rows))
    assert not batch.rejections
    lat = np.array([s["latitude_deg"] for s in rows])
    assert np.abs(lat - network.origin[0]).max() < 0.03  # within ~3 km of the origin


@pytest.mark.parametrize("speed", [1.0, 4.0, math.inf])
def test_the_timeline_keeps_10_hz_and_never_runs_ahead_of_the_sending_clock(speed):
    runs = {
        "a": [{"vehicle_id": "a", "timestamp_ms": 100 * k} for k in range(30)],
        "b": [{"vehicle_id": "b", "timestamp_ms": 100 * k} for k in range(20)],
    }
    now_s = 1_800_000_000.0
    samples = timeline(runs, speed, now_s)
    a = [s["timestamp_ms"] for s in samples if s["vehicle_id"] == "a"]
    assert len(samples) == 50 and np.all(np.diff(a) == 100)
    first = min(s["timestamp_ms"] for s in samples)
    for s in samples:  # replay sends each sample (ts - first) / speed after it starts, at now_s
        sent_ms = now_s * 1000 + (s["timestamp_ms"] - first) / speed
        assert s["timestamp_ms"] <= sent_ms + 1e-6
    if speed == 1.0:
        assert first == now_s * 1000  # live
    with pytest.raises(ValueError, match="speed"):
        timeline(runs, 0.0, now_s)
