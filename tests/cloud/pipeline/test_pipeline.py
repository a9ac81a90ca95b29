"""The streaming pipeline on its own with the fan-out (real SQLite storage, the EKF, the map and the warning engine):
what it publishes on the vehicles' friction topics, and when (on a fake clock, the rounds run by the test); how a queue
longer than a round is worked off (the pipeline's own thread)."""

from __future__ import annotations

import json
import time

import pytest
from broker_fixtures import wait_until
from drives import patch_drive
from fake_clock import FakeClock

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


def settings_of(tmp_path, **settings) -> Settings:
    return Settings(
        **{
            "data_dir": tmp_path,
            "mqtt": "off",
            "flush_interval_s": 0.01,
            "reorder_window_s": 0.05,
            "map_clock": "data",
            **settings,
        }
    )


class Clocked:
    """A pipeline and its fan-out on a fake clock, without the pipeline's thread: the test runs the rounds. What was
    published, with the clock's time; when each estimate reached the fan-out (vehicle, timestamp_ms -> s)."""

    def __init__(self, tmp_path, **settings):
        self.clock = FakeClock()
        settings = settings_of(tmp_path, **settings)
        self.storage = open_storage(settings.storage_url)
        self.published: list[tuple[float, str, list[dict]]] = []
        self.fanout = Fanout(
            self.storage,
            settings,
            FrictionMap(),
            WarningEngine(),
            clock=self.clock,
            publish=lambda topic, payload: self.published.append((self.clock(), topic, json.loads(payload))),
        )
        self.queued_s: dict[tuple[str, int], float] = {}
        self.pipeline = Pipeline(self.storage, settings, load_estimator("ekf"), self, clock=self.clock)

    def stored(self, estimates: list[dict], stored_ms: float, newest_data_ms: int) -> None:
        for e in estimates:
            self.queued_s[(e["vehicle_id"], e["timestamp_ms"])] = self.clock()
        self.fanout.stored(estimates, stored_ms, newest_data_ms)

    def tick(self, final: bool) -> None:
        self.fanout.tick(final)

    def round(self, final: bool = False) -> None:
        """One round as the pipeline's thread runs it: estimate and store, then the fan-out's tick."""
        self.pipeline.run_round(final=final)
        self.tick(final)

    def drive(self, vehicles: list[str], seconds: float) -> tuple[int, float]:
        """Each vehicle sends a 30 s run, two samples a message, over `seconds` of the clock: one message each, then
        a round. The samples per vehicle, and the clock's step between rounds."""
        streams = {v: wire_samples(patch_drive(0.9, 3), v, START_MS) for v in vehicles}
        n = len(streams[vehicles[0]])
        step_s = seconds * 2 / n
        for k in range(0, n, 2):
            for v in vehicles:
                self.pipeline.submit(v, streams[v][k : k + 2])
            self.clock.advance(step_s)
            self.round()
        return n, step_s

    def messages(self, vehicle: str) -> list[tuple[float, list[dict]]]:
        return [(at_s, estimates) for at_s, topic, estimates in self.published if topic == friction_topic(vehicle)]

    def waited_s(self, at_s: float, estimates: list[dict]) -> float:
        """How long the oldest estimate of a message published at `at_s` waited for it."""
        return at_s - min(self.queued_s[(e["vehicle_id"], e["timestamp_ms"])] for e in estimates)


@pytest.fixture
def clocked(tmp_path):
    made = []

    def make(**settings) -> Clocked:
        made.append(Clocked(tmp_path, **settings))
        return made[-1]

    yield make
    for run in made:
        run.storage.close()


def test_each_vehicles_estimates_come_out_together_once_an_interval(clocked):
    run = clocked(friction_publish_interval_s=0.5)
    vehicles = ["car-1", "car-2"]
    n, step_s = run.drive(vehicles, seconds=2.0)
    run.round(final=True)
    for vehicle in vehicles:
        messages = run.messages(vehicle)
        stamps = [e["timestamp_ms"] for _, estimates in messages for e in estimates]
        assert stamps == sorted(stamps) and len(stamps) == n  # every estimate once, in time order
        assert {e["vehicle_id"] for _, estimates in messages for e in estimates} == {vehicle}
        assert len(messages) >= 4  # 2 s of rounds at 0.5 s, then what the final round held
        for at_s, estimates in messages[:-1]:  # an interval's estimates, out at the first round once due
            assert 0.5 <= run.waited_s(at_s, estimates) < 0.5 + step_s
        at_s, estimates = messages[-1]
        assert run.waited_s(at_s, estimates) < 0.5  # not yet due: held until the pipeline stopped
    assert run.pipeline.counters.rounds > 3 * len(run.published)


def test_with_no_interval_every_round_publishes(clocked):
    run = clocked(friction_publish_interval_s=0)
    _, step_s = run.drive(["car-1"], seconds=1.0)
    run.clock.advance(step_s)
    run.round(final=True)  # the stop, a round later
    rounds_with_estimates = sorted(set(run.queued_s.values()))
    messages = run.messages("car-1")
    assert [at_s for at_s, _ in messages] == rounds_with_estimates  # one message a round that estimated
    assert all(run.waited_s(at_s, estimates) == 0 for at_s, estimates in messages)
    assert len(messages) > 100  # 150 rounds of two samples, the first few held by the reorder window


