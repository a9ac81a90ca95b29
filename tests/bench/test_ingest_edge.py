"""`roadgrip bench ingest --mode edge`: a real `roadgrip serve` takes edge vehicles' observations over MQTT; every one
acknowledged is stored once, and the service's CPU is read per stored observation."""

import pytest

from roadgrip.bench.ingest_edge import format_edge_case, observation_templates, run_edge_case


@pytest.mark.slow
def test_every_observation_acknowledged_is_stored_once_and_the_cpu_counted():
    templates = observation_templates()
    assert templates and all(o["excited"] or o["mu_proven"] >= 0.1 for o in templates)
    row = run_edge_case(vehicles=6, seconds=3.0, rate_per_s=2.0, templates=templates, progress=lambda m: None)
    assert row["sent"] == row["acknowledged"] == row["stored"] == 6 * 6
    assert row["lost"] == 0
    assert row["service_cpu_s"] > 0 and row["service_cpu_ms_per_stored"] > 0
    assert "stored 36, lost 0" in format_edge_case(row)
