"""Fleet planning, simulation and the streaming timeline."""

from __future__ import annotations

import numpy as np
import pytest

from roadgrip.data.telemetry import validate_telemetry
from roadgrip.fleet.fleet import plan_fleet, simulate_fleet, stream
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
    assert plan_fleet(network, 9, duration_s=100.0, seed=3, patch_braking_share=1.0)[4].brakes_at_m == \
        plans[4].brakes_at_m
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


class FakeClock:
    def __init__(self):
        self.now = 1_800_000_000.0

    def time(self):
        return self.now

    def sleep(self, seconds):
        self.now += seconds


@pytest.mark.parametrize("speed", [1.0, 4.0])
def test_streaming_keeps_the_10_hz_timeline_and_never_sends_the_future(speed):
    clock = FakeClock()
    runs = {"a": [{"vehicle_id": "a", "timestamp_ms": 0, "x": k} for k in range(30)],
            "b": [{"vehicle_id": "b", "timestamp_ms": 0, "x": k} for k in range(20)]}
    sent = []
    counts = stream(runs, lambda vid, msg: sent.append((clock.now, vid, msg)), speed=speed, batch=5,
                    clock=clock.time, sleep=clock.sleep)
    assert counts.sent == 50 and counts.messages == 6 + 4
    a = [s for _, vid, msg in sent if vid == "a" for s in msg]
    assert [s["x"] for s in a] == list(range(30))
    assert np.all(np.diff([s["timestamp_ms"] for s in a]) == 100)
    for at, _, msg in sent:
        assert max(s["timestamp_ms"] for s in msg) <= at * 1000 + 1e-6
    assert counts.wall_s == pytest.approx(2.9 / speed, abs=1e-6)