def test_a_long_interval_holds_the_estimates_until_the_pipeline_stops(clocked):
    run = clocked(friction_publish_interval_s=60)
    n, _ = run.drive(["car-1"], seconds=0.5)
    run.clock.advance(0.3)  # the vehicle is quiet longer than the reorder window: its last samples are released
    run.round()
    assert run.published == [] and run.pipeline.counters.estimates == n
    run.round(final=True)
    assert [(topic, len(estimates)) for _, topic, estimates in run.published] == [(friction_topic("car-1"), n)]


@pytest.fixture
def make_pipeline(tmp_path):
    """A pipeline with its own thread (started when asked), on the real clock."""
    made = []

    def make(start: bool = True, **settings):
        settings = settings_of(tmp_path, **settings)
        storage = open_storage(settings.storage_url)
        pipeline = Pipeline(
            storage, settings, load_estimator("ekf"), Fanout(storage, settings, FrictionMap(), WarningEngine())
        )
        made.append((pipeline, storage))
        if start:
            pipeline.start()
        return pipeline

    yield make
    for pipeline, storage in made:
        pipeline.stop()
        storage.close()


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


def test_a_queue_is_worked_off_in_rounds_of_at_most_max_round_samples_one_after_the_other(make_pipeline, small_rounds):
    pipeline = make_pipeline(start=False, flush_interval_s=5.0)  # a round waiting for the next: 4 x 5 s
    samples = wire_samples(patch_drive(0.9, 3), "car-1", START_MS)[:100]
    futures = [pipeline.submit("car-1", samples[k : k + 10]) for k in range(0, 100, 10)]
    started = time.monotonic()
    pipeline.start()
    assert [f.result(timeout=15) for f in futures] and time.monotonic() - started < 15  # not 4 x 5 s
    assert [f.result().stored for f in futures] == [10] * 10
    assert small_rounds == [20] * 5  # two submissions of 10 a round


def test_stopping_stores_a_queue_longer_than_a_round(make_pipeline, small_rounds):
    pipeline = make_pipeline(flush_interval_s=5.0)
    samples = wire_samples(patch_drive(0.9, 3), "car-1", START_MS)[:100]
    wait_until(lambda: pipeline.counters.rounds >= 1, what="the first (empty) round")  # the next is 5 s away
    futures = [pipeline.submit("car-1", samples[k : k + 10]) for k in range(0, 100, 10)]
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
        pipeline = Pipeline(
            storage, settings, load_estimator("ekf"), Fanout(storage, settings, FrictionMap(), WarningEngine())
        )
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


def test_a_vehicle_taken_over_is_estimated_in_order_though_the_broker_hands_its_messages_over_out_of_order(tmp_path):
    """RabbitMQ 3.10's quorum queues hand the previous owner's unacknowledged messages to the next consumer out of order
    (results/trials/cluster/handover_order.py): a worker's pipeline holds a vehicle it takes over for TAKEOVER_HOLD_S,
    so a message older than one before it, within the hold, is estimated in its place; after the hold it is late
    (stored, never estimated)."""
    clock = FakeClock()
    settings = settings_of(tmp_path)
    storage = open_storage(settings.storage_url)
    try:
        sink = Fanout(storage, settings, FrictionMap(), WarningEngine())
        pipeline = Pipeline(storage, settings, load_estimator("ekf"), sink, skip_estimated=True, clock=clock)
        late_by = {"within": 0.5 * pipeline_module.TAKEOVER_HOLD_S, "after": 2.0 * pipeline_module.TAKEOVER_HOLD_S}
        drives = {v: wire_samples(patch_drive(0.9, 3), v, START_MS)[:30] for v in late_by}
        for v, samples in drives.items():  # 10-19 first, then 20-29 (their successors), then 0-9
            pipeline.submit(v, samples[10:20])
            pipeline.submit(v, samples[20:30])
        pipeline.run_round()
        for v in sorted(late_by, key=late_by.get):
            clock.advance(late_by[v] - (clock() - 1_000.0))
            pipeline.run_round()
            pipeline.submit(v, drives[v][:10])
            pipeline.run_round()
        clock.advance(1.0)
        pipeline.run_round(final=True)
        assert pipeline.counters.late == 10
        for v, late in (("within", []), ("after", drives["after"][:10])):
            estimated = [e["timestamp_ms"] for e in storage.estimates(v)]
            assert estimated == sorted(estimated) and estimated[-1] == drives[v][-1]["timestamp_ms"]
            assert not {s["timestamp_ms"] for s in drives[v][:10] if s not in late} - set(estimated), v
            assert not {s["timestamp_ms"] for s in late} & set(estimated), v
            assert len(storage.telemetry(v)) == 30
    finally:
        storage.close()
