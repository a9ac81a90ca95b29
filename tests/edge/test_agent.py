"""The vehicle end's agent and outbox: the observations it makes are the passes the cloud would have made from its raw
telemetry (the same warning, the same measured cells), its estimator state survives an ignition cycle, its outbox keeps
what it was given across a reopen and drops the oldest at its limit."""

from __future__ import annotations

import time

import orjson
import pytest
from drives import patch_cells, patch_drive

from roadgrip.cloud.domain.cells import cell_of
from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.domain.observations import pass_rows
from roadgrip.cloud.domain.warnings import ACTIVE, WarningEngine
from roadgrip.edge.agent import EdgeAgent, evidence_of
from roadgrip.edge.outbox import Outbox
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.terminal import wire_samples
from roadgrip.vehicle.params import MIDSIZE_SEDAN, PAPER_SUV

START_MS = int(time.time() * 1000) - 600_000


def _agent(tmp_path, profile=PAPER_SUV, outbox=None) -> EdgeAgent:
    outbox = outbox or Outbox(tmp_path / "outbox.sqlite")
    return EdgeAgent("car-1", profile, load_estimator("pmf"), outbox, state_path=tmp_path / "state.json")


def _messages(outbox: Outbox, kind: str) -> list[dict]:
    return [orjson.loads(p) for _, topic, p in outbox.oldest(10_000) if topic.endswith(kind)]


@pytest.fixture(scope="module")
def icy_drive() -> list[dict]:
    return wire_samples(patch_drive(0.2, 1), "car-1", START_MS)


def test_observations_make_the_passes_raw_telemetry_makes(tmp_path, icy_drive):
    agent = _agent(tmp_path)
    for sample in icy_drive:
        agent.feed(sample)
    agent.finish()
    observations = _messages(agent.outbox, "observations")
    assert observations and all(o["vehicle_id"] == "car-1" for o in observations)

    estimator = load_estimator("pmf")
    state = estimator.start(PAPER_SUV)
    raw = []
    for sample in icy_drive:
        row = estimator.update(state, sample).to_dict()
        row |= {"latitude_deg": sample["latitude_deg"], "longitude_deg": sample["longitude_deg"]}
        raw.append(row | {"h3_cell": cell_of(row["latitude_deg"], row["longitude_deg"], 10)})
    edge_rows = [row for o in observations for row in pass_rows(o)]
    end_ms = icy_drive[-1]["timestamp_ms"] + 60_000

    warned = []
    for rows in (raw, edge_rows):
        engine = WarningEngine()
        engine.update(rows, end_ms)
        warned.append({e.cell for e in engine.active() if e.status == ACTIVE})
    assert warned[0] and warned[0] == warned[1]
    assert warned[1] <= patch_cells()

    summaries = []
    for rows in (raw, edge_rows):
        friction_map = FrictionMap()
        friction_map.add(rows, end_ms)
        summaries.append({c.cell: c for c in friction_map.cells(end_ms) if c.status == "measured"})
    assert summaries[0].keys() == summaries[1].keys()
    for cell in warned[1]:
        assert summaries[1][cell].mu_upper < 0.4
        assert summaries[1][cell].mu_upper == pytest.approx(summaries[0][cell].mu_upper, abs=0.05)


def test_a_calm_pass_is_not_sent_and_a_heartbeat_is(tmp_path, icy_drive):
    agent = _agent(tmp_path)
    calm = [s | {"accel_lon_mps2": 0.0, "accel_lat_mps2": 0.0} for s in icy_drive[:60]]  # 6 s at 25 m/s
    for sample in calm:
        agent.feed(sample)
    agent.finish()
    assert _messages(agent.outbox, "observations") == []
    (heartbeat,) = _messages(agent.outbox, "heartbeat")
    assert heartbeat["n_samples"] == 60 and heartbeat["timestamp_ms"] == calm[-1]["timestamp_ms"]


def test_the_estimator_state_survives_an_ignition_cycle(tmp_path, icy_drive):
    first = _agent(tmp_path)
    for sample in icy_drive[:100]:
        first.feed(sample)
    first.finish()
    again = _agent(tmp_path, outbox=first.outbox)
    assert again.restored
    fresh = load_estimator("pmf")
    learnt = orjson.dumps(again.estimator.state_to_dict(again.state), option=orjson.OPT_SERIALIZE_NUMPY)
    assert learnt != orjson.dumps(fresh.state_to_dict(fresh.start(PAPER_SUV)), option=orjson.OPT_SERIALIZE_NUMPY)
    assert not _agent(tmp_path, profile=MIDSIZE_SEDAN, outbox=first.outbox).restored  # another car's: not used


def test_evidence_kinds_name_the_manoeuvre():
    sample = {"abs_active": False, "tcs_active": None, "accel_lon_mps2": -1.0, "accel_lat_mps2": 3.0}
    assert evidence_of(sample, {"excited": True, "mu_proven": 0.3}) == ["bound", "lateral"]
    assert evidence_of(sample | {"abs_active": True}, {"excited": True, "mu_proven": 0.05}) == ["abs"]
    assert evidence_of(sample | {"accel_lat_mps2": 0.0}, {"excited": True, "mu_proven": None}) == ["slip_slope"]
    assert evidence_of(sample, {"excited": False, "mu_proven": 0.0}) == []


def test_the_outbox_keeps_messages_across_a_reopen_and_drops_the_oldest_at_its_limit(tmp_path):
    outbox = Outbox(tmp_path / "o.sqlite", limit_messages=3)
    ids = [outbox.put("t", f"m{i}".encode()) for i in range(5)]
    assert outbox.pending == 3 and outbox.dropped == 2
    outbox.close()
    reopened = Outbox(tmp_path / "o.sqlite", limit_messages=3)
    assert [p for _, _, p in reopened.oldest(10)] == [b"m2", b"m3", b"m4"]
    assert reopened.dropped == 2
    assert reopened.remove(ids[3]) and not reopened.remove(ids[3])
    assert [p for _, _, p in reopened.oldest(10, after_id=ids[2])] == [b"m4"]
    with pytest.raises(ValueError, match="limit_messages"):
        Outbox(tmp_path / "x.sqlite", limit_messages=0)
