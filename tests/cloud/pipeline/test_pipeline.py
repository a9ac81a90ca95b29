"""The streaming pipeline on its own with the fan-out (real SQLite storage, the EKF, the map and the warning engine):
what it publishes on the vehicles' friction topics, and how often."""

from __future__ import annotations

import json
import time

import pytest
from drives import patch_drive

from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.domain.warnings import WarningEngine
from roadgrip.cloud.pipeline import pipeline as pipeline_module
from roadgrip.cloud.pipeline.fanout import Fanout
from roadgrip.cloud.pipeline.pipeline import Pipeline
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Storage, open_storage
from roadgrip.cloud.transport.mqtt import friction_topic
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.terminal import wire_samples

START_MS = 1_700_000_000_000


@pytest.fixture
def make_pipeline(tmp_path):
    made = []

    def make(**settings):
        settings = Settings(**{"data_dir": tmp_path, "mqtt": "off", "flush_interval_s": 0.01,
                               "reorder_window_s": 0.05, "map_clock": "data", **settings})
        published: list[tuple[str, list[dict]]] = []
        storage = open_storage(settings.storage_url)
        fanout = Fanout(storage, settings, FrictionMap(), WarningEngine(),
                        publish=lambda topic, payload: published.append((topic, json.loads(payload))))
        pipeline = Pipeline(storage, settings, load_estimator("ekf"), fanout)
        made.append((pipeline, storage))
        pipeline.start()
        return pipeline, published

    yield make
    for pipeline, storage in made:
        pipeline.stop()
        storage.close()


def drive(pipeline: Pipeline, vehicles: list[str], seconds: float) -> int:
    """Each vehicle sends a 30 s run, two samples a message, paced over `seconds` of wall-clock time."""
    streams = {v: wire_samples(patch_drive(0.9, 3), v, START_MS) for v in vehicles}
    n = len(streams[vehicles[0]])
    for k in range(0, n, 2):
        for v in vehicles:
            pipeline.submit(v, streams[v][k:k + 2])
        time.sleep(seconds * 2 / n)
    return n


def test_each_vehicles_estimates_come_out_together_once_an_interval(make_pipeline):
    pipeline, published = make_pipeline(friction_publish_interval_s=0.5)
    vehicles = ["car-1", "car-2"]
    started = time.monotonic()
    n = drive(pipeline, vehicles, seconds=2.0)
    pipeline.stop()
    took_s = time.monotonic() - started
    for vehicle in vehicles:
        messages = [estimates for topic, estimates in published if topic == friction_topic(vehicle)]
        stamps = [e["timestamp_ms"] for estimates in messages for e in estimates]
        assert stamps == sorted(stamps) and len(stamps) == n  # every estimate once, in time order
        assert {e["vehicle_id"] for estimates in messages for e in estimates} == {vehicle}
        assert 2 <= len(messages) <= took_s / 0.5 + 2  # an interval's estimates per message, not a round's
    assert pipeline.counters.rounds > 3 * len(published)


def test_with_no_interval_every_round_publishes(make_pipeline):
    pipeline, published = make_pipeline(friction_publish_interval_s=0)
    drive(pipeline, ["car-1"], seconds=1.0)
    pipeline.stop()
    assert len(published) > 20  # about one a round: 150 messages over 1 s of 0.01 s rounds


def test_a_long_interval_holds_the_estimates_until_the_pipeline_stops(make_pipeline):
    pipeline, published = make_pipeline(friction_publish_interval_s=60)
    n = drive(pipeline, ["car-1"], seconds=0.5)
    time.sleep(0.3)
    assert published == [] and pipeline.counters.estimates == n
    pipeline.stop()
    assert [(topic, len(estimates)) for topic, estimates in published] == [(friction_topic("car-1"), n)]


@pytest.fixture
def small_rounds(monkeypatch):
    """Rounds of at most 20 samples; returns the number of telemetry rows each transaction wrote, as it goes."""
    monkeypatch.setattr(pipeline_module, "MAX_ROUND_SAMPLES", 20)
    written: list[int] = []
    write_batch = Storage.write_batch

    def recording(self, rows, estimates):
        written.append(len(rows))
        return write_batch(self, rows, estimates)
    monkeypatch.setattr(Storage, "write_batch", recording)
    return written


def test_a_queue_is_worked_off_in_rounds_of_at_most_max_round_samples_one_after_the_other(make_pipeline,
                                                                                        small_rounds):
    pipeline, _ = make_pipeline(flush_interval_s=2.0)
    samples = wire_samples(patch_drive(0.9, 3), "car-1", START_MS)[:100]
    time.sleep(0.2)  # the first round (empty) has run: the next one is 2 s away
    futures = [pipeline.submit("car-1", samples[k:k + 10]) for k in range(0, 100, 10)]
    started = time.monotonic()
    assert [f.result(timeout=5).stored for f in futures] == [10] * 10
    assert time.monotonic() - started < 3.0  # one flush interval, then the rounds back to back
    assert sum(small_rounds) == 100 and max(small_rounds) == 20  # two submissions of 10 a round


def test_stopping_stores_a_queue_longer_than_a_round(make_pipeline, small_rounds):
    pipeline, _ = make_pipeline(flush_interval_s=5.0)
    samples = wire_samples(patch_drive(0.9, 3), "car-1", START_MS)[:100]
    time.sleep(0.2)
    futures = [pipeline.submit("car-1", samples[k:k + 10]) for k in range(0, 100, 10)]
    pipeline.stop()
    assert [f.result(timeout=0).stored for f in futures] == [10] * 10
    assert len(pipeline.storage.telemetry("car-1")) == 100


def test_a_vehicle_forgotten_with_its_queue_dropped_is_not_started_again_from_it(tmp_path):
    """A worker that lost a vehicle's partition forgets it and drops what of it still waits: the next round must not
    open its stream again from those older samples (a partition that comes back would find its redelivered samples
    behind them: late, never estimated)."""
    settings = Settings(data_dir=tmp_path, mqtt="off", reorder_window_s=0.0)
    storage = open_storage(settings.storage_url)
    try:
        pipeline = Pipeline(storage, settings, load_estimator("ekf"), Fanout(storage, settings, FrictionMap(),
                                                                            WarningEngine()))
        samples = wire_samples(patch_drive(0.9, 3), "v1", START_MS)
        pipeline.submit("v1", samples[:20])
        pipeline.run_round(final=True)
        stale = pipeline.submit("v1", samples[20:40])
        other = pipeline.submit("v2", wire_samples(patch_drive(0.9, 3), "v2", START_MS)[:20])
        pipeline.forget_vehicle("v1", drop_queued=True)
        assert pipeline.backlog == 20
        assert isinstance(stale.exception(timeout=0), pipeline_module.VehicleMoved)
        pipeline.run_round(final=True)
        assert other.result(timeout=0).stored == 20
        pipeline.submit("v1", samples[20:40])  # redelivered to this worker later: estimated, none of it late
        pipeline.run_round(final=True)
        assert pipeline.counters.late == 0
        assert len(storage.estimates("v1")) > len(storage.estimates("v1", end_ms=samples[19]["timestamp_ms"]))
    finally:
        storage.close()
