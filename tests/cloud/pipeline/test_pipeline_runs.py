"""The pipeline feeds each vehicle's released samples to the estimator as runs (`update_many`, roadgrip/estimators/
base.py): what it stores is what the guarded pmf gives streamed one sample at a time over the same samples in time
order, restarted (`reset`) where a gap is longer than max_gap_s; a sample behind what was estimated is stored, not
estimated; each estimate carries its sample's position and that position's H3 cell. Real SQLite storage, the pipeline's
rounds run by the test on a fake clock; messages arrive out of order inside the reorder window."""

from __future__ import annotations

from drives import patch_drive
from fake_clock import FakeClock

from roadgrip.cloud.domain.cells import cell_of
from roadgrip.cloud.pipeline.pipeline import Pipeline
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import open_storage
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.terminal import wire_samples
from roadgrip.vehicle.params import PAPER_SUV

START_MS = 1_700_000_000_000
GAP_AT = 120  # the samples from here on come 3 s later: a gap that restarts the estimator


class Recorded:
    """The pipeline's sink: the stored rounds' estimates."""

    def __init__(self):
        self.estimates: list[dict] = []

    def stored(self, estimates: list[dict], stored_ms: float, newest_data_ms: int) -> None:
        self.estimates += estimates

    def tick(self, final: bool) -> None:
        pass


def _drive() -> list[dict]:
    samples = wire_samples(patch_drive(0.3, 5), "car-1", START_MS)[:200]
    return [{**s, "timestamp_ms": s["timestamp_ms"] + (3_000 if k >= GAP_AT else 0)} for k, s in enumerate(samples)]


def _streamed(samples: list[dict], max_gap_ms: float) -> list[dict]:
    estimator = load_estimator("pmf")
    state = estimator.start(PAPER_SUV)
    out, last = [], None
    for sample in samples:
        if last is not None and sample["timestamp_ms"] - last > max_gap_ms:
            estimator.reset(state)
        last = sample["timestamp_ms"]
        estimate = estimator.update(state, sample)
        if estimate is not None:
            out.append(estimate.to_dict())
    return out


def test_the_pipeline_stores_what_streaming_gives_around_a_gap_and_out_of_order_messages(tmp_path):
    settings = Settings(data_dir=tmp_path, mqtt="off", reorder_window_s=2.5, max_gap_s=0.25, estimator="pmf")
    storage = open_storage(settings.storage_url)
    sink, clock = Recorded(), FakeClock()
    pipeline = Pipeline(storage, settings, load_estimator("pmf"), sink, clock=clock)
    samples = _drive()
    messages = [samples[k : k + 10] for k in range(0, len(samples), 10)]
    for k in range(0, len(messages) - 1, 2):  # each pair of messages sent in the wrong order
        messages[k], messages[k + 1] = messages[k + 1], messages[k]
    late = {**samples[50], "timestamp_ms": samples[50]["timestamp_ms"] + 1}  # behind what was estimated when it comes
    for k, message in enumerate(messages):
        pipeline.submit("car-1", message)
        if k == 12:
            pipeline.submit("car-1", [late])
        clock.advance(1.0)
        pipeline.run_round()
    pipeline.run_round(final=True)

    expected = _streamed(samples, settings.max_gap_s * 1000.0)
    got = sink.estimates
    assert pipeline.counters.late == 1 and pipeline.counters.restarts == 1
    assert [{k: e[k] for k in expected[0]} for e in got] == expected
    assert [e["timestamp_ms"] for e in storage.estimates("car-1")] == [e["timestamp_ms"] for e in expected]
    by_time = {s["timestamp_ms"]: s for s in samples}
    for estimate in got:
        sample = by_time[estimate["timestamp_ms"]]
        assert (estimate["latitude_deg"], estimate["longitude_deg"]) == (
            sample["latitude_deg"],
            sample["longitude_deg"],
        )
        assert estimate["h3_cell"] == cell_of(sample["latitude_deg"], sample["longitude_deg"], settings.h3_resolution)
    storage.close()
