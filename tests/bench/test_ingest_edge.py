"""`roadgrip bench ingest --mode edge`, the soak at a tiny size: a real `roadgrip serve` takes edge vehicles'
observations over MQTT from the load generator of `roadgrip bench ingest`, each vehicle its own login; every one
acknowledged is stored exactly once and handed to the map once, and the latency, memory and CPU are read."""

import orjson
import pytest

from roadgrip.bench.ingest_edge import ObservationMessages, format_edge_case, observation_templates, run_edge_case


@pytest.mark.slow
def test_every_observation_acknowledged_is_stored_exactly_once():
    templates = observation_templates()
    assert templates and all(o["excited"] or o["mu_proven"] >= 0.1 for o in templates)
    row = run_edge_case(vehicles=6, seconds=3.0, rate_per_s=2.0, templates=templates, progress=lambda m: None)
    assert row["complete"]
    assert row["sent"] == row["acknowledged"] == row["stored"] == row["fanned_out"] == 6 * 6
    assert row["lost"] == 0 and row["refused"] == 0 and row["rejected"] == 0
    assert row["vehicles_stored_exactly"] == 6
    assert row["duplicates_skipped"] == 0
    assert 0 < row["latency_p50_ms"] <= row["latency_p99_ms"]
    assert row["service_cpu_s"] > 0 and row["service_cpu_ms_per_stored"] > 0 and row["rss_mb_end"] > 0
    assert "stored 36, lost 0; vehicles stored exactly as sent 6 of 6" in format_edge_case(row)


@pytest.mark.slow
def test_generators_past_their_limit_are_stopped_and_the_run_still_recorded(monkeypatch):
    from roadgrip.bench import ingest

    monkeypatch.setattr(ingest, "GENERATOR_GRACE_S", -20.0)  # the limit falls at the start of a 20 s period
    row = run_edge_case(vehicles=2, seconds=20.0, rate_per_s=1.0, templates=observation_templates()[:4])
    assert not row["complete"] and row["generators_finished"].startswith("0 of ")
    assert row["sent"] == row["acknowledged"] == 0 and row["stored"] > 0  # what the service stored is still read
    assert row["timeline"] and "INCOMPLETE: load generators finished 0 of " in format_edge_case(row)


def test_the_vehicles_messages_are_spread_over_the_period_each_its_own_key():
    messages = ObservationMessages([{"first_ms": 0, "last_ms": 4_000, "mu": 0.3}], rate_per_s=0.5, vehicles=4)
    assert messages.ticks(60.0) == 30
    assert [messages.due_s(k, 0) for k in range(4)] == [0.0, 0.5, 1.0, 1.5]
    assert messages.due_s(3, 1) == 3.5
    keys = {messages.last_ms(k, t, 1_000) for k in range(4) for t in range(30)}
    assert len(keys) == 120
    (line,) = messages.lines("car-1", 1, 2, 1_000)
    assert orjson.loads(line) == {"vehicle_id": "car-1", "first_ms": 1_500, "last_ms": 5_500, "mu": 0.3}
