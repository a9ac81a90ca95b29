"""The streaming pipeline on its own with the fan-out (real SQLite storage, the EKF, the map and the warning engine):
what it publishes on the vehicles' friction topics, and how often."""

from __future__ import annotations

import json
import time

import pytest
from drives import patch_drive

from roadgrip.cloud.fanout import Fanout
from roadgrip.cloud.friction_map import FrictionMap
from roadgrip.cloud.mqtt import friction_topic
from roadgrip.cloud.pipeline import Pipeline
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage import open_storage
from roadgrip.cloud.warning_engine import WarningEngine
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.terminal import wire_samples

START_MS = 1_700_000_000_000


@pytest.fixture
def make_pipeline(tmp_path):
    made = []

    def make(**settings):
        settings = Settings(data_dir=tmp_path, mqtt="off", flush_interval_s=0.01, reorder_window_s=0.05,
                            map_clock="data", **settings)
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
