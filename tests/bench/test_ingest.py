"""`roadgrip bench ingest` end to end on a small fleet: its counts prove what was stored, sample by sample."""

import pytest
from rich.console import Console

from roadgrip.bench.ingest import IngestCase, format_ingest, memory_trend, run_case, sample_bodies


@pytest.fixture(scope="module")
def bodies():
    return sample_bodies(runs=2)


@pytest.mark.parametrize(("transport", "batch"), [("mqtt", 10), ("http", 5)])
@pytest.mark.slow
def test_a_small_fleet_is_stored_exactly_as_sent(bodies, transport, batch):
    row = run_case(IngestCase(transport, vehicles=12, seconds=4.0, batch=batch), bodies)
    assert row["sent"] == row["acknowledged"] == row["stored_rows"] == 12 * 40
    assert row["lost"] == 0 and row["refused"] == 0
    assert row["vehicles_stored_exactly"] == 12
    assert row["estimate_rows"] == row["stored_rows"]
    # batch x 100 ms waiting in the terminal, the reorder window, a round: well under 5 s on any machine
    assert 0 < row["latency_p50_ms"] <= row["latency_p99_ms"] < 5_000
    text = Console(width=200, record=True)
    text.print(format_ingest([row]))
    assert "12 of 12" in text.export_text()


def test_memory_is_flat_when_the_second_half_grows_by_at_most_five_percent():
    def timeline(rss):
        return [{"t_s": 5.0 * k, "rss_mb": v} for k, v in enumerate(rss)]

    flat = memory_trend(timeline([400, 500, 520, 525, 530, 532, 535]))
    assert flat["memory_flat"] and flat["rss_mb_half"] == 525
    assert flat["rss_growth_mb_per_min"] == pytest.approx(60 * 10 / 15)
    assert not memory_trend(timeline([400, 500, 600, 700, 800, 900, 1000]))["memory_flat"]
    assert memory_trend(timeline([400, 500]))["memory_flat"] is None
